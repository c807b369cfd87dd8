"""The simulated rider's numpy-only design: Riccati, matrix exponential, closed-loop stability, preview."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg

from ptw_rt.sim.rider import (
    N_AUG,
    Z_EPSI,
    Z_EY,
    Z_TAU,
    RiderConfig,
    augmented,
    care,
    design_schedule,
    expm,
    steady_per_curvature,
    weights,
)


@pytest.mark.parametrize("u", [2.5, 8.0, 20.0, 38.0])
def test_care_matches_scipy(vehicle, u):
    cfg = RiderConfig()
    A, B = augmented(vehicle, u, cfg.neuromuscular_lag)
    Q, R = weights(cfg)
    P = care(A, B, Q, R)
    P_ref = scipy.linalg.solve_continuous_are(A, B, Q, R)
    assert np.abs(P - P_ref).max() <= 1e-8 * np.abs(P_ref).max()


def test_expm_matches_scipy(vehicle):
    A, _ = augmented(vehicle, 30.0, 0.04)
    for t in (1e-3, 0.05, 0.7):
        ref = scipy.linalg.expm(A * t)
        assert np.abs(expm(A * t) - ref).max() <= 1e-7 * np.abs(ref).max()


def test_schedule_stabilises_the_linear_model_over_the_whole_grid(vehicle):
    sch = design_schedule(vehicle)
    assert sch.speeds[0] <= 15 / 3.6 and sch.speeds[-1] >= 130 / 3.6
    assert np.all(sch.closed_loop_max_real < -0.05)
    # also between grid points, with linearly interpolated gains
    cfg = RiderConfig()
    for u in (3.3, 4.17, 13.9, 27.8, 36.1):
        g = np.interp(u, sch.speeds, np.arange(len(sch.speeds)))
        i = int(g)
        K = (1 - (g - i)) * sch.gains[i] + (g - i) * sch.gains[min(i + 1, len(sch.speeds) - 1)]
        A, B = augmented(vehicle, u, cfg.neuromuscular_lag)
        assert np.linalg.eigvals(A - B @ K[None, :]).real.max() < -0.05


def test_steady_turn_per_curvature_is_an_equilibrium(vehicle):
    """N kappa with the path states is an equilibrium of the linear path-augmented model under tau = N_tau kappa."""
    for u in (5.0, 15.0, 30.0):
        A, B = augmented(vehicle, u, 0.04)
        N = steady_per_curvature(vehicle, u)
        kappa = 1 / 100.0
        z = N * kappa
        dz = A @ z + B[:, 0] * z[Z_TAU]  # commanded torque = steady torque; e_psi' gets -u kappa
        dz[Z_EPSI] -= u * kappa
        assert np.abs(dz[:Z_EY]).max() < 1e-9
        assert abs(dz[Z_EY]) < 1e-12 and abs(dz[Z_EPSI]) < 1e-12
        assert z[3] == pytest.approx(u * kappa)  # yaw rate
        assert len(z) == N_AUG


def test_preview_gains_decay_over_the_horizon(vehicle):
    sch = design_schedule(vehicle)
    tail = np.abs(sch.preview[:, -5:]).max(axis=1)
    head = np.abs(sch.preview).max(axis=1)
    assert np.all(tail < 0.05 * head)


def test_lean_schedule_is_the_linear_design_upright_and_stable_at_lean(vehicle):
    from ptw_rt.sim.plant import PlantConfig
    from ptw_rt.sim.rider import design_lean_schedule

    cfg = RiderConfig()
    lean = design_lean_schedule(PlantConfig(vehicle), cfg, 1.0)
    lin = design_schedule(vehicle, cfg)
    for i, u in enumerate(lean.speeds):
        j = int(np.argmin(np.abs(lin.speeds - u)))
        if abs(lin.speeds[j] - u) < 1e-9:
            np.testing.assert_allclose(lean.gains[i, 0], lin.gains[j], rtol=2e-3, atol=1e-3)
    # every feasible node: closed loop (on the plant linearised there) stable
    assert np.all(lean.closed_loop_max_real[lean.feasible] < -0.05)
    # steady turns exist up to at least 30 deg from 30 km/h on (mu = 1)
    fast = lean.speeds >= 30 / 3.6
    assert np.all(lean.feasible[fast][:, lean.leans <= np.radians(30.01)])
    # trims: yaw rate grows with lean at every speed; roll of the trim is the grid's
    assert np.all(np.diff(lean.trims[:, :, 3], axis=1) > 0)
    np.testing.assert_allclose(
        lean.trims[:, :, 0][lean.feasible], np.broadcast_to(lean.leans, lean.feasible.shape)[lean.feasible]
    )
