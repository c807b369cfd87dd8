"""The attitude stage alone (the filter with its glue): a steady turn from the inputs stage's outputs, standstill."""

from __future__ import annotations

import math

import pytest

from ptw_rt.core import attitude as att
from ptw_rt.core import inputs as inp
from ptw_rt.core import speed as spd

G = 9.81


def _inputs(p, q, r, f_y, f_z, course=0.0, course_new=False):
    return inp.OUTPUTS.vector(
        {
            "raw": [p, q, r, 0.0, f_y, f_z, 512.0, 0.0],
            "core_ok": 1.0,
            "accel_ok": 1.0,
            "accel_trusted": 1.0,
            "rates_ok": 1.0,
            "gps_ok": 1.0 if course_new else 0.0,
            "course": course,
            "course_new": 1.0 if course_new else 0.0,
        },
        strict=False,
    )


def test_steady_turn_gives_the_coordinated_roll(settings, design):
    b = att.STAGE.alone(settings, design)
    u, r = 20.0, 0.05
    roll = math.atan(u * r / G)
    speed = spd.OUTPUTS.vector(
        accel_offset=0.0, accel_offset_age=0.0, gps_age=0.0, gps_doubted=0.0, gps_lost=0.0, u=u, known=1.0
    )
    for k in range(1000):
        t = 0.01 * k
        course_new = k % 10 == 0 and k >= 10
        course = (r * (t - 0.1) + math.pi) % (2 * math.pi) - math.pi
        inputs = _inputs(0.0, r * math.sin(roll), r * math.cos(roll), 0.0, -G / math.cos(roll), course, course_new)
        att.attitude_stage(b.state, b.params, b.outputs, inputs, speed)
    out = b.outputs
    assert out[att.OUT_OK] == 1.0
    assert out[att.OUT_ROLL] == pytest.approx(roll, abs=math.radians(0.5))
    assert out[att.OUT_YAW_RATE] == pytest.approx(r, abs=2e-3)
    assert out[att.OUT_REJECTED_RUN] == 0.0


def test_not_ok_before_the_first_sound_sample(settings, design):
    b = att.STAGE.alone(settings, design)
    inputs = _inputs(0.0, 0.0, 0.0, 0.0, -G)
    inputs[inp.OUT_RATES_OK] = 0.0
    att.attitude_stage(
        b.state,
        b.params,
        b.outputs,
        inputs,
        spd.OUTPUTS.vector(
            accel_offset=0.0, accel_offset_age=0.0, gps_age=0.0, gps_doubted=0.0, gps_lost=0.0, u=0.0, known=0.0
        ),
    )
    assert b.outputs[att.OUT_OK] == 0.0


def test_standstill_reads_the_gyro_biases(settings, design):
    b = att.STAGE.alone(settings, design)
    speed = spd.OUTPUTS.vector(
        accel_offset=0.0, accel_offset_age=0.0, gps_age=0.0, gps_doubted=0.0, gps_lost=0.0, u=0.0, known=1.0
    )  # a fix says: standing
    for _ in range(3000):
        att.attitude_stage(b.state, b.params, b.outputs, _inputs(0.004, -0.002, 0.003, 0.0, -G), speed)
    assert b.outputs[att.OUT_BP] == pytest.approx(0.004, abs=2e-4)
    assert b.outputs[att.OUT_BR] == pytest.approx(0.003, abs=2e-4)
    assert b.outputs[att.OUT_ROLL_RATE] == pytest.approx(0.0, abs=2e-4)
    # a restart (Estimator.reset) keeps the biases
    att.STAGE.reset_state(b.state, b.params)
    att.attitude_stage(b.state, b.params, b.outputs, _inputs(0.004, -0.002, 0.003, 0.0, -G), speed)
    assert b.outputs[att.OUT_BP] == pytest.approx(0.004, abs=2e-4)


def test_a_held_rate_grows_the_roll_uncertainty_with_the_length_of_the_hold(settings, design):
    """Integrating a held rate repeats one unknown error every cycle: after n held cycles the roll may be
    n x UNMEASURED_RATE_SD x dt off, not sqrt(n) x: the roll's variance grows by (2n - 1) (sd dt)^2 per cycle."""
    b = att.STAGE.alone(settings, design)
    st = b.state
    P = st[att.ST_P : att.ST_P + att.N_X * att.N_X].reshape((att.N_X, att.N_X))
    dt = float(design.sample_time)
    args = (0.0, 0.0, 0.0, 0.0, -9.81, 15.0, 0.1, True, True, 0.0, False, False)
    for _ in range(5):
        att.attitude_step(st, b.outputs, b.params, *args)
    held = list(args)
    held[7] = held[8] = False  # rates not this cycle's, no accelerometer: the prediction alone
    var0 = P[att.X_PHI, att.X_PHI]
    for _ in range(20):
        att.attitude_step(st, b.outputs, b.params, *held)
    grown = P[att.X_PHI, att.X_PHI] - var0
    # within 1 %: the first held cycle still applies the last measured cycle's lateral force (processed one cycle
    # late), which takes back a part in 10^4 of it; a sqrt(n) growth would be 20 times smaller
    assert grown >= 0.99 * (20 * att.UNMEASURED_RATE_SD * dt) ** 2
    assert st[att.ST_HELD] == 20
    att.attitude_step(st, b.outputs, b.params, *args)
    assert st[att.ST_HELD] == 0


