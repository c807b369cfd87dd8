"""The log-clocked cycle, compiled: blocks of decoded frames -> cycles (track, step, encode) in one loop.

``drive_block`` is ``ptw_rt.edge.cycle.drive_log``'s clock rule (its docstring) run inside compiled code over
a block of frames, calling the same compiled functions the daemon's cycle calls one by one: the input tracker
(``ptw_rt.edge.tracking``), the estimator's step (``ptw_rt.core.estimator.packed_step``) and the output encoder
(``ptw_rt.edge.encoding``). It stops and returns to its caller when

* ``DONE``: the block is consumed (and, for the log's last block, its last cycle closed),
* ``FULL``: the output buffers are full (the caller empties them and calls again),
* ``BREAK``: the log's clock jumped (a new segment): the caller reports it, resets the inputs and the estimator
  (``CycleRunner.restart_segment``) and calls again; the loop resumes at the frame that started the segment.

Frames arrive decoded (``Block``: the stamp, input index, what happened to it and its signal values), as
``frame_blocks`` makes them from any frame source with the codec's vectorised ``MessageLayout.unpack_many``.
The driver's own state (``STATE``) lives between calls in a float64 array.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ptw_rt.core.estimator import packed_step
from ptw_rt.core.layout import (
    E_MODE,
    ESTIMATES_SIZE,
    MODE_CONVERGING,
    MODE_DEGRADED,
    MODE_VALID,
    SAMPLE_SIZE,
)
from ptw_rt.core.stage import Layout, borrowed
from ptw_rt.edge import encoding as en
from ptw_rt.edge import tracking as tr

# what happened to a frame before the loop (Block.kinds)
FRAME_OK = 0  # decoded: values hold its signals
FRAME_UNDECODABLE = 1  # an input's identifier, but wrong length or undecodable
FRAME_UNKNOWN = 2  # not an input's identifier

# why drive_block returned
DONE, FULL, BREAK = 0, 1, 2

STATE = Layout(
    "DR_",
    t0=1,  # s, start of the segment's cycle grid
    k=1,  # index of the next cycle in the segment (its time t0 + k dt)
    now=1,  # s, time of the cycle being collected
    newest=1,  # s, newest stamp taken
    closed=1,  # s, time of the last closed cycle (-inf: none in this segment)
    consumed=1,  # 1: frames taken since the last closed cycle
    seg_cycles=1,  # cycles closed in this segment
    cycles=1,  # cycles closed in all (the output encoder's cycle index)
    segments=1,
    late_frames=1,
    bad_stamps=1,
    resume=1,  # 1: the caller has handled the break at the current frame
    break_kind=1,  # 0 gap, 1 backwards (of the last break)
    break_from=1,
    break_to=1,
    break_cycles=1,  # cycles driven before it
)
(
    DR_T0,
    DR_K,
    DR_NOW,
    DR_NEWEST,
    DR_CLOSED,
    DR_CONSUMED,
    DR_SEG_CYCLES,
    DR_CYCLES,
    DR_SEGMENTS,
    DR_LATE_FRAMES,
    DR_BAD_STAMPS,
    DR_RESUME,
    DR_BREAK_KIND,
    DR_BREAK_FROM,
    DR_BREAK_TO,
    DR_BREAK_CYCLES,
) = STATE.offsets


def initial_state(t0: float, sample_time: float, cycles: int) -> np.ndarray:
    """The driver at the start of a log whose cycle grid starts at ``t0``; ``cycles`` already driven (the
    output encoder's next cycle index)."""
    s = np.zeros(STATE.size)
    s[DR_T0] = t0
    s[DR_NEWEST] = t0
    s[DR_K] = 1.0
    s[DR_NOW] = t0 + sample_time
    s[DR_CLOSED] = -math.inf
    s[DR_SEGMENTS] = 1.0
    s[DR_CYCLES] = cycles
    return s


@njit(cache=True, inline="always")  # no call: see ptw_rt.core.stage, "Reference counting"
def _close_cycle(
    now: float,
    c: int,
    f: int,
    tstate: np.ndarray,
    tparams: np.ndarray,
    sample: np.ndarray,
    est: np.ndarray,
    s: np.ndarray,
    si: np.ndarray,
    t: np.ndarray,
    ti: np.ndarray,
    plan: np.ndarray,
    estate: np.ndarray,
    process: np.ndarray,
    cycle_index: int,
    cycle_times: np.ndarray,
    samples: np.ndarray,
    estimates: np.ndarray,
    frame_end: np.ndarray,
    messages: np.ndarray,
    words: np.ndarray,
    values: np.ndarray,
) -> int:
    """One whole cycle at ``now`` into output row ``c`` and frame rows from ``f``; returns the frames written.
    ``process``: [degraded, reasons, overrun count, cycle time us] of the process (``CycleRunner``)."""
    tr.track_fill(tstate, tparams, sample, now)
    packed_step(sample, est, s, si, t, ti)
    if process[0] != 0.0 and (est[E_MODE] == MODE_CONVERGING or est[E_MODE] == MODE_VALID):
        est[E_MODE] = MODE_DEGRADED  # the process cannot keep its period (the daemon's overrun rule)
    nf = en.encode_cycle(
        plan,
        estate,
        est,
        cycle_index,
        int(tstate[tr.TR_STALE_BITS]),
        int(process[1]),
        int(process[2]),
        int(process[3]),
        messages,
        words,
        values,
        f,
    )
    cycle_times[c] = now
    for j in range(SAMPLE_SIZE):
        samples[c, j] = sample[j]
    for j in range(ESTIMATES_SIZE):
        estimates[c, j] = est[j]
    frame_end[c] = f + nf
    return nf


@njit(cache=True)
def drive_block(
    state: np.ndarray,
    dt: float,
    max_gap: float,
    reorder_tolerance: float,
    times: np.ndarray,
    kinds: np.ndarray,
    inputs: np.ndarray,
    frame_values: np.ndarray,
    start: int,
    last_block: bool,
    tstate: np.ndarray,
    tparams: np.ndarray,
    sample: np.ndarray,
    est: np.ndarray,
    s: np.ndarray,
    si: np.ndarray,
    t: np.ndarray,
    ti: np.ndarray,
    plan: np.ndarray,
    estate: np.ndarray,
    process: np.ndarray,
    cycle_times: np.ndarray,
    samples: np.ndarray,
    estimates: np.ndarray,
    frame_end: np.ndarray,
    messages: np.ndarray,
    words: np.ndarray,
    values: np.ndarray,
    out: np.ndarray,
) -> int:
    """Drive frames ``start..`` of the block; ``out`` = [next frame, cycles written, frames written]."""
    # no reference counting on what the loop hands on per frame and per cycle (`ptw_rt.core.stage.borrowed`: an
    # atomic increment and decrement per array and call otherwise); the caller holds the arrays
    inputs, frame_values = borrowed(inputs), borrowed(frame_values)
    tstate, tparams = borrowed(tstate), borrowed(tparams)
    sample, est, s, si, t, ti = borrowed(sample), borrowed(est), borrowed(s), borrowed(si), borrowed(t), borrowed(ti)
    plan, estate, process = borrowed(plan), borrowed(estate), borrowed(process)
    cycle_times, samples, estimates = borrowed(cycle_times), borrowed(samples), borrowed(estimates)
    frame_end, messages, words, values = borrowed(frame_end), borrowed(messages), borrowed(words), borrowed(values)
    i = start
    n = times.shape[0]
    c = 0
    f = 0
    capacity = cycle_times.shape[0]
    frame_capacity = words.shape[0] - en.N_OUTPUTS
    t0 = state[DR_T0]
    k = int(state[DR_K])
    now = state[DR_NOW]
    newest = state[DR_NEWEST]
    closed = state[DR_CLOSED]
    consumed = state[DR_CONSUMED] != 0.0
    seg_cycles = int(state[DR_SEG_CYCLES])
    cycles = int(state[DR_CYCLES])
    result = DONE
    while True:
        ends_segment = False  # the frame at i starts a new segment: close what was collected, return BREAK
        if i < n:
            ts = times[i]
            if not newest - reorder_tolerance <= ts <= newest + max_gap:
                if not math.isfinite(ts):  # no clock to run on: dropped, counted
                    state[DR_BAD_STAMPS] += 1.0
                    i += 1
                    continue
                if (consumed or seg_cycles > 0) and state[DR_RESUME] == 0.0:
                    ends_segment = True
                else:  # the segment starts at this frame (the caller has handled its break)
                    state[DR_RESUME] = 0.0
                    t0 = ts
                    newest = ts
                    k = 1
                    now = t0 + dt
                    closed = -math.inf
                    seg_cycles = 0
            if not ends_segment and ts <= now:
                kind = kinds[i]
                if kind == FRAME_OK:
                    tr.track_values(tstate, tparams, inputs[i], ts, frame_values[i], True)
                elif kind == FRAME_UNDECODABLE:
                    tr.track_decode_error(tstate, inputs[i], 1.0)
                else:
                    tr.track_unknown(tstate)
                consumed = True
                if ts > newest:
                    newest = ts
                elif ts <= closed:
                    state[DR_LATE_FRAMES] += 1.0
                i += 1
                continue
        elif not (consumed and last_block):
            break  # DONE: the next block goes on from here (or, the log's last, nothing left to close)
        if consumed or not ends_segment:  # the cycle at `now` closes (at a break: its frames are this segment's)
            if c >= capacity or f > frame_capacity:
                result = FULL
                break
            f += _close_cycle(
                now, c, f, tstate, tparams, sample, est, s, si, t, ti, plan, estate, process, cycles,
                cycle_times, samples, estimates, frame_end, messages, words, values,
            )  # fmt: skip
            c += 1
            cycles += 1
            consumed = False
            closed = now
            seg_cycles += 1
            k += 1
            now = t0 + k * dt
        if ends_segment:
            state[DR_SEGMENTS] += 1.0
            state[DR_BREAK_KIND] = 0.0 if ts > newest else 1.0
            state[DR_BREAK_FROM] = newest
            state[DR_BREAK_TO] = ts
            state[DR_BREAK_CYCLES] = cycles
            state[DR_RESUME] = 1.0
            result = BREAK
            break
    state[DR_T0] = t0
    state[DR_K] = k
    state[DR_NOW] = now
    state[DR_NEWEST] = newest
    state[DR_CLOSED] = closed
    state[DR_CONSUMED] = 1.0 if consumed else 0.0
    state[DR_SEG_CYCLES] = seg_cycles
    state[DR_CYCLES] = cycles
    out[0] = i
    out[1] = c
    out[2] = f
    return result


class Outputs:
    """The buffers one ``drive_block`` call fills: up to ``capacity`` cycles and their frames."""

    def __init__(self, capacity: int) -> None:
        self.cycle_times = np.zeros(capacity)
        self.samples = np.zeros((capacity, SAMPLE_SIZE))
        self.estimates = np.zeros((capacity, ESTIMATES_SIZE))
        self.frame_end = np.zeros(capacity, dtype=np.int64)
        frames = capacity * en.N_OUTPUTS + en.N_OUTPUTS
        self.messages = np.zeros(frames, dtype=np.int64)
        self.words = np.zeros(frames, dtype=np.uint64)  # the frames little-endian (int64 in compiled code: its bits)
        self.values = np.zeros((frames, en.MAX_SIGNALS))
        self.counts = np.zeros(3, dtype=np.int64)  # next frame, cycles written, frames written
