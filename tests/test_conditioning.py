"""Sensor conditioning: encoder wrap, de-rolling the leaning IMU, latency-compensated speed."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from ptw_rt.core.conditioning import ground_yaw_rate, horizontal_lateral_accel, kinematic_roll, steer_angle
from ptw_rt.core.speed import new_speed_state, speed_step

G = 9.81


@pytest.mark.parametrize(
    ("count", "zero", "expected_counts"),
    [(512, 512, 0), (513, 512, 1), (500, 512, -12), (3, 1020, 7), (1020, 3, -7), (0, 512, 512)],
)
def test_steer_angle_wraps_around_the_calibration_zero(count, zero, expected_counts):
    assert steer_angle(count, zero, 1024) == pytest.approx(expected_counts * 2 * math.pi / 1024)


@given(st.floats(-math.pi + 0.01, math.pi - 0.01), st.integers(0, 1023))
def test_steer_angle_round_trip(angle, zero):
    count = (zero + round(angle * 1024 / (2 * math.pi))) % 1024
    assert abs(steer_angle(count, zero, 1024) - angle) <= math.pi / 1024 + 1e-12


@pytest.mark.parametrize("roll_deg", [0.0, 10.0, 30.0, -40.0])
def test_steady_turn_body_readings_map_back_to_the_ground(roll_deg):
    """Hand-derived steady coordinated turn: tan(phi) = u r / g, the IMU leans with the chassis."""
    phi = math.radians(roll_deg)
    u = 20.0
    r = G * math.tan(phi) / u
    q_b, r_b = r * math.sin(phi), r * math.cos(phi)  # body rates (zero pitch)
    a_y = u * r
    f_y = a_y * math.cos(phi) - G * math.sin(phi)  # ~0 in a coordinated turn
    f_z = -a_y * math.sin(phi) - G * math.cos(phi)
    assert f_y == pytest.approx(0.0, abs=1e-9)
    assert ground_yaw_rate(q_b, r_b, phi) == pytest.approx(r)
    assert horizontal_lateral_accel(f_y, f_z, phi) == pytest.approx(a_y)
    assert kinematic_roll(u, r, G) == pytest.approx(phi, abs=1e-9)


def run_speed(truth, accel, gps_period=10, latency=10, gps_noise=0.0, dropout=None, seed=0):
    rng = np.random.default_rng(seed)
    state = new_speed_state(latency)
    out = np.zeros(len(truth))
    for k in range(len(truth)):
        new = k % gps_period == 0 and k >= latency
        ok = not (dropout and dropout[0] <= k < dropout[1])
        gps = truth[k - latency] + gps_noise * rng.normal() if new else np.nan
        out[k] = speed_step(state, accel[k], gps, new, ok, 0.01, 0.3, 0.002, latency)
    return out


def test_speed_tracks_an_acceleration_without_lag():
    t = np.arange(3000) * 0.01
    accel = np.where((t > 5) & (t < 15), 2.0, 0.0)
    truth = 10.0 + np.cumsum(accel) * 0.01
    est = run_speed(truth, accel, gps_noise=0.05)
    err = est[600:] - truth[600:]
    assert np.sqrt(np.mean(err**2)) < 0.1
    # without latency compensation the estimate would lag by ~0.2 m/s during the ramp
    assert abs(np.mean(err[(t[600:] > 8) & (t[600:] < 14)])) < 0.05


def test_accelerometer_bias_is_learned():
    truth = np.full(6000, 15.0)
    est = run_speed(truth, np.full(6000, 0.1))  # 0.1 m/s^2 bias, constant speed
    assert abs(est[-1] - 15.0) < 0.1


def test_dropout_holds_on_the_accelerometer():
    accel = np.full(2000, 0.5)
    truth = 10.0 + np.cumsum(accel) * 0.01
    est = run_speed(truth, accel, dropout=(800, 1300))
    assert abs(est[1299] - truth[1299]) < 0.3
    assert np.all(np.isfinite(est)) and np.all(est >= 0)


def test_speed_never_negative_and_waits_for_a_first_fix():
    state = new_speed_state(10)
    assert speed_step(state, -5.0, np.nan, False, False, 0.01, 0.3, 0.002, 10) == 0.0
    assert speed_step(state, -50.0, 0.1, True, True, 0.01, 0.3, 0.002, 10) >= 0.0
    assert speed_step(state, np.nan, np.nan, False, True, 0.01, 0.3, 0.002, 10) >= 0.0
