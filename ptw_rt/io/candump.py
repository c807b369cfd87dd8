"""candump ``-L`` text logs: ``(1700000000.123456) vcan0 123#DEADBEEF``.

Written exactly as can-utils' ``candump -L`` does (10-digit zero-padded seconds, 6 decimals, 3 hex digits for
11-bit ids, 8 for 29-bit ids, uppercase payload), so ``canplayer``, python-can's ``can.LogReader`` and
``cantools decode`` read our logs. Reading is tolerant: bad lines are counted (per reason), logged with file and
line number, and skipped; the reader never raises on content (only if the file cannot be opened: missing, not a
regular file, larger than ``MAX_LOG_BYTES``).

A log is untrusted data, its time stamps included. Per line (``parse_line``): at most 10 integer and 9
fractional digits, no sign, not after 2200-01-01 (``MAX_TIMESTAMP``); a line longer than ``MAX_LINE_CHARS`` is
skipped without being held in memory. Across lines (``CandumpReader``), the time rule:

* A frame is *consistent* with a time reference r when ``r - reorder_tolerance <= t <= r + max_jump``.
* Frames consistent with the newest accepted stamp are accepted at once (the fast path). One stamped up to
  ``reorder_tolerance`` (default 20 ms, two cycles) before it is accepted as is and counted in ``reordered``:
  a consumer clocked by the log gives it to the current cycle, as the live bus would a late frame.
* Any other frame is a *suspect*: it starts (or extends) a candidate time base. A candidate that collects
  ``confirm`` (default 8) mutually consistent frames before the accepted base collects ``confirm`` more becomes
  the time base: a real gap or a jump back (concatenated logs), counted in ``discontinuities`` with its line,
  and its frames are passed on. Otherwise its frames are rejected: ``out_of_order`` if stamped before the base
  (stale data must not be fed as if fresh), ``time_jump`` if after (a stray far-future stamp).
* At the start there is no base yet: the first candidate to collect ``confirm`` frames becomes it, so a stray
  ``(0000000000.000001)`` line before a 1.7e9 log is rejected. A log too short to confirm anything is taken
  as it is (its longest candidate); at the end of a log an unconfirmed candidate is rejected.

So the frames passed on move forward in time, except by at most ``reorder_tolerance``, or at a counted
discontinuity. ``max_jump=reorder_tolerance=math.inf`` turns the rule off (the frames in file order).
Rejections are counted in ``rejected`` by reason (``REJECT_REASONS``); ``malformed`` is their sum.
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import IO, Any, NamedTuple

import numpy as np

from ptw_rt.errors import UserFacingError
from ptw_rt.io import compressed
from ptw_rt.io.candump_scan import POW10, scan_plain

__all__ = [
    "MAX_LINE_CHARS",
    "MAX_LOG_BYTES",
    "MAX_TIMESTAMP",
    "REJECT_REASONS",
    "Problem",
    "TimeRule",
    "BadTimestampError",
    "BusChoice",
    "CandumpFileError",
    "CandumpReader",
    "CandumpWriter",
    "LogFrame",
    "format_line",
    "parse_line",
    "FrameArrays",
    "payload_rows",
    "Jump",
    "read_log",
    "text_blocks",
    "timestamp_problem",
]

log = logging.getLogger(__name__)

_STD_MAX = 0x7FF
_EXT_MAX = 0x1FFFFFFF
_MAX_DATA = 8
# byte -> its two upper-case hex digits, for write_frames
_HEX_DIGITS = np.frombuffer("".join(f"{b:02X}" for b in range(256)).encode(), dtype="S2")
_TIMESTAMP_RE = re.compile(r"\(([0-9]{1,10}(?:\.[0-9]{0,9})?)\)")
_HEX_RE = re.compile(r"[0-9A-Fa-f]*")
# parse_line's fast path: the line candump -L writes (single spaces, a dotted stamp, 3 or 8 id digits, whole
# data bytes), matched once; anything else (and an id or stamp out of range) takes the checked path
_PLAIN_LINE_RE = re.compile(
    r"\(([0-9]{1,10}\.[0-9]{0,9})\) (\S+) ([0-9A-Fa-f]{3}|[0-9A-Fa-f]{8})#((?:[0-9A-Fa-f]{2}){0,8})"
)
MAX_TIMESTAMP = 7258118400.0  # 2200-01-01T00:00:00Z: later stamps are absurd
MAX_LINE_CHARS = 256  # a candump -L line is at most ~70 characters
MAX_LOG_BYTES = 16 << 30  # ~12 days of the four sensor messages at their rates
MAX_RECORDED = 1000  # line numbers / reasons kept in memory (the counts are exact)
REJECT_REASONS = ("malformed", "too_long", "bad_timestamp", "out_of_order", "time_jump")
_READ_CHUNK = 1 << 20


class BadTimestampError(ValueError):
    """``parse_line``: the time stamp is unparseable or absurd (a ``ValueError``)."""


class CandumpFileError(UserFacingError):
    """The log cannot be opened: not a regular file, too large, unreadable."""


class LogFrame(NamedTuple):
    """One classic CAN frame read from a candump log."""

    timestamp: float
    channel: str
    frame_id: int
    data: bytes
    line_no: int
    is_extended: bool = False
    is_remote: bool = False


class Problem(NamedTuple):
    """A record of a log that is skipped: where, why (``reason``), an excerpt, the ``REJECT_REASONS`` kind."""

    line_no: int
    reason: str
    line: str = ""
    kind: str = "malformed"


def timestamp_problem(timestamp: float) -> str | None:
    """Why a time stamp read as a number (not as candump text) is absurd, or None: the bound ``parse_line``
    applies to candump's digits (finite, not negative, not after 2200), for every other format."""
    if not math.isfinite(timestamp):
        return f"time stamp {timestamp!r} is not finite"
    if timestamp < 0.0:
        return f"negative time stamp {timestamp:.6f}"
    if timestamp > MAX_TIMESTAMP:
        return f"time stamp {timestamp:.6g} after 2200-01-01"
    return None


