"""Baseline tyre-force observers (seeds 002/003) on a synthetic ride of the linear Sharp model."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg
from hypothesis import given, settings
from hypothesis import strategies as st

from ptw_rt.core.force_observers import (
    A_Y_MAX,
    RDOT_MAX,
    SMO_STATE_SIZE,
    STA_STATE_SIZE,
    lateral_yaw_constants,
    run_smo,
    run_sta,
    smo_step,
    sta_step,
)
from ptw_rt.model.parameters import load_vehicle
from ptw_rt.model.sharp import DELTA_DOT, FYF, FYR, PHI_DOT, VY, R, kmh, state_space
from ptw_rt.paths import DEFAULT_CONFIG

DT = 0.01  # the product's 100 Hz
SETTLE = 1.0  # s, ignored at the start of the ride (the manoeuvre starts at 1 s)
SIGMA_R = 2e-3  # rad/s, yaw-rate gyro noise
SIGMA_AY = 0.05  # m/s^2, lateral accelerometer noise


@pytest.fixture(scope="module")
def vehicle():
    return load_vehicle(DEFAULT_CONFIG)


@pytest.fixture(scope="module")
def geom(vehicle):
    return lateral_yaw_constants(vehicle)


# Double lane change rider torque: +pulse at 1 s, -pulse at 5 s, p(t) = sin(w t) sin^4(w t / 2) on [0, 2.5 s]
_PULSE = ((1, 5.0 / 16.0), (2, -0.25), (3, 1.0 / 16.0))


def _pulse(tt, T=2.5):
    w = 2.0 * math.pi / T
    out = np.zeros_like(tt)
    m = (tt >= 0.0) & (tt <= T)
    for h, c in _PULSE:
        out[m] += c * np.sin(h * w * tt[m])
    return out / 0.5


def simulate(vehicle, speed_kmh: float, torque: float = 15.0, duration: float = 12.0, fine: float = 0.001):
    """Linear model at constant speed, exact ZOH (scipy expm) at 1 ms; returns the 100 Hz samples and truth."""
    u = kmh(speed_kmh)
    A, B = state_space(vehicle, u)
    Md = scipy.linalg.expm(np.block([[A, B[:, None]], [np.zeros((1, 9))]]) * fine)
    Ad, Bd = Md[:8, :8], Md[:8, 8]
    tf = np.arange(int(round(duration / fine))) * fine
    tau = torque * (_pulse(tf - 1.0) - _pulse(tf - 5.0))
    X = np.zeros((tf.size, 8))
    x = np.zeros(8)
    for k in range(tf.size):
        X[k] = x
        x = Ad @ x + Bd * tau[k]
    Xd = X @ A.T + np.outer(tau, B)
    idx = np.arange(0, tf.size, int(round(DT / fine)))
    t = vehicle.mass_matrix_terms()
    M = vehicle.mass
    # lateral acceleration of the CoM in the road plane (what a transported, de-rolled IMU reads)
    a_y = Xd[:, VY] + u * X[:, R] + (t["e34"] * Xd[:, R] + t["e35"] * Xd[:, PHI_DOT] + t["e36"] * Xd[:, DELTA_DOT]) / M
    x_g = t["e34"] / M
    # the yaw-moment terms the (u, r, a_y) sub-model cannot see (docstring of force_observers)
    s = math.sin(vehicle.caster)
    eta = (
        vehicle.gyro_total * u * X[:, PHI_DOT]
        + vehicle.gyro_front * s * u * X[:, DELTA_DOT]
        - (t["e45"] - x_g * t["e35"]) * Xd[:, PHI_DOT]
        - (t["e46"] - x_g * t["e36"]) * Xd[:, DELTA_DOT]
    )
    return {
        "t": tf[idx],
        "u": u,
        "r": X[idx, R],
        "r_dot": Xd[idx, R],
        "a_y": a_y[idx],
        "eta": eta[idx],
        "F_f": X[idx, FYF],
        "F_r": X[idx, FYR],
    }


@pytest.fixture(scope="module")
def rides(vehicle):
    return {speed: simulate(vehicle, speed) for speed in (50.0, 100.0)}


def noisy(ride, scale=1.0, seed=0):
    rng = np.random.default_rng(seed)
    n = ride["t"].size
    return (
        ride["r"] + scale * SIGMA_R * rng.standard_normal(n),
        ride["a_y"] + scale * SIGMA_AY * rng.standard_normal(n),
    )


def rmse_fraction(ride, F_f, F_r):
    m = ride["t"] > SETTLE
    peak = max(np.abs(ride["F_f"]).max(), np.abs(ride["F_r"]).max())
    return (
        np.sqrt(np.mean((F_f - ride["F_f"])[m] ** 2)) / peak,
        np.sqrt(np.mean((F_r - ride["F_r"])[m] ** 2)) / peak,
    )


def hf_rms(ride, F, fc=10.0):
    """RMS of the estimate's content above fc (Hz) after the settle time: the chattering measure."""
    x = F[ride["t"] > SETTLE]
    X = np.fft.rfft(x - x.mean())
    f = np.fft.rfftfreq(x.size, DT)
    return math.sqrt(2.0 * np.sum(np.abs(X[f > fc]) ** 2)) / x.size


