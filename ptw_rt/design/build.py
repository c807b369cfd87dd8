"""`ptw-rt design`: compute the whole observer design over the speed grid, check it, write it."""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from ptw_rt.design import kalman, tyre_bank, uio_sensors
from ptw_rt.design.discretize import interpolate, spectral_radius, zoh
from ptw_rt.design.file import FORMAT_VERSION, DesignData, DesignFileError, load_design_for
from ptw_rt.design.lpv_lmi import output_matrix, scheduled_gain, solve_lmis
from ptw_rt.design.uihosmo import NEVER_DETECTABLE, design_grid
from ptw_rt.errors import EXIT_USER, UserFacingError, output_error
from ptw_rt.model.sharp import lpv_model
from ptw_rt.output import emit
from ptw_rt.paths import design_file_for, own_design_file
from ptw_rt.settings import Settings, load_settings
from ptw_rt.untrusted import check_replaceable, same_file

# How many speeds to test inside each grid interval for the interpolated gains.
BETWEEN_GRID_SAMPLES = 7


class DesignInfeasibleError(UserFacingError, RuntimeError):
    pass


# what the numerics raise when a vehicle or tuning that passed the schema's ranges admits no design (a Riccati
# equation without a stabilising solution, overflow, a case that is not detectable): one line, exit 2
_NO_DESIGN = (np.linalg.LinAlgError, ArithmeticError, ValueError, MemoryError)


def make_design(settings: Settings) -> tuple[DesignData, dict[str, Any]]:
    """The design of `settings`' vehicle and tuning; `DesignInfeasibleError` (one line) when there is none."""
    try:
        with np.errstate(all="ignore"):  # a failure is reported as one line below, not as numpy's warnings
            return _make_design(settings)
    except UserFacingError:
        raise
    except _NO_DESIGN as exc:
        raise DesignInfeasibleError(
            f"{settings.source}: no design for this vehicle and tuning ({type(exc).__name__}: {exc}); "
            "check the values changed from config/scooter.yaml"
        ) from None


