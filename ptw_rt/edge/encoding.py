"""The compiled output encoder: one cycle's Estimates -> the signal values and bytes of the EST_* frames due.

One implementation for every caller: the daemon encodes each cycle through ``ptw_rt.edge.outputs.OutputEncoder``,
replay's compiled loop over a whole log (``ptw_rt.edge.drive``) calls ``encode_cycle`` for all its cycles.
What a frame holds (the rules of ``OutputEncoder``): every analog signal from its Estimates slot (a non-finite
value sent as the signal's neutral value and its ``*_Valid`` cleared), the per-signal valid bits from E_VALID,
``<Message>_Valid`` from the mode (and the message's group of valid bits), the rolling counter, and for
EST_Status the mode, stale inputs, reason bits and the process's overrun figures. The bytes: each value clipped
to its [lo, hi], NaN as its neutral value, rounded half to even as cantools does, shifted into one little-endian
word, and the E2E Profile 11 CRC in byte 0 (``ptw_rt.io.e2e``): the arithmetic of ``MessageLayout.pack`` (tested
byte-identical). A message that is not plain (Motorola or float signals) gets its values here and its bytes
from ``MessageLayout.pack``.

The plan (``PLAN``) is one block per output message in emission order: its header (``MSG``) and then
``MAX_SIGNALS`` signal rows (``SIGNAL``); the state (``STATE``) holds the rolling counters.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ptw_rt.core.layout import E_MODE, E_REASONS, E_VALID, MODE_FAULT, MODE_INIT
from ptw_rt.core.stage import Layout
from ptw_rt.io.e2e import CRC8_TABLE

MAX_SIGNALS = 10  # signals per output message the plan holds
N_OUTPUTS = 7  # EST_* messages

# what a signal of an output message carries
ROLE_ANALOG = 0  # Estimates[source]
ROLE_FLAG = 1  # 1 if E_VALID has bit `vbit` (after the analog values' own checks)
ROLE_MESSAGE_VALID = 2  # the mode runs and (no group, or some bit of the group valid)
ROLE_COUNTER = 3
ROLE_CRC = 4  # byte 0, written over by the CRC
ROLE_MODE = 5  # EST_Status ...
ROLE_SENSOR_TIMEOUTS = 6
ROLE_REASON_BITS = 7
ROLE_OVERRUN_COUNT = 8
ROLE_CYCLE_TIME_US = 9
ROLE_STATUS_VALID = 10

MSG = Layout(
    "EM_",
    frame_id=1,
    length=1,  # bytes
    period=1,  # cycles between two frames (10 Hz messages: 10)
    crc_seed=1,  # Profile 11 register after the Data ID, -1: no CRC
    modulus=1,  # of the rolling counter
    n_signals=1,
    group=1,  # V_* bits of the message's group (0: a message of diagnostics)
    plain=1,  # 1: the word below is its bytes; 0: MessageLayout.pack makes them from the values
)
EM_FRAME_ID, EM_LENGTH, EM_PERIOD, EM_CRC_SEED, EM_MODULUS, EM_N_SIGNALS, EM_GROUP, EM_PLAIN = MSG.offsets
SIGNAL = Layout(
    "ES_",
    role=1,
    source=1,  # ROLE_ANALOG: its Estimates index
    vbit=1,  # ROLE_ANALOG / ROLE_FLAG: its V_* bit (0: none)
    start=1,  # bit position of the field
    mask=1,  # 2**length - 1
    scale=1,
    offset=1,
    lo=1,
    hi=1,
    neutral=1,
)
ES_ROLE, ES_SOURCE, ES_VBIT, ES_START, ES_MASK, ES_SCALE, ES_OFFSET, ES_LO, ES_HI, ES_NEUTRAL = SIGNAL.offsets
MSG_SIZE = MSG.size
SIGNAL_SIZE = SIGNAL.size
BLOCK = MSG_SIZE + MAX_SIGNALS * SIGNAL_SIZE
PLAN_SIZE = N_OUTPUTS * BLOCK

STATE = Layout("EN_", counters=N_OUTPUTS, sent=N_OUTPUTS)
EN_COUNTERS, EN_SENT = STATE.offsets

_CRC8 = np.array(CRC8_TABLE, dtype=np.int64)


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _pack_word(plan: np.ndarray, b: int, n: int, values: np.ndarray) -> int:
    """The message's little-endian word from its values (MessageLayout.pack's arithmetic), CRC in byte 0."""
    word = 0
    for j in range(n):
        s = b + MSG_SIZE + j * SIGNAL_SIZE
        v = values[j]
        if v < plan[s + ES_LO]:
            v = plan[s + ES_LO]
        elif v > plan[s + ES_HI]:
            v = plan[s + ES_HI]
        elif v != v:  # NaN
            v = plan[s + ES_NEUTRAL]
        raw = round((v - plan[s + ES_OFFSET]) / plan[s + ES_SCALE])
        word |= (raw & int(plan[s + ES_MASK])) << int(plan[s + ES_START])
    seed = int(plan[b + EM_CRC_SEED])
    if seed >= 0:
        crc = seed
        for k in range(1, int(plan[b + EM_LENGTH])):
            crc = int(_CRC8[crc ^ ((word >> (8 * k)) & 0xFF)])
        word = (word & ~0xFF) | crc
    return word


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def encode_message(
    plan: np.ndarray,
    state: np.ndarray,
    m: int,
    est: np.ndarray,
    stale_bits: int,
    reasons: int,
    overrun_count: int,
    cycle_time_us: int,
    status_valid: bool,
    values: np.ndarray,
) -> int:
    """Message ``m``'s signal values (into ``values``) and, for a plain message, its word; advances its counter."""
    b = m * BLOCK
    n = int(plan[b + EM_N_SIGNALS])
    mode = est[E_MODE]
    mode_ok = math.isfinite(mode) and int(mode) != MODE_INIT and int(mode) != MODE_FAULT
    v = est[E_VALID]
    valid = int(v) if math.isfinite(v) else 0
    # the analog values first: a non-finite one clears its own valid bit before the flags are written
    for j in range(n):
        s = b + MSG_SIZE + j * SIGNAL_SIZE
        if int(plan[s + ES_ROLE]) == ROLE_ANALOG:
            x = est[int(plan[s + ES_SOURCE])]
            if not math.isfinite(x):  # NaN or inf: never a number on the wire
                valid &= ~int(plan[s + ES_VBIT])
                x = math.nan
            values[j] = x
    counter = int(state[EN_COUNTERS + m])
    state[EN_COUNTERS + m] = counter + 1 if counter + 1 < int(plan[b + EM_MODULUS]) else 0
    state[EN_SENT + m] += 1.0
    group = int(plan[b + EM_GROUP])
    for j in range(n):
        s = b + MSG_SIZE + j * SIGNAL_SIZE
        role = int(plan[s + ES_ROLE])
        if role == ROLE_ANALOG:
            continue
        if role == ROLE_FLAG:
            x = 1.0 if valid & int(plan[s + ES_VBIT]) else 0.0
        elif role == ROLE_MESSAGE_VALID:
            x = 1.0 if mode_ok and (group == 0 or valid & group) else 0.0
        elif role == ROLE_COUNTER:
            x = float(counter)
        elif role == ROLE_MODE:
            x = mode if math.isfinite(mode) else float(MODE_FAULT)
        elif role == ROLE_SENSOR_TIMEOUTS:
            x = float(stale_bits & 0xF)
        elif role == ROLE_REASON_BITS:
            r = est[E_REASONS]
            x = float(((int(r) if math.isfinite(r) else 0) & 0xFFFF) | (reasons & 0xFFFF))
        elif role == ROLE_OVERRUN_COUNT:
            x = float(min(overrun_count, 65535))
        elif role == ROLE_CYCLE_TIME_US:
            x = float(min(cycle_time_us, 65535))
        elif role == ROLE_STATUS_VALID:
            x = 1.0 if status_valid else 0.0
        else:  # ROLE_CRC: written over by the CRC
            x = 0.0
        values[j] = x
    if plan[b + EM_PLAIN] == 0.0:
        return 0
    return _pack_word(plan, b, n, values)


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def encode_cycle(
    plan: np.ndarray,
    state: np.ndarray,
    est: np.ndarray,
    cycle_index: int,
    stale_bits: int,
    reasons: int,
    overrun_count: int,
    cycle_time_us: int,
    messages: np.ndarray,
    words: np.ndarray,
    values: np.ndarray,
    first: int,
) -> int:
    """The frames of cycle ``cycle_index`` (0, 1, ...): every message whose period divides it, in plan order,
    written from row ``first`` on (``messages[i]`` its plan index, ``words[i]`` its bytes, ``values[i]`` its
    signal values). Returns how many."""
    i = first
    for m in range(N_OUTPUTS):
        if cycle_index % int(plan[m * BLOCK + EM_PERIOD]) == 0:
            messages[i] = m
            words[i] = encode_message(
                plan, state, m, est, stale_bits, reasons, overrun_count, cycle_time_us, True, values[i]
            )
            i += 1
    return i - first