def format_line(timestamp: float, channel: str, frame_id: int, data: bytes, *, extended: bool | None = None) -> str:
    """One candump ``-L`` line (without newline).

    ``extended=None`` picks 29-bit format only for ids above 0x7FF. Raises ValueError for an invalid
    timestamp, channel, id or a payload longer than 8 bytes.
    """
    if not (timestamp >= 0.0 and math.isfinite(timestamp)):
        raise ValueError(f"invalid timestamp {timestamp!r}")
    if not channel or any(ch.isspace() for ch in channel) or "#" in channel:
        raise ValueError(f"invalid channel name {channel!r}")
    if len(data) > _MAX_DATA:
        raise ValueError(f"classic CAN payload is at most 8 bytes, got {len(data)}")
    if extended is None:
        extended = frame_id > _STD_MAX
    if not 0 <= frame_id <= (_EXT_MAX if extended else _STD_MAX):
        raise ValueError(f"invalid {'29' if extended else '11'}-bit frame id {frame_id!r}")
    fid = f"{frame_id:08X}" if extended else f"{frame_id:03X}"
    return f"({timestamp:017.6f}) {channel} {fid}#{bytes(data).hex().upper()}"


def parse_line(line: str, line_no: int = 0) -> LogFrame:
    """Parse one candump ``-L`` line. Raises ValueError (message = the reason) if it is malformed.

    Accepts an optional trailing ``R``/``T`` (rx/tx) field, 3-digit (11-bit) and 8-digit (29-bit) ids and
    remote frames (``123#R``, ``123#R8``: empty data, ``is_remote=True``). CAN FD (``##``) and error
    frames are rejected; so is a time stamp with more than 10 + 9 digits, a sign, or after 2200
    (``BadTimestampError``, a ValueError).
    """
    plain = _PLAIN_LINE_RE.fullmatch(line)
    if plain is not None:
        ts_s, channel, id_s, data_s = plain.groups()
        timestamp = float(ts_s)
        frame_id = int(id_s, 16)
        extended = len(id_s) == 8
        if timestamp <= MAX_TIMESTAMP and frame_id <= (_EXT_MAX if extended else _STD_MAX) and "#" not in channel:
            return LogFrame(timestamp, channel, frame_id, bytes.fromhex(data_s), line_no, extended, False)
    fields = line.split()
    if not fields:
        raise ValueError("empty line")
    if len(fields) == 4 and fields[3] in ("R", "T", "r", "t"):
        fields = fields[:3]
    if len(fields) != 3:
        raise ValueError(f"expected '(time) channel ID#DATA', got {len(fields)} fields")
    ts_s, channel, frame = fields
    m = _TIMESTAMP_RE.fullmatch(ts_s)
    if m is None:
        raise BadTimestampError(f"bad timestamp {ts_s[:40]!r}")
    timestamp = float(m.group(1))
    if timestamp > MAX_TIMESTAMP:
        raise BadTimestampError(f"timestamp {ts_s!r} after 2200-01-01")
    id_s, sep, data_s = frame.partition("#")
    if not sep:
        raise ValueError("missing '#' between id and data")
    if len(id_s) == 3:
        extended = False
    elif len(id_s) == 8:
        extended = True
    else:
        raise ValueError(f"bad frame id {id_s!r} (need 3 or 8 hex digits)")
    if not _HEX_RE.fullmatch(id_s):
        raise ValueError(f"bad frame id {id_s!r}")
    frame_id = int(id_s, 16)
    if extended and frame_id > _EXT_MAX:
        raise ValueError(f"error frame or invalid 29-bit id {id_s}")
    if not extended and frame_id > _STD_MAX:
        raise ValueError(f"11-bit id {id_s} out of range")
    if data_s.startswith("#"):
        raise ValueError("CAN FD frame not supported")
    if data_s[:1] in ("R", "r"):
        if len(data_s) > 2 or (len(data_s) == 2 and data_s[1] not in "012345678"):
            raise ValueError(f"bad remote frame {data_s!r}")
        return LogFrame(timestamp, channel, frame_id, b"", line_no, extended, True)
    if not _HEX_RE.fullmatch(data_s):
        raise ValueError("bad hex payload")
    if len(data_s) % 2:
        raise ValueError("odd number of hex digits")
    if len(data_s) > 2 * _MAX_DATA:
        raise ValueError(f"payload longer than 8 bytes ({len(data_s) // 2})")
    return LogFrame(timestamp, channel, frame_id, bytes.fromhex(data_s), line_no, extended, False)