def _make_design(settings: Settings) -> tuple[DesignData, dict[str, Any]]:
    p, est = settings.vehicle, settings.estimator
    dt = est.sample_time
    grid = est.speed_grid_ms()

    # seed 000 case 2 is a diagnostic: below its detectability floor (unstable invariant zeros) the runtime holds it
    # in reset (ptw_rt.core.diagnostics), and a vehicle whose floor is high still gets every published estimate
    uh = design_grid(p, grid, est.uihosmo_decay_rate, est.uihosmo_output_weight, dt)

    sol = solve_lmis(
        p, (float(grid[0]), float(grid[-1])), est.decay_rate, est.stiffness_deviation_bound, est.pole_disk_radius
    )
    if not sol.feasible:
        raise DesignInfeasibleError(
            f"LMIs (33)-(34) of the adaptive observer are infeasible (solver status {sol.status}); "
            "lower estimator.adaptive.decay_rate or stiffness_deviation_bound, or widen pole_disk_radius"
        )
    model = lpv_model(p)
    C = output_matrix(p)
    ad_Phi, ad_B = [], []
    for u in grid:
        L = scheduled_gain(sol, float(u))
        Phi, Bd = zoh(model.A(u) - L @ C, np.column_stack([model.B, model.D, L]), dt)
        ad_Phi.append(Phi)
        ad_B.append(Bd)
    ad_B = np.array(ad_B)
    nominal = np.array(p.nominal_stiffness())
    kf_Phi, kf_K, kf_Gd = kalman.design_grid(p, grid, dt, est.kalman)
    bank = tyre_bank.design_bank(p, grid, dt, est.kalman, est.tyre_bank)
    us = uio_sensors.design_grid(
        p,
        grid,
        uio_sensors.CHOSEN_OUTPUTS,
        uio_sensors.CHOSEN_UNKNOWN,
        est.uihosmo_decay_rate,
        uio_sensors.CHOSEN_OUTPUT_WEIGHT,
        dt,
        uio_sensors.CHOSEN_EXTRA,
        uio_sensors.CHOSEN_INJECTION_SCALE,
    )
    data = DesignData(
        format_version=FORMAT_VERSION,
        config_hash=settings.config_hash,
        vehicle_name=p.name,
        sample_time=dt,
        grid=grid,
        min_valid_speed=est.min_valid_speed_kmh / 3.6,
        detectability_floor=uh.detectability_floor,
        uh_detectable=uh.detectable,
        uh_Phi=np.array([pt.Phi for pt in uh.points]),
        uh_Gamma=np.array([pt.Gamma for pt in uh.points]),
        uh_T=np.array([pt.T for pt in uh.points]),
        uh_T_inv=np.array([pt.T_inv for pt in uh.points]),
        uh_Abar=np.array([pt.Abar for pt in uh.points]),
        uh_Dbar_inv=np.array([pt.Dbar_inv for pt in uh.points]),
        uh_Phi22=np.array([pt.Phi22 for pt in uh.points]),
        uh_Gamma21=np.array([pt.Gamma21 for pt in uh.points]),
        uh_Ramp_y=np.array([pt.Ramp_y for pt in uh.points]),
        uh_Ramp21=np.array([pt.Ramp21 for pt in uh.points]),
        uh_complement_rows=np.array(uh.complement_rows),
        uh_differentiator_lambda=est.differentiator_lambda,
        ad_Phi=np.array(ad_Phi),
        ad_B_tau=ad_B[:, :, 0],
        ad_B_theta=ad_B[:, :, 1:3],
        ad_B_y=ad_B[:, :, 3:],
        ad_C=C,
        ad_T=sol.T_physical,
        ad_gamma=np.array(est.adaptation_gain),
        ad_theta_nominal=nominal,
        ad_theta_bound=est.stiffness_deviation_bound * nominal,
        ad_pe_threshold=np.array(
            [
                est.excitation_slip_velocity / p.sigma_f,
                est.excitation_camber_velocity / p.sigma_f,
                est.excitation_slip_velocity / p.sigma_r,
                est.excitation_camber_velocity / p.sigma_r,
            ]
        ),
        ad_pe_forgetting=float(np.exp(-dt / est.excitation_time_constant)),
        ad_L_vertices=np.array(sol.L_vertices),
        ad_speed_vertices=np.array(sol.speed_vertices),
        ad_lmi_slack=sol.slack,
        ad_lmi_residual=sol.residual,
        regressor_constants=np.array([p.sigma_f, p.sigma_r, p.l_f, p.l_r, p.caster, p.trail]),
        kf_Phi=kf_Phi,
        kf_K=kf_K,
        kf_C=kalman.output_matrix(p),
        kf_Gd=kf_Gd,
        kf_nonlinear=kalman.nonlinear_constants(p),
        **bank,
        **uio_sensors.design_fields(p, us, est.min_valid_speed_kmh / 3.6),
    )
    return data, {"lmi_solution": sol, "uihosmo": uh, "uio_sensors": us}


def uihosmo_radius(Phi: np.ndarray, Phi22: np.ndarray) -> float:
    """Spectral radius of the block-triangular linear error dynamics (pre-observer, zero dynamics)."""
    return max(spectral_radius(Phi), spectral_radius(Phi22))


