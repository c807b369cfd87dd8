"""The conditioning stage alone: steer angle, a_y at the centre of mass, observers on/off, the published roll."""

from __future__ import annotations

import math

import pytest

from ptw_rt.core import attitude as att
from ptw_rt.core import conditioning as cnd
from ptw_rt.core import inputs as inp
from ptw_rt.core import layout as lay
from ptw_rt.core import speed as spd

G = 9.81


def _inputs(p=0.0, q=0.0, r=0.0, f_y=0.0, f_z=-G, steer=512.0, reasons=0):
    return inp.OUTPUTS.vector(
        {"raw": [p, q, r, 0.0, f_y, f_z, steer, 0.0], "core_ok": 1.0, "reasons": reasons}, strict=False
    )


def _step(b, inputs, speed, attitude, imu_age=0.0, zero_error=0.0, zero_error_sd=math.inf):
    s = lay.new_sample()
    s[lay.S_IMU_AGE] = imu_age
    cnd.conditioning_stage(s, b.state, b.params, b.outputs, inputs, speed, attitude, zero_error, zero_error_sd)
    return b.outputs


def test_without_the_attitude_filter_the_roll_is_pulled_to_the_kinematic_roll(settings, design):
    b = cnd.STAGE.alone(settings, design)
    u, r = 20.0, 0.05
    speed = spd.OUTPUTS.vector(
        accel_offset=0.0, accel_offset_age=0.0, gps_age=0.0, gps_doubted=0.0, gps_lost=0.0, u=u, known=1.0
    )
    no_attitude = att.OUTPUTS.vector({}, strict=False)
    steps = int(10.0 / b.params[cnd.P_FUSION_RATE] / b.params[cnd.P_DT])  # ten time constants
    for _ in range(steps):
        roll = b.outputs[cnd.OUT_ROLL]
        out = _step(b, _inputs(q=r * math.sin(roll), r=r * math.cos(roll)), speed, no_attitude)
    roll_kin = math.atan(u * r / G)
    assert out[cnd.OUT_ROLL] == pytest.approx(roll_kin, abs=1e-3)
    assert out[cnd.OUT_ROLL_KIN] == pytest.approx(roll_kin, abs=1e-4)
    assert out[cnd.OUT_YAW_RATE] == pytest.approx(r, abs=1e-6)
    assert out[cnd.OUT_RUN] == 1.0 and out[cnd.OUT_SPEED_LOW] == 0.0 and out[cnd.OUT_DIVERGED] == 0.0


def test_with_the_attitude_filter(settings, design):
    b = cnd.STAGE.alone(settings, design)
    roll, p, r = 0.2, 0.1, 0.05
    attitude = att.OUTPUTS.vector({"ok": 1.0, "roll": roll, "roll_rate": p, "yaw_rate": r, "bay": 0.1}, strict=False)
    speed = spd.OUTPUTS.vector(
        accel_offset=0.0, accel_offset_age=0.0, gps_age=0.0, gps_doubted=0.0, gps_lost=0.0, u=20.0, known=1.0
    )
    f_y, f_z = 1.0, -9.0
    for _ in range(300):  # the derivative filters settle on constant rates
        out = _step(b, _inputs(steer=522.0, f_y=f_y, f_z=f_z), speed, attitude, imu_age=0.004)
    assert out[cnd.OUT_DEROLL] == roll and out[cnd.OUT_ROLL_RATE] == p and out[cnd.OUT_YAW_RATE] == r
    assert out[cnd.OUT_ROLL] == pytest.approx(roll + p * 0.004)  # carried to the cycle's time
    assert out[cnd.OUT_STEER] == pytest.approx(10 * 2 * math.pi / 1024)
    assert out[cnd.OUT_YAW_ACCEL] == pytest.approx(0.0, abs=1e-9)
    # constant rates: a_y at the CoM is the horizontal specific force, bias removed
    assert out[cnd.OUT_A_Y] == pytest.approx((f_y - 0.1) * math.cos(roll) - f_z * math.sin(roll), abs=1e-9)
    # an implausible roll is replaced by the kinematic one and reported
    attitude[att.OUT_ROLL] = 3.0
    out = _step(b, _inputs(), speed, attitude)
    assert out[cnd.OUT_DIVERGED] == 1.0 and out[cnd.OUT_ROLL] == out[cnd.OUT_ROLL_KIN]
    assert out[cnd.OUT_ROLL_LAST] == pytest.approx(roll + p * 0.004)