# ----- the sub-model ------------------------------------------------------------------------------------------


def test_sub_model_constants_and_balances(vehicle, geom, rides):
    M, I_z, a_f, a_r = geom
    t = vehicle.mass_matrix_terms()
    x_g = t["e34"] / vehicle.mass
    assert M == pytest.approx(303.31, abs=0.01)
    assert I_z == pytest.approx(t["e44"] - M * x_g**2) and abs(I_z - t["e44"]) < 0.01 * t["e44"]
    assert a_f + a_r == pytest.approx(vehicle.l_f + vehicle.l_r)
    for ride in rides.values():
        # lateral balance M a_y = F_f + F_r holds exactly in the linear model
        np.testing.assert_allclose(M * ride["a_y"], ride["F_f"] + ride["F_r"], atol=1e-9 * np.abs(ride["F_f"]).max())
        # yaw balance about the CoM, with eta the couplings listed in the module docstring
        lhs = I_z * ride["r_dot"]
        rhs = a_f * ride["F_f"] - a_r * ride["F_r"] + ride["eta"]
        np.testing.assert_allclose(lhs, rhs, atol=1e-9 * np.abs(lhs).max())
        # and eta is not small: the tyre yaw moment is a fraction of it at 100 km/h
        assert np.abs(ride["eta"]).max() > 0.5 * np.abs(a_f * ride["F_f"] - a_r * ride["F_r"]).max()


# ----- accuracy -----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("speed", [50.0, 100.0])
@pytest.mark.parametrize("observer", ["smo", "sta"])
def test_observers_reconstruct_the_tyre_forces(rides, geom, speed, observer):
    """Noisy 100 Hz samples, default gains: RMSE < 15 % of the peak force after the settle time."""
    ride = rides[speed]
    r, a_y = noisy(ride)
    run = run_smo if observer == "smo" else run_sta
    F_f, F_r = run(ride["u"], r, a_y, DT, geom)
    ef, er = rmse_fraction(ride, F_f, F_r)
    assert ef < 0.15 and er < 0.15, (ef, er)


@pytest.mark.parametrize("observer", ["smo", "sta"])
def test_observers_with_heavy_noise_stay_useful(rides, geom, observer):
    ride = rides[100.0]
    r, a_y = noisy(ride, scale=4.0, seed=3)
    run = run_smo if observer == "smo" else run_sta
    F_f, F_r = run(ride["u"], r, a_y, DT, geom)
    assert np.all(np.isfinite(F_f)) and np.all(np.isfinite(F_r))
    ef, er = rmse_fraction(ride, F_f, F_r)
    assert ef < 0.25 and er < 0.25, (ef, er)


def test_known_coupling_moment_makes_the_sta_nearly_exact(rides, geom):
    """Clean data and m_known = eta: only the half-sample ZOH lag of the yaw channel is left."""
    ride = rides[100.0]
    F_f, F_r = run_sta(ride["u"], ride["r"], ride["a_y"], DT, geom, m_known=ride["eta"])
    ef, er = rmse_fraction(ride, F_f, F_r)
    assert ef < 0.01 and er < 0.01, (ef, er)
    F_f0, F_r0 = run_sta(ride["u"], ride["r"], ride["a_y"], DT, geom)
    assert max(rmse_fraction(ride, F_f0, F_r0)) > 3.0 * max(ef, er)  # eta is the dominant error without it


# ----- chattering ---------------------------------------------------------------------------------------------


