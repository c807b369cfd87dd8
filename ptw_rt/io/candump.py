"""candump ``-L`` text logs: ``(1700000000.123456) vcan0 123#DEADBEEF``.

Written exactly as can-utils' ``candump -L`` does (10-digit zero-padded seconds, 6 decimals, 3 hex digits for
11-bit ids, 8 for 29-bit ids, uppercase payload), so ``canplayer``, python-can's ``can.LogReader`` and
``cantools decode`` read our logs. Reading is tolerant: malformed lines are counted, logged with file and line
number, and skipped; the reader never raises on content (only if the file cannot be opened).
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Iterator
from pathlib import Path
from types import TracebackType
from typing import IO, NamedTuple

__all__ = [
    "CandumpReader",
    "CandumpWriter",
    "LogFrame",
    "format_line",
    "parse_line",
    "read_log",
]

log = logging.getLogger(__name__)

_STD_MAX = 0x7FF
_EXT_MAX = 0x1FFFFFFF
_MAX_DATA = 8
_TIMESTAMP_RE = re.compile(r"\(([0-9]+(?:\.[0-9]*)?)\)")
_HEX_RE = re.compile(r"[0-9A-Fa-f]*")


class LogFrame(NamedTuple):
    """One classic CAN frame read from a candump log."""

    timestamp: float
    channel: str
    frame_id: int
    data: bytes
    line_no: int
    is_extended: bool = False
    is_remote: bool = False


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
    frames are rejected.
    """
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
        raise ValueError(f"bad timestamp {ts_s!r}")
    timestamp = float(m.group(1))
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


class CandumpReader(Iterator[LogFrame]):
    """Iterator over the frames of a candump ``-L`` log; skips and counts malformed lines.

    After (or during) iteration: ``frames`` (good frames yielded), ``malformed`` (count),
    ``malformed_lines`` (their 1-based line numbers) and ``problems`` ((line_no, reason) pairs).
    A warning naming the file and line is logged for the first ``max_warnings`` malformed lines,
    then one summary warning at the end.
    """

    def __init__(self, source: str | Path | IO[str], *, max_warnings: int = 20) -> None:
        if isinstance(source, (str, Path)):
            path = Path(source)
            if not path.is_file():
                raise FileNotFoundError(f"candump log not found: {path}")
            self.name = str(path)
            self._path: Path | None = path
            self._stream: IO[str] | None = None
        else:
            self.name = getattr(source, "name", "<stream>")
            self._path = None
            self._stream = source
        self.max_warnings = max_warnings
        self.frames = 0
        self.malformed = 0
        self.malformed_lines: list[int] = []
        self.problems: list[tuple[int, str]] = []
        self._gen = self._generate()

    def _generate(self) -> Iterator[LogFrame]:
        if self._path is not None:
            with open(self._path, encoding="utf-8", errors="replace") as fh:
                yield from self._parse(fh)
        else:
            assert self._stream is not None
            yield from self._parse(self._stream)

    def _parse(self, lines: IO[str]) -> Iterator[LogFrame]:
        for line_no, line in enumerate(lines, start=1):
            try:
                frame = parse_line(line, line_no)
            except ValueError as exc:
                self._bad(line_no, str(exc), line)
                continue
            self.frames += 1
            yield frame
        hidden = self.malformed - self.max_warnings
        if hidden > 0:
            log.warning("%s: %d more malformed candump lines skipped (%d in total)", self.name, hidden, self.malformed)

    def _bad(self, line_no: int, reason: str, line: str) -> None:
        self.malformed += 1
        self.malformed_lines.append(line_no)
        self.problems.append((line_no, reason))
        if self.malformed <= self.max_warnings:
            log.warning("%s:%d: skipping malformed candump line (%s): %.80r", self.name, line_no, reason, line.rstrip())

    def __iter__(self) -> CandumpReader:
        return self

    def __next__(self) -> LogFrame:
        return next(self._gen)

    def close(self) -> None:
        """Stop reading and close the file (if opened here)."""
        self._gen.close()

    def __enter__(self) -> CandumpReader:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def read_log(source: str | Path | IO[str], *, max_warnings: int = 20) -> CandumpReader:
    """Frames of a candump ``-L`` log (path or text stream), malformed lines skipped and counted.

    Returns a ``CandumpReader`` (an ``Iterator[LogFrame]``) exposing ``malformed`` / ``malformed_lines``.
    Raises FileNotFoundError if a path does not exist; never raises on file content.
    """
    return CandumpReader(source, max_warnings=max_warnings)