class CandumpWriter:
    """Writes candump ``-L`` lines to a path (opened/closed here) or to an open text stream (left open).

    >>> with CandumpWriter("out.log", channel="vcan0") as w:  # doctest: +SKIP
    ...     w.write(1700000000.0, 0x300, b"\\x00" * 8)
    """

    def __init__(self, target: str | Path | IO[str], channel: str = "can0", *, append: bool = False) -> None:
        if isinstance(target, (str, Path)):
            self._stream: IO[str] = open(target, "a" if append else "w", encoding="ascii", newline="\n")
            self._owns = True
            self.name = str(target)
        else:
            self._stream = target
            self._owns = False
            self.name = getattr(target, "name", "<stream>")
        format_line(0.0, channel, 0, b"")  # validate the channel name early
        self.channel = channel
        self.lines_written = 0
        # write_cycle: frame id -> its " ID#" text (checked once by format_line), not formatted per frame
        self._id_text: dict[int, str] = {}

    def write(
        self,
        timestamp: float,
        frame_id: int,
        data: bytes,
        *,
        channel: str | None = None,
        extended: bool | None = None,
    ) -> None:
        self._stream.write(format_line(timestamp, channel or self.channel, frame_id, data, extended=extended) + "\n")
        self.lines_written += 1

    def write_cycle(self, timestamp: float, frames: Sequence[tuple[int, bytes]]) -> None:
        """All frames of one cycle, stamped ``timestamp``, in one write: the same lines as ``write`` per frame
        (byte for byte), at a fraction of the cost (replay writes ~3 frames per 10 ms of log)."""
        head = format_line(timestamp, self.channel, 0, b"")  # checks the stamp once for the whole cycle
        head = head[: head.index(" ", head.index(" ") + 1)]  # "(stamp) channel"
        ids = self._id_text
        parts = []
        for frame_id, data in frames:
            fid = ids.get(frame_id)
            if fid is None:
                line = format_line(timestamp, self.channel, frame_id, b"")  # range check, as write does
                fid = ids[frame_id] = line[len(head) :]  # " ID#"
            if len(data) > _MAX_DATA:
                raise ValueError(f"classic CAN payload is at most 8 bytes, got {len(data)}")
            parts.append(f"{head}{fid}{data.hex().upper()}\n")
        self._stream.write("".join(parts))
        self.lines_written += len(parts)

    def write_frames(
        self,
        times: np.ndarray,
        cycle_of: np.ndarray,
        ids: Sequence[int] | np.ndarray,
        data: np.ndarray,
        lengths: Sequence[int] | np.ndarray,
    ) -> None:
        """Many frames in one write, the same lines as ``write`` per frame (byte for byte): frame i has id
        ``ids[i]``, the first ``lengths[i]`` bytes of row i of ``data`` (``uint8[n, 8]``) and the stamp
        ``times[cycle_of[i]]`` (replay writes a chunk of cycles at once)."""
        if not times.size:
            return
        if not (np.all(times >= 0.0) and np.all(times < 1e10)):  # not a stamp format_line takes: its error
            bad = times[~((times >= 0.0) & (times < 1e10))][0]
            format_line(float(bad), self.channel, 0, b"")
        ids = np.asarray(ids, dtype=np.int64)
        lengths = np.asarray(lengths, dtype=np.int64)
        if lengths.size and int(lengths.max()) > _MAX_DATA:
            raise ValueError(f"classic CAN payload is at most {_MAX_DATA} bytes")
        # one %-template mapped over the stamps: the same text as f"({t:017.6f}) {channel} ", a third faster
        heads = list(map(("(%017.6f) " + self.channel.replace("%", "%%") + " ").__mod__, times.tolist()))
        texts = self._id_text
        unique, id_index = np.unique(ids, return_inverse=True)
        for frame_id in unique.tolist():
            if frame_id not in texts:
                line = format_line(0.0, self.channel, frame_id, b"")  # range check, as write does
                texts[frame_id] = line[line.index(" ", line.index(" ") + 1) + 1 :]  # "ID#"
        id_texts = [texts[u] for u in unique.tolist()]
        digits = _HEX_DIGITS[np.ascontiguousarray(data, dtype=np.uint8)]
        if bool(np.all(lengths == _MAX_DATA)) and len(set(map(len, id_texts))) == 1 and heads[0].isascii():
            # every line the same width (8-byte frames, one id width, fixed-width stamps): the lines as one
            # block of bytes, column by column, instead of one string per frame (the same bytes: tested)
            id_rows = np.frombuffer("".join(id_texts).encode("ascii"), dtype=np.uint8)
            head_rows = np.frombuffer("".join(heads).encode("ascii"), dtype=np.uint8).reshape(len(heads), -1)
            columns = (
                head_rows[cycle_of],
                id_rows.reshape(len(unique), -1)[id_index],
                digits.view(np.uint8).reshape(ids.size, 2 * _MAX_DATA),
                np.full((ids.size, 1), ord("\n"), dtype=np.uint8),
            )
            self._write_ascii(np.concatenate(columns, axis=1).tobytes())
            self.lines_written += ids.size
            return
        hexes = digits.tobytes().decode("ascii")
        self._stream.write(
            "".join(
                [
                    f"{heads[c]}{id_texts[k]}{hexes[16 * i : 16 * i + 2 * n]}\n"
                    for i, (c, k, n) in enumerate(
                        zip(cycle_of.tolist(), id_index.tolist(), lengths.tolist(), strict=True)
                    )
                ]
            )
        )
        self.lines_written += ids.size

    def _write_ascii(self, block: bytes) -> None:
        """ASCII bytes written as they are to a file's byte buffer (its text flushed first, so the order holds),
        not decoded to text and encoded again (a tenth of a 20-min replay's output time); as text to a stream
        without one."""
        buffer = getattr(self._stream, "buffer", None)
        if buffer is None:
            self._stream.write(block.decode("ascii"))
            return
        self._stream.flush()
        buffer.write(block)

    def write_frame(self, frame: LogFrame) -> None:
        """Write a frame read from another log (keeps its time stamp and channel)."""
        self.write(frame.timestamp, frame.frame_id, frame.data, channel=frame.channel, extended=frame.is_extended)

    def flush(self) -> None:
        self._stream.flush()

    def close(self) -> None:
        if self._owns:
            if not self._stream.closed:
                self._stream.close()
        else:
            self._stream.flush()

    def __enter__(self) -> CandumpWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def text_blocks(read: Callable[[], str], max_chars: int = MAX_LINE_CHARS) -> Iterator[list[str]]:
    """Lists of lines (no newline) from ``read()`` (chunks of text, "" at the end); a line longer than
    ``max_chars`` is never held whole: it comes as one line of ``max_chars + 1`` characters, which the parser
    rejects (``too_long``). Used by every text log format."""
    rest = ""
    skipping = False  # inside an over-long line: drop up to its newline
    first = True
    while True:
        chunk = read()
        if not chunk:
            break
        if first:  # a byte-order mark (Windows editors save one) is not part of the first line
            chunk, first = chunk.removeprefix("\ufeff"), False
            if not chunk:
                continue
        cut = chunk.rfind("\n")
        if cut < 0:  # no line ends in this chunk
            if not skipping:
                rest += chunk
                if len(rest) > max_chars:
                    rest, skipping = rest[: max_chars + 1], True
            continue
        lines = chunk[:cut].split("\n")
        if skipping:
            lines[0] = rest  # the tail of the over-long line is dropped; the line itself counts once
            skipping = False
        elif rest:
            lines[0] = rest + lines[0]
        rest = chunk[cut + 1 :]
        if len(rest) > max_chars:
            rest, skipping = rest[: max_chars + 1], True
        yield lines
    if rest:
        yield [rest]


