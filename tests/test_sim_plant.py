"""The simulator's nonlinear plant: agreement with the linear model, tyre law, robustness at standstill."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.linalg import expm

from ptw_rt.model.sharp import state_space
from ptw_rt.sim.plant import NAUX, NX, PHI, PlantConfig, U, pack, rhs, simulate_open_loop
from ptw_rt.sim.tyres import TyreShape, lateral_force

# Small-amplitude agreement: every lateral state of the nonlinear plant stays within this fraction
# of that state's peak from the linear model's exact (ZOH) solution (measured: ~6e-5).
LINEAR_AGREEMENT_TOL = 0.01


@pytest.mark.parametrize("kmh", [60.0, 100.0])
def test_small_amplitude_agrees_with_linear_model(vehicle, kmh):
    u = kmh / 3.6
    dt, n = 1e-3, 4000
    tau = np.zeros(n)
    tau[100:200] = 1.0  # 1 N m for 0.1 s: roll stays below ~0.3 deg
    x0 = np.zeros(NX)
    x0[U] = u
    nl = simulate_open_loop(PlantConfig(vehicle, hold_speed=True), x0, tau, dt)
    A, B = state_space(vehicle, u)
    Ad = expm(A * dt)
    Bd = np.linalg.solve(A, (Ad - np.eye(8)) @ B)
    lin = np.zeros((n + 1, 8))
    for k in range(n):
        lin[k + 1] = Ad @ lin[k] + Bd * tau[k]
    peak = np.abs(lin).max(axis=0)
    err = np.abs(nl[:, :8] - lin).max(axis=0)
    assert np.abs(nl[:, PHI]).max() < math.radians(0.5)
    assert np.all(err <= LINEAR_AGREEMENT_TOL * peak), err / peak


def test_large_amplitude_is_not_linear(vehicle):
    """The plant must be nonlinear: a big torque pulse departs from the linear prediction."""
    u = 60 / 3.6
    dt, n = 1e-3, 1500
    tau = np.zeros(n)
    tau[100:400] = -40.0
    x0 = np.zeros(NX)
    x0[U] = u
    nl = simulate_open_loop(PlantConfig(vehicle, hold_speed=True), x0, tau, dt)
    A, B = state_space(vehicle, u)
    Ad = expm(A * dt)
    Bd = np.linalg.solve(A, (Ad - np.eye(8)) @ B)
    lin = np.zeros((n + 1, 8))
    for k in range(n):
        lin[k + 1] = Ad @ lin[k] + Bd * tau[k]
    k_end = 1000  # 0.6 s after the pulse: ~15 deg of roll in the linear model
    assert abs(lin[k_end, PHI]) > math.radians(10)
    assert abs(nl[k_end, PHI] - lin[k_end, PHI]) > 0.2 * abs(lin[k_end, PHI])


@pytest.mark.parametrize("mu", [1.0, 0.9, 0.5])
@pytest.mark.parametrize(("c_alpha", "c_gamma", "fz"), [(22486.0, 1064.0, 1817.7), (20178.0, 644.0, 1157.8)])
def test_tyre_small_slip_slopes_are_mu_times_stiffness(mu, c_alpha, c_gamma, fz):
    shape = TyreShape()
    args = (mu, fz, c_alpha, c_gamma, shape.slip_shape, shape.camber_shape, shape.min_mu)
    h = 1e-7
    slope_a = (lateral_force(h, 0.0, *args)[0] - lateral_force(-h, 0.0, *args)[0]) / (2 * h)
    slope_g = (lateral_force(0.0, h, *args)[0] - lateral_force(0.0, -h, *args)[0]) / (2 * h)
    assert slope_a == pytest.approx(mu * c_alpha, rel=1e-6)
    assert slope_g == pytest.approx(mu * c_gamma, rel=1e-6)
    alphas = np.linspace(-1.0, 1.0, 2001)
    forces = np.array([lateral_force(a, 0.0, *args)[0] for a in alphas])
    assert forces.max() == pytest.approx(mu * fz, rel=1e-3)  # the peak is mu F_z
    assert np.all(np.sign(forces[alphas > 0]) > 0)  # never pushes the wrong way
    np.testing.assert_allclose(forces, -forces[::-1], atol=1e-9)  # odd
    # camber thrust plus slip never exceeds the friction limit
    combo = [lateral_force(a, g, *args)[0] for a in (0.1, 0.3) for g in (0.5, 1.0)]
    assert max(combo) <= mu * fz * (1 + 1e-12)


@settings(max_examples=200, deadline=None)
@given(
    st.floats(-1.2, 1.2),
    st.floats(-1.5, 1.5),
    st.floats(-5, 5),
    st.floats(-3, 3),
    st.floats(-5, 5),
    st.floats(-20, 20),
    st.floats(-3000, 3000),
    st.floats(-3000, 3000),
    st.floats(0.0, 40.0),
    st.floats(-100, 100),
    st.floats(-3000, 3000),
    st.floats(0.0, 1.2),
)
def test_rhs_is_finite_everywhere_including_standstill(vehicle, phi, delta, vy, r, p, dd, ff, fr, u, tau, fx, mu):
    pp, m4 = pack(PlantConfig(vehicle))
    x = np.array([phi, delta, vy, r, p, dd, ff, fr, u, 0.3, 1.0, 2.0])
    dx = np.zeros(NX)
    aux = np.zeros(NAUX)
    rhs(x, tau, fx, mu, pp, m4, dx, aux)
    assert np.all(np.isfinite(dx)) and np.all(np.isfinite(aux))
    if u == 0.0:
        assert dx[U] >= 0.0  # braking never reverses


def test_standstill_is_upright_and_still(vehicle):
    """At u = 0 the feet hold the roll, the tyres damp sliding: lateral states die out (bars held straight)."""
    x0 = np.zeros(NX)
    x0[PHI] = math.radians(8)
    x0[2] = 0.3  # lateral velocity
    x0[3] = 0.2  # yaw rate
    n = 6000
    # the rider holds the brake and the bars straight: tau = -250 delta - 15 delta_dot, step by step
    cfg = PlantConfig(vehicle)
    x = x0.copy()
    for _ in range(n // 10):
        tau = -250.0 * x[1] - 15.0 * x[5]
        out = simulate_open_loop(cfg, x, np.full(10, tau), fx=np.full(10, -900.0))
        x = out[-1]
    assert np.all(np.isfinite(x))
    assert abs(x[PHI]) < math.radians(0.1)
    assert np.abs(x[1:8]).max() < 1e-2
    assert x[U] < 1e-3
