"""The diagnostics stage alone: UIHOSMO and super-twisting force observer on known signals, reset on a blow-up."""

from __future__ import annotations

import numpy as np
import pytest

from ptw_rt.core import conditioning as cnd
from ptw_rt.core import diagnostics as dia
from ptw_rt.core import inputs as inp
from ptw_rt.core import speed as spd


def _step(b, cond, u=20.0):
    inputs = inp.OUTPUTS.vector({"accel_ok": 1.0, "core_ok": 1.0}, strict=False)
    speed = spd.OUTPUTS.vector(gps_age=0.0, gps_doubted=0.0, gps_lost=0.0, u=u, known=1.0)
    dia.diagnostics_stage(b.state, b.params, b.outputs, b.tables, b.tindex, 0, inputs, speed, cond)
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
