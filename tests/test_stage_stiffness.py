"""The stiffness stage alone: frozen while not allowed, reset keeps what was learned, start values."""

from __future__ import annotations

import numpy as np
import pytest

from ptw_rt.core import adaptive as ad
from ptw_rt.core import conditioning as cnd
from ptw_rt.core import inputs as inp
from ptw_rt.core import lateral as lat
from ptw_rt.core import speed as spd
from ptw_rt.core import stiffness as stf


def _step(b, cond, run_time=10.0, gps_lost=0.0):
    inputs = inp.OUTPUTS.vector({"accel_ok": 1.0, "gps_lost": gps_lost}, strict=False)
    # a GPS lost to the inputs stage is lost to the speed stage too (its age counts fixes taken, not received)
    speed = spd.OUTPUTS.vector(
        accel_offset=0.0, accel_offset_age=0.0, gps_age=0.0, gps_doubted=0.0, gps_lost=gps_lost, u=20.0, known=1.0
    )
    lateral = lat.OUTPUTS.vector({"run_time": run_time}, strict=False)
    stf.stiffness_stage(b.state, b.params, b.outputs, b.tables, b.tindex, 0, inputs, speed, cond, lateral)
    return b.outputs


def _turning(k):
    """A weaving ride's conditioned signals (enough to excite the regressor)."""
    w = 2.0 * np.pi * 0.5 * k * 0.01
    return cnd.OUTPUTS.vector(
        {
            "run": 1.0,
            "steer": 0.01 * np.sin(w),
            "yaw_rate": 0.1 * np.sin(w),
            "roll_rate": 0.2 * np.cos(w),
            "a_y": 2.0 * np.sin(w),
            "roll": 0.2 * np.sin(w),
        },
        strict=False,
    )


def test_not_running_publishes_the_start_values(settings, design):
    b = stf.STAGE.alone(settings, design)
    out = _step(b, cnd.OUTPUTS.vector({"run": 0.0}, strict=False))
    np.testing.assert_array_equal(out[stf.OUT_STIFFNESS : stf.OUT_STIFFNESS + 4], design.ad_theta_nominal)
    assert out[stf.OUT_ROLL] == out[stf.OUT_Y_A] == out[stf.OUT_EXCITATION] == 0.0
    stf.start_from_scale(b.state, 0.8, 1.2, design)
    out = _step(b, cnd.OUTPUTS.vector({"run": 0.0}, strict=False))
    np.testing.assert_allclose(
        out[stf.OUT_STIFFNESS : stf.OUT_STIFFNESS + 4], design.ad_theta_nominal * [0.8, 0.8, 1.2, 1.2]
    )


@pytest.mark.parametrize("blocker", ["converging", "gps_lost"])
def test_no_learning_while_not_allowed(settings, design, blocker):
    b = stf.STAGE.alone(settings, design)
    kw = {"run_time": 0.5} if blocker == "converging" else {"gps_lost": 1.0}
    for k in range(500):
        out = _step(b, _turning(k), **kw)
    np.testing.assert_array_equal(out[stf.OUT_STIFFNESS : stf.OUT_STIFFNESS + 4], design.ad_theta_nominal)
    assert out[stf.OUT_EXCITATION] == 0.0 and np.all(np.isfinite(out))


def test_a_blown_up_observer_is_reset_keeping_the_stiffness(settings, design):
    b = stf.STAGE.alone(settings, design)
    stf.start_from_scale(b.state, 0.9, 1.1, design)
    _step(b, _turning(0))
    b.state[stf.ST_AD + ad.X0 : stf.ST_AD + ad.X1] = 1e12
    out = _step(b, _turning(1))
    assert out[stf.OUT_DIVERGED] == 1.0
    np.testing.assert_allclose(
        out[stf.OUT_STIFFNESS : stf.OUT_STIFFNESS + 4], design.ad_theta_nominal * [0.9, 0.9, 1.1, 1.1]
    )
    assert b.state[stf.ST_AD + ad.INIT] == 0.0
    # the next cycle starts it again, on the roll
    _step(b, _turning(2))
    assert b.state[stf.ST_AD + ad.X0 + ad.PHI] == pytest.approx(_turning(2)[cnd.OUT_ROLL])


def test_reset_keeps_the_learned_values(settings, design):
    b = stf.STAGE.alone(settings, design)
    stf.restore(b.state, design.ad_theta_nominal * 1.1, design)
    for k in range(50):
        _step(b, _turning(k))
    before = stf.learned(b.state, design)
    stf.STAGE.reset_state(b.state, b.params)
    np.testing.assert_array_equal(stf.learned(b.state, design), before)
    assert b.state[stf.ST_RESTORED] == 1.0 and b.state[stf.ST_AD + ad.INIT] == 0.0
    with pytest.raises(ValueError):
        stf.restore(b.state, [1.0, 2.0], design)
