"""The compiled input tracker: decoded input frames -> the cycle's Sample, with the health of every input.

One implementation for every caller: the daemon calls ``track_values`` once per received frame (through
``ptw_rt.edge.inputs.InputTracker``), replay calls the same functions inside its compiled loop over a whole
log (``ptw_rt.edge.drive``). The rules (``InputTracker``'s docstring) per input message ``k``:

* ``track_values``: a decoded frame (or the signals of another source, ``counted`` False): its rolling counter
  checked (following neither the previous frame's nor, by the frames since, the last in-sequence frame's ->
  counter_jumps, REASON_COUNTER_JUMPS, the message suspect this cycle), every
  signal whose raw field can leave its DBC range checked (outside or NaN -> out_of_range, REASON_OUT_OF_RANGE,
  the frame dropped), for an input whose noise spans many LSBs (the IMU's) a payload repeated ``frozen_after``
  times not taken as fresh (frozen_frames: a stuck sensor behind a live counter goes stale), the signals copied
  into the Sample's slots, the message fresh;
* ``track_decode_error``: a frame that could not be decoded (it took a slot of the counter's sequence);
  ``track_unknown``: someone else's frame;
* ``track_fill``: the Sample at the cycle's time: stale inputs (no valid frame within their timeout, a
  fresh -> stale transition counted), the IMU's age, the cycle's fresh/reason/suspect bits, which then restart.

State and parameters are flat float64 arrays with the named layouts below (bits and counts held as floats:
exact below 2**53). Nothing here allocates or raises.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ptw_rt.core.layout import (
    REASON_COUNTER_JUMPS,
    REASON_DECODE_ERRORS,
    REASON_OUT_OF_RANGE,
    S_FRESH,
    S_GPS_AGE,
    S_IMU_AGE,
    S_INPUT_REASONS,
    S_STALE,
    S_STEER_AGE,
    S_SUSPECT,
    S_TIME,
    SAMPLE_SIZE,
)
from ptw_rt.core.stage import Layout

N_INPUTS = 4  # IMU_Rates, IMU_Accel, Steer_Encoder, GPS_Velocity (``ptw_rt.edge.inputs.SIGNAL_SLOTS`` order)
MAX_SIGNALS = 8  # signals per input message the tables hold
MAX_INPUT_AGE = 0.05  # s: the Sample's IMU and steer ages are bounded (beyond a few cycles the input is stale)
NO_COUNTER = -1.0  # TR_COUNTER_LAST before the first counter after construction or a restart

STATE = Layout(
    "TR_",
    row=SAMPLE_SIZE,  # the newest valid value of every input signal, kept from cycle to cycle
    last_valid=N_INPUTS,  # s, time of the newest valid frame (-inf: none)
    stale=N_INPUTS,  # 1 while the input is stale (at the last fill)
    frames=N_INPUTS,  # cumulative counts, per input
    decode_errors=N_INPUTS,
    out_of_range=N_INPUTS,
    counter_jumps=N_INPUTS,
    timeouts=N_INPUTS,  # fresh -> stale transitions
    counter_last=N_INPUTS,  # the last rolling counter seen (NO_COUNTER: none yet)
    counter_good=N_INPUTS,  # the counter of the last frame that was in sequence (NO_COUNTER: none yet)
    since_good=N_INPUTS,  # frames of the input since that one, undecodable ones included (each took a slot)
    previous=N_INPUTS * MAX_SIGNALS,  # [k * MAX_SIGNALS + j]: signal j of input k's last frame
    repeats=N_INPUTS,  # consecutive frames whose payload (counter and CRC aside) repeats the one before
    frozen_frames=N_INPUTS,  # cumulative: frames not taken as fresh because their payload no longer changes
    fresh=1,  # MSG_* bits of this cycle
    reasons=1,  # REASON_* bits of this cycle
    suspect=1,  # MSG_* bits with a broken counter this cycle
    stale_bits=1,  # MSG_* bits stale at the last fill
    unknown_ids=1,  # frames of identifiers that are not inputs
)
(
    TR_ROW,
    TR_LAST_VALID,
    TR_STALE,
    TR_FRAMES,
    TR_DECODE_ERRORS,
    TR_OUT_OF_RANGE,
    TR_COUNTER_JUMPS,
    TR_TIMEOUTS,
    TR_COUNTER_LAST,
    TR_COUNTER_GOOD,
    TR_SINCE_GOOD,
    TR_PREVIOUS,
    TR_REPEATS,
    TR_FROZEN_FRAMES,
    TR_FRESH,
    TR_REASONS,
    TR_SUSPECT,
    TR_STALE_BITS,
    TR_UNKNOWN_IDS,
) = STATE.offsets

PARAMS = Layout(
    "TP_",
    timeout=N_INPUTS,  # s without a valid frame before the input is stale
    bit=N_INPUTS,  # its MSG_* bit
    counter_pos=N_INPUTS,  # position of its rolling counter among its signals, -1: none
    modulus=N_INPUTS,  # of that counter
    n_signals=N_INPUTS,
    check=N_INPUTS * MAX_SIGNALS,  # [k * MAX_SIGNALS + j]: 1 if signal j's raw field can decode outside [lo, hi]
    lo=N_INPUTS * MAX_SIGNALS,
    hi=N_INPUTS * MAX_SIGNALS,
    slot=N_INPUTS * MAX_SIGNALS,  # Sample index signal j is copied to, -1: none
    imu=1,  # the input whose age is the Sample's IMU age
    steer=1,  # the input whose age is the Sample's steer age
    gps=1,  # the input whose age is the Sample's GPS age
    frozen_after=N_INPUTS,  # repeated payloads after which a frame is not fresh (0: never, a value may hold)
    crc_pos=N_INPUTS,  # position of its CRC among its signals, -1: none (it changes with the counter)
)
(
    TP_TIMEOUT,
    TP_BIT,
    TP_COUNTER_POS,
    TP_MODULUS,
    TP_N_SIGNALS,
    TP_CHECK,
    TP_LO,
    TP_HI,
    TP_SLOT,
    TP_IMU,
    TP_STEER,
    TP_GPS,
    TP_FROZEN_AFTER,
    TP_CRC_POS,
) = PARAMS.offsets

# the cumulative counts of ``InputTracker.summary``, with their state offsets
COUNTS = (
    ("frames", TR_FRAMES),
    ("decode_errors", TR_DECODE_ERRORS),
    ("out_of_range", TR_OUT_OF_RANGE),
    ("counter_jumps", TR_COUNTER_JUMPS),
    ("timeouts", TR_TIMEOUTS),
    ("frozen_frames", TR_FROZEN_FRAMES),
)


def initial_state() -> np.ndarray:
    state = np.zeros(STATE.size)
    track_restart(state)  # the suspect bits, which a restart keeps, start at 0
    return state


@njit(cache=True)
def track_restart(state: np.ndarray) -> None:
    """Forget every input's values, freshness and rolling counter (a new segment of a log); the cumulative
    counts and the suspect bits are kept."""
    state[TR_ROW : TR_ROW + SAMPLE_SIZE] = 0.0
    bits = 0
    for k in range(N_INPUTS):
        state[TR_STALE + k] = 1.0  # stale again without a timeout transition: nothing has been received yet
        state[TR_LAST_VALID + k] = -math.inf
        state[TR_COUNTER_LAST + k] = NO_COUNTER
        state[TR_COUNTER_GOOD + k] = NO_COUNTER
        state[TR_SINCE_GOOD + k] = 0.0
        bits |= 1 << k
    state[TR_STALE_BITS] = bits
    state[TR_FRESH] = 0.0
    state[TR_REASONS] = 0.0
    state[TR_REPEATS : TR_REPEATS + N_INPUTS] = 0.0


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def track_values(state: np.ndarray, params: np.ndarray, k: int, t: float, values, counted: bool) -> None:
    """Input ``k``'s decoded signals (``values[j]``, DBC order) stamped ``t``; ``counted``: a CAN frame, whose
    rolling counter is checked."""
    state[TR_FRAMES + k] += 1.0
    bit = int(params[TP_BIT + k])
    pos = int(params[TP_COUNTER_POS + k])
    if counted and pos >= 0:
        counter = int(values[pos])
        modulus = int(params[TP_MODULUS + k])
        last = state[TR_COUNTER_LAST + k]
        good = state[TR_COUNTER_GOOD + k]
        since = state[TR_SINCE_GOOD + k] + 1.0
        state[TR_COUNTER_LAST + k] = counter
        # in sequence: the counter follows the previous frame's, or the last in-sequence frame's by the frames
        # since. A garbage payload (a random counter) between two sound frames took a slot: the sound frame after
        # it was suspect too (only the previous frame's counter was asked), and in a burst where every other frame
        # was garbage every sound frame was held (`sensor_faults`: 0.3 s of held rates and steer)
        follows_last = last == NO_COUNTER or (counter - int(last)) % modulus == 1
        # (within one turn of the counter: beyond it, 16 frames lost and none are the same count)
        follows_good = good != NO_COUNTER and since < modulus and (counter - int(good)) % modulus == int(since)
        if follows_last or follows_good:
            state[TR_COUNTER_GOOD + k] = counter
            state[TR_SINCE_GOOD + k] = 0.0
        else:
            state[TR_SINCE_GOOD + k] = since
            state[TR_COUNTER_JUMPS + k] += 1.0
            state[TR_REASONS] = int(state[TR_REASONS]) | REASON_COUNTER_JUMPS
            state[TR_SUSPECT] = int(state[TR_SUSPECT]) | bit  # the payload of a broken sequence may be garbage
    n = int(params[TP_N_SIGNALS + k])
    base = k * MAX_SIGNALS
    for j in range(n):
        if params[TP_CHECK + base + j] != 0.0:
            v = values[j]
            if not params[TP_LO + base + j] <= v <= params[TP_HI + base + j]:  # also NaN
                state[TR_OUT_OF_RANGE + k] += 1.0
                state[TR_REASONS] = int(state[TR_REASONS]) | REASON_OUT_OF_RANGE
                return
    if params[TP_FROZEN_AFTER + k] > 0.0:
        # a sensor whose noise spans many LSBs never repeats a payload: one that does has stopped measuring behind a
        # live counter (a hung IMU front end held roll 10 deg and the torque 25 N m off VALID: daemon fuzzing,
        # 2026-11-26); its frames stop counting as fresh, and the input goes stale after its timeout
        crc = int(params[TP_CRC_POS + k])
        same = True
        for j in range(n):
            if j != pos and j != crc and values[j] != state[TR_PREVIOUS + base + j]:
                same = False
            state[TR_PREVIOUS + base + j] = values[j]
        state[TR_REPEATS + k] = state[TR_REPEATS + k] + 1.0 if same else 0.0
        if state[TR_REPEATS + k] >= params[TP_FROZEN_AFTER + k]:
            state[TR_FROZEN_FRAMES + k] += 1.0
            return
    for j in range(n):
        slot = int(params[TP_SLOT + base + j])
        if slot >= 0:
            state[TR_ROW + slot] = values[j]
    state[TR_LAST_VALID + k] = t
    state[TR_FRESH] = int(state[TR_FRESH]) | bit


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def track_decode_error(state: np.ndarray, k: int, count: float) -> None:
    """``count`` records of input ``k`` that could not be decoded (a serial receiver's bad lines come counted: one
    call per line, 750 000 a second of junk, stalled the cycle 209 ms)."""
    state[TR_DECODE_ERRORS + k] += count
    state[TR_SINCE_GOOD + k] += count  # they took slots of the sequence: the next sound frame's counter skips them
    state[TR_REASONS] = int(state[TR_REASONS]) | REASON_DECODE_ERRORS


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def track_unknown(state: np.ndarray) -> None:
    state[TR_UNKNOWN_IDS] += 1.0


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def track_fill(state: np.ndarray, params: np.ndarray, sample: np.ndarray, now: float) -> None:
    """Write the cycle's Sample at time ``now`` and start collecting the next cycle."""
    stale_bits = 0
    for k in range(N_INPUTS):
        stale = now - state[TR_LAST_VALID + k] > params[TP_TIMEOUT + k]
        if stale and state[TR_STALE + k] == 0.0:
            state[TR_TIMEOUTS + k] += 1.0
        state[TR_STALE + k] = 1.0 if stale else 0.0
        if stale:
            stale_bits |= int(params[TP_BIT + k])
    state[TR_STALE_BITS] = stale_bits
    row = TR_ROW
    state[row + S_TIME] = now
    state[row + S_FRESH] = state[TR_FRESH]
    state[row + S_STALE] = stale_bits
    state[row + S_INPUT_REASONS] = state[TR_REASONS]
    age = now - state[TR_LAST_VALID + int(params[TP_IMU])]
    state[row + S_IMU_AGE] = min(max(age, 0.0), MAX_INPUT_AGE)
    age = now - state[TR_LAST_VALID + int(params[TP_STEER])]
    state[row + S_STEER_AGE] = min(max(age, 0.0), MAX_INPUT_AGE)
    age = now - state[TR_LAST_VALID + int(params[TP_GPS])]
    state[row + S_GPS_AGE] = min(max(age, 0.0), MAX_INPUT_AGE)
    state[row + S_SUSPECT] = state[TR_SUSPECT]
    for i in range(SAMPLE_SIZE):
        sample[i] = state[row + i]
    state[TR_FRESH] = 0.0
    state[TR_REASONS] = 0.0
    state[TR_SUSPECT] = 0.0