def test_low_speed_or_a_missing_core_sensor_stops_the_observers(settings, design):
    b = cnd.STAGE.alone(settings, design)
    attitude = att.OUTPUTS.vector({"ok": 1.0}, strict=False)
    out = _step(
        b,
        _inputs(),
        spd.OUTPUTS.vector(
            accel_offset=0.0, accel_offset_age=0.0, gps_age=0.0, gps_doubted=0.0, gps_lost=0.0, u=2.0, known=1.0
        ),
        attitude,
    )
    assert out[cnd.OUT_SPEED_LOW] == 1.0 and out[cnd.OUT_RUN] == 0.0
    assert int(out[cnd.OUT_REASONS]) == lay.REASON_SPEED_LOW
    out = _step(
        b,
        _inputs(reasons=lay.REASON_STALE),
        spd.OUTPUTS.vector(
            accel_offset=0.0, accel_offset_age=0.0, gps_age=0.0, gps_doubted=0.0, gps_lost=0.0, u=20.0, known=0.0
        ),
        attitude,
    )
    assert out[cnd.OUT_SPEED_LOW] == 1.0  # speed not known yet
    inputs = _inputs()
    inputs[inp.OUT_CORE_OK] = 0.0
    out = _step(
        b,
        inputs,
        spd.OUTPUTS.vector(
            accel_offset=0.0, accel_offset_age=0.0, gps_age=0.0, gps_doubted=0.0, gps_lost=0.0, u=20.0, known=1.0
        ),
        attitude,
    )
    assert out[cnd.OUT_SPEED_LOW] == 0.0 and out[cnd.OUT_RUN] == 0.0


def test_a_speed_that_has_taken_no_fix_for_the_hold_time_is_gps_lost(settings, design):
    """Fixes arrive (the inputs stage sees them fresh) but the speed stage takes none (a doubted receiver)."""
    b = cnd.STAGE.alone(settings, design)
    attitude = att.OUTPUTS.vector({"ok": 1.0}, strict=False)
    speed = spd.OUTPUTS.vector(
        accel_offset=0.0, accel_offset_age=0.0, gps_age=1.5, gps_doubted=1.0, gps_lost=1.0, u=20.0, known=1.0
    )
    out = _step(b, _inputs(), speed, attitude)
    assert int(out[cnd.OUT_REASONS]) == lay.REASON_GPS_LOST and out[cnd.OUT_RUN] == 1.0
    speed[spd.OUT_GPS_LOST] = 0.0
    assert int(_step(b, _inputs(), speed, attitude)[cnd.OUT_REASONS]) == 0


COUNT = 2 * math.pi / 1024


def _learn(b, steer, r=0.0, f_y=0.0, u=20.0, reasons=0, seconds=50.0):
    attitude = att.OUTPUTS.vector({"ok": 1.0, "yaw_rate": r}, strict=False)
    speed = spd.OUTPUTS.vector(
        accel_offset=0.0, accel_offset_age=0.0, gps_age=0.0, gps_doubted=0.0, gps_lost=0.0, u=u, known=1.0
    )
    inputs = _inputs(r=r, f_y=f_y, steer=steer, reasons=reasons)
    inputs[inp.OUT_ACCEL_OK] = 1.0
    cycles = int(seconds / b.params[cnd.P_DT])
    for _ in range(cycles):
        out = _step(b, inputs, speed, attitude)
    return out


@pytest.fixture
def learner(settings, design):
    assert settings.sensors.steer_zero_time_constant == 10.0  # _learn's 50 s: five time constants
    return cnd.STAGE.alone(settings, design)


def test_the_steer_zero_is_learned_riding_straight(learner):
    """A calibration a count off (the encoder reads 513 straight ahead): riding straight the steer angle is the
    kinematic L r / (u cos caster) ~ 0, so after five time constants the learned zero error is the count and the
    published steer angle is straight ahead again."""
    out = _learn(learner, steer=513.0)
    assert out[cnd.OUT_STEER_ZERO_SHIFT] == pytest.approx(COUNT, rel=0.01)
    assert out[cnd.OUT_STEER] == pytest.approx(0.0, abs=0.01 * COUNT)
    # a restart of the estimator keeps the calibration
    cnd.STAGE.reset_state(learner.state, learner.params)
    assert learner.state[cnd.ST_STEER_ZERO_SHIFT] == pytest.approx(COUNT, rel=0.01)