def test_sta_chatters_less_than_the_first_order_smo(rides, geom):
    """The seeds' claim, on noisy data: the STA's continuous estimate has less >10 Hz content than
    (a) the first-order SMO's equivalent injection before filtering (its direct counterpart), and
    (b) the first-order SMO discretised as in the seeds (forward Euler), even filtered and with small gains.
    """
    ride = rides[100.0]
    r, a_y = noisy(ride)
    sta = run_sta(ride["u"], r, a_y, DT, geom)
    smo_raw = run_smo(ride["u"], r, a_y, DT, geom, t_filter=0.0)
    smo_euler = run_smo(ride["u"], r, a_y, DT, geom, lam_r=1.0, lam_w=3.0, t_filter=0.1, implicit=False)
    for k in range(2):
        assert hf_rms(ride, sta[k]) < 0.8 * hf_rms(ride, smo_raw[k])
        assert hf_rms(ride, sta[k]) < 0.5 * hf_rms(ride, smo_euler[k])


def test_implicit_discretisation_removes_numerical_chattering(rides, geom):
    """Clean data: the implicit schemes add no >10 Hz content of their own; forward Euler does, at 100 Hz."""
    ride = rides[100.0]
    truth = max(hf_rms(ride, ride["F_f"]), hf_rms(ride, ride["F_r"]))
    args = (ride["u"], ride["r"], ride["a_y"], DT, geom)
    sta_i, sta_e = run_sta(*args), run_sta(*args, implicit=False)
    smo_i, smo_e = run_smo(*args), run_smo(*args, implicit=False)
    for k in range(2):
        assert hf_rms(ride, sta_i[k]) < 2.0 * truth + 0.05
        assert hf_rms(ride, smo_i[k]) < 2.0 * truth + 0.05
        assert hf_rms(ride, sta_e[k]) > 20.0 * hf_rms(ride, sta_i[k])
        assert hf_rms(ride, smo_e[k]) > 20.0 * hf_rms(ride, smo_i[k])
    # forward-Euler first-order SMO with the default gains does not recover the forces at all
    assert min(rmse_fraction(ride, *smo_e)) > 0.5
    # sub-stepping the explicit STA moves it towards the implicit one
    sta_sub = run_sta(*args, implicit=False, substeps=10)
    assert max(rmse_fraction(ride, *sta_sub)) < max(rmse_fraction(ride, *sta_e))


# ----- robustness ---------------------------------------------------------------------------------------------

ODD = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, -1.0, 1e-300, 1e300, -1e300, float("nan"), float("inf"), -float("inf")]),
    st.floats(-5.0, 5.0),
)
SAMPLE = st.tuples(ODD, ODD, ODD, st.one_of(st.just(DT), ODD), st.one_of(st.just(0.0), ODD))


@settings(max_examples=150, deadline=None)
@given(
    samples=st.lists(SAMPLE, min_size=1, max_size=50),
    implicit=st.booleans(),
    gain=st.one_of(st.just(None), ODD),
)
def test_adversarial_inputs_never_raise_and_stay_bounded(geom, samples, implicit, gain):
    M, I_z, a_f, a_r = geom
    bound = (max(a_f, a_r) * M * A_Y_MAX + I_z * RDOT_MAX) / (a_f + a_r) * (1 + 1e-12)
    xs, xt = np.zeros(SMO_STATE_SIZE), np.zeros(STA_STATE_SIZE)
    out_s, out_t = np.zeros(2), np.zeros(2)
    g1 = 10.0 if gain is None else gain
    for u, r, a_y, dt, mk in samples:
        smo_step(xs, out_s, u, r, a_y, dt, geom, g1, 15.0 if gain is None else gain, 0.04, mk, implicit)
        sta_step(xt, out_t, u, r, a_y, dt, geom, g1, g1, mk, implicit, 2)
        for out in (out_s, out_t):
            assert np.all(np.isfinite(out))
            assert np.all(np.abs(out) <= bound)
        assert np.all(np.isfinite(xs)) and np.all(np.isfinite(xt))


def test_invalid_samples_hold_the_estimate(rides, geom):
    ride = rides[100.0]
    r, a_y = noisy(ride)
    r[600:603] = np.nan
    a_y[700] = np.inf
    dt = np.full(r.size, DT)
    dt[800] = 0.0
    for run in (run_smo, run_sta):
        F_f, F_r = run(ride["u"], r, a_y, dt, geom)
        assert F_f[600] == F_f[599] and F_f[602] == F_f[599]
        assert F_r[700] == F_r[699] and F_r[800] == F_r[799]
        assert max(rmse_fraction(ride, F_f, F_r)) < 0.15
