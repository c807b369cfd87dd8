"""The kinematic attitude filter alone (ptw_rt.core.attitude) on exact rigid-body kinematics.

Synthetic rides: a prescribed roll, yaw rate and speed; body rates and specific force computed from the
same rigid-body kinematics as the simulator's IMU (docs/simulator.md), with gyro and accelerometer biases,
white noise, a lever arm, and GPS course at 10 Hz with 0.1 s latency. No tyre model anywhere.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from ptw_rt.core import attitude as att
from ptw_rt.paths import DEFAULT_CONFIG
from ptw_rt.settings import load_settings

G = 9.81
DT = 0.01
BIAS_GYRO = (0.003, -0.002, 0.0035)
BIAS_AY = 0.05


def _ride(phi, r, u, h, x_i, seed=1, noise=True, slope=0.0):
    """Sensor arrays for roll phi(t), ground yaw rate r(t), speed u(t) (sideslip zero), on a road of constant
    `slope` [rad, uphill]: the vehicle turns about the vertical, and its pitched roll axis sees -r sin(slope)."""
    rng = np.random.default_rng(seed)
    n = len(phi)
    phid = np.gradient(phi, DT)
    phidd = np.gradient(phid, DT)
    rd = np.gradient(r, DT)
    s, c = np.sin(phi), np.cos(phi)
    a_y = u * r + x_i * rd - h * r * r * s + h * (c * phidd - s * phid**2)
    a_z = h * (s * phidd + c * phid**2)
    gn = 0.002 if noise else 0.0
    an = 0.03 if noise else 0.0
    ss, cs = math.sin(slope), math.cos(slope)
    p = phid - r * ss + BIAS_GYRO[0] + gn * rng.standard_normal(n)
    q = r * s * cs + BIAS_GYRO[1] + gn * rng.standard_normal(n)
    rb = r * c * cs + BIAS_GYRO[2] + gn * rng.standard_normal(n)
    fy = a_y * c + (a_z - G * cs) * s + BIAS_AY + an * rng.standard_normal(n)
    fz = -a_y * s + (a_z - G * cs) * c + an * rng.standard_normal(n)
    psi = np.cumsum(r) * DT
    return p, q, rb, fy, fz, psi


def _run(
    phi, r, u, h=0.5, x_i=0.0, filter_h=None, gps_from=0.0, gps_until=math.inf, seed=1, slope=0.0, accel_x_offset=None
):
    """The filter on `_ride`'s sensors; `accel_x_offset`: the speed stage's longitudinal offset fed every cycle
    (None: none, as without GPS speed)."""
    settings = load_settings(DEFAULT_CONFIG)
    tuning = settings.estimator.attitude
    prm = att.attitude_params(DT, G, h if filter_h is None else filter_h, x_i, tuning, 0.1)
    p, q, rb, fy, fz, psi = _ride(phi, r, u, h, x_i, seed, slope=slope)
    offset = math.nan if accel_x_offset is None else accel_x_offset
    st = att.new_state()
    out = np.zeros(att.OUT_SIZE)
    roll = np.zeros(len(phi))
    sd = np.zeros(len(phi))
    rng = np.random.default_rng(seed + 100)
    for k in range(len(phi)):
        t = k * DT
        course_new = k % 10 == 4 and k >= 10 and gps_from <= t < gps_until
        course = psi[k - 10] + math.radians(0.3) * rng.standard_normal() if course_new else 0.0
        course = (course + math.pi) % (2 * math.pi) - math.pi
        u_sd = 0.1 if gps_from <= t < gps_until else 2.0
        att.attitude_step(
            st,
            out,
            prm,
            p[k],
            q[k],
            rb[k],
            fy[k],
            fz[k],
            u[k],
            u_sd,
            True,
            True,
            course,
            course_new,
            False,
            accel_x_offset=offset,
        )
        roll[k] = out[att.OUT_ROLL]
        sd[k] = out[att.OUT_ROLL_SD]
    return roll, sd, out


def _smooth_step(t, t0, t1):
    z = np.clip((t - t0) / (t1 - t0), 0.0, 1.0)
    return z * z * z * (10 - 15 * z + 6 * z * z)


def _rms_deg(e):
    return math.degrees(float(np.sqrt(np.mean(e**2))))


def test_steady_turn_roll_and_biases():
    t = np.arange(0, 60, DT)
    u = np.full_like(t, 20.0)
    phi = math.radians(25.0) * _smooth_step(t, 15, 18)  # straight first: the biases become observable
    r = G * np.tan(phi) / u
    roll, sd, out = _run(phi, r, u)
    turn = t > 30
    assert _rms_deg(roll[turn] - phi[turn]) < 0.3
    assert out[att.OUT_BR] == pytest.approx(BIAS_GYRO[2], abs=5e-4)
    assert out[att.OUT_BQ] == pytest.approx(BIAS_GYRO[1], abs=5e-4)
    assert out[att.OUT_BP] == pytest.approx(BIAS_GYRO[0], abs=3e-4)
    # the accelerometer bias is separable from roll only across changes of lean (here one): partly learned
    assert 0.25 * BIAS_AY < out[att.OUT_BAY] < 1.5 * BIAS_AY
    # the claimed uncertainty covers the error
    assert np.all(np.abs(roll[turn] - phi[turn]) < 4.0 * sd[turn] + math.radians(0.05))


def test_lane_change_with_lever_arm():
    t = np.arange(0, 30, DT)
    u = np.full_like(t, 100 / 3.6)
    phi = math.radians(12.0) * (_smooth_step(t, 10, 11.5) - 2 * _smooth_step(t, 12, 13.5) + _smooth_step(t, 14, 15.5))
    r = G * np.tan(phi) / u
    roll, _, _ = _run(phi, r, u, h=0.8, x_i=0.3)
    scored = t > 5
    assert _rms_deg(roll[scored] - phi[scored]) < 0.25


def test_hard_braking_in_a_curve():
    """120 -> 55 km/h at 6 m/s^2 on a constant radius: roll follows u^2 / (g R) through it."""
    t = np.arange(0, 40, DT)
    u = np.interp(t, [0, 20, 23.0, 40], [120 / 3.6, 120 / 3.6, 55 / 3.6, 55 / 3.6])
    radius = 400.0
    entry = _smooth_step(t, 8, 12)
    r = entry * u / radius
    phi = np.arctan(u * r / G)
    roll, _, _ = _run(phi, r, u, h=0.6, x_i=0.2)
    scored = t > 5
    assert _rms_deg(roll[scored] - phi[scored]) < 0.35


def _winding(t, lean_deg=20.0, period=8.0, u0=15.0):
    """Turns of either hand, one every `period` / 2 s, after 10 s of straight riding."""
    u = np.full_like(t, u0)
    phi = math.radians(lean_deg) * np.sin(2 * math.pi * t / period) * _smooth_step(t, 10, 12)
    return phi, G * np.tan(phi) / u, u


@pytest.mark.parametrize("slope_deg", [4.0, -4.0])
def test_on_a_slope_the_turns_teach_the_pitch_and_the_roll_stays_right(slope_deg):
    """On a 4 deg slope (7 %) a turn about the vertical leaks tan(slope) r_ground into the roll gyro: integrated
    as the roll, 0.6 deg/s at 0.14 rad/s. The pitch state takes it, from the turns and the speed stage's offset
    (here g sin(slope) + 0.03 m/s^2 of accelerometer bias)."""
    slope = math.radians(slope_deg)
    t = np.arange(0, 60, DT)
    phi, r, u = _winding(t)
    roll, _, out = _run(phi, r, u, slope=slope, accel_x_offset=G * math.sin(slope) + 0.03)
    scored = t > 30
    assert _rms_deg(roll[scored] - phi[scored]) < 0.2
    assert math.degrees(out[att.OUT_PITCH]) == pytest.approx(slope_deg, abs=0.5)


def test_without_an_offset_the_turns_alone_teach_the_pitch():
    t = np.arange(0, 90, DT)
    phi, r, u = _winding(t)
    roll, _, out = _run(phi, r, u, slope=math.radians(3.0))
    scored = t > 60
    assert _rms_deg(roll[scored] - phi[scored]) < 0.25
    assert math.degrees(out[att.OUT_PITCH]) == pytest.approx(3.0, abs=0.75)


def test_gps_dropout_keeps_roll_bounded():
    t = np.arange(0, 60, DT)
    u = np.full_like(t, 20.0)
    phi = math.radians(20.0) * (_smooth_step(t, 20, 22) - _smooth_step(t, 40, 42))
    r = G * np.tan(phi) / u
    roll, sd, _ = _run(phi, r, u, gps_until=25.0)
    scored = t > 25
    assert _rms_deg(roll[scored] - phi[scored]) < 0.8
    assert np.all(np.isfinite(roll)) and np.all(sd > 0)


def test_restart_keeps_biases():
    t = np.arange(0, 30, DT)
    u = np.full_like(t, 20.0)
    phi = math.radians(20.0) * _smooth_step(t, 10, 12)
    r = G * np.tan(phi) / u
    _, _, out = _run(phi, r, u)
    settings = load_settings(DEFAULT_CONFIG)
    prm = att.attitude_params(DT, G, 0.5, 0.0, replace(settings.estimator.attitude), 0.1)
    st = att.new_state()
    o = np.zeros(att.OUT_SIZE)
    att.attitude_step(st, o, prm, 0.0, 0.0, 0.0, 0.0, -G, 0.0, 0.1, True, True, 0.0, False, False)
    att.set_biases(st, 0.001, 0.002, 0.003, 0.04, math.nan, math.nan, 1e-3, 0.02, 0.05)
    att.restart(st)
    att.attitude_step(st, o, prm, 0.0, 0.0, 0.0, 0.0, -G, 0.0, 0.1, True, True, 0.0, False, False)
    assert st[att.ST_INIT] == 1.0
    assert st[att.ST_X + att.X_BR] == pytest.approx(0.003, abs=1e-6)
    assert st[att.ST_X + att.X_BAY] == pytest.approx(0.04, abs=1e-3)


def test_biases_restored_before_the_first_sample_leave_the_states_not_restored_at_their_priors():
    """The state file keeps b_p, b_q, b_r and b_ay; the pitch, b_ax and b_az start from their priors (a state with no
    variance is never learned: a slope's pitch read as level on every ride after the first). Restored into a filter
    that has run, those three are kept as learned."""
    settings = load_settings(DEFAULT_CONFIG)
    prm = att.attitude_params(DT, G, 0.5, 0.0, settings.estimator.attitude, 0.1)
    st = att.new_state()
    att.set_biases(st, 0.001, 0.002, 0.003, 0.04, math.nan, math.nan, 1e-3, 0.02, 0.05)
    o = np.zeros(att.OUT_SIZE)
    att.attitude_step(st, o, prm, 0.0, 0.0, 0.0, 0.0, -G, 0.0, 0.1, True, True, 0.0, False, False)
    P = st[att.ST_P : att.ST_P + att.N_X * att.N_X].reshape((att.N_X, att.N_X))
    assert P[att.X_PITCH, att.X_PITCH] == pytest.approx(att.INITIAL_PITCH_SD**2, rel=0.01)
    assert P[att.X_BAX, att.X_BAX] == pytest.approx(0.05**2, rel=0.01)
    assert P[att.X_BAZ, att.X_BAZ] == pytest.approx(0.05**2, rel=0.01)
    assert st[att.ST_X + att.X_BQ] == pytest.approx(0.002, abs=1e-6)
    P[att.X_PITCH, att.X_PITCH] = 1e-6  # as if learned
    att.set_biases(st, 0.001, 0.002, 0.003, 0.04, math.nan, math.nan, 1e-3, 0.02, 0.05)
    assert P[att.X_PITCH, att.X_PITCH] == 1e-6


def test_standstill_reads_gyro_biases():
    settings = load_settings(DEFAULT_CONFIG)
    prm = att.attitude_params(DT, G, 0.5, 0.0, settings.estimator.attitude, 0.1)
    st = att.new_state()
    o = np.zeros(att.OUT_SIZE)
    rng = np.random.default_rng(3)
    for _ in range(1000):
        n = 0.002 * rng.standard_normal(3)
        att.attitude_step(
            st, o, prm, 0.004 + n[0], -0.003 + n[1], 0.002 + n[2], 0.0, -G, 0.0, 0.1, True, True, 0.0, False, True
        )
    assert o[att.OUT_BP] == pytest.approx(0.004, abs=3e-4)
    assert o[att.OUT_BQ] == pytest.approx(-0.003, abs=3e-4)
    assert o[att.OUT_BR] == pytest.approx(0.002, abs=3e-4)


def _straight_with_course(speed: float, upset_state: int, upset_value: float, add: bool = False):
    """20 s straight at `speed` with exact GPS course fixes; at 5 s one filter state is upset (set, or added to).
    Returns the heading error, the roll error and v_y per cycle."""
    t = np.arange(0, 20, DT)
    u = np.full_like(t, speed)
    phi = np.zeros_like(t)
    r = np.zeros_like(t)
    settings = load_settings(DEFAULT_CONFIG)
    prm = att.attitude_params(DT, G, 0.5, 0.0, settings.estimator.attitude, 0.1)
    p, q, rb, fy, fz, psi = _ride(phi, r, u, 0.5, 0.0, 1)
    st = att.new_state()
    out = np.zeros(att.OUT_SIZE)
    heading_error, roll_error, vy = np.zeros(len(t)), np.zeros(len(t)), np.zeros(len(t))
    for k in range(len(t)):
        if k == 500:
            st[att.ST_X + upset_state] = st[att.ST_X + upset_state] + upset_value if add else upset_value
        course_new = k % 10 == 4 and k >= 10
        course = psi[k - 10] if course_new else 0.0
        att.attitude_step(
            st, out, prm, p[k], q[k], rb[k], fy[k], fz[k], u[k], 0.1, True, True, course, course_new, False
        )
        heading_error[k] = (out[att.OUT_HEADING] - psi[k] + math.pi) % (2 * math.pi) - math.pi
        roll_error[k] = out[att.OUT_ROLL] - phi[k]
        vy[k] = out[att.OUT_VY]
    return t, heading_error, roll_error, vy


def test_a_heading_beyond_the_gate_is_taken_from_the_course_again():
    """A heading that drifted beyond the innovation gate (a long GPS outage on a biased yaw gyro) would refuse
    every later fix; after COURSE_REINIT_FIXES refused fixes the next one sets it."""
    _, heading_error, _, _ = _straight_with_course(20.0, att.X_PSI, 0.5, add=True)  # 29 deg off, beyond the gate
    assert abs(heading_error[499]) < math.radians(1.0)
    assert abs(heading_error[520]) > math.radians(20.0)  # refused at first: one bad fix is not believed
    back = np.flatnonzero(np.abs(heading_error) < math.radians(1.0))
    assert back[back > 500][0] * DT <= 5.0 + 1.2  # within COURSE_REINIT_FIXES fixes and one more


def test_a_sideslip_a_slide_left_far_off_is_restarted_not_matched_by_the_heading():
    """A slide can leave v_y metres per second off (the random ride that found it: 6 m/s at 18 m/s, true 0).
    The course then refuses fix after fix; re-taking the heading from the course while keeping that v_y made
    heading + v_y/u fit the course with both wrong, and the roll drifted 7 deg off on the straight after.
    The restart puts the sideslip back at its prior: the roll stays right and v_y returns to the truth."""
    t, heading_error, roll_error, vy = _straight_with_course(18.0, att.X_VY, 6.0)  # what the slide left
    after = t >= 7.0  # the course refuses fixes for 1 s, then heading and sideslip restart
    assert np.max(np.abs(vy[after])) < 0.5
    assert np.max(np.abs(heading_error[after])) < math.radians(2.0)
    assert np.max(np.abs(roll_error[t >= 5.0])) < math.radians(1.0)


def _run_with_faults(phi, r, u, h=0.5, p_fault=None, fy_fault=None, imu_fresh=True, seed=1):
    """`_run`'s ride with faults added to the roll gyro and the lateral accelerometer; the roll, its sd and the roll-
    gyro bias step the filter took each cycle (`attitude._roll_gyro_step`)."""
    settings = load_settings(DEFAULT_CONFIG)
    prm = att.attitude_params(DT, G, h, 0.0, settings.estimator.attitude, 0.1)
    p, q, rb, fy, fz, psi = _ride(phi, r, u, h, 0.0, seed)
    p = p + (0.0 if p_fault is None else p_fault)
    fy = fy + (0.0 if fy_fault is None else fy_fault)
    st = att.new_state()
    out = np.zeros(att.OUT_SIZE)
    roll, sd, steps = (np.zeros(len(phi)) for _ in range(3))
    for k in range(len(phi)):
        course_new = k % 10 == 4 and k >= 10
        course = (psi[k - 10] + math.pi) % (2 * math.pi) - math.pi if course_new else 0.0
        att.attitude_step(
            st, out, prm, p[k], q[k], rb[k], fy[k], fz[k], u[k], 0.1, True, True, course, course_new, False,
            False, True, imu_fresh,
        )  # fmt: skip
        roll[k], sd[k], steps[k] = out[att.OUT_ROLL], out[att.OUT_ROLL_SD], out[att.OUT_GYRO_STEP]
    return roll, sd, steps


@pytest.mark.parametrize("bias", [0.05, -0.05, 0.1])
def test_a_roll_gyro_bias_step_is_taken_at_once(bias):
    """Riding straight at 30 m/s, the roll gyro's bias steps at 20 s. No roll acceleration made that jump (the
    accelerometer, 0.5 m above the ground, did not feel it), so it is taken as a bias step in the cycle after it:
    the roll stays right. Without the check (no fresh samples to compare) it runs off at 2.9 deg/s per 0.05 rad/s
    until the lateral force, which a sideslip can explain for seconds, pulls it back."""
    t = np.arange(0, 40, DT)
    u = np.full_like(t, 30.0)
    phi = math.radians(1.0) * np.sin(2 * math.pi * 0.3 * t)  # a rider's small weave
    r = G * np.tan(phi) / u
    fault = np.where(t >= 20.0, bias, 0.0)
    roll, sd, steps = _run_with_faults(phi, r, u, p_fault=fault)
    taken = np.flatnonzero(steps)
    assert len(taken) == 1 and 20.0 <= t[taken[0]] <= 20.03
    assert steps[taken[0]] == pytest.approx(bias, abs=0.01)
    after = t >= 20.0
    healthy, _, _ = _run_with_faults(phi, r, u)  # (its roll carries the accelerometer's unlearned bias, 0.3 deg)
    assert np.max(np.abs(roll[after] - healthy[after])) < math.radians(0.3)
    assert np.all(np.abs(roll[after] - phi[after]) < 3.0 * sd[after] + math.radians(0.1))  # its sd covers it
    unchecked, _, none = _run_with_faults(phi, r, u, p_fault=fault, imu_fresh=False)
    assert not none.any()
    assert np.max(np.abs(unchecked[after] - phi[after])) > math.radians(1.5)  # what the check saves


@pytest.mark.parametrize(("lean_deg", "duration"), [(12.0, 1.5), (25.0, 0.6)])
def test_a_quick_lane_change_is_no_gyro_step(lean_deg, duration):
    """A lane change at 100 km/h, up to 25 deg reversed within 0.6 s with the IMU 0.8 m up: the roll rate changes
    by up to 0.03 rad/s per sample, and the accelerometer feels each change through the lever arm: no step."""
    t = np.arange(0, 30, DT)
    u = np.full_like(t, 100 / 3.6)
    a, d = 10.0, duration
    phi = math.radians(lean_deg) * (
        _smooth_step(t, a, a + d) - 2 * _smooth_step(t, a + d + 0.3, a + 2 * d + 0.3)
        + _smooth_step(t, a + 2 * d + 0.6, a + 3 * d + 0.6)
    )  # fmt: skip
    r = G * np.tan(phi) / u
    _, _, steps = _run_with_faults(phi, r, u, h=0.8)
    assert not steps.any()


def test_a_kick_of_the_accelerometer_alone_is_no_gyro_step():
    """A pothole's lateral spike (8 m/s^2 for one sample) is not the gyro's: the gyro's own share of the comparison
    stays at its noise, so nothing is taken."""
    t = np.arange(0, 30, DT)
    u = np.full_like(t, 20.0)
    phi = np.zeros_like(t)
    kick = np.where(np.abs(t - 15.0) < 0.005, 8.0, 0.0)
    _, _, steps = _run_with_faults(phi, np.zeros_like(t), u, fy_fault=kick)
    assert not steps.any()


def test_a_bias_that_grows_over_a_second_is_no_step():
    """The check sees jumps between two samples only: a bias growing by 0.05 rad/s over 1 s (a thermal transient)
    passes it, and is the consistency monitor's (tests/test_attitude_consistency.py)."""
    t = np.arange(0, 40, DT)
    u = np.full_like(t, 30.0)
    phi = np.zeros_like(t)
    _, _, steps = _run_with_faults(phi, phi, u, p_fault=0.05 * np.clip(t - 20.0, 0.0, 1.0))
    assert not steps.any()