class Jump(NamedTuple):
    """A discontinuity of the time stamps the time rule took: it starts at frame ``index`` of a ``FrameArrays``."""

    index: int
    line_no: int
    t_from: float
    t_to: float


class FrameArrays(NamedTuple):
    """Data frames of a log as columns (a block of them, in the time rule's order): stamps, identifiers, 29-bit
    or not, DLCs and the bytes (``uint8[n, 8]``, zero-padded); the channel of the first, and the
    discontinuities of the time stamps that start in the block."""

    times: np.ndarray
    ids: np.ndarray
    extended: np.ndarray
    lengths: np.ndarray
    data: np.ndarray
    channel: str | None
    jumps: list[Jump]

    @classmethod
    def of(cls, frames: Sequence[LogFrame], jumps: list[Jump]) -> FrameArrays:
        n = len(frames)
        return cls(
            np.fromiter((f.timestamp for f in frames), dtype=np.float64, count=n),
            np.fromiter((f.frame_id for f in frames), dtype=np.int64, count=n),
            np.fromiter((f.is_extended for f in frames), dtype=bool, count=n),
            np.fromiter((len(f.data) for f in frames), dtype=np.int64, count=n),
            payload_rows([bytes(f.data) for f in frames]),
            frames[0].channel if frames else None,
            jumps,
        )

    def __len__(self) -> int:  # type: ignore[override]
        return int(self.times.shape[0])

    def concat(self, other: FrameArrays) -> FrameArrays:
        jumps = self.jumps + [j._replace(index=j.index + len(self)) for j in other.jumps]
        return FrameArrays(
            *(np.concatenate((a, b)) for a, b in zip(self[:5], other[:5], strict=True)),
            self.channel if len(self) else other.channel,
            jumps,
        )

    def rows(self, start: int, stop: int) -> FrameArrays:
        """Frames ``start..stop-1`` (the discontinuities among them re-indexed)."""
        jumps = [j._replace(index=j.index - start) for j in self.jumps if start <= j.index < stop]
        return FrameArrays(*(a[start:stop] for a in self[:5]), self.channel, jumps)


def payload_rows(payloads: Sequence[bytes]) -> np.ndarray:
    """``uint8[n, 8]``: each payload (at most 8 bytes) zero-padded."""
    joined = b"".join(p if len(p) == 8 else p.ljust(8, b"\0") for p in payloads)
    return np.frombuffer(joined, dtype=np.uint8).reshape(len(payloads), 8)


_FAST_WINDOW = 4096  # frames the time rule's column fast path checks at once
_SLOW_RUN = 64  # frames then taken one by one when fewer than this passed it


def _plain_columns(lines: list[str]) -> tuple[FrameArrays, tuple[str, ...]] | None:
    """The frames of a block of lines as columns when every line is the plain line ``parse_line`` takes on its
    fast path (with the same checks: stamp, id range, no '#' in the channel), with each line's channel; None
    otherwise (the block then goes line by line). Parsed by the compiled scan of ``candump_scan``."""
    n = len(lines)
    if not n:
        return None
    joined = "\n".join(lines)
    if not joined.isascii():
        return None
    text = np.frombuffer(joined.encode("ascii"), dtype=np.uint8)
    times = np.empty(n)
    ids = np.empty(n, dtype=np.int64)
    extended = np.empty(n, dtype=bool)
    lengths = np.empty(n, dtype=np.int64)
    data = np.zeros((n, _MAX_DATA), dtype=np.uint8)
    span = np.zeros(3, dtype=np.int64)
    if scan_plain(text, MAX_LINE_CHARS, MAX_TIMESTAMP, POW10, times, ids, extended, lengths, data, span) != n:
        return None
    channel = joined[span[0] : span[1]]
    if span[2]:
        channels: tuple[str, ...] = (channel,) * n
    else:  # several channels: each line's own (rare; the regular expression is the definition)
        channels = tuple(_PLAIN_LINE_RE.fullmatch(line).group(2) for line in lines)  # type: ignore[union-attr]
    return FrameArrays(times, ids, extended, lengths, data, channel, []), channels


