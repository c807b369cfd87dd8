"""Stage 8, supervisor: mode, reason bits and per-signal validity from the other stages' outputs (jitted).

Reasons: the cycle's conditions (conditioning's OUT_REASONS: the inputs' reasons and SPEED_LOW) and
REASON_DIVERGING when any stage reset an observer this cycle (their OUT_DIVERGED / OUT_RESET). An event is
held for ``reason_hold`` seconds so a one-cycle event is visible on the bus; conditions that are states
(speed low, GPS lost, sensor stale) end as soon as they end.

Mode: INIT until the speed is known, FAULT when the IMU's rates are missing (nothing can be estimated) or an
observer diverged while the observers cannot run, DEGRADED with any reason (a silent steering encoder among
them: roll still comes from the IMU), CONVERGING for ``converge_time`` after the observers (re)start, then
VALID.

Validity: roll from its own uncertainty (3 sigma of the attitude filter's roll within ``roll_tolerance``, the
filter not rejecting its measurements); torque, steer rate, lateral velocity and forces once the observers
have settled. Tyre stiffness (the tyre bank's scale, lateral stage) from its own posterior and consistency:
the posterior spread of log k within ``tyre_valid_log_sd`` (the data single out one tyre), the most likely
filter's windowed normalised innovation within ``tyre_valid_max_nis`` (that tyre explains the data), no
short-window inconsistency (``tyre_valid_max_nis_fast``, a sudden change of road) for ``tyre_hold`` seconds,
the most likely hypothesis unchanged for ``tyre_settle`` seconds, and the observers settled.

Plausibility (issue #16): the published torque against the UIHOSMO on the sensors (``_plausibility``), and the
steer angle against the kinematics (``_steer_kinematics``): riding nearly straight (a_y and u r small, where
the tyres' slip adds little) the steer angle is L r cos(roll) / (u cos(caster)); a running mean of the difference
beyond ``STEER_RESIDUAL`` is an encoder that slipped or was mounted off (REASON_IMPLAUSIBLE, steer, steer
rate and torque not valid).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ptw_rt.core import attitude as att
from ptw_rt.core import conditioning as cnd
from ptw_rt.core import diagnostics as dia
from ptw_rt.core import inputs as inp
from ptw_rt.core import kalman as kf
from ptw_rt.core import lateral as lat
from ptw_rt.core import speed as spd
from ptw_rt.core import stiffness as stf
from ptw_rt.core import uio_sensors as cus
from ptw_rt.core.layout import (
    MODE_CONVERGING,
    MODE_DEGRADED,
    MODE_FAULT,
    MODE_INIT,
    MODE_VALID,
    REASON_ATTITUDE_INCONSISTENT,
    REASON_COUNTER_JUMPS,
    REASON_DECODE_ERRORS,
    REASON_DIVERGING,
    REASON_GPS_LOST,
    REASON_IMPLAUSIBLE,
    REASON_OUT_OF_RANGE,
    REASON_SPEED_LOW,
    REASON_STALE,
    V_CAMBER,
    V_CORNERING,
    V_FY_FRONT,
    V_FY_REAR,
    V_LAT_VEL,
    V_RIDER_TORQUE,
    V_ROLL,
    V_ROLL_RATE,
    V_STEER,
    V_STEER_RATE,
)
from ptw_rt.core.stage import Layout, Stage

N_REASONS = 16

STATE = Layout(
    "ST_",
    time=1,  # s since start (sum of dt)
    reason_until=N_REASONS,  # per reason bit: time until which it stays raised
    tyre_alarm_until=1,  # s: the tyres are not valid before this (a short-window inconsistency was seen)
    tyre_stable_since=1,  # s: since when the most likely tyre hypothesis has been the same and concentrated
    tyre_last_map=1,  # that hypothesis' scale
    torque_ms=1,  # N^2 m^2: windowed mean square of published - UIHOSMO-on-sensors torque (plausibility)
    implausible_until=1,  # s: the plausibility alarm holds until this
    steer_residual=1,  # rad: running mean of steer - kinematic steer, riding nearly straight
    steer_implausible_until=1,  # s: the steer-kinematics alarm holds until this
)
(
    ST_TIME,
    ST_REASON_UNTIL,
    ST_TYRE_ALARM_UNTIL,
    ST_TYRE_STABLE_SINCE,
    ST_TYRE_LAST_MAP,
    ST_TORQUE_MS,
    ST_IMPLAUSIBLE_UNTIL,
    ST_STEER_RESIDUAL,
    ST_STEER_IMPLAUSIBLE_UNTIL,
) = STATE.offsets
MAX_BANDS = 8  # speed bands of the plausibility threshold
RESIDUAL_CLIP = 2.0  # thresholds: bound of one cycle's torque difference in the plausibility window
# The steer-kinematics check (`_steer_kinematics`), from the evaluation matrix (2026-11-25): riding with both
# the body-frame a_y and the turn's centripetal u r below STEER_MAX_LATERAL_ACCEL (a steady lean keeps a_y near
# zero in any corner: gated on a_y alone, `radius_accel` with +80 kg false-alarmed on the tyres' slip) its 0.3 s
# running mean stayed within 0.23 deg on all 40 healthy cells and 48 further rides (other seeds, tyres x0.6 and
# x1.4, mu 0.7, +-80 kg); a 3-count (1 deg) encoder offset crosses 0.5 deg in 0.2 s at 40-120 km/h, 1.0 s in a
# slalom, 2.2 s in town (only its straighter moments count). In a long corner this check is blind: the torque
# plausibility sees the offset there.
STEER_WINDOW = 0.3  # s
STEER_RESIDUAL = math.radians(0.5)  # rad
STEER_MAX_LATERAL_ACCEL = 1.0  # m/s^2
# input faults that make this cycle's steer or yaw rate a held or doubtful value: not compared
_STEER_INPUT_FAULTS = REASON_STALE | REASON_OUT_OF_RANGE | REASON_COUNTER_JUMPS | REASON_DECODE_ERRORS

PARAMS = Layout(
    "P_",
    dt=1,
    reason_hold=1,  # s an event reason stays raised
    converge_time=1,  # s after the observers (re)start before VALID
    roll_tolerance=1,  # rad: the published roll is valid while 3 sigma of it is within this
    max_rejected=1,  # consecutive rejected attitude innovations from which the roll is not valid
    tyre_valid_log_sd=1,  # the tyre scale is valid while the posterior sd of log k is within this ...
    tyre_valid_max_nis=1,  # ... the most likely filter's windowed NIS within this ...
    tyre_valid_max_nis_fast=1,  # ... and its short-window NIS has not exceeded this
    tyre_hold=1,  # s: for this long after it did
    tyre_settle=1,  # s the most likely hypothesis must have stayed the same
    plausibility_alpha=1,  # share of each cycle in the torque residual's mean square
    plausibility_hold=1,  # s the alarm is held after the residual is back under its threshold
    band_count=1,  # speed bands of the threshold
    band_start=MAX_BANDS,  # m/s where each band starts (increasing, the first 0)
    band_threshold=MAX_BANDS,  # N m: RMS residual beyond which the torque is implausible, per band
    wheelbase=1,  # m
    cos_caster=1,
    steer_alpha=1,  # share of each cycle in the steer-kinematics residual's running mean (STEER_WINDOW)
)
(
    P_DT,
    P_REASON_HOLD,
    P_CONVERGE_TIME,
    P_ROLL_TOLERANCE,
    P_MAX_REJECTED,
    P_TYRE_VALID_LOG_SD,
    P_TYRE_VALID_MAX_NIS,
    P_TYRE_VALID_MAX_NIS_FAST,
    P_TYRE_HOLD,
    P_TYRE_SETTLE,
    P_PLAUSIBILITY_ALPHA,
    P_PLAUSIBILITY_HOLD,
    P_BAND_COUNT,
    P_BAND_START,
    P_BAND_THRESHOLD,
    P_WHEELBASE,
    P_COS_CASTER,
    P_STEER_ALPHA,
) = PARAMS.offsets

OUTPUTS = Layout(
    "OUT_",
    mode=1,  # MODE_*
    reasons=1,  # REASON_* bits
    valid=1,  # V_* bits
    roll_sd=1,  # rad, standard deviation of the published roll (10 when unknown)
    torque_residual=1,  # N m, windowed RMS of published - UIHOSMO-on-sensors rider torque (0 while not compared)
    plausibility=1,  # that over its speed band's threshold (> 1: REASON_IMPLAUSIBLE)
    steer_residual=1,  # rad, running mean of steer - kinematic steer (the steer-kinematics check's; 0 while stopped)
)
OUT_MODE, OUT_REASONS, OUT_VALID, OUT_ROLL_SD, OUT_TORQUE_RESIDUAL, OUT_PLAUSIBILITY, OUT_STEER_RESIDUAL = (
    OUTPUTS.offsets
)


def build_params(settings, design) -> np.ndarray:
    est = settings.estimator
    return PARAMS.vector(
        dt=float(design.sample_time),
        reason_hold=est.reason_hold_time,
        converge_time=est.converge_time,
        roll_tolerance=math.radians(est.roll_tolerance_deg),
        max_rejected=10,
        tyre_valid_log_sd=est.tyre_bank.valid_log_sd,
        tyre_valid_max_nis=est.tyre_bank.valid_max_nis,
        tyre_valid_max_nis_fast=est.tyre_bank.valid_max_nis_fast,
        tyre_hold=est.tyre_bank.alarm_hold,
        tyre_settle=est.tyre_bank.settle_time,
        plausibility_alpha=1.0 - math.exp(-float(design.sample_time) / est.plausibility.window),
        plausibility_hold=est.plausibility.hold,
        band_count=len(est.plausibility.band_start_kmh),
        band_start=_padded([v / 3.6 for v in est.plausibility.band_start_kmh]),
        band_threshold=_padded(est.plausibility.torque_residual_nm),
        wheelbase=settings.vehicle.l_f + settings.vehicle.l_r,
        cos_caster=math.cos(settings.vehicle.caster),
        steer_alpha=1.0 - math.exp(-float(design.sample_time) / STEER_WINDOW),
    )


def _padded(values) -> np.ndarray:
    """MAX_BANDS entries, the unused ones 0 (never read: `band_count` says how many there are)."""
    out = np.zeros(MAX_BANDS)
    out[: len(values)] = values
    return out


@njit(cache=True)
def _raise(st: np.ndarray, bits: int, hold: float) -> None:
    t = st[ST_TIME] + hold
    for k in range(N_REASONS):
        if bits >> k & 1:
            if st[ST_REASON_UNTIL + k] < t:
                st[ST_REASON_UNTIL + k] = t


@njit(cache=True)
def _held_reasons(st: np.ndarray) -> int:
    """REASON_* bits still held by `_raise` at the current time."""
    bits = 0
    for k in range(N_REASONS):
        if st[ST_REASON_UNTIL + k] > st[ST_TIME]:
            bits |= 1 << k
    return bits


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _plausibility(
    st: np.ndarray, prm: np.ndarray, out: np.ndarray, cond: np.ndarray, diag: np.ndarray, lateral: np.ndarray, u: float
) -> bool:
    """The plausibility monitor (docs/estimator.md, "Plausibility"): is the published rider torque (the tyre
    bank's fusion filters) contradicted by the UIHOSMO on the sensors (model inversion through steer'' with
    finite-time differentiators: a structurally different path)? The windowed RMS of their difference against
    the threshold of the speed band, learned from the evaluation matrix's healthy rides; the alarm is held
    `plausibility_hold` after the residual is back. Compared only while both run and have settled."""
    us = diag[dia.OUT_US : dia.OUT_US + cus.OUT_SIZE]
    compare = (
        cond[cnd.OUT_RUN] != 0.0 and lateral[lat.OUT_RUN_TIME] >= prm[P_CONVERGE_TIME] and us[cus.OUT_VALID] != 0.0
    )
    band = 0
    for k in range(1, int(prm[P_BAND_COUNT])):
        if u >= prm[P_BAND_START + k]:
            band = k
    threshold = prm[P_BAND_THRESHOLD + band]
    if compare:
        # each cycle's difference bounded at RESIDUAL_CLIP thresholds: a spike of a few cycles (the steer
        # differentiator after a loop stall or a late burst of frames) is not a disagreement; a persistent one
        # still fills the window within ~0.3 s
        r = min(
            max(lateral[lat.OUT_Z + kf.TAU] - us[cus.OUT_TORQUE], -RESIDUAL_CLIP * threshold), RESIDUAL_CLIP * threshold
        )
        st[ST_TORQUE_MS] += prm[P_PLAUSIBILITY_ALPHA] * (r * r - st[ST_TORQUE_MS])
    else:
        st[ST_TORQUE_MS] = 0.0
    rms = math.sqrt(max(st[ST_TORQUE_MS], 0.0))
    ratio = rms / threshold
    if compare and ratio > 1.0:
        st[ST_IMPLAUSIBLE_UNTIL] = st[ST_TIME] + prm[P_PLAUSIBILITY_HOLD]
    out[OUT_TORQUE_RESIDUAL] = rms
    out[OUT_PLAUSIBILITY] = ratio
    return st[ST_IMPLAUSIBLE_UNTIL] > st[ST_TIME]


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _steer_kinematics(st: np.ndarray, prm: np.ndarray, cond: np.ndarray, u: float) -> bool:
    """Is the steer angle contradicted by the kinematics (module docstring)? Compared while the observers run
    (speed valid), on sound inputs and nearly straight; the running mean is held otherwise, reset when the
    observers stop. The alarm holds ``plausibility_hold`` after the mean is back."""
    if cond[cnd.OUT_RUN] == 0.0:
        st[ST_STEER_RESIDUAL] = 0.0
    elif (
        abs(u * cond[cnd.OUT_YAW_RATE]) < STEER_MAX_LATERAL_ACCEL  # the turn's centripetal acceleration: a lean
        and abs(cond[cnd.OUT_A_Y]) < STEER_MAX_LATERAL_ACCEL  # hides it from the body-frame a_y
        and int(cond[cnd.OUT_REASONS]) & _STEER_INPUT_FAULTS == 0
    ):
        kinematic = prm[P_WHEELBASE] * cond[cnd.OUT_YAW_RATE] * math.cos(cond[cnd.OUT_ROLL]) / (u * prm[P_COS_CASTER])
        st[ST_STEER_RESIDUAL] += prm[P_STEER_ALPHA] * (cond[cnd.OUT_STEER] - kinematic - st[ST_STEER_RESIDUAL])
        if abs(st[ST_STEER_RESIDUAL]) > STEER_RESIDUAL:
            st[ST_STEER_IMPLAUSIBLE_UNTIL] = st[ST_TIME] + prm[P_PLAUSIBILITY_HOLD]
    return st[ST_STEER_IMPLAUSIBLE_UNTIL] > st[ST_TIME]


@njit(cache=True)
def supervisor_stage(
    st: np.ndarray,
    prm: np.ndarray,
    out: np.ndarray,
    inputs: np.ndarray,
    speed: np.ndarray,
    attitude: np.ndarray,
    cond: np.ndarray,
    diag: np.ndarray,
    lateral: np.ndarray,
    stiffness: np.ndarray,
) -> None:
    """One cycle, after every other stage."""
    st[ST_TIME] += prm[P_DT]
    reasons_now = int(cond[cnd.OUT_REASONS])
    diverged = (
        cond[cnd.OUT_DIVERGED] != 0.0
        or diag[dia.OUT_RESET] != 0.0
        or lateral[lat.OUT_DIVERGED] != 0.0
        or stiffness[stf.OUT_DIVERGED] != 0.0
    )
    _raise(st, (reasons_now | REASON_DIVERGING) if diverged else reasons_now, prm[P_REASON_HOLD])
    if attitude[att.OUT_INCONSISTENT] != 0.0:  # held by the attitude stage's own monitor
        reasons_now |= REASON_ATTITUDE_INCONSISTENT
    implausible = _plausibility(st, prm, out, cond, diag, lateral, speed[spd.OUT_U])
    steer_implausible = _steer_kinematics(st, prm, cond, speed[spd.OUT_U])
    out[OUT_STEER_RESIDUAL] = st[ST_STEER_RESIDUAL]
    if implausible or steer_implausible:
        reasons_now |= REASON_IMPLAUSIBLE
    # conditions that are states, not events, end as soon as they end
    states = REASON_SPEED_LOW | REASON_GPS_LOST | REASON_STALE | REASON_ATTITUDE_INCONSISTENT | REASON_IMPLAUSIBLE
    reasons = (reasons_now & states) | (_held_reasons(st) & ~states)

    core_ok = inputs[inp.OUT_CORE_OK] != 0.0
    imu_ok = inputs[inp.OUT_IMU_OK] != 0.0
    accel_ok = inputs[inp.OUT_ACCEL_OK] != 0.0
    run = cond[cnd.OUT_RUN] != 0.0
    run_time = lateral[lat.OUT_RUN_TIME]
    if speed[spd.OUT_KNOWN] == 0.0 and core_ok:
        mode = MODE_INIT
    elif not imu_ok:  # without the IMU's rates nothing can be estimated; without the encoder, roll still can
        mode = MODE_FAULT
    elif reasons & REASON_DIVERGING and not run and core_ok:
        mode = MODE_FAULT
    elif reasons != 0:
        mode = MODE_DEGRADED
    elif run_time < prm[P_CONVERGE_TIME]:
        mode = MODE_CONVERGING
    else:
        mode = MODE_VALID

    valid = 0
    attitude_consistent = attitude[att.OUT_INCONSISTENT] == 0.0
    if core_ok and not steer_implausible:
        valid |= V_STEER
        if attitude_consistent:  # the roll rate is the gyro less a bias the monitor doubts
            valid |= V_ROLL_RATE
    # roll is valid from its own uncertainty: 3 sigma within the documented tolerance, filter consistent
    roll_sd = attitude[att.OUT_ROLL_SD] if attitude[att.OUT_OK] != 0.0 else math.inf
    if (
        attitude_consistent
        and inputs[inp.OUT_RATES_OK] != 0.0
        and accel_ok
        and 3.0 * roll_sd <= prm[P_ROLL_TOLERANCE]
        and attitude[att.OUT_REJECTED_RUN] < prm[P_MAX_REJECTED]
    ):
        valid |= V_ROLL
    if run and run_time >= prm[P_CONVERGE_TIME]:  # the observers have settled
        if not steer_implausible:
            valid |= V_STEER_RATE
        if not (implausible or steer_implausible):  # the diverse channels do not contradict it
            valid |= V_RIDER_TORQUE
        valid |= V_LAT_VEL
        if accel_ok:
            valid |= V_FY_FRONT | V_FY_REAR
    # tyre scale: valid from the bank's posterior and consistency (module doc)
    t = st[ST_TIME]
    if lateral[lat.OUT_TYRE_NIS_FAST] > prm[P_TYRE_VALID_MAX_NIS_FAST]:
        st[ST_TYRE_ALARM_UNTIL] = t + prm[P_TYRE_HOLD]
    concentrated = lateral[lat.OUT_TYRE_LOG_SD] <= prm[P_TYRE_VALID_LOG_SD]
    if not concentrated or lateral[lat.OUT_TYRE_MAP_SCALE] != st[ST_TYRE_LAST_MAP]:
        st[ST_TYRE_STABLE_SINCE] = t
    st[ST_TYRE_LAST_MAP] = lateral[lat.OUT_TYRE_MAP_SCALE]
    if (
        run
        and run_time >= prm[P_CONVERGE_TIME]
        and concentrated
        and lateral[lat.OUT_TYRE_NIS] <= prm[P_TYRE_VALID_MAX_NIS]
        and t >= st[ST_TYRE_ALARM_UNTIL]
        and t - st[ST_TYRE_STABLE_SINCE] >= prm[P_TYRE_SETTLE]
    ):
        valid |= V_CORNERING | V_CAMBER
    out[OUT_MODE] = mode
    out[OUT_REASONS] = reasons
    out[OUT_VALID] = valid
    out[OUT_ROLL_SD] = roll_sd if math.isfinite(roll_sd) else 10.0


STAGE = Stage(
    name="supervisor",
    state=STATE,
    params=PARAMS,
    outputs=OUTPUTS,
    build_params=build_params,
    doc="mode, reason bits (events held, states live), per-signal valid bits",
)