@pytest.mark.parametrize("spike", [0.02, 0.03, 0.05, 0.1, 0.3])
def test_a_gyro_spike_is_no_step_or_one_its_uncertainty_covers(spike):
    """A glitch of one or two samples (or a garbage frame whose rolling counter happened to match, within the input
    checks' 0.5 rad/s) jumps and comes back: taken as a step it would leave the bias 1.5 times the spike off. One
    whose shape is clearly a spike's is not taken; one near the noise may be, but with an uncertainty that covers
    it being no step at all: the roll is never further off than 3 of its sd say."""
    t = np.arange(0, 30, DT)
    u = np.full_like(t, 30.0)
    phi = np.zeros_like(t)
    integrated = 3.0 * spike * DT + math.radians(0.05)  # what integrating the glitch itself moves the roll by, and more
    one = np.where(np.abs(t - 15.0) < 0.005, spike, 0.0)
    two = np.where((t > 14.995) & (t < 15.015), spike, 0.0)
    after = t >= 5.0
    for seed in range(1, 6):  # near the noise, whether a glitch is taken depends on the noise's draw
        for glitch in (one, two):
            roll, sd, steps = _run_with_faults(phi, phi, u, p_fault=glitch, seed=seed)
            assert np.all(np.abs(roll[after] - phi[after]) <= 3.0 * sd[after] + integrated)
            if spike >= 0.1 and glitch is one:
                assert not steps.any()  # 1.5 x 0.1 rad/s against the 0.0045 of its neighbours' noise: a spike


