"""The speed stage alone: GPS + accelerometer, latency compensated."""

from __future__ import annotations

import numpy as np
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


def _run_fixes(b, inputs, speeds, accel=0.0):
    """One fix every 10 cycles from ``speeds``; the stage's outputs after each cycle."""
    outs = []
    for k in range(10 * len(speeds)):
        new = k % 10 == 0
        inputs[inp.OUT_RAW + inp.RAW_AX] = accel
        inputs[inp.OUT_RAW + inp.RAW_GPS_SPEED] = speeds[k // 10] if new else 0.0
        inputs[inp.OUT_GPS_OK] = 1.0 if new else 0.0
        spd.speed_stage(b.state, b.params, b.outputs, inputs)
        outs.append(b.outputs.copy())
    return np.array(outs)


def test_a_receiver_whose_fixes_are_mostly_refused_is_doubted_and_the_gps_lost(settings, design):
    """Garbage speeds (random 0-100 m/s, counters right) at 20 m/s: within a second the receiver is doubted, none
    of its fixes is taken (the speed dead-reckons), and after gps_hold the GPS counts as lost: the estimator then
    raises REASON_GPS_LOST (conditioning) and the attitude filter widens the speed's uncertainty and drops the
    course. A healthy receiver's glitch does none of this, nor does a long outage that the fixes end."""
    b = spd.STAGE.alone(settings, design)
    inputs = inp.OUTPUTS.vector({"accel_ok": 1.0}, strict=False)
    rng = np.random.default_rng(11)
    garbage = rng.uniform(0.0, 100.0, 600)
    out = _run_fixes(b, inputs, np.concatenate([np.full(50, 20.0), garbage]))
    t = np.arange(len(out)) * b.params[spd.P_DT]
    after = t >= 5.0
    assert np.all(np.abs(out[after, spd.OUT_U] - 20.0) < 0.5)
    doubted = out[:, spd.OUT_GPS_DOUBTED] != 0.0
    assert not doubted[~after].any() and doubted[t >= 6.0].all()
    lost = out[:, spd.OUT_GPS_LOST] != 0.0
    hold = b.params[spd.P_GPS_HOLD]
    assert not lost[t < 4.89 + hold].any() and lost[t >= 7.0 + hold].all()  # the last fix taken: 4.9 s
    # sane again: ten fixes that agree re-take it, and it is believed at once
    out = _run_fixes(b, inputs, np.full(30, 12.0))
    assert out[-1, spd.OUT_U] == pytest.approx(12.0, abs=0.1)
    assert out[-1, spd.OUT_GPS_DOUBTED] == 0.0 and out[-1, spd.OUT_GPS_LOST] == 0.0


def test_a_healthy_receivers_glitches_and_outages_are_not_doubt(settings, design):
    b = spd.STAGE.alone(settings, design)
    inputs = inp.OUTPUTS.vector({"accel_ok": 1.0}, strict=False)
    speeds = np.full(300, 20.0)
    speeds[[60, 61, 90, 150, 151, 152]] = 0.0  # glitches, up to three in a row
    out = _run_fixes(b, inputs, speeds)
    assert not out[:, spd.OUT_GPS_DOUBTED].any() and not out[:, spd.OUT_GPS_LOST].any()
    assert np.all(np.abs(out[10:, spd.OUT_U] - 20.0) < 0.05)
    # a 20 s outage with the accelerometer reading 0.5 m/s^2 too much: the speed is 10 m/s off when fixes return
    inputs[inp.OUT_GPS_OK] = 0.0
    for _ in range(2000):
        inputs[inp.OUT_RAW + inp.RAW_AX] = 0.5
        spd.speed_stage(b.state, b.params, b.outputs, inputs)
    assert b.outputs[spd.OUT_GPS_LOST] == 1.0
    out = _run_fixes(b, inputs, np.full(20, 20.0))
    assert out[-1, spd.OUT_U] == pytest.approx(20.0, abs=0.1)
    assert out[-1, spd.OUT_GPS_DOUBTED] == 0.0 and out[-1, spd.OUT_GPS_LOST] == 0.0


def _speed_on_a_hill(settings, design, pitch_told: bool) -> float:
    """RMS speed error [m/s] at a steady 8.3 m/s over a grade swinging by 5 deg every 400 m (48 s a swing), the
    accelerometer reading g sin(grade) and the GPS the truth 0.1 s late; the pitch told to the stage (as the
    attitude stage estimates it) or not."""
    b = spd.STAGE.alone(settings, design)
    dt, g = b.params[spd.P_DT], settings.vehicle.g
    lag = int(b.params[spd.P_LATENCY_SAMPLES])
    inputs = inp.OUTPUTS.vector({"accel_ok": 1.0}, strict=False)
    u, period = 8.3, 400.0 / 8.3
    errors = []
    for k in range(6000):
        grade = np.radians(5.0) * np.sin(2.0 * np.pi * k * dt / period)
        gps_new = k % 10 == 0
        inputs[inp.OUT_RAW + inp.RAW_AX] = g * np.sin(grade)
        inputs[inp.OUT_RAW + inp.RAW_GPS_SPEED] = u if gps_new else 0.0
        inputs[inp.OUT_GPS_OK] = 1.0 if gps_new else 0.0
        spd.speed_stage(b.state, b.params, b.outputs, inputs, grade if pitch_told else 0.0)
        if k >= 1000 + lag:
            errors.append(b.outputs[spd.OUT_U] - u)
    return float(np.sqrt(np.mean(np.square(errors))))


def test_on_a_changing_grade_the_pitch_keeps_gravity_out_of_the_speed(settings, design):
    """A grade that swings changes the accelerometer's g sin(pitch) faster than the speed's bias learns: the speed
    ran ~0.2 m/s off, which the tyres read as slip (`slalom_30` on 5 deg every 400 m: stiffness VALID 22 % off).
    With the attitude stage's pitch taken out of the reading it follows the GPS; the offset (what the attitude
    stage reads the pitch from) is still of the reading as it is."""
    told, not_told = _speed_on_a_hill(settings, design, True), _speed_on_a_hill(settings, design, False)
    assert told < 0.01 and not_told > 0.1


@pytest.mark.parametrize("forward", [0.0, 0.4])
def test_what_a_turn_adds_along_x_is_the_simulated_imus_kinematics(forward):
    """`attitude.turn_accel_along` (what the speed stage takes out of the accelerometer before integrating it) is
    the simulator's IMU kinematics, derived apart (`sim.sensors.imu_readings`): its x specific force less the speed's
    rate, on a level road, at leans, rates and accelerations of a slalom and beyond."""
    from ptw_rt.core import attitude as att
    from ptw_rt.sim import loop
    from ptw_rt.sim.plant import PHI, PHI_DOT, VY, R, U
    from ptw_rt.sim.sensors import imu_readings

    rng = np.random.default_rng(5)
    height = 0.5
    for _ in range(50):
        phi, p, r, vy = rng.uniform(-0.6, 0.6), rng.uniform(-1, 1), rng.uniform(-0.6, 0.6), rng.uniform(-0.5, 0.5)
        dr, du = rng.uniform(-2, 2), rng.uniform(-3, 3)
        rec = np.zeros((2, loop.NREC))
        rec[:, loop.REC_T] = (0.0, 1.0)
        for col, value in ((PHI, phi), (PHI_DOT, p), (R, r), (VY, vy), (U, 10.0)):
            rec[:, loop.REC_X0 + col] = value
        rec[:, loop.REC_DR] = dr
        rec[:, loop.REC_DU] = du
        ax = imu_readings(rec, np.array([0.5]), 9.81, height, forward)["AccelX"][0]
        assert att.turn_accel_along(vy, r, dr, phi, p, forward, height) == pytest.approx(ax - du, abs=1e-12)


def test_a_slaloms_leans_do_not_move_the_speed():
    """At 30 km/h through a slalom (leans to 17 deg, noise-free sensors) the accelerometer's reading along x swings
    by 0.1-0.15 m/s^2 with the turn (the lean carries the IMU sideways); integrated as the speed's rate it read the
    speed 0.09 m/s low at every full lean (a slope of -0.31 m/s per rad of |roll|), which the tyre filters read
    as stiffer tyres. Taken out, the speed's error does not follow the lean."""
    import ptw_rt.eval.evaluate as ev
    from ptw_rt.core import layout as L  # noqa: N812

    e = ev.evaluate_scenario("slalom_30", None, ["imu_noise=0.01", "imu_bias=0", "rider_noise=0.01"])
    after = e.t > 5.0
    err = e.estimates[after, L.E_SPEED] - e.truth["speed"][after]
    slope = np.polyfit(np.abs(e.truth["roll"][after]), err, 1)[0]
    assert abs(slope) < 0.1, f"speed error {slope:+.3f} m/s per rad of lean"
    assert np.sqrt(np.mean(err**2)) < 0.03
