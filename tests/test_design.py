"""Offline design: UIHOSMO transformation, LMI solution, exact discretisation, stability, the design file."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest
import yaml

from ptw_rt.analysis.observability import invariant_zeros
from ptw_rt.design.build import check_design
from ptw_rt.design.discretize import interpolate, spectral_radius, zoh
from ptw_rt.design.file import DesignFileError, load_design
from ptw_rt.design.lpv_lmi import lipschitz_jacobians
from ptw_rt.design.uihosmo import complement_rows
from ptw_rt.model.sharp import case2, kmh, lpv_model, state_space
from ptw_rt.paths import DEFAULT_CONFIG, DEFAULT_DESIGN
from ptw_rt.settings import load_settings


@pytest.fixture(scope="module")
def design(fresh_design):
    return fresh_design[0]


@pytest.fixture(scope="module")
def extras(fresh_design):
    return fresh_design[1]


def test_committed_design_file_is_current(settings):
    """Fails when config/scooter.yaml changed without `ptw-rt design` being re-run."""
    data = load_design(DEFAULT_DESIGN, settings.config_hash, DEFAULT_CONFIG)
    assert data.config_hash == settings.config_hash


# what the design computes in closed form (discretisations, Riccati and Kalman gains, transformations): the
# committed file must hold what `ptw-rt design` makes from the config, whatever the machine's LAPACK
CLOSED_FORM = ("uh_Phi", "uh_T", "uh_Dbar_inv", "us_Phi", "kf_Phi", "kf_K", "tb_Phi", "tb_K", "tb_Sinv")


def test_committed_design_equals_a_fresh_design(design):
    committed = load_design(DEFAULT_DESIGN)
    for name in CLOSED_FORM:
        a, b = getattr(committed, name), getattr(design, name)
        assert np.allclose(a, b, rtol=1e-6, atol=1e-9 * np.abs(b).max()), name
    assert np.array_equal(committed.uh_complement_rows, design.uh_complement_rows)


def test_committed_lmi_solution_is_certified_like_a_fresh_one(design):
    """The adaptive observer's gains come from an LMI: any feasible point is a valid design, and which one an
    SDP solver returns depends on its version (clarabel 0.11 and its predecessor give gains 14 % apart), so the
    committed solution is held to what it must certify, not to equality: feasible, every grid point's and every
    in-between error dynamics stable, as a fresh solution is."""
    committed = load_design(DEFAULT_DESIGN)
    for data in (committed, design):
        check = check_design(data)
        assert check["adaptive"]["lmi"]["feasible"] and check["stable"]
        assert max(check["adaptive"]["spectral_radius"]) < 1.0
        assert check["between_grid"]["adaptive"]["max_spectral_radius"] < 1.0
    # the parts fixed by the model, not by the solver, are the same
    for name in ("ad_C", "ad_theta_nominal", "ad_theta_bound", "ad_speed_vertices", "regressor_constants"):
        a, b = getattr(committed, name), getattr(design, name)
        assert np.allclose(a, b, rtol=1e-6, atol=1e-9 * max(np.abs(b).max(), 1.0)), name


def test_stale_design_is_refused(tmp_path, settings):
    doc = yaml.safe_load(DEFAULT_CONFIG.read_text())
    doc["vehicle"]["rear_tyre"]["cornering_stiffness"] = 19000
    changed = tmp_path / "changed.yaml"
    changed.write_text(yaml.safe_dump(doc))
    other = load_settings(changed)
    with pytest.raises(DesignFileError, match="made for another configuration.*ptw-rt design --config"):
        load_design(DEFAULT_DESIGN, other.config_hash, changed)


def test_a_vehicle_file_of_ones_own_gets_its_own_design_file(tmp_path, settings):
    """A rider's `added_mass` in a copy of the file: `ptw-rt design --config rider.yaml` writes rider.design.npz beside
    it (it wrote the shipped design, which the shipped file then no longer matched), and every command reads that
    one by default. Before it exists, the refusal names it, not the shipped file."""
    from ptw_rt.edge.cycle import build_runner

    doc = yaml.safe_load(DEFAULT_CONFIG.read_text())
    doc["vehicle"]["added_mass"] = 30.0
    rider = tmp_path / "rider.yaml"
    rider.write_text(yaml.safe_dump(doc))
    with pytest.raises(DesignFileError, match=f"--config {rider} --out {tmp_path / 'rider.design.npz'}$"):
        build_runner(rider)
    shipped = DEFAULT_DESIGN.read_bytes()
    proc = subprocess.run(
        [sys.executable, "-m", "ptw_rt.cli", "design", "--config", str(rider)], capture_output=True, text=True
    )
    assert proc.returncode == 0, proc.stderr
    assert DEFAULT_DESIGN.read_bytes() == shipped
    assert build_runner(rider).estimator.design.config_hash == load_settings(rider).config_hash
    # a copy of the shipped file with no design of its own reads the shipped design (the hash says it fits)
    copy = tmp_path / "copy.yaml"
    copy.write_text(DEFAULT_CONFIG.read_text())
    assert build_runner(copy).estimator.design.config_hash == settings.config_hash


def test_design_file_errors(tmp_path):
    with pytest.raises(DesignFileError, match="not found"):
        load_design(tmp_path / "missing.npz")
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"not a zip file")
    with pytest.raises(DesignFileError, match="not a readable design file"):
        load_design(garbage)
    old = tmp_path / "old.npz"
    np.savez(old, format_version=np.array(0))
    with pytest.raises(DesignFileError, match="format version 0"):
        load_design(old)


def test_every_observer_is_stable_at_and_between_grid_speeds(design):
    result = check_design(design)
    assert result["stable"]
    assert max(result["uihosmo"]["spectral_radius"]) < 1.0
    assert max(result["adaptive"]["spectral_radius"]) < 1.0
    assert result["between_grid"]["max_spectral_radius"] < 1.0
    assert design.grid[0] * 3.6 == pytest.approx(10) and design.grid[-1] * 3.6 == pytest.approx(130)


def test_detectability_floor_and_validity(design, vehicle):
    floor = design.detectability_floor
    assert 13.5 / 3.6 < floor < 15.0 / 3.6
    assert invariant_zeros(case2(vehicle, floor - 0.05)).real.max() > 0
    assert invariant_zeros(case2(vehicle, floor + 0.05)).real.max() < 0
    assert design.min_valid_speed > floor
    assert np.array_equal(design.uh_detectable, design.grid >= floor)


def test_uihosmo_transformation_structure(extras, vehicle):
    for pt in extras["uihosmo"].points:
        if pt.speed * 3.6 < 15:
            continue
        sys = case2(vehicle, pt.speed)
        T2 = pt.T[3:]
        assert np.abs(T2 @ sys.D).max() < 1e-9 * np.abs(T2).max() * np.abs(sys.D).max()
        # zero dynamics = invariant zeros (strong detectability seen from the observer)
        zeros = list(invariant_zeros(sys))
        for ev in np.linalg.eigvals(pt.A22):
            nearest = min(zeros, key=lambda z, ev=ev: abs(z - ev))
            assert abs(nearest - ev) < 1e-6 * max(1.0, abs(ev))
            zeros.remove(nearest)
        assert abs(np.linalg.det(pt.Dbar)) > 1e-3
        At = sys.A - pt.L @ sys.C
        assert np.linalg.eigvals(At).real.max() <= -15.0 + 1e-6  # prescribed decay rate


def test_unknown_input_reconstruction_is_exact_given_exact_derivatives(extras, vehicle):
    """Eq. 15: with the true error xi and its derivative, [phi, tau] = Dbar^-1 (xi_dot[1,2] - Abar xi)."""
    rng = np.random.default_rng(3)
    for pt in extras["uihosmo"].points[4::8]:
        sys = case2(vehicle, pt.speed)
        At = sys.A - pt.L @ sys.C
        e = rng.normal(size=7) * np.array([0.01, 0.3, 0.1, 0.3, 0.1, 500, 500])
        zeta = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-40, 40)])
        xi_dot = pt.T @ (At @ e + sys.D @ zeta)
        rebuilt = pt.Dbar_inv @ (xi_dot[[1, 2]] - pt.Abar @ (pt.T @ e))
        assert np.allclose(rebuilt, zeta, rtol=1e-7, atol=1e-9)


def test_complement_is_continuous_in_speed(vehicle):
    rows = (1, 2, 3, 5)
    prev = None
    for v in np.arange(20, 130, 0.25):
        T2 = complement_rows(case2(vehicle, kmh(v)).D, rows)
        if prev is not None:
            assert np.abs(T2 - prev).max() < 0.02
        prev = T2


def test_lmi_solution_satisfies_the_inequalities(extras):
    sol = extras["lmi_solution"]
    assert sol.feasible
    assert np.linalg.eigvalsh(sol.P).min() > 0
    for i in (0, 1):
        assert np.linalg.eigvalsh(sol.lmi34(i)).max() < 0
        assert np.linalg.eigvalsh(sol.disk_lmi(i)).max() < 0
    assert np.linalg.eigvalsh(sol.lmi33()).min() > -1e-7
    assert sol.residual < 1e-2


def test_lmi_lipschitz_bound_holds(extras, vehicle, settings):
    sol = extras["lmi_solution"]
    from ptw_rt.design.lpv_lmi import STATE_SCALE

    S = np.diag(STATE_SCALE)
    bound = settings.estimator.stiffness_deviation_bound * np.array(vehicle.nominal_stiffness())
    for J in lipschitz_jacobians(lpv_model(vehicle), sol.speed_vertices, bound):
        Js = np.linalg.solve(S, J @ S)
        assert np.linalg.eigvalsh(sol.R - Js.T @ sol.Q @ Js).min() > -1e-6 * np.abs(sol.R).max()


def test_adaptive_gain_stabilises_every_speed_in_continuous_time(extras, vehicle, design):
    from ptw_rt.design.lpv_lmi import output_matrix, scheduled_gain

    m, C = lpv_model(vehicle), output_matrix(vehicle)
    sol = extras["lmi_solution"]
    for u in np.linspace(design.grid[0], design.grid[-1], 37):
        ev = np.linalg.eigvals(m.A(u) - scheduled_gain(sol, u) @ C)
        assert ev.real.max() < -sol.decay_rate + 1e-6
        assert np.abs(ev).max() < 2 * sol.pole_disk_radius


def test_zoh_is_exact():
    a, b, dt = -7.0, 2.0, 0.01
    Phi, Gamma = zoh(np.array([[a]]), np.array([[b]]), dt)
    assert Phi[0, 0] == pytest.approx(np.exp(a * dt), rel=1e-12)
    assert Gamma[0, 0] == pytest.approx(b * (np.exp(a * dt) - 1) / a, rel=1e-12)


def test_forward_euler_at_10ms_would_be_unstable(vehicle):
    """Why the design discretises exactly: the tyre modes at 130 km/h are faster than 2/dt."""
    A, _ = state_space(vehicle, kmh(130))
    assert spectral_radius(np.eye(8) + 0.01 * A) > 1.0
    Phi, _ = zoh(A, np.zeros((8, 1)), 0.01)
    assert spectral_radius(Phi) < 1.0


def test_interpolation_rule():
    grid = np.array([1.0, 2.0, 4.0])
    table = np.array([[0.0], [1.0], [3.0]])
    assert interpolate(grid, table, 3.0)[0] == pytest.approx(2.0)
    assert interpolate(grid, table, 0.0)[0] == 0.0 and interpolate(grid, table, 9.0)[0] == 3.0


def test_design_check_cli_json():
    proc = subprocess.run(
        [sys.executable, "-m", "ptw_rt.cli", "design", "--check", "--json"], capture_output=True, text=True
    )
    assert proc.returncode == 0, proc.stderr
    data = json.loads(proc.stdout)
    assert len(data["grid_kmh"]) == len(data["uihosmo"]["spectral_radius"]) == len(data["adaptive"]["spectral_radius"])
    assert data["adaptive"]["lmi"]["feasible"] is True
    assert {"slack", "residual"} <= set(data["adaptive"]["lmi"])
    assert data["between_grid"]["max_spectral_radius"] < 1


def test_design_cli_writes_a_loadable_file(tmp_path, settings):
    out = tmp_path / "d.npz"
    proc = subprocess.run(
        [sys.executable, "-m", "ptw_rt.cli", "design", "--out", str(out)], capture_output=True, text=True
    )
    assert proc.returncode == 0, proc.stderr
    assert load_design(out, settings.config_hash).grid.shape == (49,)


def test_a_matrix_that_overflowed_is_not_stable():
    """A decay rate of 1e6 1/s overflowed the UIHOSMO's tables to inf: the check said so with numpy's LinAlgError
    traceback (found by fuzzing, 2026-11-26); a non-finite matrix has an infinite spectral radius (not stable)."""
    assert spectral_radius(np.array([[0.5, np.inf], [0.0, 0.5]])) == math.inf
    assert spectral_radius(np.array([[np.nan]])) == math.inf
    assert spectral_radius(np.diag([0.5, -0.9])) == pytest.approx(0.9)


def _designed(doc: dict, stem):
    """`ptw-rt design` on the config `doc` (written next to `stem`): (config, design file, settings, design data,
    the command's summary), the command having succeeded."""
    cfg, out = stem.with_suffix(".yaml"), stem.with_suffix(".npz")
    cfg.write_text(yaml.safe_dump(doc))
    proc = subprocess.run(
        [sys.executable, "-m", "ptw_rt", "design", "--config", cfg, "--out", out],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    settings = load_settings(cfg)
    return cfg, out, settings, load_design(out, settings.config_hash, cfg), proc.stdout


def test_a_vehicle_whose_case_2_floor_is_above_the_validity_speed_is_designed_and_the_diagnostic_waits(tmp_path):
    """A front tyre 30 % softer than the file's lifts seed 000 case 2's detectability floor to ~76 km/h. Case 2 is
    a diagnostic: the design must not refuse the vehicle (it did), and the runtime holds case 2 in reset below its
    floor while every published estimate runs from the validity speed."""
    from ptw_rt.core import diagnostics
    from ptw_rt.core import layout as L  # noqa: N812
    from ptw_rt.eval.evaluate import evaluate_ride
    from ptw_rt.sim.ride import simulate

    doc = yaml.safe_load(DEFAULT_CONFIG.read_text())
    front = doc["vehicle"]["front_tyre"]
    front["cornering_stiffness"] *= 0.7
    front["camber_stiffness"] *= 0.7
    cfg, out, settings, data, _ = _designed(doc, tmp_path / "soft_front")
    assert data.detectability_floor * 3.6 > 60.0 > settings.estimator.min_valid_speed_kmh
    prm = diagnostics.build_params(settings, data)
    assert prm[diagnostics.P_UH_MIN_SPEED] == pytest.approx(data.detectability_floor)
    ev = evaluate_ride(simulate("urban", duration=30.0, vehicle=cfg), cfg, out)
    slow = ev.estimates[:, L.E_SPEED] < 0.9 * data.detectability_floor
    running = (ev.estimates[:, L.E_MODE] == L.MODE_VALID) & slow
    assert running.sum() > 500  # the published estimates run in town
    assert np.all(ev.estimates[running, L.E_ROLL_UIHOSMO] == 0.0)  # case 2 waits for its floor
    assert np.all(np.isfinite(ev.estimates[running, L.E_ROLL]))


def _vehicle_scaled_at_random(seed: int, spread: float) -> dict:
    """The config with every vehicle number times U(1 - spread, 1 + spread) (the scratch sweep that found it)."""
    import random

    rng = random.Random(seed)

    def walk(node):
        if isinstance(node, dict):
            # added_mass (0, and newer than the sweep) draws nothing: the vehicles stay the ones the sweep found
            return {k: (v if k in ("name", "gravity", "added_mass") else walk(v)) for k, v in node.items()}
        if isinstance(node, (int, float)) and not isinstance(node, bool):
            return node * rng.uniform(1 - spread, 1 + spread)
        return node

    doc = yaml.safe_load(DEFAULT_CONFIG.read_text())
    doc["vehicle"] = walk(doc["vehicle"])
    return doc


def test_a_vehicle_for_which_case_2_is_never_detectable_is_designed_and_estimated(tmp_path):
    """Seed 000 case 2 is a diagnostic: a vehicle for which it is not strongly detectable at any speed (3 of 12
    vehicles within +-30 % of this one) is designed all the same, case 2 never runs, and the published estimates
    are right (until 2026-11-26 `design` refused such a vehicle)."""
    from ptw_rt.core import layout as L  # noqa: N812
    from ptw_rt.design.uihosmo import NEVER_DETECTABLE
    from ptw_rt.eval.evaluate import evaluate_ride
    from ptw_rt.sim.ride import simulate

    cfg, out, settings, data, summary = _designed(_vehicle_scaled_at_random(1004, 0.3), tmp_path / "other")
    assert "case 2 not strongly detectable at any speed" in summary
    assert data.detectability_floor == NEVER_DETECTABLE and not data.uh_detectable.any()
    ev = evaluate_ride(simulate("dlc_50", vehicle=cfg), cfg, out)
    assert np.all(ev.estimates[:, L.E_ROLL_UIHOSMO] == 0.0)
    roll_err = np.degrees(ev.estimates[ev.mask, L.E_ROLL] - ev.truth["roll"][ev.mask])
    assert np.sqrt(np.mean(roll_err**2)) < 0.5


@pytest.mark.parametrize(("member", "factor"), [("ad_theta_nominal", 10.0), ("ad_theta_bound", 1e5), ("tb_scale", 1.5)])
def test_a_design_whose_hash_is_right_but_whose_bounds_are_not_is_refused(tmp_path, member, factor):
    """The nominal stiffness, its deviation bound and the tyre hypotheses bound what a state file may restore. A
    design file with the configuration's hash and those values edited passed every check, and the daemon restored
    a learned stiffness ten times the file's from a state file (found by fuzzing, 2026-12-07)."""
    from ptw_rt.design.file import DesignFileError, load_design_for
    from ptw_rt.paths import DEFAULT_CONFIG, DEFAULT_DESIGN
    from ptw_rt.settings import load_settings

    settings = load_settings(DEFAULT_CONFIG)
    with np.load(DEFAULT_DESIGN, allow_pickle=False) as shipped:
        members = {name: shipped[name] for name in shipped.files}
    load_design_for(settings, DEFAULT_DESIGN)  # the shipped one passes
    members[member] = members[member] * factor
    edited = tmp_path / "edited.npz"
    np.savez_compressed(edited, **members)
    with pytest.raises(DesignFileError, match=f"its {member} .* is not what the configuration makes"):
        load_design_for(settings, edited)


EDITED_GAINS = [
    ("kf_K", 1e3, "fusion"),
    ("tb_K_pub", -5.0, "tyre_bank"),
    ("ad_Phi", 1.2, "adaptive"),
    ("uh_Phi22", 1.5, "uihosmo"),
]


@pytest.mark.parametrize(("member", "factor", "observer"), EDITED_GAINS)
def test_a_design_whose_gains_were_edited_is_refused_at_load(tmp_path, member, factor, observer):
    """A design file with the configuration's hash and bounds but a gain edited (finite: x1000) passed every
    check, `run --check-config` included, and the estimator ran on filters that diverge. Every observer's error
    dynamics are checked stable at the grid speeds at load (numpy alone: the runtime has no scipy), as `design
    --check` checks them; the shipped design's radii are those `check_design` reports."""
    from ptw_rt.design.build import check_design
    from ptw_rt.design.file import DesignFileError, error_dynamics_radii, load_design_for
    from ptw_rt.paths import DEFAULT_CONFIG, DEFAULT_DESIGN
    from ptw_rt.settings import load_settings

    settings = load_settings(DEFAULT_CONFIG)
    shipped = load_design_for(settings, DEFAULT_DESIGN)
    radii, check = error_dynamics_radii(shipped), check_design(shipped)
    assert radii["fusion"] == pytest.approx(max(check["fusion"]["spectral_radius"]), rel=1e-9)
    assert radii["adaptive"] == pytest.approx(max(check["adaptive"]["spectral_radius"]), rel=1e-9)
    assert radii["tyre_bank"] == pytest.approx(check["tyre_bank"]["max_spectral_radius"], rel=1e-9)
    assert max(radii.values()) < 1.0
    with np.load(DEFAULT_DESIGN, allow_pickle=False) as npz:
        members = {name: npz[name] for name in npz.files}
    members[member] = members[member] * factor
    edited = tmp_path / "edited.npz"
    np.savez_compressed(edited, **members)
    with pytest.raises(DesignFileError, match=f"unstable error dynamics .*{observer} "):
        load_design_for(settings, edited)