def test_a_prior_widened_later_is_as_if_it_had_been_wide_from_the_start():
    """`_widen_prior` takes the narrower prior's extra information out of a filter that has run: on linear updates
    the result is the filter run from the wider prior (state and covariance), and a state the data never narrowed
    below that extra information (an alarm reopened it) just gains the prior's difference."""
    rng = np.random.default_rng(7)
    tight, wide = 0.05**2, 0.12**2
    runs = []
    for prior in (tight, wide):
        st = att.new_state()
        P = st[att.ST_P : att.ST_P + att.N_X * att.N_X].reshape((att.N_X, att.N_X))
        for i in range(att.N_X):
            P[i, i] = 0.1**2
        P[att.X_BAY, att.X_BAY] = prior
        runs.append(st)
    H = np.zeros(att.N_X)
    for _ in range(40):  # the same measurements, with a roll-like and a bias-like state in most of them
        H[:] = 0.0
        H[att.X_PHI] = rng.normal(-9.8, 2.0)
        H[att.X_BAY] = 1.0
        H[rng.integers(att.N_X)] += rng.normal()
        y = rng.normal(0.0, 0.1)
        for st in runs:
            assert att._update(st, H, y - float(H @ st[att.ST_X : att.ST_X + att.N_X]), 0.05**2, 1e9)
    narrow, from_start = runs
    assert abs(narrow[att.ST_X + att.X_BAY] - from_start[att.ST_X + att.X_BAY]) > 1e-3  # the prior mattered
    att._widen_prior(narrow, att.X_BAY, tight, wide)
    filter_part = slice(att.ST_X, att.ST_P + att.N_X * att.N_X)  # x then P
    np.testing.assert_allclose(narrow[filter_part], from_start[filter_part], atol=1e-9)
    reopened = att.new_state()
    reopened[att.ST_P + att.X_BAY * (att.N_X + 1)] = tight + 0.05**2
    att._widen_prior(reopened, att.X_BAY, tight, wide)
    assert reopened[att.ST_P + att.X_BAY * (att.N_X + 1)] == pytest.approx(wide + 0.05**2)


