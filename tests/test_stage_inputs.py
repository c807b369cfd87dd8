"""The inputs stage alone: plausibility, hold of stale and suspect messages, steer-encoder jumps, GPS age."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ptw_rt.core import inputs as inp
from ptw_rt.core import layout as lay


@pytest.fixture
def stage(settings, design):
    return inp.STAGE.alone(settings, design)


def sample(p=0.01, steer=512.0, gps=20.0, fresh=lay.MSG_IMU_RATES | lay.MSG_IMU_ACCEL | lay.MSG_STEER, stale=0):
    s = lay.new_sample()
    s[lay.S_ROLL_RATE_BODY] = p
    s[lay.S_ACCEL_Z] = -9.81
    s[lay.S_STEER_COUNT] = steer
    s[lay.S_GPS_SPEED] = gps
    s[lay.S_GPS_FIX] = 3.0
    s[lay.S_GPS_COURSE] = 90.0
    s[lay.S_FRESH] = fresh
    s[lay.S_STALE] = stale
    return s


def run(b, s):
    inp.inputs_stage(s, b.state, b.params, b.outputs)
    return b.outputs


def test_plausible_values_pass_and_implausible_ones_are_held_and_flagged(stage):
    out = run(stage, sample(p=0.02))
    assert out[inp.OUT_RAW + inp.RAW_P] == 0.02 and int(out[inp.OUT_REASONS]) == 0
    for bad in (math.nan, math.inf, 1e6):
        out = run(stage, sample(p=bad))
        assert out[inp.OUT_RAW + inp.RAW_P] == 0.02
        assert int(out[inp.OUT_REASONS]) & lay.REASON_OUT_OF_RANGE
    out = run(stage, sample(gps=-1.0))  # a negative speed is not a speed
    assert out[inp.OUT_RAW + inp.RAW_GPS_SPEED] == 20.0


def test_stale_and_suspect_messages_are_held(stage):
    run(stage, sample(p=0.02))
    out = run(stage, sample(p=0.3, stale=lay.MSG_IMU_RATES))
    assert out[inp.OUT_RAW + inp.RAW_P] == 0.02 and out[inp.OUT_CORE_OK] == 0.0 and out[inp.OUT_RATES_OK] == 0.0
    assert int(out[inp.OUT_REASONS]) & lay.REASON_STALE
    s = sample(p=0.3)
    s[lay.S_SUSPECT] = lay.MSG_IMU_RATES | lay.MSG_IMU_ACCEL
    out = run(stage, s)
    assert out[inp.OUT_RAW + inp.RAW_P] == 0.02 and out[inp.OUT_RATES_OK] == 0.0
    assert out[inp.OUT_CORE_OK] == 1.0 and out[inp.OUT_ACCEL_OK] == 1.0 and out[inp.OUT_ACCEL_TRUSTED] == 0.0


def test_a_steer_jump_is_held_until_it_persists(stage):
    run(stage, sample(steer=512.0))
    resync = int(stage.params[inp.P_STEER_RESYNC])
    for _ in range(resync):
        out = run(stage, sample(steer=700.0))
        assert out[inp.OUT_RAW + inp.RAW_STEER] == 512.0
    out = run(stage, sample(steer=700.0))
    assert out[inp.OUT_RAW + inp.RAW_STEER] == 700.0
    out = run(stage, sample(steer=703.0))  # a small step is a steering motion
    assert out[inp.OUT_RAW + inp.RAW_STEER] == 703.0 and int(out[inp.OUT_REASONS]) == 0
    out = run(stage, sample(steer=1.0))
    assert out[inp.OUT_RAW + inp.RAW_STEER] == 703.0 and int(out[inp.OUT_REASONS]) & lay.REASON_OUT_OF_RANGE


def test_a_small_step_across_the_encoders_wrap_is_a_steering_motion(stage):
    run(stage, sample(steer=1022.0))
    out = run(stage, sample(steer=1.0))
    assert out[inp.OUT_RAW + inp.RAW_STEER] == 1.0 and int(out[inp.OUT_REASONS]) == 0


def test_gps_age_and_course(stage):
    fresh = lay.MSG_IMU_RATES | lay.MSG_IMU_ACCEL | lay.MSG_STEER
    out = run(stage, sample(fresh=fresh | lay.MSG_GPS))
    assert out[inp.OUT_GPS_OK] == 1.0 and out[inp.OUT_GPS_AGE] == 0.0
    assert out[inp.OUT_COURSE_NEW] == 1.0 and out[inp.OUT_COURSE] == pytest.approx(math.pi / 2)
    hold = stage.params[inp.P_GPS_HOLD]
    n = int(np.ceil(hold / stage.params[inp.P_DT])) + 1
    for _ in range(n):
        out = run(stage, sample(fresh=fresh))
    assert out[inp.OUT_GPS_LOST] == 1.0 and int(out[inp.OUT_REASONS]) & lay.REASON_GPS_LOST
    assert out[inp.OUT_COURSE_NEW] == 0.0 and out[inp.OUT_COURSE] == 0.0
    out = run(stage, sample(fresh=fresh | lay.MSG_GPS))
    assert out[inp.OUT_GPS_LOST] == 0.0


def test_a_gyro_step_no_body_can_make_is_held_until_it_persists(stage):
    """A rate 2.2 rad/s from the last sound one within 10 ms is a corrupt sample (within the range check): held
    and flagged, the rates marked not this cycle's, until the time since the last sound rate allows that much
    change (RATE_NOISE_STEP + MAX_ANGULAR_ACCEL x that time) or it persisted RATE_RESYNC cycles."""
    for _ in range(3):
        out = run(stage, sample(p=0.1))
    assert out[inp.OUT_RATES_OK] == 1.0
    out = run(stage, sample(p=0.1 + inp.RATE_NOISE_STEP + 0.2))  # a quick but possible change: taken
    assert out[inp.OUT_RATES_OK] == 1.0 and int(out[inp.OUT_REASONS]) == 0
    last = out[inp.OUT_RAW + inp.RAW_P]
    dt = 0.01
    held = 0
    while inp.RATE_NOISE_STEP + inp.MAX_ANGULAR_ACCEL * dt * (held + 1) < 3.0 - last and held < inp.RATE_RESYNC:
        out = run(stage, sample(p=3.0))
        assert out[inp.OUT_RAW + inp.RAW_P] == last and out[inp.OUT_RATES_OK] == 0.0
        assert int(out[inp.OUT_REASONS]) & lay.REASON_OUT_OF_RANGE
        held += 1
    assert held >= 4
    out = run(stage, sample(p=3.0))  # it persisted long enough to be a motion: the sensor really says so
    assert out[inp.OUT_RAW + inp.RAW_P] == 3.0 and out[inp.OUT_RATES_OK] == 1.0


def test_the_gyro_step_allowed_grows_with_the_time_without_sound_rates(stage):
    """After a dropout the body may have turned faster: what was held for n cycles allows a step n times larger
    (an out-of-range value replaced by the last one is no sound rate either)."""
    run(stage, sample(p=0.0))
    for _ in range(8):
        out = run(stage, sample(p=1e6))  # out of range: replaced, not sound
        assert out[inp.OUT_RATES_OK] == 0.0
    out = run(stage, sample(p=2.0))  # 2 rad/s in 90 ms: within 0.5 + 30 x 0.09, taken when the next agrees
    assert out[inp.OUT_RAW + inp.RAW_P] == 0.0 and out[inp.OUT_RATES_OK] == 0.0
    assert int(out[inp.OUT_REASONS]) == 0  # not refused: waiting
    out = run(stage, sample(p=2.1))
    assert out[inp.OUT_RAW + inp.RAW_P] == 2.1 and out[inp.OUT_RATES_OK] == 1.0


def test_rates_after_a_gap_are_taken_only_when_the_next_sample_agrees(stage):
    """The IMU_Rates frame has no CRC either: garbage inside the window a gap grew, taken, became the baseline;
    the true rates were then refused as jumps and the garbage held (and integrated into the roll) for RATE_RESYNC
    cycles. Now it waits for the next sample; the true rates, within one cycle's change of the last sound ones,
    are taken at once."""
    run(stage, sample(p=0.1))
    for _ in range(6):
        run(stage, sample(p=0.1, stale=lay.MSG_IMU_RATES))
    out = run(stage, sample(p=2.0))  # garbage within the grown window
    assert out[inp.OUT_RAW + inp.RAW_P] == 0.1 and out[inp.OUT_RATES_OK] == 0.0
    out = run(stage, sample(p=0.12))  # the true rate
    assert out[inp.OUT_RAW + inp.RAW_P] == 0.12 and out[inp.OUT_RATES_OK] == 1.0 and int(out[inp.OUT_REASONS]) == 0
    out = run(stage, sample(p=0.15))
    assert out[inp.OUT_RAW + inp.RAW_P] == 0.15 and out[inp.OUT_RATES_OK] == 1.0


def test_the_encoders_first_value_and_one_after_a_silence_are_not_jumps(stage):
    """Live, the loop runs before the encoder's first frame (stale, held at 0): its first value is no jump (it
    once raised InputRange for the daemon's first second and doubted the attitude filter); after a silence of
    n cycles the steering may have turned n x max_steer_step."""
    for _ in range(5):
        out = run(stage, sample(steer=0.0, stale=lay.MSG_STEER))
    out = run(stage, sample(steer=512.0))
    assert out[inp.OUT_RAW + inp.RAW_STEER] == 512.0 and not int(out[inp.OUT_REASONS]) & lay.REASON_OUT_OF_RANGE
    step = stage.params[inp.P_MAX_STEER_STEP]
    for _ in range(4):
        run(stage, sample(steer=512.0, stale=lay.MSG_STEER))
    out = run(stage, sample(steer=512.0 + 4.5 * step))  # 5 cycles since the last sound value: within the window
    assert out[inp.OUT_RAW + inp.RAW_STEER] == 512.0 and int(out[inp.OUT_REASONS]) == 0  # taken when confirmed
    out = run(stage, sample(steer=512.0 + 5.0 * step))  # the next frame agrees: the steering did turn
    assert out[inp.OUT_RAW + inp.RAW_STEER] == 512.0 + 5.0 * step and int(out[inp.OUT_REASONS]) == 0


def test_a_value_after_a_gap_is_taken_only_when_the_next_frame_agrees(stage):
    """The encoder's frame has no CRC: in a burst of garbage a random count whose counter happens to match lands
    in the window that grew with the gap. Taken, it became the baseline and the true values were refused as
    jumps (`sensor_faults` seed 419: the steer 4 deg off and the torque 30 N m for 0.2 s). It now waits for the
    next frame; the true value, within one cycle's motion of the last sound one, is taken at once."""
    step = stage.params[inp.P_MAX_STEER_STEP]
    run(stage, sample(steer=512.0))
    for _ in range(5):  # a burst: held frames
        run(stage, sample(steer=0.0, stale=lay.MSG_STEER))
    out = run(stage, sample(steer=512.0 + 3.0 * step))  # garbage inside the window
    assert out[inp.OUT_RAW + inp.RAW_STEER] == 512.0
    out = run(stage, sample(steer=513.0))  # the true steer, a count on
    assert out[inp.OUT_RAW + inp.RAW_STEER] == 513.0 and int(out[inp.OUT_REASONS]) == 0
    out = run(stage, sample(steer=514.0))
    assert out[inp.OUT_RAW + inp.RAW_STEER] == 514.0 and int(out[inp.OUT_REASONS]) == 0
    # garbage never confirmed by its follower is never taken, however often it comes
    for k in range(20):
        run(stage, sample(steer=0.0, stale=lay.MSG_STEER))
        out = run(stage, sample(steer=514.0 + (3.0 + (k % 3)) * step * (1 if k % 2 else -1)))
        assert out[inp.OUT_RAW + inp.RAW_STEER] == 514.0