def check_design(data: DesignData) -> dict[str, Any]:
    """Spectral radii of each observer's discrete error dynamics at and between grid speeds."""
    grid = data.grid
    uh_rho = [uihosmo_radius(data.uh_Phi[i], data.uh_Phi22[i]) for i in range(len(grid))]
    us_rho = [uihosmo_radius(data.us_Phi[i], data.us_Phi22[i]) for i in range(len(grid))]
    ad_rho = [spectral_radius(data.ad_Phi[i]) for i in range(len(grid))]
    kf_rho = [spectral_radius(kalman.error_dynamics(data.kf_Phi[i], data.kf_K[i], data.kf_C)) for i in range(len(grid))]
    worst = {"uihosmo": 0.0, "adaptive": 0.0, "fusion": 0.0, "uio_sensors": 0.0}
    worst_at = {"uihosmo": None, "adaptive": None, "fusion": None, "uio_sensors": None}
    for i in range(len(grid) - 1):
        for w in np.linspace(0.0, 1.0, BETWEEN_GRID_SAMPLES + 2)[1:-1]:
            u = (1 - w) * grid[i] + w * grid[i + 1]
            r_uh = uihosmo_radius(interpolate(grid, data.uh_Phi, u), interpolate(grid, data.uh_Phi22, u))
            r_ad = spectral_radius(interpolate(grid, data.ad_Phi, u))
            r_us = uihosmo_radius(interpolate(grid, data.us_Phi, u), interpolate(grid, data.us_Phi22, u))
            r_kf = spectral_radius(
                kalman.error_dynamics(interpolate(grid, data.kf_Phi, u), interpolate(grid, data.kf_K, u), data.kf_C)
            )
            for key, r in (("uihosmo", r_uh), ("adaptive", r_ad), ("fusion", r_kf), ("uio_sensors", r_us)):
                if r > worst[key]:
                    worst[key], worst_at[key] = r, u
    feasible = bool(math.isfinite(data.ad_lmi_slack))
    result = {
        "grid_kmh": [round(float(u) * 3.6, 6) for u in grid],
        "uihosmo": {
            "spectral_radius": uh_rho,
            "detectable": [bool(d) for d in data.uh_detectable],
            "detectability_floor_kmh": data.detectability_floor * 3.6,
            "min_valid_speed_kmh": data.min_valid_speed * 3.6,
        },
        "adaptive": {
            "spectral_radius": ad_rho,
            "lmi": {"feasible": feasible, "slack": data.ad_lmi_slack, "residual": data.ad_lmi_residual},
        },
        "fusion": {"spectral_radius": kf_rho},
        "uio_sensors": {
            "spectral_radius": us_rho,
            "outputs": [uio_sensors.OUTPUT_NAMES[int(c)] for c in data.us_outputs],
            "observed": [uio_sensors.OUTPUT_NAMES[int(c)] for c in data.us_observed],
            "unknown_inputs": "tau (roll measured)" if data.us_roll_input else "phi, tau",
            "detectability_floor_kmh": data.us_detectability_floor * 3.6,
            "min_valid_speed_kmh": data.us_min_valid_speed * 3.6,
        },
        "between_grid": {
            "max_spectral_radius": max(worst.values()),
            "uihosmo": {"max_spectral_radius": worst["uihosmo"], "at_kmh": worst_at["uihosmo"] * 3.6},
            "adaptive": {"max_spectral_radius": worst["adaptive"], "at_kmh": worst_at["adaptive"] * 3.6},
            "fusion": {"max_spectral_radius": worst["fusion"], "at_kmh": worst_at["fusion"] * 3.6},
            "uio_sensors": {"max_spectral_radius": worst["uio_sensors"], "at_kmh": worst_at["uio_sensors"] * 3.6},
            "samples_per_interval": BETWEEN_GRID_SAMPLES,
        },
    }
    tb_grid, tb_between = tyre_bank.bank_spectral_radii(data, grid, BETWEEN_GRID_SAMPLES)
    result["tyre_bank"] = {
        "scales": [round(float(k), 4) for k in data.tb_scale],
        "max_spectral_radius": tb_grid,
        "between_grid_max_spectral_radius": tb_between,
    }
    result["stable"] = bool(
        tb_grid < 1.0
        and tb_between < 1.0
        and feasible
        and max(uh_rho) < 1.0
        and max(ad_rho) < 1.0
        and max(kf_rho) < 1.0
        and max(us_rho) < 1.0
        and result["between_grid"]["max_spectral_radius"] < 1.0
    )
    return result