def test_a_gyro_at_its_full_scale_grows_the_roll_uncertainty_like_a_held_rate(settings, design):
    """A fall: the roll rate passed the gyro's 3 rad/s while it read 3.0, and the roll integrated from it ran 5 deg
    behind, VALID (random set 81, `radius_accel` seed 8539, at the ride's end). A reading at full scale is a bound,
    not the rate: the roll's uncertainty grows as a held rate's, enough within 4 cycles to end the roll's VALID
    (3 sd within its 3 deg tolerance), and the stage says the gyro saturated (the supervisor drops the roll rate)."""
    b = att.STAGE.alone(settings, design)
    speed = spd.OUTPUTS.vector(
        accel_offset=0.0, accel_offset_age=0.0, gps_age=0.0, gps_doubted=0.0, gps_lost=0.0, u=15.0, known=1.0
    )
    for k in range(3000):  # riding straight at 15 m/s, GPS courses at 10 Hz
        inputs = _inputs(0.0, 0.0, 0.0, 0.0, -G, 0.0, k % 10 == 0 and k > 10)
        att.attitude_stage(b.state, b.params, b.outputs, inputs, speed)
    sd0 = b.outputs[att.OUT_ROLL_SD]
    assert b.outputs[att.OUT_SATURATED] == 0.0 and 3.0 * sd0 < math.radians(3.0)  # the roll VALID
    for _ in range(4):
        att.attitude_stage(b.state, b.params, b.outputs, _inputs(att.GYRO_FULL_SCALE, 0.0, 0.0, 0.0, -G), speed)
        assert b.outputs[att.OUT_SATURATED] == 1.0
    grown = math.sqrt(b.outputs[att.OUT_ROLL_SD] ** 2 - sd0**2)
    assert grown > math.radians(0.75)  # a sound rate's 4 cycles: a few hundredths of a degree
    assert 3.0 * b.outputs[att.OUT_ROLL_SD] > math.radians(3.0)  # no longer VALID
    att.attitude_stage(b.state, b.params, b.outputs, _inputs(2.9, 0.0, 0.0, 0.0, -G), speed)
    assert b.outputs[att.OUT_SATURATED] == 0.0


def test_a_burst_of_corrupt_input_doubts_what_it_moved_when_it_ends(settings, design):
    """Garbage that passed every check may have moved the biases along what a steady turn cannot observe: after
    a burst of BURST_CYCLES or more cycles of corrupt input, each bias's and the roll's variance grows, once and
    when it ends, by the square of what the burst's measurement updates moved it. A burst that moved nothing (its
    frames dropped or as before) leaves the filter as sure as it was; a shorter one is not a burst."""
    from ptw_rt.core import layout as lay

    b = att.STAGE.alone(settings, design)
    u, r = 20.0, 0.05
    roll = math.atan(u * r / G)
    speed = spd.OUTPUTS.vector(
        accel_offset=0.0, accel_offset_age=0.0, gps_age=0.0, gps_doubted=0.0, gps_lost=0.0, u=u, known=1.0
    )
    clean = _inputs(0.0, r * math.sin(roll), r * math.cos(roll), 0.0, -G / math.cos(roll))
    garbage = clean.copy()
    garbage[inp.OUT_RAW + inp.RAW_AY] = 1.0  # m/s^2 off, within the gate: it passes and moves the estimate

    def ride(cycles, reasons, inputs=clean):
        inputs[inp.OUT_REASONS] = reasons
        for _ in range(cycles):
            att.attitude_stage(b.state, b.params, b.outputs, inputs, speed)

    x = b.state[att.ST_X : att.ST_X + att.N_X]
    P = b.state[att.ST_P : att.ST_P + att.N_X * att.N_X].reshape((att.N_X, att.N_X))
    ride(300, 0)
    before = P.diagonal().copy()
    ride(att.BURST_CYCLES, lay.REASON_COUNTER_JUMPS)  # corrupt-flagged, but the data are the clean ride's
    ride(1, 0)
    assert (P.diagonal()[att.X_BP : att.X_BAY + 1] <= 1.001 * before[att.X_BP : att.X_BAY + 1]).all()
    assert P[att.X_PHI, att.X_PHI] <= 1.001 * before[att.X_PHI]  # nothing moved: nothing doubted

    ride(att.BURST_GAP, 0)
    ride(att.BURST_CYCLES - 1, lay.REASON_OUT_OF_RANGE, garbage)
    before = P.diagonal().copy()
    ride(1, 0)
    assert P[att.X_BAY, att.X_BAY] <= 1.001 * before[att.X_BAY]  # a short burst: nothing reopened

    ride(600, 0)
    start = x.copy()
    before = P.diagonal().copy()
    ride(3 * att.BURST_CYCLES, lay.REASON_OUT_OF_RANGE, garbage)
    assert P[att.X_BP, att.X_BP] <= 1.001 * before[att.X_BP]  # not during the burst
    during = P.diagonal().copy()
    ride(1, 0)  # the first clean cycle (its update takes the last garbage sample: the filter runs a cycle late)
    moved = x - start
    assert abs(moved[att.X_BP]) > 1e-4  # the garbage moved the roll gyro's bias ...
    assert P[att.X_BP, att.X_BP] > during[att.X_BP] + 0.9 * moved[att.X_BP] ** 2  # ... and it is doubted so much
    # the roll moved by its updates (its prediction moved it too, by the gyro): some 0.3 deg, doubted as much
    assert P[att.X_PHI, att.X_PHI] > during[att.X_PHI] + math.radians(0.2) ** 2
