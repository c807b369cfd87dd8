"""The UIHOSMO channel's own kinematics alone (`ptw_rt.core.channel_kinematics`): roll, ground yaw rate and a_y
from the raw IMU and the speed, on signals made with the simulator's IMU kinematics (v_y_dot = 0, so the
kinematics are exact and every error is the filter's)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ptw_rt.core import channel_kinematics as ck

DT = 0.01
G = 9.81


def _imu(phi, p, p_dot, r, r_dot, u, h, x_i):
    """Body rates and specific force of an IMU at height h, x_i ahead (ptw_rt/sim/sensors.py, v_y_dot = 0)."""
    sp, cp = math.sin(phi), math.cos(phi)
    a_y = u * r + r_dot * x_i - r * r * h * sp + h * (cp * p_dot - sp * p * p)
    a_z = h * (sp * p_dot + cp * p * p)
    f_y, f_z = a_y, a_z - G
    return p, r * sp, r * cp, f_y * cp + f_z * sp, -f_y * sp + f_z * cp


def _buffers(settings, design):
    return np.zeros(ck.STATE_SIZE), ck.build_params(settings, design), np.zeros(ck.OUT_SIZE)


def _run(settings, design, trajectory, seconds, bias=0.0, accel_sound=True, zero_accel_from=None, lever=True):
    """Feed ``trajectory(t) -> (phi, p, p_dot, r, r_dot, u)``; returns (t, true roll, outputs) per cycle.
    ``lever=False``: the channel told the IMU sits on the ground (its lever arm not removed)."""
    st, prm, out = _buffers(settings, design)
    h, x_i = prm[ck.P_IMU_HEIGHT], prm[ck.P_IMU_FORWARD]
    if not lever:
        prm[ck.P_IMU_HEIGHT] = 0.0
    rows = []
    for k in range(int(seconds / DT)):
        t = k * DT
        phi, p, p_dot, r, r_dot, u = trajectory(t)
        gp, gq, gr, f_y, f_z = _imu(phi, p, p_dot, r, r_dot, u, h, x_i)
        if zero_accel_from is not None and t >= zero_accel_from:
            f_y = f_z = 0.0
        ck.channel_kinematics_step(st, prm, out, gp + bias, gq, gr, f_y, f_z, u, accel_sound)
        rows.append((t, phi, *out))
    a = np.array(rows)
    return a[:, 0], a[:, 1], a[:, 2:]


def test_a_steady_turn_gives_its_roll_ground_yaw_rate_and_lateral_acceleration(settings, design):
    u, r, phi = 20.0, 0.19, 0.4
    t, roll, out = _run(settings, design, lambda t: (phi, 0.0, 0.0, r, 0.0, u), 10.0)
    assert out[-1, ck.OUT_VALID] == 1.0
    assert out[-1, ck.OUT_ROLL] == pytest.approx(phi, abs=1e-4)
    assert out[-1, ck.OUT_YAW_RATE] == pytest.approx(r, abs=1e-5)
    assert out[-1, ck.OUT_A_Y] == pytest.approx(u * r, abs=0.02)  # the centre of mass's, road plane


def test_a_lane_change_with_the_imu_above_the_ground_is_followed(settings, design):
    """Roll 0.3 rad at 0.5 Hz, a coordinated turn at 20 m/s: the IMU 0.5 m up feels h phi_ddot (up to 1.5 m/s^2,
    9 deg of apparent roll) and h phi_dot^2, which the channel removes. What is left (0.6 deg) is the lag of the
    4 Hz derivative filter on phi_ddot (14 deg of phase at 0.5 Hz) and the gyro's rectangle-rule integration; on
    the realistic plant a faster derivative (10, 20 Hz) changed the roll RMSE by < 0.05 deg (v_y_dot dominates)."""
    u, amp, w = 20.0, 0.3, 2.0 * math.pi * 0.5

    def trajectory(t):
        phi = amp * math.sin(w * t)
        p, p_dot = amp * w * math.cos(w * t), -amp * w * w * math.sin(w * t)
        r = G * math.tan(phi) / u
        r_dot = G * p / (u * math.cos(phi) ** 2)
        return phi, p, p_dot, r, r_dot, u

    t, roll, out = _run(settings, design, trajectory, 20.0)
    late = t > 5.0
    err = np.max(np.abs(out[late, ck.OUT_ROLL] - roll[late]))
    assert err < math.radians(0.7)
    t, roll, out = _run(settings, design, trajectory, 20.0, lever=False)
    assert np.max(np.abs(out[late, ck.OUT_ROLL] - roll[late])) > 3.0 * err


def test_a_roll_gyro_bias_moves_it_by_at_most_the_bias_over_the_crossover(settings, design):
    bias = 0.05
    crossover = settings.estimator.plausibility.roll_crossover
    t, roll, out = _run(settings, design, lambda t: (0.0, 0.0, 0.0, 0.0, 0.0, 15.0), 20.0, bias=bias)
    err = out[:, ck.OUT_ROLL] - roll
    assert np.max(np.abs(err)) <= 1.01 * bias / crossover
    assert err[-1] == pytest.approx(bias / crossover, rel=0.02)  # and no less: nothing learns the bias away


def test_an_accelerometer_reading_zero_is_no_roll(settings, design):
    """A dead accelerometer reads 0: its direction would be a roll of 180 deg. Rejected by size, the gyro holds."""
    t, roll, out = _run(settings, design, lambda t: (0.0, 0.0, 0.0, 0.0, 0.0, 15.0), 6.0, zero_accel_from=3.0)
    assert np.max(np.abs(out[:, ck.OUT_ROLL])) < 1e-9
    t, roll, out = _run(settings, design, lambda t: (0.0, 0.0, 0.0, 0.0, 0.0, 15.0), 1.0, zero_accel_from=0.0)
    assert not out[:, ck.OUT_VALID].any()  # nothing to start from


def test_without_the_accelerometer_the_gyro_carries_the_roll_and_a_y_is_not_given(settings, design):
    st, prm, out = _buffers(settings, design)
    _, _, _, f_y, f_z = _imu(0.0, 0.0, 0.0, 0.0, 0.0, 10.0, prm[ck.P_IMU_HEIGHT], prm[ck.P_IMU_FORWARD])
    ck.channel_kinematics_step(st, prm, out, 0.0, 0.0, 0.0, f_y, f_z, 10.0, True)
    for _ in range(100):
        ck.channel_kinematics_step(st, prm, out, 0.1, 0.0, 0.0, math.nan, math.nan, 10.0, False)
    assert out[ck.OUT_ROLL] == pytest.approx(0.1, rel=1e-9)  # 1 s of 0.1 rad/s
    assert math.isnan(out[ck.OUT_A_Y]) and out[ck.OUT_VALID] == 1.0
    before = out.copy()
    ck.channel_kinematics_step(st, prm, out, math.nan, 0.0, 0.0, f_y, f_z, 10.0, True)
    assert np.array_equal(before, out, equal_nan=True)  # a non-finite rate holds the cycle


def test_a_roll_the_gyro_alone_ran_beyond_any_lean_starts_again(settings, design):
    """An accelerometer rejected for long (reading zero) leaves the gyro alone; a roll it carries beyond the configured
    maximum is no lean: the channel says it is not valid (the UIHOSMO waits) and starts again from gravity."""
    st, prm, out = _buffers(settings, design)
    _, _, _, f_y, f_z = _imu(0.0, 0.0, 0.0, 0.0, 0.0, 10.0, prm[ck.P_IMU_HEIGHT], prm[ck.P_IMU_FORWARD])
    ck.channel_kinematics_step(st, prm, out, 0.0, 0.0, 0.0, f_y, f_z, 10.0, True)
    seen_invalid = False
    for _ in range(300):  # 0.5 rad/s for 3 s, the accelerometer reading zero
        ck.channel_kinematics_step(st, prm, out, 0.5, 0.0, 0.0, 0.0, 0.0, 10.0, True)
        assert abs(out[ck.OUT_ROLL]) <= prm[ck.P_MAX_ROLL]
        seen_invalid |= out[ck.OUT_VALID] == 0.0
    assert seen_invalid
    ck.channel_kinematics_step(st, prm, out, 0.0, 0.0, 0.0, f_y, f_z, 10.0, True)
    assert out[ck.OUT_VALID] == 1.0 and out[ck.OUT_ROLL] == pytest.approx(0.0, abs=1e-9)