ALL_BUT_STEER = lay.MSG_IMU_RATES | lay.MSG_IMU_ACCEL
ALL_BUT_RATES = lay.MSG_IMU_ACCEL | lay.MSG_STEER


def test_a_cycle_without_a_new_steer_frame_confirms_nothing(stage):
    """Between frames the sample still carries the last frame's count. Read again, a garbage count whose counter
    matched (refused, waiting) confirmed itself a cycle later and was taken, and the true counts were then refused
    as jumps (`sensor_faults` seed 2804 of random set 2401: the steer 11-17 deg off, the torque -169 N m)."""
    step = stage.params[inp.P_MAX_STEER_STEP]
    run(stage, sample(steer=512.0))
    for _ in range(5):  # a burst: held frames, the window grows
        run(stage, sample(steer=0.0, stale=lay.MSG_STEER))
    garbage = 512.0 + 3.0 * step
    out = run(stage, sample(steer=garbage))
    assert out[inp.OUT_RAW + inp.RAW_STEER] == 512.0
    for _ in range(3):  # no new encoder frame: the same garbage count in the sample
        out = run(stage, sample(steer=garbage, fresh=ALL_BUT_STEER))
        assert out[inp.OUT_RAW + inp.RAW_STEER] == 512.0
    out = run(stage, sample(steer=513.0))  # the true steer
    assert out[inp.OUT_RAW + inp.RAW_STEER] == 513.0 and int(out[inp.OUT_REASONS]) == 0


