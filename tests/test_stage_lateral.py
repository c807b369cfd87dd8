"""The lateral stage alone: the fusion filter on a straight ride, its convergence clock, reset on a blow-up."""

from __future__ import annotations

import numpy as np
import pytest

from ptw_rt.core import attitude as att
from ptw_rt.core import conditioning as cnd
from ptw_rt.core import inputs as inp
from ptw_rt.core import kalman as kf
from ptw_rt.core import lateral as lat
from ptw_rt.core import speed as spd
from ptw_rt.core import tyre_bank as tb


def _step(b, cond, accel=1.0, attitude_ok=1.0):
    inputs = inp.OUTPUTS.vector({"accel_trusted": accel}, strict=False)
    speed = spd.OUTPUTS.vector(gps_age=0.0, gps_doubted=0.0, gps_lost=0.0, u=20.0, known=1.0)
    attitude = att.OUTPUTS.vector({"ok": attitude_ok}, strict=False)
    lat.lateral_stage(b.state, b.params, b.outputs, b.tables, b.tindex, 0, inputs, speed, attitude, cond)
    return b.outputs


def test_straight_upright_ride_stays_at_zero_and_the_clock_runs(settings, design):
    b = lat.STAGE.alone(settings, design)
    cond = cnd.OUTPUTS.vector({"run": 1.0}, strict=False)
    for _ in range(200):
        out = _step(b, cond)
    z = out[lat.OUT_Z : lat.OUT_Z + kf.N_Z]
    np.testing.assert_allclose(z, 0.0, atol=1e-9)
    assert out[lat.OUT_RUN_TIME] == pytest.approx(2.0)
    # no accelerometer, no attitude filter this cycle: their rows predict themselves, nothing moves
    out = _step(b, cond, accel=0.0, attitude_ok=0.0)
    np.testing.assert_allclose(out[lat.OUT_Z : lat.OUT_Z + kf.N_Z], 0.0, atol=1e-9)
    # stopping the observers restarts the clock and zeroes everything (a diagnostic observer's reset does not:
    # the stage does not even see the diagnostics)
    out = _step(b, cnd.OUTPUTS.vector({"run": 0.0}, strict=False))
    assert out[lat.OUT_RUN_TIME] == 0.0 and not np.any(out[lat.OUT_Z : lat.OUT_Z + kf.N_Z])


def test_a_steady_roll_measurement_is_followed(settings, design):
    b = lat.STAGE.alone(settings, design)
    cond = cnd.OUTPUTS.vector({"run": 1.0, "deroll": 0.05}, strict=False)
    for _ in range(500):
        out = _step(b, cond)
    assert 0.0 < out[lat.OUT_Z + kf.PHI] <= 0.05 + 1e-6


def test_a_blown_up_filter_is_reset_and_says_so(settings, design):
    b = lat.STAGE.alone(settings, design)
    cond = cnd.OUTPUTS.vector({"run": 1.0, "roll_last": 0.1, "steer": 0.02, "yaw_rate": 0.03}, strict=False)
    _step(b, cond)
    H = len(design.tb_scale)
    for first in (0, tb._published0(H)):  # every evidence filter of the bank, or every publishing one
        state = b.state.copy()
        for h in range(H):
            b.state[lat.ST_BANK + first + h * tb.BLOCK : lat.ST_BANK + first + h * tb.BLOCK + kf.N_Z] = 1e12
        out = _step(b, cond)
        assert out[lat.OUT_DIVERGED] == 1.0
        assert out[lat.OUT_Z + kf.PHI] == 0.1 and out[lat.OUT_Z + kf.DELTA] == 0.02 and out[lat.OUT_Z + kf.TAU] == 0.0
        assert _step(b, cond)[lat.OUT_DIVERGED] == 0.0
        b.state[:] = state


def _share(b, yaw_rate_sd, a_y_of_t, u=14.0, seconds=20.0, a_y_sd=0.0):
    st = b.state.copy()
    dt = b.params[lat.P_DT]
    share = 0.0
    for k in range(int(seconds / dt)):
        share = lat._bias_share(st, b.params, yaw_rate_sd, a_y_sd, a_y_of_t(k * dt), u)
    return share


def test_no_tyre_learning_on_a_yaw_gyro_bias_the_attitude_filter_has_not_pinned_down(settings, design):
    """The slip angles are measured against the kinematic steer L r / (u cos caster): in a one-way corner a yaw
    rate 0.01 rad/s off (the attitude filter's spread in its first seconds) moves k by ~30 % per sd (it read a
    wet road's x0.9 as x1.75 and published it VALID); once the bias is known (spread 0.0006 rad/s) it does not;
    riding left and right the shift averages out of the fit."""
    b = lat.STAGE.alone(settings, design)
    limit = b.params[lat.P_MAX_LEARNING_BIAS_SHARE]
    one_way = lambda t: 1.8 + 0.6 * np.sin(2.0 * np.pi * t / 6.0)  # noqa: E731 (mu_drop's weave about a corner)
    assert _share(b, 0.01, one_way) > 2.5 * limit
    assert _share(b, 0.0006, one_way) < limit
    slalom = lambda t: 2.0 * np.sin(2.0 * np.pi * t / 3.6)  # noqa: E731
    assert _share(b, 0.005, slalom, u=8.3) < limit  # in a one-way corner at that speed: 0.25
    # an accelerometer bias the attitude filter is unsure of (0.05 m/s^2) matters in a gentle bend, not a corner
    assert _share(b, 0.0, lambda t: 0.3, a_y_sd=0.05) > limit
    assert _share(b, 0.0, one_way, a_y_sd=0.05) < limit


def test_the_tyre_evidence_count_fades_with_the_banks_memories(settings, design):
    """What the supervisor's tyre validity rests on: seconds of learning cycles, faded with the bank's learning
    memory while it learns (tau (1 - exp(-t / tau))) and with its idle memory otherwise; a restart zeroes it."""
    b = lat.STAGE.alone(settings, design)
    st, dt = b.state.copy(), b.params[lat.P_DT]
    tun = settings.estimator.tyre_bank
    for _ in range(int(round(2.0 / dt))):
        count = lat._count_evidence(st, b.params, True)
    assert count == pytest.approx(tun.learning_memory * (1.0 - np.exp(-2.0 / tun.learning_memory)), rel=1e-3)
    for _ in range(int(round(30.0 / dt))):
        faded = lat._count_evidence(st, b.params, False)
    assert faded == pytest.approx(count * np.exp(-30.0 / tun.idle_memory), rel=1e-3)
    lat.reset(st, b.params)
    assert st[lat.ST_TYRE_EVIDENCE] == 0.0