class BusChoice:
    """Which bus (channel) of a log of several is read: the one named, or the inputs' (the daemon reads one bus):
    the channel with the most input frames among the first ``VOTES`` of them, an input frame being a classic data
    frame with an input's 11-bit identifier and length (``inputs``: id -> DLC). One stray frame ahead of the ride (a
    29-bit, remote or short one, or one frame of another bus) decided it when the first input id did, and the whole
    ride was skipped as another bus. The reader holds the frames while the choice is pending: at most ``HOLD``, then
    the choice is made on what was seen (none: every frame is read, as in a log of one bus)."""

    VOTES = 64
    HOLD = 1 << 16

    def __init__(self, inputs: Mapping[int, int] | None = None, name: str | None = None) -> None:
        self.inputs = {int(i): int(n) for i, n in (inputs or {}).items()}
        ids = sorted(self.inputs)
        self.input_ids_array = np.array(ids, dtype=np.int64)
        self.input_lengths_array = np.array([self.inputs[i] for i in ids], dtype=np.int64)
        self.name = name
        self.chosen = name
        self.decided = name is not None
        self._votes: dict[str, int] = {}  # channel -> its input frames seen, in the order channels were first seen

    def vote(self, frame: LogFrame) -> None:
        if not (frame.is_extended or frame.is_remote) and self.inputs.get(frame.frame_id) == len(frame.data):
            self._votes[frame.channel] = self._votes.get(frame.channel, 0) + 1

    def vote_columns(self, frames: FrameArrays, channels: tuple[str, ...]) -> None:
        """``vote`` over a block of columns (data frames: none is remote)."""
        if not self.input_ids_array.size or not len(frames):
            return
        k = np.clip(np.searchsorted(self.input_ids_array, frames.ids), 0, self.input_ids_array.size - 1)
        hit = (self.input_ids_array[k] == frames.ids) & (self.input_lengths_array[k] == frames.lengths)
        hit &= ~frames.extended
        rows = np.flatnonzero(hit)
        if not rows.size:
            return
        if channels.count(channels[0]) == len(channels):
            self._votes[channels[0]] = self._votes.get(channels[0], 0) + int(rows.size)
            return
        for r in rows.tolist():
            self._votes[channels[r]] = self._votes.get(channels[r], 0) + 1

    def ready(self) -> bool:
        return sum(self._votes.values()) >= self.VOTES

    def decide(self) -> None:
        """The channel with the most votes (the first seen of equals); none: every channel is read."""
        if not self.decided:
            self.decided = True
            if self._votes:
                self.chosen = max(self._votes, key=self._votes.__getitem__)

    def keeps(self, channel: str) -> bool:
        """Whether a frame on ``channel`` is read, once decided."""
        return self.chosen is None or channel == self.chosen


