"""The speed stage alone: GPS + accelerometer, latency compensated."""

from __future__ import annotations

import pytest

from ptw_rt.core import inputs as inp
from ptw_rt.core import speed as spd


def test_speed_from_gps_and_accelerometer(settings, design):
    b = spd.STAGE.alone(settings, design)
    dt = b.params[spd.P_DT]
    inputs = inp.OUTPUTS.vector({"accel_ok": 1.0}, strict=False)
    spd.speed_stage(b.state, b.params, b.outputs, inputs)
    assert b.outputs[spd.OUT_KNOWN] == 0.0 and b.outputs[spd.OUT_U] == 0.0  # no fix yet
    # accelerating at 1 m/s^2 from 10 m/s, the GPS reports 10 Hz fixes `latency` late
    lag = int(b.params[spd.P_LATENCY_SAMPLES])
    truth = [10.0 + k * dt for k in range(1000)]
    for k in range(1000):
        gps_new = k % 10 == 0 and k >= lag
        inputs[inp.OUT_RAW + inp.RAW_AX] = 1.0
        inputs[inp.OUT_RAW + inp.RAW_GPS_SPEED] = truth[k - lag] if gps_new else 0.0
        inputs[inp.OUT_GPS_OK] = 1.0 if (gps_new or k == 0) else 0.0
        if k == 0:
            inputs[inp.OUT_RAW + inp.RAW_GPS_SPEED] = truth[0]
        spd.speed_stage(b.state, b.params, b.outputs, inputs)
    assert b.outputs[spd.OUT_KNOWN] == 1.0
    assert b.outputs[spd.OUT_U] == pytest.approx(truth[-1], abs=0.02)
    # without the accelerometer (stale) the speed is held
    inputs[inp.OUT_ACCEL_OK] = 0.0
    inputs[inp.OUT_GPS_OK] = 0.0
    u = b.outputs[spd.OUT_U]
    spd.speed_stage(b.state, b.params, b.outputs, inputs)
    assert b.outputs[spd.OUT_U] == pytest.approx(u - dt * b.state[spd.SPD_BIAS])