def test_only_new_steer_frames_count_towards_the_resync(stage):
    """`steer_resync` refused frames in a row take the encoder's word; re-reads of one frame are not more frames."""
    resync = int(stage.params[inp.P_STEER_RESYNC])
    run(stage, sample(steer=512.0))
    run(stage, sample(steer=700.0))  # one refused frame ...
    for _ in range(resync):  # ... read again and again (not so long that the window grows to 700)
        out = run(stage, sample(steer=700.0, fresh=ALL_BUT_STEER))
        assert out[inp.OUT_RAW + inp.RAW_STEER] == 512.0
    for _ in range(resync - 1):
        out = run(stage, sample(steer=700.0))
        assert out[inp.OUT_RAW + inp.RAW_STEER] == 512.0
    out = run(stage, sample(steer=700.0))  # the resync-th new frame that says so
    assert out[inp.OUT_RAW + inp.RAW_STEER] == 700.0


def test_a_cycle_without_new_rates_confirms_nothing(stage):
    """The gyro's case of the same: garbage rates inside the window a gap grew wait for the next frame; the sample
    read again in a cycle without a new IMU_Rates frame is not that frame."""
    run(stage, sample(p=0.1))
    for _ in range(6):
        run(stage, sample(p=0.1, stale=lay.MSG_IMU_RATES))
    out = run(stage, sample(p=2.0))  # garbage within the grown window: waits
    assert out[inp.OUT_RAW + inp.RAW_P] == 0.1 and out[inp.OUT_RATES_OK] == 0.0
    out = run(stage, sample(p=2.0, fresh=ALL_BUT_RATES))  # no new frame
    assert out[inp.OUT_RAW + inp.RAW_P] == 0.1 and out[inp.OUT_RATES_OK] == 0.0
    out = run(stage, sample(p=0.12))  # the true rate
    assert out[inp.OUT_RAW + inp.RAW_P] == 0.12 and out[inp.OUT_RATES_OK] == 1.0