def test_the_accelerometers_prior_widens_once_the_road_is_level_and_not_for_biases_restored():
    """From nothing the accelerometers' biases start from the tight prior a changing grade needs, and take the wide one
    (`level_road_accel_bias_sd`) after LEVEL_ROAD_TIME of riding on a level road; biases restored from a state file
    are known, and keep what the file says."""
    settings = load_settings(DEFAULT_CONFIG)
    tuning = settings.estimator.attitude
    assert tuning.level_road_accel_bias_sd > tuning.initial_accel_bias_sd
    prm = att.attitude_params(DT, G, 0.5, 0.0, tuning, 0.1)
    due_at = {}
    for restored in (False, True):
        st = att.new_state()
        if restored:
            att.set_biases(st, 0.0, 0.0, 0.0, 0.01, 0.0, 0.0, 1e-3, 0.02, 0.05)
        o = np.zeros(att.OUT_SIZE)
        due = []
        for _ in range(500):  # 5 s straight and level at 15 m/s
            att.attitude_step(st, o, prm, 0.0, 0.0, 0.0, 0.0, -G, 15.0, 0.1, True, True, 0.0, False, False)
            due.append(st[att.ST_LEVEL_PRIOR_DUE])
        due_at[restored] = np.array(due)
        P = st[att.ST_P : att.ST_P + att.N_X * att.N_X].reshape((att.N_X, att.N_X))
        # a straight pins the sum of the roll's and b_ay's offsets, not b_ay (b_az it reads directly)
        assert (P[att.X_BAY, att.X_BAY] > 0.1**2) != restored
    first = due_at[False]
    assert first[0] == 1.0 and first[-1] == 0.0
    widened = (int(np.argmax(first == 0.0)) + 1) * DT  # s ridden when it widened
    assert att.LEVEL_ROAD_TIME <= widened <= att.LEVEL_ROAD_TIME + 0.5
    assert not due_at[True].any()


