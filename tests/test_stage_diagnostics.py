"""The diagnostics stage alone: UIHOSMO and super-twisting force observer on known signals, reset on a blow-up."""

from __future__ import annotations

import numpy as np
import pytest

from ptw_rt.core import attitude as att
from ptw_rt.core import conditioning as cnd
from ptw_rt.core import diagnostics as dia
from ptw_rt.core import inputs as inp
from ptw_rt.core import speed as spd


def _step(b, cond, u=20.0):
    attitude = att.OUTPUTS.vector({}, strict=False)
    inputs = inp.OUTPUTS.vector({"accel_ok": 1.0, "core_ok": 1.0}, strict=False)
    speed = spd.OUTPUTS.vector(
        accel_offset=0.0, accel_offset_age=0.0, gps_age=0.0, gps_doubted=0.0, gps_lost=0.0, u=u, known=1.0
    )
    dia.diagnostics_stage(b.state, b.params, b.outputs, b.tables, b.tindex, 0, inputs, speed, attitude, cond)
    return b.outputs


def test_steady_lateral_acceleration_gives_the_total_tyre_force(settings, design):
    b = dia.STAGE.alone(settings, design)
    u, a_y = 20.0, 2.0
    cond = cnd.OUTPUTS.vector({"run": 1.0, "yaw_rate": a_y / u, "a_y": a_y}, strict=False)
    for _ in range(500):
        out = _step(b, cond, u)
    mass = b.params[dia.P_GEOM]
    assert out[dia.OUT_FY_FRONT] + out[dia.OUT_FY_REAR] == pytest.approx(mass * a_y, rel=1e-3)
    assert np.isfinite(out[dia.OUT_ROLL]) and np.isfinite(out[dia.OUT_TORQUE]) and out[dia.OUT_RESET] == 0.0


def test_not_running_is_all_zero(settings, design):
    b = dia.STAGE.alone(settings, design)
    out = _step(b, cnd.OUTPUTS.vector({"run": 0.0, "a_y": 2.0}, strict=False))
    assert out[dia.OUT_ROLL] == out[dia.OUT_TORQUE] == out[dia.OUT_FY_FRONT] == out[dia.OUT_FY_REAR] == 0.0
    assert b.state[dia.ST_UH + dia.uh.INIT] == 0.0


def test_a_blown_up_uihosmo_is_reset_and_says_so(settings, design):
    b = dia.STAGE.alone(settings, design)
    cond = cnd.OUTPUTS.vector({"run": 1.0, "roll_last": 0.1, "steer": 0.01}, strict=False)
    _step(b, cond)
    b.state[dia.ST_UH : dia.ST_UH + 7] = 1e12
    out = _step(b, cond)
    assert out[dia.OUT_RESET] == 1.0
    assert out[dia.OUT_ROLL] == 0.1 and out[dia.OUT_TORQUE] == 0.0  # the last published roll stands in
    assert b.state[dia.ST_UH + dia.uh.INIT] == 0.0
    out = _step(b, cond)
    assert out[dia.OUT_RESET] == 0.0 and abs(out[dia.OUT_ROLL]) < 1.0


def test_the_uihosmo_on_the_sensors_takes_its_own_roll_not_the_attitude_filters(settings, design):
    """Issue #16's diversity: upright on the IMU, while the conditioning (the attitude filter's chain) says 0.3 rad
    of roll and 0.2 rad/s of yaw. The channel's roll, rates and a_y come from the raw IMU (core.channel_kinematics),
    so the UIHOSMO's measured roll is the IMU's 0, not the published 0.3. Of the attitude filter it takes the yaw
    gyro's and the lateral accelerometer's biases (calibrations: upright and straight they read 0.01 rad/s and
    0.1 m/s^2), never the roll-rate gyro's (0.2 here)."""
    from ptw_rt.core import channel_kinematics as ck
    from ptw_rt.core import uio_sensors as cus

    b = dia.STAGE.alone(settings, design)
    g = settings.vehicle.g
    raw = np.array([0.0, 0.0, 0.01, 0.0, 0.1, -g, 512.0, 20.0])  # the yaw gyro and accelerometer read their biases
    flags = {"accel_ok": 1.0, "accel_trusted": 1.0, "core_ok": 1.0, "imu_ok": 1.0, "rates_ok": 1.0}
    inputs = inp.OUTPUTS.vector({**flags, "raw": raw}, strict=False)
    speed = spd.OUTPUTS.vector(
        accel_offset=0.0, accel_offset_age=0.0, gps_age=0.0, gps_doubted=0.0, gps_lost=0.0, u=20.0, known=1.0
    )
    # the attitude filter: its yaw-gyro bias is taken (a calibration), its roll-rate bias is not
    attitude = att.OUTPUTS.vector({"ok": 1.0, "roll": 0.3, "bp": 0.2, "br": 0.01, "bay": 0.1}, strict=False)
    cond = cnd.OUTPUTS.vector(
        {"run": 1.0, "deroll": 0.3, "roll": 0.3, "roll_last": 0.3, "yaw_rate": 0.2, "roll_rate": 0.1, "a_y": 4.0},
        strict=False,
    )
    for _ in range(200):
        dia.diagnostics_stage(b.state, b.params, b.outputs, b.tables, b.tindex, 0, inputs, speed, attitude, cond)
    ch = b.outputs[dia.OUT_CH : dia.OUT_CH + ck.OUT_SIZE]
    us = b.outputs[dia.OUT_US : dia.OUT_US + cus.OUT_SIZE]
    assert ch[ck.OUT_VALID] == 1.0 and us[cus.OUT_VALID] == 1.0
    assert ch[ck.OUT_ROLL] == pytest.approx(0.0, abs=1e-9) and ch[ck.OUT_YAW_RATE] == 0.0
    assert ch[ck.OUT_A_Y] == pytest.approx(0.0, abs=1e-9)
    assert us[cus.OUT_ROLL] == pytest.approx(0.0, abs=1e-9)  # the measured roll it ran on
    # a held gyro value (rates not new this cycle) is not integrated: the channel holds
    inputs[inp.OUT_RATES_OK] = 0.0
    inputs[inp.OUT_RAW + inp.RAW_P] = 0.5
    before = ch.copy()
    dia.diagnostics_stage(b.state, b.params, b.outputs, b.tables, b.tindex, 0, inputs, speed, attitude, cond)
    assert np.array_equal(before, b.outputs[dia.OUT_CH : dia.OUT_CH + ck.OUT_SIZE])
