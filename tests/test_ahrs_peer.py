"""The Fusion AHRS peer (issue #12): sign, units and motion compensation on known and simulated rides."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ptw_rt.core import layout as L  # noqa: N812
from ptw_rt.eval import ahrs_peer

pytest.importorskip("imufusion")

G = 9.81


def _samples(n: int, gyro, accel, speed: float = 0.0, dt: float = 0.01) -> np.ndarray:
    s = np.zeros((n, L.SAMPLE_SIZE))
    s[:, L.S_TIME] = np.arange(n) * dt
    s[:, [L.S_ROLL_RATE_BODY, L.S_PITCH_RATE_BODY, L.S_YAW_RATE_BODY]] = gyro
    s[:, [L.S_ACCEL_X, L.S_ACCEL_Y, L.S_ACCEL_Z]] = accel
    s[:, L.S_GPS_SPEED] = speed
    s[::10, L.S_FRESH] = L.MSG_GPS  # a GPS fix every 10th cycle (10 Hz)
    return s


def test_static_tilt_right_is_positive_roll():
    phi = math.radians(8.0)
    # specific force of a sensor at rest rolled right (SAE body axes, z down): (0, -g sin, -g cos)
    s = _samples(600, (0.0, 0.0, 0.0), (0.0, -G * math.sin(phi), -G * math.cos(phi)))
    out = ahrs_peer.run_peer(s, 0.01, 0.5, 0.0, 0.1)
    assert math.degrees(out["roll"][-1]) == pytest.approx(8.0, abs=0.05)
    assert abs(math.degrees(out["pitch"][-1])) < 0.05


def test_synthetic_steady_turn_motion_terms_removed():
    """u = 15 m/s, r = 0.3 rad/s: roll atan(u r / g) = 24.6 deg; without compensation the AHRS would say ~0."""
    u, r, h = 15.0, 0.3, 0.5
    phi = math.atan(u * r / G)
    sp, cp = math.sin(phi), math.cos(phi)
    q, rb = r * sp, r * cp
    # yaw-frame acceleration of the IMU (u r - r^2 h sin phi laterally), then rotated into the body
    ay = u * r - r * r * h * sp
    f = (0.0, ay * cp - G * sp, -ay * sp - G * cp)
    s = _samples(1500, (0.0, q, rb), f, speed=u)
    out = ahrs_peer.run_peer(s, 0.01, h, 0.0, 0.1)
    assert math.degrees(out["roll"][-1]) == pytest.approx(math.degrees(phi), abs=0.1)
    gyro, f_grav = ahrs_peer.gravity_specific_force(s, 0.01, h, 0.0, 0.1, ahrs_peer.PeerSettings())
    np.testing.assert_allclose(f_grav[-1], (0.0, -G * sp, -G * cp), atol=1e-9)


def test_gps_speed_line_and_latency():
    t = np.arange(200) * 0.01
    v = 10.0 + 2.0 * np.floor(t * 10) / 10  # a fix every 0.1 s of a speed rising at 2 m/s^2
    fresh = np.zeros(200, bool)
    fresh[::10] = True
    stale = np.zeros(200, bool)
    u0, du0 = ahrs_peer.gps_speed_and_derivative(t, v, fresh, stale, 0.0, 5)
    u1, du1 = ahrs_peer.gps_speed_and_derivative(t, v, fresh, stale, 0.1, 5)
    assert du0[-1] == pytest.approx(2.0) and du1[-1] == pytest.approx(2.0)
    # with the latency compensated the speed leads by 2 m/s^2 x 0.1 s
    assert u1[-1] - u0[-1] == pytest.approx(0.2)
    stale[150:] = True
    u2, du2 = ahrs_peer.gps_speed_and_derivative(t, v, fresh, stale, 0.0, 5)
    assert du2[-1] == 0.0 and np.isfinite(u2).all()


def _simulated(scenario, duration: float):
    from ptw_rt.eval.evaluate import evaluate_ride
    from ptw_rt.sim.ride import simulate

    return evaluate_ride(simulate(scenario, duration=duration))


def test_simulated_steady_turn_sign_and_magnitude():
    from ptw_rt.sim.scenarios import Scenario, Seg, plan_from_segments

    lat = 3.0  # m/s^2 to the right: roll ~ +17 deg
    turn = Scenario(
        "steady_right_turn",
        "50 km/h, steady right turn",
        12.0,
        7,
        lambda d: plan_from_segments([Seg(2.0, 50), Seg(2.0, 50, lat, 2.0), Seg(20.0, 50, lat, 0.1)], d, 50),
        0.0,
    )
    ev = _simulated(turn, 12.0)
    steady = ev.t >= 7.0
    truth = np.degrees(ev.truth["roll"][steady])
    peer = np.degrees(ev.baselines["ahrs_peer_roll"][steady])
    assert truth.mean() > 10.0  # a right-hand turn leans right: positive
    assert peer.mean() == pytest.approx(truth.mean(), abs=1.0)
    assert np.sqrt(np.mean((peer - truth) ** 2)) < 1.0
    assert ev.result["baselines"]["ahrs_peer_roll_rmse_deg"] < 1.0


def test_simulated_lane_change():
    ev = _simulated("dlc_50", 10.0)
    m = ev.t >= 3.0
    err = np.degrees(ev.baselines["ahrs_peer_roll"][m] - ev.truth["roll"][m])
    assert np.degrees(np.max(np.abs(ev.truth["roll"][m]))) > 5.0  # the lane change happened
    assert np.sqrt(np.mean(err**2)) < 0.5