@pytest.mark.slow
def test_from_nothing_an_accelerometer_bias_the_tight_prior_doubts_is_not_left_in_the_roll():
    """Noise seed 11 gives the lateral accelerometer a bias of 0.078 m/s^2, 1.6 of the tight prior's sd. With that
    prior all ride, the straights split it between the bias and the roll, which took 0.127 deg RMSE on `dlc_50`
    against the Fusion AHRS peer's 0.094; the level road's wide prior leaves the roll 0.06 (docs/estimator.md,
    "The accelerometer's bias a priori, once the road is level")."""
    from ptw_rt.eval.evaluate import evaluate_scenario

    ev = evaluate_scenario("dlc_50", 11)
    ours = ev.result["metrics"]["roll_rmse_deg"]
    peer = ev.result["baselines"]["ahrs_peer_roll_rmse_deg"]
    assert ours <= 0.8 * peer


def test_the_grade_odds_favour_two_sensors_that_agree_and_not_one_alone():
    """`_grade_odds` at 50 km/h (the gyros' bias prior 0.01 rad/s, the vertical accelerometer's 0.118 m/s^2 read as
    a pitch rate, a hilly road's rate 0.015 rad/s): a pitch rate both the gyros and the vertical accelerometer read is
    a grade's; one only one of them reads is that sensor's bias; two that disagree, or nothing read, a level road."""
    var_seen, var_felt, var_rate = 0.01**2, (0.118 / 13.9) ** 2, 0.015**2
    grade = math.log(att.GRADE_TEST_ODDS)
    assert att._grade_odds(0.03, 0.03, var_seen, var_felt, var_rate) > grade
    assert att._grade_odds(-0.03, -0.03, var_seen, var_felt, var_rate) > grade
    assert att._grade_odds(0.02, 0.0, var_seen, var_felt, var_rate) < 0.0  # the gyro's bias
    assert att._grade_odds(0.0, 0.02, var_seen, var_felt, var_rate) < grade  # the accelerometer's
    assert att._grade_odds(0.02, -0.01, var_seen, var_felt, var_rate) < 0.0  # the two disagree
    assert att._grade_odds(0.0, 0.0, var_seen, var_felt, var_rate) < 0.0