class TimeRule(Iterator[LogFrame]):
    """The time rule of the module docstring, for the frames of any log format, with the counts of what it
    skipped. A subclass supplies ``_items()``: the log's records in file order, each a ``LogFrame`` (with
    ``line_no`` = the line or record number) or a ``Problem`` (a record that could not be read).

    After (or during) iteration: ``frames`` (good frames yielded), ``malformed`` (records skipped, every reason),
    ``rejected`` (reason -> count, reasons of ``REJECT_REASONS``), ``reordered`` (accepted frames stamped
    slightly before an earlier one), ``discontinuities`` (count) and ``discontinuity_lines`` ((line_no, from,
    to) of each confirmed time-base change), ``malformed_lines`` and ``problems`` ((line_no, reason) pairs; the
    first ``MAX_RECORDED`` of each). A warning naming the file and line is logged for the first
    ``max_warnings`` bad records, then one summary warning at the end (``max_warnings=None``: none, the caller
    summarises with ``examples``, the first three bad records escaped); likewise for the discontinuities unless
    ``warn_discontinuities`` is set to False (a consumer reporting them itself, as replay's segmentation does).
    """

    unit = "line"  # what a record is called in warnings: "candump line", "ASC line", "BLF object", ...

    def __init__(
        self,
        name: str,
        *,
        max_warnings: int | None = 20,
        max_jump: float = 1.0,
        reorder_tolerance: float = 0.02,
        confirm: int = 8,
    ) -> None:
        self.name = name
        self._quiet = max_warnings is None  # None: no warning per bad record (the caller summarises: ``examples``)
        self.max_warnings = 0 if max_warnings is None else max_warnings
        # False: a consumer that reports the discontinuities itself (replay: one line saying what it did)
        self.warn_discontinuities = True
        self.max_jump = float(max_jump)
        self.reorder_tolerance = float(reorder_tolerance)
        self.confirm = max(1, int(confirm))
        self.frames = 0
        self.malformed = 0
        self.rejected = dict.fromkeys(REJECT_REASONS, 0)
        self.reordered = 0
        self.discontinuities = 0
        self.remote = 0  # remote frames left out by ``arrays`` (the per-frame iteration gives them)
        self.discontinuity_lines: list[tuple[int, float, float]] = []
        # a log of several buses (`candump -L any`): with ``bus`` (a ``BusChoice``) the frames on the others are
        # skipped (the same frames on can0 and can1 had left every cycle INIT, silently), else read as one bus;
        # either way counted, and their channels named, for the reader's user
        self.bus: BusChoice | None = None
        self.first_channel: str | None = None
        self.other_channel_frames = 0
        self.other_channels: list[str] = []  # their names, the first few
        self.malformed_lines: list[int] = []
        self.problems: list[tuple[int, str]] = []
        self.examples: list[str] = []  # the first few bad records, escaped (``ascii``), for a summary
        self._last: float | None = None  # newest stamp of the accepted time base (None: none confirmed yet)
        self._chains: list[list] = []  # candidate time bases: [frames, newest stamp]
        self._base_votes = 0  # frames accepted on the base since the oldest pending candidate started
        self._gen = self._generate()

    def _items(self) -> Iterator[LogFrame | Problem]:
        raise NotImplementedError

    @property
    def bus_read(self) -> str | None:
        """The channel whose frames are read: the bus chosen, else the first frame's."""
        if self.bus is not None and self.bus.chosen is not None:
            return self.bus.chosen
        return self.first_channel

    def _other_channel(self, channel: str, frames: int = 1) -> None:
        self.other_channel_frames += frames
        if channel not in self.other_channels and len(self.other_channels) < 4:
            self.other_channels.append(channel)

    def _on_bus(self, channel: str) -> bool:
        """Whether a frame is read (``bus``), counting it when it is on another channel."""
        if self.first_channel is None:
            self.first_channel = channel
        bus = self.bus
        if bus is None:
            if channel != self.first_channel:
                self._other_channel(channel)
            return True
        if bus.keeps(channel):
            return True
        self._other_channel(channel)
        return False

    def _bus_only(self, items: Iterable[LogFrame | Problem]) -> Iterator[LogFrame | Problem]:
        """``items`` less the frames on other buses (``_on_bus``); while the bus is not chosen (``BusChoice``), the
        records are held and counted as votes, at most ``BusChoice.HOLD``, and the end of ``items`` decides."""
        on_bus = self._on_bus
        bus = self.bus
        held: list[LogFrame | Problem] = []
        for item in items:
            if bus is not None and not bus.decided:
                held.append(item)
                if item.__class__ is not Problem:
                    bus.vote(item)  # type: ignore[arg-type]
                if not (bus.ready() or len(held) >= bus.HOLD):
                    continue
                bus.decide()
                yield from self._bus_only(held)
                held = []
                continue
            if item.__class__ is Problem or on_bus(item.channel):  # type: ignore[union-attr]
                yield item
        if held:
            bus.decide()  # type: ignore[union-attr]
            yield from self._bus_only(held)

    def _bus_rows(self, frames: FrameArrays, channels: tuple[str, ...]) -> np.ndarray | None:
        """The rows of a block of columns on the bus read (``_on_bus`` per frame, whole columns when the block is
        of one channel); None: all of them."""
        n = len(frames)
        if not n:
            return None
        first = channels[0]
        if channels.count(first) == n:  # one channel (C speed: the same object n times)
            if self.first_channel is None:
                self.first_channel = first
            bus = self.bus
            if bus is None or bus.keeps(first):
                if bus is None and first != self.first_channel:
                    self._other_channel(first, n)
                return None
            self._other_channel(first, n)
            return np.empty(0, dtype=np.int64)
        keep = [self._on_bus(c) for c in channels]
        return None if all(keep) else np.flatnonzero(keep)

    def _release(self) -> None:
        """Close what the reader opened (called once the records are read, or on ``close``)."""

    def _generate(self) -> Iterator[LogFrame]:
        try:
            yield from self._rule(self._bus_only(self._items()))
        finally:
            self._release()

    def _rule(self, items: Iterator[LogFrame | Problem]) -> Iterator[LogFrame]:
        """The time rule over a log's records (``TimeRule``'s module docstring), with the fast path inlined."""
        tol = self.reorder_tolerance
        jump = self.max_jump
        suspect = self._suspect
        bad = self._bad
        last = self._last
        for frame in items:
            if frame.__class__ is Problem:
                bad(*frame)
                continue
            if last is not None and not self._chains:  # the fast path: no candidate pending
                d = frame.timestamp - last
                if 0.0 <= d <= jump:
                    last = frame.timestamp
                    self.frames += 1
                    yield frame
                    continue
                if -tol <= d < 0.0:
                    self.reordered += 1
                    self.frames += 1
                    yield frame
                    continue
            self._last = last
            out = suspect(frame)
            last = self._last
            if out:
                self.frames += len(out)
                yield from out
        yield from self._end()

    def _end(self) -> list[LogFrame]:
        """The end of the log: what ``_finish`` releases, and the summary warnings."""
        out = self._finish()
        self.frames += len(out)
        hidden = self.malformed - self.max_warnings
        if hidden > 0 and not self._quiet:
            log.warning("%s: %d more bad %ss skipped (%d in total)", self.name, hidden, self.unit, self.malformed)
        if self.discontinuities > self.max_warnings and self.warn_discontinuities:
            log.warning("%s: %d discontinuities of the time stamps in total", self.name, self.discontinuities)
        return out

    def _one(self, frame: LogFrame) -> list[LogFrame]:
        """The time rule for one frame: what one turn of ``_rule``'s loop does (its fast path included)."""
        last = self._last
        if last is not None and not self._chains:
            d = frame.timestamp - last
            if 0.0 <= d <= self.max_jump:
                self._last = frame.timestamp
                self.frames += 1
                return [frame]
            if -self.reorder_tolerance <= d < 0.0:
                self.reordered += 1
                self.frames += 1
                return [frame]
        out = self._suspect(frame)
        self.frames += len(out)
        return out

    def _rule_records(self, items: Iterable[LogFrame | Problem]) -> tuple[list[LogFrame], list[Jump]]:
        """The time rule over some records: the data frames it gives (remote frames counted in ``remote`` and
        left out) and the discontinuities that start at one of them (``Jump``: its index in that list)."""
        out: list[LogFrame] = []
        jumps: list[Jump] = []
        for item in items:
            if item.__class__ is Problem:
                self._bad(*item)
                continue
            seen = self.discontinuities
            got = self._one(item)
            if self.discontinuities != seen and got and len(self.discontinuity_lines) >= self.discontinuities:
                jumps.append(Jump(len(out), *self.discontinuity_lines[self.discontinuities - 1]))
            for frame in got:
                if frame.is_remote:
                    self.remote += 1
                else:
                    out.append(frame)
        return out, jumps

    def _consistent(self, t: float, reference: float) -> bool:
        return reference - self.reorder_tolerance <= t <= reference + self.max_jump

    def _suspect(self, frame: LogFrame) -> list[LogFrame]:
        """The slow path: a frame off the accepted time base, or any frame before a base is confirmed."""
        t = frame.timestamp
        last = self._last
        if last is not None and self._consistent(t, last):
            if t < last:
                self.reordered += 1
            else:
                self._last = t
            self._base_votes += 1
            if self._base_votes >= self.confirm:  # the base outlasted every candidate: they were outliers
                self._reject_chains(self._chains)
            return [frame]
        for chain in self._chains:
            if self._consistent(t, chain[1]):
                chain[0].append(frame)
                chain[1] = max(chain[1], t)
                if len(chain[0]) < self.confirm:
                    return []
                return self._adopt(chain)
        if len(self._chains) >= 3:  # bounded work: drop the weakest candidate
            weakest = min(self._chains, key=lambda c: len(c[0]))
            self._reject_chains([weakest])
        self._chains.append([[frame], t])
        return []

    def _adopt(self, chain: list) -> list[LogFrame]:
        """``chain`` becomes the time base; the other candidates are rejected."""
        if self._last is not None:
            self.discontinuities += 1
            first = chain[0][0]
            if len(self.discontinuity_lines) < MAX_RECORDED:
                self.discontinuity_lines.append((first.line_no, self._last, first.timestamp))
            if self.discontinuities > self.max_warnings or not self.warn_discontinuities:
                return self._take(chain)
            log.warning(
                "%s:%d: time stamps jump %+.3f s (from %.6f to %.6f); taken as a discontinuity of the log",
                self.name,
                first.line_no,
                first.timestamp - self._last,
                self._last,
                first.timestamp,
            )
        return self._take(chain)

    def _take(self, chain: list) -> list[LogFrame]:
        self._reject_chains([c for c in self._chains if c is not chain])
        self._chains = []
        self._last = chain[1]
        self._base_votes = 0
        return chain[0]

    def _reject_chains(self, chains: list[list]) -> None:
        last = self._last
        for chain in chains:
            for frame in chain[0]:
                if last is not None and frame.timestamp < last:
                    reason = f"out of order: {last - frame.timestamp:.3f} s before an earlier line, not confirmed"
                    kind = "out_of_order"
                else:
                    if last is None:
                        reason = f"time stamp {frame.timestamp:.6f} at the log's start not confirmed by the next lines"
                    else:
                        reason = (
                            f"time stamp {frame.timestamp:.6f} jumps {frame.timestamp - last:+.3f} s and is not "
                            "confirmed by the next lines"
                        )
                    kind = "time_jump"
                self._bad(frame.line_no, reason, "", kind)
        self._chains = [c for c in self._chains if not any(c is d for d in chains)]
        if not self._chains:
            self._base_votes = 0

    def _finish(self) -> list[LogFrame]:
        """End of the log: a log too short to confirm a base is taken as it is; other candidates are rejected."""
        if not self._chains:
            return []
        if self._last is None:
            longest = max(self._chains, key=lambda c: len(c[0]))
            self._reject_chains([c for c in self._chains if c is not longest])
            self._chains = []
            self._last = longest[1]
            return longest[0]
        self._reject_chains(list(self._chains))
        return []

    def _bad(self, line_no: int, reason: str, line: str, kind: str = "malformed") -> None:
        self.malformed += 1
        self.rejected[kind] += 1
        if len(self.problems) < MAX_RECORDED:
            self.malformed_lines.append(line_no)
            self.problems.append((line_no, reason))
        if self.malformed <= self.max_warnings and not self._quiet:
            if line:
                log.warning("%s:%d: skipping %s (%s): %.80a", self.name, line_no, self.unit, reason, line.rstrip())
            else:
                log.warning("%s:%d: skipping %s (%s)", self.name, line_no, self.unit, reason)
        if len(self.examples) < 3:
            self.examples.append(
                f"{self.name}:{line_no}: {reason}" + (f": {ascii(line.rstrip()[:60])}" if line else "")
            )

    def __iter__(self) -> TimeRule:
        return self

    def __next__(self) -> LogFrame:
        return next(self._gen)

    def close(self) -> None:
        """Stop reading and close the file (if opened here)."""
        self._gen.close()
        self._release()

    def __enter__(self) -> TimeRule:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