def test_a_cycle_without_new_frames_holds_the_last_sound_values(stage):
    """At the encoder's or the IMU's slower rate, or a frame late: nothing changes and nothing is flagged."""
    run(stage, sample(p=0.1, steer=520.0))
    out = run(stage, sample(p=0.1, steer=520.0, fresh=lay.MSG_IMU_ACCEL))
    assert out[inp.OUT_RAW + inp.RAW_P] == 0.1 and out[inp.OUT_RAW + inp.RAW_STEER] == 520.0
    assert out[inp.OUT_RATES_OK] == 1.0 and int(out[inp.OUT_REASONS]) == 0
    out = run(stage, sample(p=0.11, steer=522.0))
    assert out[inp.OUT_RAW + inp.RAW_P] == 0.11 and out[inp.OUT_RAW + inp.RAW_STEER] == 522.0


def test_a_cycle_without_a_new_accelerometer_frame_trusts_only_what_the_last_one_was(stage):
    """The accelerometer's values are not replaced, only not trusted; but a suspect frame's garbage stays in the
    Sample, and the next cycle without a new IMU_Accel frame read it again as trusted."""
    out = run(stage, sample())
    assert out[inp.OUT_ACCEL_TRUSTED] == 1.0
    out = run(stage, sample(fresh=lay.MSG_IMU_RATES | lay.MSG_STEER))  # a late frame
    assert out[inp.OUT_ACCEL_TRUSTED] == 1.0  # the last one was sound
    s = sample()
    s[lay.S_SUSPECT] = lay.MSG_IMU_ACCEL
    out = run(stage, s)
    assert out[inp.OUT_ACCEL_TRUSTED] == 0.0
    for _ in range(3):  # no new frame: the suspect one's values still in the Sample
        out = run(stage, sample(fresh=lay.MSG_IMU_RATES | lay.MSG_STEER))
        assert out[inp.OUT_ACCEL_TRUSTED] == 0.0
    out = run(stage, sample())
    assert out[inp.OUT_ACCEL_TRUSTED] == 1.0