@pytest.mark.parametrize("fix_older_than_imu", [-0.004, 0.0, 0.0063])
def test_the_course_is_compared_with_the_heading_and_sideslip_of_its_epoch(fix_older_than_imu):
    """The course describes the vehicle the receiver's latency before its frame; the filter's state is the previous
    IMU sample's. Whole cycles put the heading 12 ms before that epoch on the simulator's phases, and the sideslip
    was the current one (`_course_epoch`): here each cycle turned the heading by k mrad and the sideslip angle of
    k cycles back was k mrad, so the epoch's are read off exactly, between cycles too."""
    settings = load_settings(DEFAULT_CONFIG)
    prm = att.attitude_params(DT, G, 0.5, 0.0, settings.estimator.attitude, 0.1)
    st = att.new_state()
    for k in range(att.MAX_LATENCY_CYCLES):
        st[att.ST_PSI_HIST + k] = 0.001 * (k + 1)  # the increment into the state k cycles back
        st[att.ST_BETA_HIST + k] = 0.001 * (k + 1)  # the sideslip angle k + 1 cycles back
    psi, beta = 1.0, 0.0
    delayed_psi, delayed_beta = att._course_epoch(st, prm, psi, beta, fix_older_than_imu)
    delay = (0.1 - DT + fix_older_than_imu) / DT  # cycles back from the state's instant
    j, frac = int(delay), delay - int(delay)
    assert delayed_psi == pytest.approx(psi - 0.001 * (j * (j + 1) / 2 + frac * (j + 1)), abs=1e-12)
    assert delayed_beta == pytest.approx(0.001 * delay, abs=1e-12)


