"""Stage 8, supervisor: mode, reason bits and per-signal validity from the other stages' outputs (jitted).

Reasons: the cycle's conditions (conditioning's OUT_REASONS: the inputs' reasons and SPEED_LOW) and
REASON_DIVERGING when any stage reset an observer this cycle (their OUT_DIVERGED / OUT_RESET). An event is
held for ``reason_hold`` seconds so a one-cycle event is visible on the bus; conditions that are states
(speed low, GPS lost, sensor stale) end as soon as they end.

Mode: INIT until the speed is known, FAULT when the core inputs (IMU rates, steer) are missing or an observer
diverged while the observers cannot run, DEGRADED with any reason, CONVERGING for ``converge_time`` after the
observers (re)start, then VALID.

Validity: roll from its own uncertainty (3 sigma of the attitude filter's roll within ``roll_tolerance``, the
filter not rejecting its measurements); torque, steer rate, lateral velocity and forces once the observers
have settled. Tyre stiffness is never published VALID by this estimator yet. The timer-and-bound rule it had
set the bits on 15 of 40 cells of the evaluation matrix while the values were 20-150 % off (issue #12); a valid
bit must come from the learned value's own uncertainty, which the adaptive law does not carry. Until a
stiffness learner with a covariance replaces it, V_CORNERING / V_CAMBER stay clear.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ptw_rt.core import attitude as att
from ptw_rt.core import conditioning as cnd
from ptw_rt.core import diagnostics as dia
from ptw_rt.core import inputs as inp
from ptw_rt.core import lateral as lat
from ptw_rt.core import speed as spd
from ptw_rt.core import stiffness as stf
from ptw_rt.core.layout import (
    MODE_CONVERGING,
    MODE_DEGRADED,
    MODE_FAULT,
    MODE_INIT,
    MODE_VALID,
    REASON_DIVERGING,
    REASON_GPS_LOST,
    REASON_SPEED_LOW,
    REASON_STALE,
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
)
ST_TIME, ST_REASON_UNTIL = STATE.offsets

PARAMS = Layout(
    "P_",
    dt=1,
    reason_hold=1,  # s an event reason stays raised
    converge_time=1,  # s after the observers (re)start before VALID
    roll_tolerance=1,  # rad: the published roll is valid while 3 sigma of it is within this
    max_rejected=1,  # consecutive rejected attitude innovations from which the roll is not valid
)
P_DT, P_REASON_HOLD, P_CONVERGE_TIME, P_ROLL_TOLERANCE, P_MAX_REJECTED = PARAMS.offsets

OUTPUTS = Layout(
    "OUT_",
    mode=1,  # MODE_*
    reasons=1,  # REASON_* bits
    valid=1,  # V_* bits
    roll_sd=1,  # rad, standard deviation of the published roll (10 when unknown)
)
OUT_MODE, OUT_REASONS, OUT_VALID, OUT_ROLL_SD = OUTPUTS.offsets


def build_params(settings, design) -> np.ndarray:
    est = settings.estimator
    return PARAMS.vector(
        dt=float(design.sample_time),
        reason_hold=est.reason_hold_time,
        converge_time=est.converge_time,
        roll_tolerance=math.radians(est.roll_tolerance_deg),
        max_rejected=10,
    )


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
    # conditions that are states, not events, end as soon as they end
    states = REASON_SPEED_LOW | REASON_GPS_LOST | REASON_STALE
    reasons = (reasons_now & states) | (_held_reasons(st) & ~states)

    core_ok = inputs[inp.OUT_CORE_OK] != 0.0
    accel_ok = inputs[inp.OUT_ACCEL_OK] != 0.0
    run = cond[cnd.OUT_RUN] != 0.0
    run_time = lateral[lat.OUT_RUN_TIME]
    if speed[spd.OUT_KNOWN] == 0.0 and core_ok:
        mode = MODE_INIT
    elif not core_ok:
        mode = MODE_FAULT
    elif reasons & REASON_DIVERGING and not run:
        mode = MODE_FAULT
    elif reasons != 0:
        mode = MODE_DEGRADED
    elif run_time < prm[P_CONVERGE_TIME]:
        mode = MODE_CONVERGING
    else:
        mode = MODE_VALID

    valid = 0
    if core_ok:
        valid |= V_ROLL_RATE | V_STEER
    # roll is valid from its own uncertainty: 3 sigma within the documented tolerance, filter consistent
    roll_sd = attitude[att.OUT_ROLL_SD] if attitude[att.OUT_OK] != 0.0 else math.inf
    if (
        inputs[inp.OUT_RATES_OK] != 0.0
        and accel_ok
        and 3.0 * roll_sd <= prm[P_ROLL_TOLERANCE]
        and attitude[att.OUT_REJECTED_RUN] < prm[P_MAX_REJECTED]
    ):
        valid |= V_ROLL
    if run and run_time >= prm[P_CONVERGE_TIME]:  # the observers have settled
        valid |= V_RIDER_TORQUE | V_STEER_RATE
        valid |= V_LAT_VEL
        if accel_ok:
            valid |= V_FY_FRONT | V_FY_REAR
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