def test_the_steer_zero_is_not_learned_in_a_corner_or_from_flagged_input(learner):
    out = _learn(learner, steer=515.0, r=0.1, f_y=2.0)  # a corner: the steer angle is the corner's
    assert out[cnd.OUT_STEER_ZERO_SHIFT] == 0.0
    out = _learn(learner, steer=513.0, reasons=lay.REASON_OUT_OF_RANGE)
    assert out[cnd.OUT_STEER_ZERO_SHIFT] == 0.0
    out = _learn(learner, steer=513.0, u=3.0)  # too slow: the rider balances with the handlebar
    assert out[cnd.OUT_STEER_ZERO_SHIFT] == 0.0


def test_the_learned_steer_zero_is_bounded(learner, settings):
    """An encoder that slipped by 4 counts is not re-zeroed: the shift stops at its bound and what is left stays
    visible to the steer check."""
    out = _learn(learner, steer=516.0, seconds=200.0)
    assert out[cnd.OUT_STEER_ZERO_SHIFT] == pytest.approx(settings.sensors.steer_zero_max_shift * COUNT)
    assert out[cnd.OUT_STEER] == pytest.approx((4.0 - settings.sensors.steer_zero_max_shift) * COUNT)


def test_the_steer_zero_follows_the_tyre_banks_evidence_once_it_is_known(learner, settings):
    """In a corner (nothing learned riding straight) the zero moves by the error the tyre bank's zero check points
    to, with its time constant, only while that error's sd is within the check's valid spread, and within its
    bound; a non-finite error (the bank did not run) moves nothing."""
    attitude = att.OUTPUTS.vector({"ok": 1.0, "yaw_rate": 0.1}, strict=False)
    speed = spd.OUTPUTS.vector(
        accel_offset=0.0, accel_offset_age=0.0, gps_age=0.0, gps_doubted=0.0, gps_lost=0.0, u=20.0, known=1.0
    )
    inputs = _inputs(r=0.1, f_y=2.0, steer=515.0)
    known = 0.5 * settings.estimator.tyre_bank.valid_zero_sd * COUNT
    for sd in (2.0 * settings.estimator.tyre_bank.valid_zero_sd * COUNT, math.inf, math.nan):
        out = _step(learner, inputs, speed, attitude, zero_error=0.5 * COUNT, zero_error_sd=sd)
        assert out[cnd.OUT_STEER_ZERO_SHIFT] == 0.0
    out = _step(learner, inputs, speed, attitude, zero_error=math.nan, zero_error_sd=known)
    assert out[cnd.OUT_STEER_ZERO_SHIFT] == 0.0
    time_constant = settings.sensors.steer_zero_evidence_time_constant
    cycles = int(time_constant / learner.params[cnd.P_DT])
    for _ in range(cycles):  # the bank re-centres on the moved zero: the error left shrinks as the zero moves
        left = 0.5 * COUNT - learner.state[cnd.ST_STEER_ZERO_SHIFT]
        out = _step(learner, inputs, speed, attitude, zero_error=left, zero_error_sd=known)
    assert out[cnd.OUT_STEER_ZERO_SHIFT] == pytest.approx(0.5 * COUNT * (1.0 - math.exp(-1.0)), rel=0.01)
    for _ in range(3 * cycles):
        out = _step(learner, inputs, speed, attitude, zero_error=10.0 * COUNT, zero_error_sd=known)
    assert out[cnd.OUT_STEER_ZERO_SHIFT] == pytest.approx(settings.sensors.steer_zero_max_shift * COUNT)


def test_the_steer_zeros_spread_shrinks_as_it_is_learned_riding_straight(learner, settings):
    """What the tyre bank's zero check assumes of the zero a priori: the configured sd at first, its share
    exp(-seconds / time constant) left after straight riding, never below the floor of what straight riding tells."""
    first = _learn(learner, steer=512.0, seconds=0.01)[cnd.OUT_STEER_ZERO_SD]
    assert first == pytest.approx(settings.sensors.steer_zero_sd * COUNT, rel=0.01)
    after = _learn(learner, steer=512.0, seconds=10.0)[cnd.OUT_STEER_ZERO_SD]
    assert after == pytest.approx(
        math.hypot(settings.sensors.steer_zero_sd * math.exp(-1.0), cnd.STEER_ZERO_FLOOR) * COUNT, rel=0.01
    )
    late = _learn(learner, steer=512.0, seconds=100.0)[cnd.OUT_STEER_ZERO_SD]
    assert late == pytest.approx(cnd.STEER_ZERO_FLOOR * COUNT, rel=0.01)
