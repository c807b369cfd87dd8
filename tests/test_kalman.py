"""Fusion filter (steady-state Kalman on the torque-augmented Sharp model): design and jitted step."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import expm

from ptw_rt.core import kalman as kf
from ptw_rt.design.build import check_design
from ptw_rt.model.sharp import state_space

# the linear model itself: no nonlinear correction (zero vehicle constants make it vanish)
NO_CORRECTION = (np.zeros(7), np.zeros(kf.N_D))

DT = 0.01


@pytest.fixture(scope="module")
def design(fresh_design):
    return fresh_design[0]


def test_error_dynamics_stable_on_and_between_grid_points(design):
    """`ptw-rt design --check`'s figures: at every grid speed and at 7 interpolated speeds per interval."""
    result = check_design(design)
    radii = result["fusion"]["spectral_radius"]
    assert len(radii) == len(design.grid)
    # the slowest error modes are the gyro biases' (a time constant of about a minute): strictly inside the circle
    for radius in (max(radii), result["between_grid"]["fusion"]["max_spectral_radius"]):
        assert -DT / np.log(radius) < 120.0


def test_transition_is_the_exact_zero_order_hold(design, vehicle):
    """Phi at a grid speed is expm of the augmented model: exact, not Euler (poles faster than 1/dt)."""
    g = len(design.grid) // 2
    A, B = state_space(vehicle, float(design.grid[g]))
    Aa = np.zeros((kf.N_Z, kf.N_Z))  # torque and gyro biases: random walks (zero rows)
    Aa[:8, :8] = A
    Aa[:8, kf.TAU] = B
    np.testing.assert_allclose(design.kf_Phi[g], expm(Aa * DT), rtol=1e-9, atol=1e-12)
    # Euler would be unstable or far off here: the model is stiff at 100 Hz
    assert np.max(np.abs(np.eye(kf.N_Z) + Aa * DT - design.kf_Phi[g])) > 1e-3


def simulate_linear(design, vehicle, u: float, torque: np.ndarray, yaw_bias: float = 0.0, roll_bias: float = 0.0):
    """Exact discrete simulation of the linear model under piecewise-constant rider torque; biased gyros."""
    A, B = state_space(vehicle, u)
    Ad_B = expm(np.block([[A, B[:, None]], [np.zeros((1, 9))]]) * DT)
    Ad, Bd = Ad_B[:8, :8], Ad_B[:8, 8]
    x = np.zeros(8)
    states = []
    for tau in torque:
        states.append(x.copy())
        x = Ad @ x + Bd * tau
    X = np.array(states)
    Y = X @ design.kf_C[:, :8].T
    Y[:, 1] += yaw_bias
    Y[:, 2] += roll_bias
    return X, Y


@pytest.mark.parametrize("u_kmh", [40.0, 77.0, 100.0])
def test_reconstructs_states_and_rider_torque_on_the_linear_model(design, vehicle, u_kmh):
    """Noise-free measurements of the model it was designed on: the unknown torque converges to truth."""
    u = u_kmh / 3.6
    n = 800
    t = np.arange(n) * DT
    torque = np.where(t < 1.0, 0.0, 8.0) + 5.0 * np.sin(2 * np.pi * 0.4 * t) * (t > 3.0)
    X, Y = simulate_linear(design, vehicle, u, torque)
    state, out = kf.new_state(), np.zeros(kf.N_Z)
    est = np.zeros((n, kf.N_Z))
    for k in range(n):
        kf.kalman_step(
            state, out, Y[k], u, 0.0, design.grid, design.kf_Phi, design.kf_K, design.kf_C, design.kf_Gd, *NO_CORRECTION
        )
        est[k] = out
    late = t > 6.0
    # the filter is one cycle behind an input step at most; a smooth torque is tracked closely
    assert np.sqrt(np.mean((est[late, kf.TAU] - torque[late]) ** 2)) < 0.05 * np.max(np.abs(torque))
    for i, scale in ((kf.PHI, 0.002), (kf.VY, 0.005), (kf.FYF, 5.0), (kf.FYR, 5.0)):
        assert np.max(np.abs(est[late, i] - X[late, i])) < scale, (i, np.max(np.abs(est[late, i] - X[late, i])))


def test_starts_from_the_given_roll_and_measured_outputs(design):
    """Measurements no steady turn has (a roll rate at a constant roll, a_y half the lean's): the start settles on
    them to a finite compromise near the given roll (a consistent turn: the test below)."""
    state, out = kf.new_state(), np.zeros(kf.N_Z)
    y = np.array([0.01, 0.05, 0.02, 0.5, 0.1])
    kf.kalman_step(
        state, out, y, 20.0, 0.1, design.grid, design.kf_Phi, design.kf_K, design.kf_C, design.kf_Gd, *NO_CORRECTION
    )
    assert state[kf.INIT] == 1.0
    assert out[kf.PHI] == pytest.approx(0.1, abs=0.02)
    assert np.all(np.isfinite(out))


def test_a_start_in_a_steady_turn_begins_near_its_forces_and_torque(design, vehicle):
    """A filter (re)started in a steady turn settles on its first measurement (`kf.SETTLE_STEPS`) before its first
    step: its first estimate already has the turn's tyre forces and torque, not zero (which the torque's random
    walk took 2-3 s to work off)."""
    u = 60.0 / 3.6
    n = 600  # a constant torque held until the turn is steady (the model is stable at this speed)
    X, Y = simulate_linear(design, vehicle, u, np.full(n, 3.0))
    state, out = kf.new_state(), np.zeros(kf.N_Z)
    kf.kalman_step(
        state, out, Y[-1], u, X[-1, kf.PHI], design.grid, design.kf_Phi, design.kf_K, design.kf_C, design.kf_Gd,
        *NO_CORRECTION,
    )  # fmt: skip
    for i in (kf.FYF, kf.FYR):
        assert out[i] == pytest.approx(X[-1, i], rel=0.15), i
    assert out[kf.TAU] == pytest.approx(3.0, abs=1.0)
    assert out[kf.PHI] == pytest.approx(X[-1, kf.PHI], abs=0.005)
    assert out[kf.DELTA] == pytest.approx(X[-1, kf.DELTA], abs=1e-3)


def test_speed_outside_the_grid_is_clamped_not_extrapolated(design):
    """Speeds beyond the design range use the edge design (the supervisor flags them); never NaN."""
    for u in (0.0, -1.0, 200.0):
        state, out, y = kf.new_state(), np.zeros(kf.N_Z), np.array([0.02, 0.1, 0.0, 1.0, 0.0])
        for _ in range(300):
            kf.kalman_step(
                state,
                out,
                y,
                u,
                0.0,
                design.grid,
                design.kf_Phi,
                design.kf_K,
                design.kf_C,
                design.kf_Gd,
                *NO_CORRECTION,
            )
        assert np.all(np.isfinite(out)), u
