"""Stage 1, inputs: plausibility and hold of the raw sensor values of one Sample (jitted, allocation-free).

A non-finite or implausible value (beyond the configured limits) is replaced by the last good one and flagged
(REASON_OUT_OF_RANGE), and so are gyro rates that step further than the body can turn (``MAX_ANGULAR_ACCEL``);
a stale message, or one whose rolling counter broke this cycle (S_SUSPECT: its payload
may be garbage), is held; a steer-encoder jump larger than the steering can turn in one cycle is a corrupt
frame and held, unless it persists for ``steer_resync`` new frames (then the encoder really is there, e.g. after
a long silence). Both windows grow with the time since the last sound value, and neither frame has a CRC: after a
gap, a steer count or gyro rates further than one cycle's motion from the last sound ones are taken only when the
next frame agrees with them (garbage whose counter matched had become the baseline and locked the true values
out). A cycle without a new frame of a message holds its last sound values: the sample still carries the last
frame's, which confirm nothing. GPS: a new fix whose counter held, with at least a 2D solution, is usable; its age
decides GPS_LOST.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ptw_rt.core.layout import (
    MSG_GPS,
    MSG_IMU_ACCEL,
    MSG_IMU_RATES,
    MSG_STEER,
    REASON_GPS_LOST,
    REASON_OUT_OF_RANGE,
    REASON_STALE,
    S_ACCEL_X,
    S_ACCEL_Y,
    S_ACCEL_Z,
    S_FRESH,
    S_GPS_AGE,
    S_GPS_COURSE,
    S_GPS_FIX,
    S_GPS_SPEED,
    S_IMU_AGE,
    S_INPUT_REASONS,
    S_PITCH_RATE_BODY,
    S_ROLL_RATE_BODY,
    S_STALE,
    S_STEER_COUNT,
    S_SUSPECT,
    S_TIME,
    S_YAW_RATE_BODY,
)
from ptw_rt.core.stage import Layout, Stage

N_REASON_BITS = 16  # EST_Status.ReasonBits
REASON_MASK = (1 << N_REASON_BITS) - 1
REASON_OTHER = 1 << N_REASON_BITS  # in OUT_REASONS: the edge's reason field had bits beyond the 16 (garbage)

# the raw values, in this order (outputs RAW + k and state LAST + k)
RAW_P, RAW_Q, RAW_R, RAW_AX, RAW_AY, RAW_AZ, RAW_STEER, RAW_GPS_SPEED = range(8)
N_RAW = 8

STATE = Layout(
    "ST_",
    last=N_RAW,  # last good raw values
    steer_jumps=1,  # consecutive implausible steer-encoder jumps
    gps_age=1,  # s since the last usable GPS fix
    init=1,  # 1 once a sample has been seen
    rate_jumps=1,  # consecutive cycles with an implausible step of a gyro rate
    rates_age=1,  # cycles since the last new and sound rates (the baseline of the step check)
    steer_seen=1,  # 1 once the encoder has given a sound value (before: nothing to compare a value with)
    steer_age=1,  # cycles since its last sound value
    steer_pending=1,  # 1 while a value after a gap waits for the next frame to confirm it
    steer_candidate=1,  # that value (counts)
    rates_pending=1,  # the same for the gyro rates
    rates_candidate=3,  # p, q, r [rad/s]
    accel_sound=1,  # 1 while the accelerometer's last frame was sound (a cycle without a new frame re-reads it)
    last_time=1,  # s, the previous cycle's time stamp (S_TIME)
)
(
    ST_LAST,
    ST_STEER_JUMPS,
    ST_GPS_AGE,
    ST_INIT,
    ST_RATE_JUMPS,
    ST_RATES_AGE,
    ST_STEER_SEEN,
    ST_STEER_AGE,
    ST_STEER_PENDING,
    ST_STEER_CANDIDATE,
    ST_RATES_PENDING,
    ST_RATES_CANDIDATE,
    ST_ACCEL_SOUND,
    ST_LAST_TIME,
) = STATE.offsets

# The body cannot change its rotation rate faster than this: a scooter's quickest roll or yaw flick is ~20 rad/s^2
# (30 deg of lean reversed in half a second); gyro noise and engine vibration are a fraction of RATE_NOISE_STEP.
# A rate further from the last sound one than RATE_NOISE_STEP + MAX_ANGULAR_ACCEL x the time since it is a corrupt
# sample (a garbage payload that passed the edge's range check once drove the gyro-integrated roll 7 deg off,
# published VALID): held and flagged like an out-of-range one, unless it persists RATE_RESYNC cycles (the sensor
# really says so).
MAX_ANGULAR_ACCEL = 30.0  # rad/s^2
RATE_NOISE_STEP = 0.5  # rad/s
RATE_RESYNC = 10  # cycles

PARAMS = Layout(
    "P_",
    dt=1,
    max_rate=1,  # rad/s: plausibility limit of the gyros
    max_accel=1,  # m/s^2: ... of the accelerometer
    steer_cpr=1,  # encoder counts per revolution (also the limit of a count)
    max_gps_speed=1,  # m/s
    max_steer_step=1,  # counts per cycle: a larger jump of the encoder is not a steering motion
    steer_resync=1,  # cycles: after this many implausible jumps in a row the encoder's value is taken as the truth
    gps_hold=1,  # s without a usable fix before GPS_LOST
    # the IMU's mount off the chassis axes (sensors.imu_mount_roll / _pitch): 1 if there is one, and the cosines and
    # sines of its roll and pitch
    mounted=1,
    mount_cos_roll=1,
    mount_sin_roll=1,
    mount_cos_pitch=1,
    mount_sin_pitch=1,
)
(
    P_DT,
    P_MAX_RATE,
    P_MAX_ACCEL,
    P_STEER_CPR,
    P_MAX_GPS_SPEED,
    P_MAX_STEER_STEP,
    P_STEER_RESYNC,
    P_GPS_HOLD,
    P_MOUNTED,
    P_MOUNT_COS_ROLL,
    P_MOUNT_SIN_ROLL,
    P_MOUNT_COS_PITCH,
    P_MOUNT_SIN_PITCH,
) = PARAMS.offsets

OUTPUTS = Layout(
    "OUT_",
    raw=N_RAW,  # held and checked raw values: p, q, r [rad/s], ax, ay, az [m/s^2], steer count, GPS speed [m/s]
    reasons=1,  # REASON_* bits of this cycle's inputs (edge's, out of range, stale, GPS lost); REASON_OTHER
    core_ok=1,  # 1: IMU rates and steer encoder not stale
    imu_ok=1,  # 1: IMU rates not stale (roll can be estimated without the encoder)
    steer_ok=1,  # 1: steer encoder not stale
    accel_ok=1,  # 1: accelerometer not stale
    accel_trusted=1,  # 1: the accelerometer's values are its last frame's, and that frame was sound (not held)
    steer_trusted=1,  # 1: the steer is the last frame's sound value (not held: suspect, refused or waiting)
    rates_ok=1,  # 1: this cycle's rates are new and sound
    gps_ok=1,  # 1: a usable GPS fix arrived this cycle
    gps_lost=1,  # 1: no usable fix for longer than gps_hold
    gps_age=1,  # s since the last usable fix
    course=1,  # rad, GPS course over ground wrapped to (-pi, pi] (0 when course_new is 0)
    course_new=1,  # 1: a usable course arrived this cycle
    # s by which the fix's frame is older than the IMU's (its epoch is the receiver's latency before that): the course
    # is compared with the heading at its own instant, to the millisecond (0 without a new course)
    fix_older_than_imu=1,
    imu_fresh=1,  # 1: new IMU_Rates and IMU_Accel frames arrived this cycle, both sound (new samples, not re-read)
)
(
    OUT_RAW,
    OUT_REASONS,
    OUT_CORE_OK,
    OUT_IMU_OK,
    OUT_STEER_OK,
    OUT_ACCEL_OK,
    OUT_ACCEL_TRUSTED,
    OUT_STEER_TRUSTED,
    OUT_RATES_OK,
    OUT_GPS_OK,
    OUT_GPS_LOST,
    OUT_GPS_AGE,
    OUT_COURSE,
    OUT_COURSE_NEW,
    OUT_FIX_OLDER_THAN_IMU,
    OUT_IMU_FRESH,
) = OUTPUTS.offsets


def build_params(settings, design) -> np.ndarray:
    est, sens = settings.estimator, settings.sensors
    dt = float(design.sample_time)
    roll, pitch = math.radians(sens.imu_mount_roll), math.radians(sens.imu_mount_pitch)
    return PARAMS.vector(
        dt=dt,
        max_rate=est.max_abs_rate,
        max_accel=est.max_abs_accel,
        steer_cpr=sens.steer_counts_per_rev,
        max_gps_speed=est.max_gps_speed,
        # 3 rad/s of steer rate (the contract's range) at most, in encoder counts per cycle, one count of margin
        max_steer_step=3.0 * dt * sens.steer_counts_per_rev / (2.0 * math.pi) + 1.0,
        steer_resync=10,
        gps_hold=est.gps_hold_time,
        mounted=1.0 if roll != 0.0 or pitch != 0.0 else 0.0,
        mount_cos_roll=math.cos(roll),
        mount_sin_roll=math.sin(roll),
        mount_cos_pitch=math.cos(pitch),
        mount_sin_pitch=math.sin(pitch),
    )


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _to_chassis(v: np.ndarray, i: int, prm: np.ndarray) -> None:
    """v[i : i + 3], a vector in the IMU's axes, into the chassis axes: the mount's pitch undone, then its roll (the
    simulator's `sensors.mounted` turns the other way)."""
    cr, sr, cq, sq = prm[P_MOUNT_COS_ROLL], prm[P_MOUNT_SIN_ROLL], prm[P_MOUNT_COS_PITCH], prm[P_MOUNT_SIN_PITCH]
    x, y, z = v[i], v[i + 1], v[i + 2]
    x, z = x * cq + z * sq, -x * sq + z * cq
    y, z = y * cr - z * sr, y * sr + z * cr
    v[i], v[i + 1], v[i + 2] = x, y, z


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _count_distance(a: float, b: float, counts_per_rev: float) -> float:
    """Encoder counts between two readings, the short way round the wrap."""
    d = abs(a - b)
    return min(d, counts_per_rev - d)


@njit(cache=True)
def _wrap_pi(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@njit(cache=True)
def inputs_stage(sample: np.ndarray, st: np.ndarray, prm: np.ndarray, out: np.ndarray) -> None:
    """One cycle: `sample` (ptw_rt.core.layout) -> OUTPUTS."""
    dt = prm[P_DT]
    fresh = int(sample[S_FRESH])
    stale = int(sample[S_STALE])
    reasons_now = int(sample[S_INPUT_REASONS])
    raw = out[OUT_RAW : OUT_RAW + N_RAW]
    src = (
        S_ROLL_RATE_BODY,
        S_PITCH_RATE_BODY,
        S_YAW_RATE_BODY,
        S_ACCEL_X,
        S_ACCEL_Y,
        S_ACCEL_Z,
        S_STEER_COUNT,
        S_GPS_SPEED,
    )
    rates_replaced = False
    for k in range(N_RAW):
        v = sample[src[k]]
        if k < 3:
            limit = prm[P_MAX_RATE]
        elif k < 6:
            limit = prm[P_MAX_ACCEL]
        elif k == 6:
            limit = prm[P_STEER_CPR]
        else:
            limit = prm[P_MAX_GPS_SPEED]
        plausible = math.isfinite(v) and abs(v) <= limit and (k < 6 or v >= 0.0)
        if plausible:
            raw[k] = v
        else:
            raw[k] = st[ST_LAST + k]
            reasons_now |= REASON_OUT_OF_RANGE
            if k < 3:
                rates_replaced = True
    # a stale message, or one whose rolling counter broke this cycle (its payload may be garbage): held
    held = stale | int(sample[S_SUSPECT])
    if held & MSG_IMU_RATES:
        for k in range(3):
            raw[k] = st[ST_LAST + k]
    elif st[ST_INIT] != 0.0 and (fresh & MSG_IMU_RATES) == 0:
        # no new frame: the sample still carries the last one's rates, which are no new evidence. Read again, a
        # refused (waiting) garbage frame confirmed itself (`sensor_faults` seed 2804: the steer encoder's case)
        for k in range(3):
            raw[k] = st[ST_LAST + k]
        if st[ST_RATES_PENDING] != 0.0 or st[ST_RATES_AGE] > 0.0:
            rates_replaced = True  # the last frame was not sound: what is held is older than it
    elif st[ST_INIT] != 0.0:  # a step no body can make since the last sound rates: a corrupt sample
        one_cycle = RATE_NOISE_STEP + MAX_ANGULAR_ACCEL * dt
        step = RATE_NOISE_STEP + MAX_ANGULAR_ACCEL * dt * (st[ST_RATES_AGE] + 1.0)
        jumped = False
        far = False  # further from the last sound rates than one cycle's change
        confirmed = st[ST_RATES_PENDING] != 0.0  # ... and within one cycle's change of the value that waits
        for k in range(3):
            d = abs(raw[k] - st[ST_LAST + k])
            if d > step:
                jumped = True
            if d > one_cycle:
                far = True
            if abs(raw[k] - st[ST_RATES_CANDIDATE + k]) > one_cycle:
                confirmed = False
        resync = st[ST_RATE_JUMPS] >= RATE_RESYNC
        refused = jumped and not resync
        # after a gap the window has grown with it: garbage whose counter matched, taken there, became the baseline,
        # and the true rates were refused as jumps and the garbage held for RATE_RESYNC cycles (the steer encoder's
        # case below). Such rates, and refused ones (a value that persists confirms itself once the window allows
        # it), wait until the next sample agrees with them
        if refused or (st[ST_RATES_AGE] > 0.0 and far and not confirmed and not resync):
            st[ST_RATES_PENDING] = 1.0
            for k in range(3):
                st[ST_RATES_CANDIDATE + k] = raw[k]
                raw[k] = st[ST_LAST + k]
            rates_replaced = True
            if refused:
                st[ST_RATE_JUMPS] += 1.0
                reasons_now |= REASON_OUT_OF_RANGE
        else:
            st[ST_RATE_JUMPS] = 0.0
            st[ST_RATES_PENDING] = 0.0
    if rates_replaced:  # some rate of this cycle is a held value: the rates are not this cycle's measurement
        held |= MSG_IMU_RATES
    if held & MSG_STEER:
        raw[RAW_STEER] = st[ST_LAST + RAW_STEER]
        st[ST_STEER_AGE] += 1.0
    elif st[ST_STEER_SEEN] != 0.0 and (fresh & MSG_STEER) == 0:
        # no new frame: the sample still carries the last one's count. Read again, a refused garbage count
        # confirmed itself a cycle later and was taken (`sensor_faults` seed 2804, random set 2401: the steer
        # 11-17 deg off for 0.2 s, the torque -169 N m), and each re-read counted towards the resync
        raw[RAW_STEER] = st[ST_LAST + RAW_STEER]
        if st[ST_STEER_AGE] > 0.0 or st[ST_STEER_PENDING] != 0.0:
            st[ST_STEER_AGE] += 1.0  # the gap since the last sound value goes on
    elif st[ST_STEER_SEEN] != 0.0:
        # the steering cannot turn more than max_steer_step counts per cycle since its last sound value; a
        # bigger jump is a corrupt frame (unless it persists: then the encoder really is there)
        step = prm[P_MAX_STEER_STEP]
        jump = _count_distance(raw[RAW_STEER], st[ST_LAST + RAW_STEER], prm[P_STEER_CPR])
        confirmed = (
            st[ST_STEER_PENDING] != 0.0
            and _count_distance(raw[RAW_STEER], st[ST_STEER_CANDIDATE], prm[P_STEER_CPR]) <= step
        )
        resync = st[ST_STEER_JUMPS] >= prm[P_STEER_RESYNC]  # refused that often in a row: the encoder says so
        refused = jump > step * (st[ST_STEER_AGE] + 1.0) and not resync
        # after a gap (held or refused frames) the window has grown with it, and a garbage payload whose counter
        # happens to match lands in it (the frame has no CRC): a random count 3 deg off, taken, locked the steer
        # there and refused the true values as jumps (`sensor_faults` seed 419: 30 N m of torque). Such a value, and
        # a refused one (a value that persists confirms itself once the window allows it), waits until the next
        # frame agrees with it; within one cycle's motion of the last sound value it is taken now
        if refused or (st[ST_STEER_AGE] > 0.0 and jump > step and not confirmed and not resync):
            st[ST_STEER_PENDING] = 1.0
            st[ST_STEER_CANDIDATE] = raw[RAW_STEER]
            st[ST_STEER_AGE] += 1.0
            raw[RAW_STEER] = st[ST_LAST + RAW_STEER]
            if refused:
                st[ST_STEER_JUMPS] += 1.0
                reasons_now |= REASON_OUT_OF_RANGE
        else:
            st[ST_STEER_JUMPS] = 0.0
            st[ST_STEER_AGE] = 0.0
            st[ST_STEER_PENDING] = 0.0
    elif raw[RAW_STEER] == sample[S_STEER_COUNT]:  # the encoder's first sound value: nothing to compare it with
        st[ST_STEER_SEEN] = 1.0
        st[ST_STEER_AGE] = 0.0
    for k in range(N_RAW):
        st[ST_LAST + k] = raw[k]  # in the IMU's axes: what the next frames are checked against
    if prm[P_MOUNTED] != 0.0:  # what the later stages read: the chassis' rates and specific force
        _to_chassis(raw, RAW_P, prm)
        _to_chassis(raw, RAW_AX, prm)
    st[ST_RATES_AGE] = 0.0 if (held & MSG_IMU_RATES) == 0 else st[ST_RATES_AGE] + 1.0
    if stale != 0:
        reasons_now |= REASON_STALE

    gps_fix = sample[S_GPS_FIX]
    # a fix whose counter broke is held like any other message's (its payload may be garbage; the speed stage's gate
    # then sees only what passed): a GPS frame of a corrupt burst was taken as a fix
    gps_new = (fresh & MSG_GPS) != 0 and ((stale | int(sample[S_SUSPECT])) & MSG_GPS) == 0
    gps_ok = gps_new and gps_fix >= 2.0 and math.isfinite(sample[S_GPS_SPEED])
    if gps_ok:
        st[ST_GPS_AGE] = 0.0
    else:
        st[ST_GPS_AGE] += dt
    gps_lost = st[ST_GPS_AGE] > prm[P_GPS_HOLD]
    if gps_lost:
        reasons_now |= REASON_GPS_LOST
    course_new = gps_ok and sample[S_GPS_FIX] >= 2.0 and math.isfinite(sample[S_GPS_COURSE])
    course = math.radians(sample[S_GPS_COURSE]) if course_new else 0.0
    st[ST_INIT] = 1.0

    # 16 REASON_* bits, and bit 16 for anything beyond them in the edge's field (only garbage can set those):
    # exact in a float64 whatever came in, and still "a reason" to the later stages
    out[OUT_REASONS] = (reasons_now & REASON_MASK) | (REASON_OTHER if reasons_now & ~REASON_MASK else 0)
    out[OUT_CORE_OK] = 1.0 if (stale & (MSG_IMU_RATES | MSG_STEER)) == 0 else 0.0
    out[OUT_IMU_OK] = 1.0 if (stale & MSG_IMU_RATES) == 0 else 0.0
    out[OUT_STEER_OK] = 1.0 if (stale & MSG_STEER) == 0 else 0.0
    out[OUT_ACCEL_OK] = 1.0 if (stale & MSG_IMU_ACCEL) == 0 else 0.0
    # the accelerometer's values are never replaced, only not trusted: in a cycle without a new frame the Sample
    # re-reads the last one, trusted only if that one was (a suspect frame's garbage is still in the Sample)
    if held & MSG_IMU_ACCEL:
        st[ST_ACCEL_SOUND] = 0.0
    elif fresh & MSG_IMU_ACCEL:
        st[ST_ACCEL_SOUND] = 1.0
    out[OUT_ACCEL_TRUSTED] = st[ST_ACCEL_SOUND]
    out[OUT_STEER_TRUSTED] = 1.0 if st[ST_STEER_AGE] == 0.0 and (stale & MSG_STEER) == 0 else 0.0
    out[OUT_RATES_OK] = 1.0 if (held & MSG_IMU_RATES) == 0 else 0.0
    out[OUT_GPS_OK] = 1.0 if gps_ok else 0.0
    out[OUT_GPS_LOST] = 1.0 if gps_lost else 0.0
    out[OUT_GPS_AGE] = st[ST_GPS_AGE]
    out[OUT_COURSE] = _wrap_pi(course)
    out[OUT_COURSE_NEW] = 1.0 if course_new else 0.0
    lag = sample[S_GPS_AGE] - sample[S_IMU_AGE]
    out[OUT_FIX_OLDER_THAN_IMU] = min(max(lag, -2.0 * dt), 2.0 * dt) if course_new and math.isfinite(lag) else 0.0
    imu = MSG_IMU_RATES | MSG_IMU_ACCEL
    # ... and one cycle after the last: after missed cycles (an overrun) the newest samples are not the next ones, and
    # their change is not one period's (docs/estimator.md, "The step check learns its noise")
    one_period = abs(sample[S_TIME] - st[ST_LAST_TIME] - dt) < 0.5 * dt
    st[ST_LAST_TIME] = sample[S_TIME]
    imu_fresh = (fresh & imu) == imu and (held & imu) == 0 and not reasons_now & REASON_OUT_OF_RANGE and one_period
    out[OUT_IMU_FRESH] = 1.0 if imu_fresh else 0.0


STAGE = Stage(
    name="inputs",
    state=STATE,
    params=PARAMS,
    outputs=OUTPUTS,
    build_params=build_params,
    doc="plausibility and hold of the raw values, stale and suspect messages held, steer-encoder jumps, GPS age",
)