class CandumpReader(TimeRule):
    """Iterator over the frames of a candump ``-L`` log; skips and counts bad lines (module docstring: the rules;
    ``TimeRule``: the counts).
    """

    unit = "candump line"

    def __init__(
        self,
        source: str | Path | IO[str],
        *,
        max_warnings: int = 20,
        max_jump: float = 1.0,
        reorder_tolerance: float = 0.02,
        confirm: int = 8,
        max_bytes: int = MAX_LOG_BYTES,
    ) -> None:
        self._fh: IO[bytes] | None = None
        if isinstance(source, (str, Path)):
            path = Path(source)
            name = str(path)
            try:
                self._fh = compressed.open_log_file(
                    path, max_bytes=max_bytes, what="candump log", error=CandumpFileError
                )
            except CandumpFileError as exc:
                if str(exc).endswith("not found"):
                    raise FileNotFoundError(f"candump log not found: {path}") from None
                raise
            self._stream: IO[str] | None = None
        else:
            name = getattr(source, "name", "<stream>")
            self._stream = source
        super().__init__(
            name, max_warnings=max_warnings, max_jump=max_jump, reorder_tolerance=reorder_tolerance, confirm=confirm
        )

    @property
    def position(self) -> int:
        """Bytes read so far (0 for a stream): for a progress bar."""
        return compressed.position(self._fh)

    def _release(self) -> None:
        if self._fh is not None:
            self._fh.close()

    # ------------------------------------------------------------------ lines

    def _blocks(self) -> Iterator[list[str]]:
        if self._fh is not None:
            fh = self._fh

            def read() -> str:
                return fh.read(_READ_CHUNK).decode("utf-8", "replace")  # may split a character: a bad line anyway

        else:
            assert self._stream is not None
            stream = self._stream

            def read() -> str:
                return stream.read(_READ_CHUNK)

        return text_blocks(read)

    def _items(self) -> Iterator[LogFrame | Problem]:
        line_no = 0
        for block in self._blocks():
            yield from self._block_items(block, line_no)
            line_no += len(block)

    def _block_items(self, block: list[str], line_no: int) -> Iterator[LogFrame | Problem]:
        """The records of a block of lines whose first is line ``line_no + 1`` (what ``_items`` gives)."""
        for line in block:
            line_no += 1
            if len(line) > MAX_LINE_CHARS:
                yield Problem(line_no, f"line longer than {MAX_LINE_CHARS} characters", line, "too_long")
                continue
            try:
                yield parse_line(line, line_no)
            except BadTimestampError as exc:
                yield Problem(line_no, str(exc), line, "bad_timestamp")
            except ValueError as exc:
                yield Problem(line_no, str(exc), line, "malformed")

    def arrays(self) -> Iterator[FrameArrays]:
        """The log's data frames through the time rule as columns, a block of lines (~1 MiB) at a time: the same
        frames, counts and discontinuities as iterating the reader (tested), remote frames counted in
        ``remote``. A block whose lines are all plain, on an accepted time base, is parsed and ruled as
        whole columns (numpy); any other goes record by record."""
        try:
            line_no = 0
            bus = self.bus
            held: list[tuple] = []  # blocks read while the bus is not chosen (``BusChoice``), in order
            held_frames = 0
            for block in self._blocks():
                first = line_no
                line_no += len(block)
                plain = _plain_columns(block)
                if plain is not None:
                    part: tuple = (first, line_no, *plain)
                else:
                    part = (first, line_no, list(self._block_items(block, first)))
                held.append(part)
                if bus is not None and not bus.decided:
                    if plain is not None:
                        bus.vote_columns(*plain)
                        held_frames += len(plain[0])
                    else:
                        for item in part[2]:
                            if item.__class__ is not Problem:
                                bus.vote(item)
                        held_frames += len(part[2])
                    if not (bus.ready() or held_frames >= bus.HOLD):
                        continue
                    bus.decide()
                yield from self._read_parts(held)
                held = []
            if held:
                bus.decide()  # type: ignore[union-attr]
                yield from self._read_parts(held)
            tail = []
            for frame in self._end():
                if frame.is_remote:
                    self.remote += 1
                else:
                    tail.append(frame)
            if tail:
                yield FrameArrays.of(tail, [])
        finally:
            self._release()

    def _read_parts(self, parts: list[tuple]) -> Iterator[FrameArrays]:
        """``_read_part`` over held blocks, in order, the non-empty ones."""
        for part in parts:
            out = self._read_part(part)
            if len(out):
                yield out

    def _read_part(self, part: tuple) -> FrameArrays:
        """One block of ``arrays``: its plain lines as columns (``first``, ``end``, frames, channels), or its
        records (``first``, ``end``, records), through the bus and the time rule."""
        if len(part) == 3:
            return FrameArrays.of(*self._rule_records(self._bus_only(part[2])))
        first, end, frames, channels = part
        rows = self._bus_rows(frames, channels)
        if rows is None:
            line_nos = np.arange(first + 1, end + 1)
        else:
            frames = FrameArrays(*(a[rows] for a in frames[:5]), frames.channel, [])
            channels = tuple(channels[r] for r in rows.tolist())
            line_nos = first + 1 + rows
        return self._rule_columns(frames, channels, line_nos)

    def _rule_columns(self, frames: FrameArrays, channels: tuple[str, ...], line_nos: np.ndarray) -> FrameArrays:
        """The time rule on a block of parsed lines: while a time base is accepted and no candidate pending, its
        fast path on whole columns (a window of frames at a time: each within the tolerances of the newest stamp
        before it is taken, as ``_one`` takes it); frame by frame (``_rule_records``) otherwise, for at least
        ``_SLOW_RUN`` frames so that a log full of outliers costs no more than going frame by frame."""
        n = len(frames)
        parts: list[FrameArrays] = []
        i = 0
        while i < n:
            if self._last is not None and not self._chains:
                stop = min(n, i + _FAST_WINDOW)
                times = frames.times[i:stop]
                newest = np.maximum.accumulate(np.concatenate(([self._last], times)))
                d = times - newest[:-1]
                fast = (d >= -self.reorder_tolerance) & (d <= self.max_jump)
                k = times.size if fast.all() else int(np.argmin(fast))
                if k:
                    self.frames += k
                    self.reordered += int(np.count_nonzero(d[:k] < 0.0))
                    self._last = float(newest[k])
                    parts.append(frames.rows(i, i + k))
                    i += k
                if k >= _SLOW_RUN or i == n:
                    continue
            stop = min(n, i + _SLOW_RUN)
            records = [
                LogFrame(float(frames.times[r]), channels[r], int(frames.ids[r]),
                         frames.data[r, : frames.lengths[r]].tobytes(), int(line_nos[r]), bool(frames.extended[r]))
                for r in range(i, stop)
            ]  # fmt: skip
            parts.append(FrameArrays.of(*self._rule_records(records)))
            i = stop
        if len(parts) == 1:
            return parts[0]
        out = FrameArrays.of([], [])
        for part in parts:
            out = out.concat(part)
        return out

    def __enter__(self) -> CandumpReader:
        return self


def read_log(source: str | Path | IO[str], *, max_warnings: int = 20, **rules: Any) -> CandumpReader:
    """Frames of a candump ``-L`` log (path or text stream), bad lines skipped and counted.

    Returns a ``CandumpReader`` (an ``Iterator[LogFrame]``) exposing ``malformed`` / ``rejected`` / ... ;
    ``rules``: ``max_jump``, ``reorder_tolerance``, ``confirm``, ``max_bytes``. Raises FileNotFoundError if a
    path does not exist, ``CandumpFileError`` (one line, exit code 2 in the CLI) if it is not a regular file
    or too large; never raises on file content.
    """
    return CandumpReader(source, max_warnings=max_warnings, **rules)