def test_a_noise_free_slalom_reads_the_tyres_it_rides_on():
    """The slalom read the tyres 4.5 % stiff with exact sensors: the GPS course was compared with the heading of 12
    ms before its epoch and with the current sideslip, and in a slalom both errors go with the turns; the yaw gyro's
    bias followed them (sd 3.7e-4 rad/s where its truth is constant) and the ground yaw rate with it, which the tyre
    filters are most sensitive to (docs/estimator.md, "The course at its own instant")."""
    from ptw_rt.core import layout as L  # noqa: N812
    from ptw_rt.eval.evaluate import evaluate_ride
    from ptw_rt.sim.ride import Perturbation, simulate

    ride = simulate("slalom_30", perturbation=Perturbation(imu_noise=0.01, imu_bias=0.0, rider_noise=0.01))
    ev = evaluate_ride(ride)
    second_half = ev.t > ev.t[-1] / 2
    nominal = load_settings(DEFAULT_CONFIG).vehicle.nominal_stiffness()[0]  # front cornering, N/rad
    truth = ev.truth["c_alpha_front"][second_half] / nominal
    error = float(np.mean(ev.estimates[second_half, L.E_TYRE_SCALE] / truth) - 1.0)
    assert abs(error) < 0.02, f"tyres read {100 * error:+.2f} % over the second half"
