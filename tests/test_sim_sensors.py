"""Sensor models against hand-derived values: leaning IMU, 10-bit steering encoder, bus timing."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from ptw_rt.core.conditioning import ground_yaw_rate, horizontal_lateral_accel, steer_angle
from ptw_rt.sim import loop
from ptw_rt.sim.plant import PHI, PHI_DOT, VY, R, U
from ptw_rt.sim.ride import parse_perturbations
from ptw_rt.sim.sensors import frame_times, imu_readings, road_grade, steer_counts

G = 9.81


def record(n=5, **values):
    """A constant 1 kHz record with the given states/derivatives (everything else zero)."""
    rec = np.zeros((n, loop.NREC))
    rec[:, loop.REC_T] = np.arange(n) * 1e-3
    cols = {
        "phi": loop.REC_X0 + PHI,
        "p": loop.REC_X0 + PHI_DOT,
        "r": loop.REC_X0 + R,
        "u": loop.REC_X0 + U,
        "vy": loop.REC_X0 + VY,
        "dvy": loop.REC_DVY,
        "dr": loop.REC_DR,
        "dp": loop.REC_DP,
        "du": loop.REC_DU,
    }
    for k, v in values.items():
        rec[:, cols[k]] = v
    return rec


def read(rec, height=0.5, forward=0.0, slope=0.0, slope_rate=0.0):
    out = imu_readings(rec, np.array([2e-3]), G, height, forward, slope, slope_rate)
    return {k: float(v[0]) for k, v in out.items()}


def test_at_rest_and_level_accel_z_reads_minus_g():
    m = read(record())
    assert m["AccelZ"] == pytest.approx(-G)
    assert m["AccelX"] == m["AccelY"] == 0.0
    assert m["RollRate"] == m["PitchRate"] == m["YawRate"] == 0.0


@pytest.mark.parametrize("roll_deg", [10.0, 25.0, -35.0])
@pytest.mark.parametrize("height", [0.0, 0.5, 0.8])
def test_steady_coordinated_turn(roll_deg, height):
    """tan(phi) = u r / g: the leaning body feels no side force and g / cos(phi) along its z axis."""
    phi = math.radians(roll_deg)
    u = 20.0
    r = G * math.tan(phi) / u
    m = read(record(phi=phi, r=r, u=u), height=height)
    assert m["YawRate"] == pytest.approx(r * math.cos(phi))
    assert m["PitchRate"] == pytest.approx(r * math.sin(phi))
    assert m["RollRate"] == 0.0
    # the lever arm adds the centripetal term -r^2 h sin(phi) at the mount height
    assert m["AccelY"] == pytest.approx(-(r**2) * height * math.sin(phi) * math.cos(phi), abs=1e-12)
    assert m["AccelZ"] == pytest.approx(-G / math.cos(phi) + r**2 * height * math.sin(phi) ** 2, rel=1e-12)
    # the conditioning module maps them back to the ground frame
    assert ground_yaw_rate(m["PitchRate"], m["YawRate"], phi) == pytest.approx(r)
    a_y = horizontal_lateral_accel(m["AccelY"], m["AccelZ"], phi)
    assert a_y == pytest.approx(u * r - r**2 * height * math.sin(phi))


def test_a_grade_that_changes_pitches_the_chassis_and_curves_the_path():
    """Over a crest the chassis pitches nose-down (pitch' < 0): the pitch gyro reads pitch' cos(roll), the yaw gyro
    -pitch' sin(roll), and the path's vertical curvature u pitch' lightens the vehicle along the road's normal."""
    u, rate, phi = 15.0, -0.02, math.radians(20.0)
    m = read(record(u=u), height=0.0, slope=0.03, slope_rate=rate)
    assert m["PitchRate"] == pytest.approx(rate)
    assert m["YawRate"] == 0.0
    assert m["AccelZ"] == pytest.approx(-G * math.cos(0.03) - u * rate)  # less than g: a crest
    r = G * math.tan(phi) / u
    leaning = read(record(phi=phi, r=r, u=u), height=0.0, slope=0.0, slope_rate=rate)
    level = read(record(phi=phi, r=r, u=u), height=0.0)
    assert leaning["PitchRate"] - level["PitchRate"] == pytest.approx(rate * math.cos(phi))
    assert leaning["YawRate"] - level["YawRate"] == pytest.approx(-rate * math.sin(phi))
    # the gyros' pitch rate q cos(roll) - r sin(roll) is the grade's rate, the turn's part cancels
    q, r_b = leaning["PitchRate"], leaning["YawRate"]
    assert q * math.cos(phi) - r_b * math.sin(phi) == pytest.approx(rate)


def test_the_grade_swings_over_the_distance_ridden_not_over_time():
    """`road_slope_swing` over `road_slope_length` metres: riding, the chassis pitches at u d(grade)/ds; standing
    still it does not, whatever the time."""
    pert = parse_perturbations(["road_slope=1", "road_slope_swing=4", "road_slope_length=400"])
    n = 2001
    rec = np.zeros((n, loop.NREC))
    rec[:, loop.REC_T] = np.arange(n) * 1e-2  # 20 s
    rec[:, loop.REC_X0 + U] = np.where(rec[:, loop.REC_T] < 10.0, 20.0, 0.0)  # 200 m, then standing
    ts = np.array([0.0, 5.0, 15.0, 19.0])
    grade, rate = road_grade(pert, rec, ts)
    k = 2.0 * math.pi / 400.0
    assert grade[0] == pytest.approx(math.radians(1.0))
    assert grade[1] == pytest.approx(math.radians(1.0) + math.radians(4.0) * math.sin(k * 100.0), abs=1e-3)
    assert rate[1] == pytest.approx(math.radians(4.0) * k * math.cos(k * 100.0) * 20.0, rel=1e-3)
    assert grade[2] == pytest.approx(grade[3])  # standing still: the grade under the wheels stays
    assert rate[2] == rate[3] == 0.0
    flat = road_grade(parse_perturbations(["road_slope=-2"]), rec, ts)
    assert np.all(flat[0] == math.radians(-2.0)) and np.all(flat[1] == 0.0)


def test_roll_acceleration_lever_arm():
    """Upright, rolling: the mount at height h sees h * phi_ddot sideways and h * phi_dot^2 'down'."""
    m = read(record(p=0.5, dp=3.0), height=0.5)
    assert m["RollRate"] == 0.5
    assert m["AccelY"] == pytest.approx(0.5 * 3.0)
    assert m["AccelZ"] == pytest.approx(0.5 * 0.25 - G)


def test_longitudinal_and_yaw_lever_arms():
    m = read(record(du=2.0, u=10.0, r=0.3, vy=0.1, dr=1.0), height=0.5, forward=0.2)
    assert m["AccelX"] == pytest.approx(2.0 - 0.1 * 0.3 - 0.3**2 * 0.2)
    assert m["AccelY"] == pytest.approx(10.0 * 0.3 + 1.0 * 0.2)


@pytest.mark.parametrize(
    ("delta_counts", "zero", "offset", "expected"),
    [(0, 512, 0, 512), (1, 512, 0, 513), (-12, 512, 0, 500), (10, 1020, 0, 6), (-5, 2, 0, 1021), (3, 512, 2, 517)],
)
def test_steer_counts_rise_to_the_right_and_wrap(delta_counts, zero, offset, expected):
    delta = delta_counts * 2 * math.pi / 1024
    assert steer_counts(np.array([delta]), zero, offset, 1024)[0] == expected


@given(st.floats(-math.pi + 0.01, math.pi - 0.01), st.integers(0, 1023))
def test_steer_quantisation_round_trip(angle, zero):
    count = int(steer_counts(np.array([angle]), zero, 0, 1024)[0])
    assert 0 <= count <= 1023
    assert abs(steer_angle(count, zero, 1024) - angle) <= math.pi / 1024 + 1e-12


def test_frame_times_jitter_phase_and_range():
    rng = np.random.default_rng(0)
    t = frame_times(rng, 0.01, 0.0021, 50e-6, 10.0)
    d = np.diff(t)
    assert len(t) == 1000
    assert np.all(np.abs(d - 0.01) < 6 * 50e-6 + 1e-12)
    assert 20e-6 < np.std(t - (0.0021 + 0.01 * np.arange(1000))) < 80e-6
    assert t[0] > 0 and t[-1] <= 10.0


def test_on_a_slope_gravity_and_the_vertical_turn_rate_have_parts_along_the_roll_axis():
    """Uphill by 4 deg, leaning 20 deg in a steady turn: the accelerometer reads g sin(slope) forward, and the roll
    gyro reads -r sin(slope) of the turn about the vertical (its roll axis points up the slope)."""
    slope = math.radians(4.0)
    m = read(record(), slope=slope)
    assert m["AccelX"] == pytest.approx(G * math.sin(slope))
    assert m["AccelZ"] == pytest.approx(-G * math.cos(slope))
    phi = math.radians(20.0)
    u = 15.0
    r = G * math.tan(phi) / u
    m = read(record(phi=phi, r=r, u=u), height=0.0, slope=slope)
    assert m["RollRate"] == pytest.approx(-r * math.sin(slope))
    assert m["YawRate"] == pytest.approx(r * math.cos(phi) * math.cos(slope))
    assert m["PitchRate"] == pytest.approx(r * math.sin(phi) * math.cos(slope))


def test_an_imu_mounted_pitched_reads_the_chassis_vectors_turned():
    from ptw_rt.sim.sensors import mounted

    x, y, z = mounted((np.array([0.0]), np.array([0.0]), np.array([-G])), 0.0, math.radians(3.0))
    assert float(x[0]) == pytest.approx(G * math.sin(math.radians(3.0)))
    assert float(z[0]) == pytest.approx(-G * math.cos(math.radians(3.0)))
    x, y, z = mounted((np.array([0.0]), np.array([0.0]), np.array([-G])), math.radians(2.0), 0.0)
    assert float(y[0]) == pytest.approx(-G * math.sin(math.radians(2.0)))  # as if the vehicle leaned right