def test_a_gps_frame_whose_counter_broke_is_no_fix(stage):
    """Held like every other message's: its payload may be garbage (the speed stage's gate sees only what passed)."""
    every = lay.MSG_IMU_RATES | lay.MSG_IMU_ACCEL | lay.MSG_STEER | lay.MSG_GPS
    out = run(stage, sample(fresh=every))
    assert out[inp.OUT_GPS_OK] == 1.0 and out[inp.OUT_COURSE_NEW] == 1.0
    s = sample(gps=70.0, fresh=every)
    s[lay.S_SUSPECT] = lay.MSG_GPS
    out = run(stage, s)
    assert out[inp.OUT_GPS_OK] == 0.0 and out[inp.OUT_COURSE_NEW] == 0.0
    out = run(stage, sample(fresh=every))
    assert out[inp.OUT_GPS_OK] == 1.0


def test_imu_fresh_only_for_a_new_sound_sample_of_both_imu_messages(stage):
    """The attitude filter's roll-gyro step check compares consecutive samples: a cycle that re-reads the last
    frame, or whose frame is suspect, stale or refused, is no sample (a re-read in a lane change reads as a step),
    and neither is one that comes after missed cycles (an overrun: its change is not one period's, and a check that
    had learned the IMU's noise took it for a step, the roll 1.8 deg off on `slalom_30`)."""
    both = lay.MSG_IMU_RATES | lay.MSG_IMU_ACCEL
    dt = stage.params[inp.P_DT]
    cycle = [0]

    def fresh_at(s, periods=1):
        cycle[0] += periods
        s[lay.S_TIME] = 100.0 + cycle[0] * dt
        return run(stage, s)[inp.OUT_IMU_FRESH]

    assert fresh_at(sample(p=0.02)) == 0.0  # the first cycle: no previous one to follow
    assert fresh_at(sample(p=0.02)) == 1.0
    assert fresh_at(sample(p=0.02, fresh=lay.MSG_IMU_ACCEL)) == 0.0  # rates re-read
    assert fresh_at(sample(p=0.02, fresh=lay.MSG_IMU_RATES)) == 0.0  # accelerometer re-read
    assert fresh_at(sample(p=0.02, fresh=both, stale=lay.MSG_IMU_ACCEL)) == 0.0
    s = sample(p=0.02)
    s[lay.S_SUSPECT] = lay.MSG_IMU_RATES
    assert fresh_at(s) == 0.0
    assert fresh_at(sample(p=2.0)) == 0.0  # a step no body can make: refused
    assert fresh_at(sample(p=0.02, steer=math.nan)) == 0.0  # garbage in this cycle's input
    assert fresh_at(sample(p=0.02)) == 1.0
    assert fresh_at(sample(p=0.02), periods=3) == 0.0  # two cycles missed
    assert fresh_at(sample(p=0.02)) == 1.0