def format_check(result: dict[str, Any]) -> str:
    lines = [
        f"{'speed [km/h]':>12} {'UIHOSMO rho':>12} {'detectable':>10} {'adaptive rho':>13} {'fusion rho':>11}"
        f" {'UIO-sensors rho':>16}"
    ]
    uh, ad, kf, us = result["uihosmo"], result["adaptive"], result["fusion"], result["uio_sensors"]
    rows = zip(
        result["grid_kmh"],
        uh["spectral_radius"],
        uh["detectable"],
        ad["spectral_radius"],
        kf["spectral_radius"],
        us["spectral_radius"],
        strict=True,
    )
    for v, r1, d, r2, r3, r4 in rows:
        lines.append(f"{v:12.1f} {r1:12.4f} {'yes' if d else 'NO':>10} {r2:13.4f} {r3:11.4f} {r4:16.4f}")
    bg = result["between_grid"]
    lmi = ad["lmi"]
    lines += [
        (
            f"case 2 strongly detectable above {uh['detectability_floor_kmh']:.1f} km/h (held in reset below: a "
            "diagnostic)"
            if uh["detectability_floor_kmh"] < NEVER_DETECTABLE * 3.6
            else "case 2 not strongly detectable at any speed for this vehicle (never run: a diagnostic)"
        )
        + f"; estimates valid above {uh['min_valid_speed_kmh']:.1f} km/h",
        f"between grid points ({bg['samples_per_interval']} per interval, interpolated gains): max rho "
        f"UIHOSMO {bg['uihosmo']['max_spectral_radius']:.4f} at {bg['uihosmo']['at_kmh']:.1f} km/h, "
        f"adaptive {bg['adaptive']['max_spectral_radius']:.4f} at {bg['adaptive']['at_kmh']:.1f} km/h, "
        f"fusion {bg['fusion']['max_spectral_radius']:.4f} at {bg['fusion']['at_kmh']:.1f} km/h, "
        f"UIO-sensors {bg['uio_sensors']['max_spectral_radius']:.4f} at {bg['uio_sensors']['at_kmh']:.1f} km/h",
        f"UIHOSMO on the sensors: reconstruction outputs {'+'.join(us['outputs'])}, pre-observer "
        f"{'+'.join(us['observed'])}, unknown inputs {us['unknown_inputs']}; zero dynamics stable above "
        f"{us['detectability_floor_kmh']:.1f} km/h, valid above {us['min_valid_speed_kmh']:.1f} km/h",
        f"tyre bank: {len(result['tyre_bank']['scales'])} hypotheses (an evidence and a publishing filter each, "
        f"and two balance filters) for tyres x "
        f"{result['tyre_bank']['scales'][0]:g}..{result['tyre_bank']['scales'][-1]:g}: max rho "
        f"{result['tyre_bank']['max_spectral_radius']:.4f} at grid speeds, "
        f"{result['tyre_bank']['between_grid_max_spectral_radius']:.4f} between them",
        f"LMI feasible: {lmi['feasible']}, slack {lmi['slack']:.3g}, ||D^T P - T C|| {lmi['residual']:.3g}",
        "STABLE at and between every grid speed" if result["stable"] else "NOT STABLE: see the rows above",
    ]
    return "\n".join(lines)


def run_design(args) -> int:
    settings = load_settings(args.config)
    if args.check:
        path = args.design_file or (design_file_for(args.config) if args.out is None else args.out)
        if Path(path).exists():
            try:
                data = load_design_for(settings, path, args.config)
            except DesignFileError as exc:  # a design file to fix first, as `run` and `evaluate` say (exit 2)
                print(f"ptw-rt design --check: {exc}", file=sys.stderr)
                return EXIT_USER
            source = str(path)
        else:
            data, _ = make_design(settings)
            source = "fresh design (no design file at " + str(path) + ")"
        result = check_design(data)
        result["design_source"] = source
        emit(result, args.json, f"Design check of {source}\n" + format_check(result))
        return 0 if result["stable"] else 1
    out = args.out or own_design_file(args.config)
    if same_file(out, args.config):
        raise UserFacingError(f"--out {out} is the configuration it is designed from: name the design file")
    try:
        check_replaceable(out)  # before the minutes of designing
    except OSError as exc:
        raise output_error(out, exc) from None
    data, _ = make_design(settings)
    result = check_design(data)
    if not result["stable"]:
        print(format_check(result), file=sys.stderr)
        print("ptw-rt design: the design is not stable; nothing written", file=sys.stderr)
        return 1
    try:
        data.save(out)
    except OSError as exc:  # a directory, a device, a full disk: one line, exit 74
        raise output_error(out, exc) from None
    print(
        f"wrote {out} ({len(data.grid)} grid speeds {data.grid[0] * 3.6:.1f}-{data.grid[-1] * 3.6:.1f} km/h, "
        f"config hash {data.config_hash[:12]})"
    )
    print(format_check(result))
    return 0
