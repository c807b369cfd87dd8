"""Compiled scan of a block of plain candump ``-L`` lines into columns (replay's parser; jitted, no objects).

A block of lines read from a log is either *plain* (every line exactly as ``candump -L`` writes it, the form
``parse_line`` takes on its fast path: ``(digits.digits) channel ID#HEX`` with single spaces, 3 or 8 id
digits, whole payload bytes, nothing after) or not. `scan_plain` parses a plain block in one compiled pass
and says "not plain" at the first line that is not; the caller then takes the block line by line through
``parse_line``, which is the definition. So this scan only has to be right on the lines it accepts, and it
accepts a subset of what ``parse_line`` takes, never more (tests/test_candump_scan.py compares them on
mutated lines):

* the stamp: 1-10 integer and 0-9 fractional digits with at most 2^53 as the integer of all its digits, so
  that ``digits / 10**fraction_digits`` is one correctly rounded IEEE division of two exact doubles: the same
  double as Python's ``float(text)``; a longer stamp, or one after ``MAX_TIMESTAMP``, is "not plain";
* the channel: printable ASCII without ``#`` (Python's ``\\S`` also takes other characters; those blocks go
  line by line, to the same result);
* the id in range for its width (0x7FF, 0x1FFFFFFF), a payload of at most 8 whole bytes, nothing after it
  (a trailing ``\\r``, an ``R`` remote frame or a direction field are "not plain").

Why compiled: the regular-expression parse of a 20-minute log (370 000 lines) took 0.7 s of a replay whose
estimator needs 0.85 s for the same log (issue #15's replay-work figure).
"""

from __future__ import annotations

import numpy as np
from numba import njit

NOT_PLAIN = -1

_EXACT_INTEGER = 1 << 53  # integers up to here are exact doubles
POW10 = np.array([10.0**k for k in range(10)])  # exact doubles


@njit(cache=True)
def _hex_value(byte: np.uint8) -> int:
    """The value of an ASCII hex digit, -1 for any other byte."""
    c = np.int64(byte)
    if 48 <= c <= 57:
        return c - 48
    if 65 <= c <= 70:
        return c - 55
    if 97 <= c <= 102:
        return c - 87
    return -1


@njit(cache=True)
def scan_plain(
    text: np.ndarray,
    max_line: int,
    max_timestamp: float,
    pow10: np.ndarray,
    times: np.ndarray,
    ids: np.ndarray,
    extended: np.ndarray,
    lengths: np.ndarray,
    data: np.ndarray,
    channel_span: np.ndarray,
) -> int:
    """Parse ``text`` (``uint8``: the block's lines joined by ``\\n``, no final newline) into the columns (each as
    long as the block has lines; ``data`` zeroed, ``uint8[n, 8]``). ``channel_span`` receives the first line's
    channel [start, stop) and, in [2], 1 if every line's channel equals it. Returns the number of lines parsed
    (all of them), or NOT_PLAIN at the first line that is not plain."""
    n_bytes = text.shape[0]
    n = times.shape[0]
    p = 0
    same_channel = 1
    for row in range(n):
        line_start = p
        # (stamp)
        if p >= n_bytes or text[p] != 40:  # '('
            return NOT_PLAIN
        p += 1
        value = 0
        digits = 0
        while p < n_bytes and 48 <= text[p] <= 57:
            value = value * 10 + (np.int64(text[p]) - 48)
            digits += 1
            p += 1
            if value > _EXACT_INTEGER:
                return NOT_PLAIN
        if digits == 0 or digits > 10 or p >= n_bytes or text[p] != 46:  # '.'
            return NOT_PLAIN
        p += 1
        fraction = 0
        while p < n_bytes and 48 <= text[p] <= 57:
            value = value * 10 + (np.int64(text[p]) - 48)
            fraction += 1
            p += 1
            if value > _EXACT_INTEGER or fraction > 9:
                return NOT_PLAIN
        if p + 1 >= n_bytes or text[p] != 41 or text[p + 1] != 32:  # ') '
            return NOT_PLAIN
        p += 2
        t = float(value) / pow10[fraction]
        if not t <= max_timestamp:
            return NOT_PLAIN
        # channel: printable ASCII but '#', up to one space
        c0 = p
        while p < n_bytes and 33 <= text[p] <= 126 and text[p] != 35:
            p += 1
        c1 = p
        if c1 == c0 or p >= n_bytes or text[p] != 32:
            return NOT_PLAIN
        p += 1
        if row == 0:
            channel_span[0] = c0
            channel_span[1] = c1
        elif same_channel == 1:
            if c1 - c0 != channel_span[1] - channel_span[0]:
                same_channel = 0
            else:
                for k in range(c1 - c0):
                    if text[c0 + k] != text[channel_span[0] + k]:
                        same_channel = 0
                        break
        # ID#
        frame_id = 0
        id_digits = 0
        while p < n_bytes:
            h = _hex_value(text[p])
            if h < 0:
                break
            frame_id = frame_id * 16 + h
            id_digits += 1
            p += 1
            if id_digits > 8:
                return NOT_PLAIN
        if p >= n_bytes or text[p] != 35:  # '#'
            return NOT_PLAIN
        p += 1
        if id_digits == 3:
            if frame_id > 0x7FF:
                return NOT_PLAIN
            extended[row] = False
        elif id_digits == 8:
            if frame_id > 0x1FFFFFFF:
                return NOT_PLAIN
            extended[row] = True
        else:
            return NOT_PLAIN
        # payload: whole bytes up to the end of the line
        count = 0
        while p < n_bytes and text[p] != 10:
            if p + 1 >= n_bytes or count >= 8:
                return NOT_PLAIN
            hi = _hex_value(text[p])
            lo = _hex_value(text[p + 1])
            if hi < 0 or lo < 0:
                return NOT_PLAIN
            data[row, count] = hi * 16 + lo
            count += 1
            p += 2
        if p - line_start > max_line:
            return NOT_PLAIN
        times[row] = t
        ids[row] = frame_id
        lengths[row] = count
        p += 1  # the newline (or past the end after the last line)
    if p < n_bytes:  # more lines than the caller counted
        return NOT_PLAIN
    channel_span[2] = same_channel
    return n
