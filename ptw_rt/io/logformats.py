"""Every CAN log format python-can reads, in and out: candump ``-L``, ASC, BLF, TRC, CSV, MF4 (ASAM MDF 4) and
SQLite (``.db``, ``ptw_rt.io.sqlite_log``); in only, candump's screen output (``-t a/A/z/d``) and python-can's
text (``can.Printer``); in, each of them but MF4 and SQLite gzip-compressed too (``ride.log.gz``:
``ptw_rt.io.compressed``, bounded), and out, the text ones (``--out est.log.gz``).

    open_log(path)            -> (iterator of (timestamp, id, data, extended), LogStats)
    open_writer(path, ...)    -> a writer of the format the extension names (candump: our own, byte-identical)

The format comes from the extension (``.log`` candump, ``.asc``, ``.blf``, ``.trc``, ``.csv``, ``.mf4``/``.mdf``)
and is confirmed by the content: the first ``SNIFF_BYTES`` are searched for a frame (or the signature, for the
binary formats) of every format. A file whose extension is missing, unknown or wrong (``.log`` is also what
many other tools write) is read as the format its content shows. A file showing none is ``NotACanLogError``
(one line, exit code 2 in the CLI); an empty file, or a log without a single frame, is ``EmptyLogError``.

Every log is untrusted data, read within bounds like ``ptw_rt.io.candump`` (whose time rule every format shares:
``TimeRule``, one implementation, and ``timestamp_problem`` for stamps read as numbers):

* text formats (candump, ASC, TRC, CSV) are read in 1 MiB chunks, a line longer than ``MAX_TEXT_LINE`` is skipped
  without being held (``text_blocks``); a line python-can cannot parse is counted and skipped, the next line is
  read (python-can's own readers stop at the first one: here its per-line parsers are called line by line);
* BLF is parsed here (python-can's ``BLFReader`` reads an object of any declared size, a negative size as "the
  rest of the file", decompresses a container without limit and keeps an unfinished object across containers
  without limit, and raises ``struct.error`` on a truncated file): objects and containers at most ``MAX_BLF_OBJECT``
  bytes, compressed or not; garbage between objects is skipped to the next ``LOBJ`` signature and counted;
* MF4 goes through python-can's ``MF4Reader`` and ``asammdf`` (the ``mf4`` extra) in a child process under memory,
  CPU and wall-clock limits (``ptw_rt.io.mf4_sandbox``: asammdf parses the whole file in native code in its
  constructor, and crafted files hung or aborted it); the declared record counts are checked against the file's
  size before a record is read, and any error of asammdf, or the end of the child, ends the log as counted.

Frames that are not classic data frames (remote, error, CAN FD) are counted in ``LogStats.skipped`` by kind.
"""

from __future__ import annotations

import base64
import binascii
import logging
import math
import re
import struct
import zlib
from collections.abc import Iterator, Sequence
from pathlib import Path
from types import TracebackType
from typing import IO, Any

from ptw_rt import _deferred_imports
from ptw_rt.errors import UserFacingError
from ptw_rt.io import compressed, mf4_sandbox, sqlite_log
from ptw_rt.io.candump import (
    MAX_LOG_BYTES,
    BusChoice,
    CandumpFileError,
    CandumpReader,
    CandumpWriter,
    FrameArrays,
    Jump,
    LogFrame,
    Problem,
    TimeRule,
    text_blocks,
    timestamp_problem,
)
from ptw_rt.untrusted import error_text, excerpt, file_size

__all__ = [
    "BusChoice",
    "EXTENSIONS",
    "FAMILIES",
    "FORMATS",
    "GZIP_SUFFIX",
    "SNIFF_BYTES",
    "EmptyLogError",
    "LogFormatError",
    "LogStats",
    "open_log_arrays",
    "NotACanLogError",
    "detect_format",
    "format_of_extension",
    "open_log",
    "open_writer",
    "output_name",
    "sniff",
    "uncompressed_name",
    "writer_format",
]

log = logging.getLogger(__name__)

# format -> name in messages; in the order the sniffer tries them
FORMATS = {
    "candump": "candump",
    "asc": "ASC",
    "blf": "BLF",
    "trc": "TRC",
    "csv": "CSV",
    "mf4": "MF4",
    "db": "SQLite",
    "candump_t": "candump -t",
    "candump_td": "candump -td",
    "pycan_txt": "python-can text",
}
EXTENSIONS = {
    ".log": "candump",
    ".asc": "asc",
    ".blf": "blf",
    ".trc": "trc",
    ".csv": "csv",
    ".mf4": "mf4",
    ".mdf": "mf4",
    ".db": "db",
    ".txt": "candump_t",  # what `candump -ta can0 > ride.txt` leaves, or python-can's text (FAMILIES; read only)
}
# an extension several formats share: its content picks among them without a warning (a `.txt` is candump's
# screen output or python-can's `Printer` text)
FAMILIES = {"candump_t": ("candump_t", "candump_td", "pycan_txt")}
GZIP_SUFFIX = ".gz"  # any format above, gzip-compressed (read only: ``ptw_rt.io.compressed``)
SNIFF_BYTES = 64 << 10
MAX_TEXT_LINE = 1024  # ASC/TRC lines of CAN FD frames reach ~400 characters; ours are < 100
MAX_BLF_OBJECT = 16 << 20  # an object, a container and a container's unpacked data (writers use 128 KiB)
# a container's unpacked data at most this many times its packed size (CAN objects pack ~4x: python-can's writer
# 4.2x): 200 containers of 48 kB that each unpacked to 16 MiB (340x) made a 9.8 MB file of 7e7 frames, minutes a MB
MAX_BLF_EXPANSION = 64
_READ_CHUNK = 1 << 20
ARRAY_BLOCK_FRAMES = 32768  # open_log_arrays: frames of a non-candump log gathered per block
_EXAMPLES = 3
_STD_MAX = 0x7FF


class LogFormatError(UserFacingError):
    """A log that cannot be read at all (one line; exit code 2 in the CLI)."""


class NotACanLogError(LogFormatError):
    """No frame of any supported format in the first ``SNIFF_BYTES``."""


class EmptyLogError(LogFormatError):
    """An empty file, or a log without a single CAN frame."""


def format_of_extension(path: str | Path) -> str | None:
    """The format an extension names, None for none or an unknown one; a compressed log's (``ride.asc.gz``) is
    the one before ``.gz``."""
    return EXTENSIONS.get(Path(uncompressed_name(path)).suffix.lower())


READ_ONLY = ("candump_t", "candump_td", "pycan_txt")  # read, not written: their replay's output is candump
# formats written gzip-compressed when the output's name ends in .gz: the text ones (a BLF writer seeks back to its
# header when it closes, an MF4's and an SQLite's library writes the file itself)
GZIP_WRITABLE = ("candump", "asc", "trc", "csv")


def output_name(path: str | Path) -> str:
    """The name of a log's replay output: its own, in its own format; candump ``.log`` for a format read only
    (``ride.txt`` -> ``ride.log``) or a name whose extension names no format (``ride.bin`` -> ``ride.bin.log``);
    compressed when the input was and the output's format is written compressed (``ride.asc.gz`` -> itself,
    ``ride.blf.gz`` -> ``ride.blf``)."""
    name = uncompressed_name(path)
    fmt = format_of_extension(name)
    if fmt is None:
        name, fmt = name + ".log", "candump"
    elif fmt in READ_ONLY:
        name, fmt = str(Path(name).with_suffix(".log")), "candump"
    packed = Path(path).name.lower().endswith(GZIP_SUFFIX)
    return name + GZIP_SUFFIX if packed and fmt in GZIP_WRITABLE else name


def uncompressed_name(path: str | Path) -> str:
    """The name of a log without its ``.gz`` (``ride.asc.gz`` -> ``ride.asc``): the name its format is read from."""
    name = Path(path).name
    return name[: -len(GZIP_SUFFIX)] if name.lower().endswith(GZIP_SUFFIX) else name


# ---------------------------------------------------------------------- sniffing

_CANDUMP_RE = re.compile(rb"^[ \t]*\([0-9.]+\)[ \t]+\S+[ \t]+[0-9A-Fa-f]+#", re.M)
_ASC_FRAME_RE = re.compile(rb"^[ \t]*\d+\.\d+[ \t]+(\d+[ \t]+(\w+x?[ \t]+(Tx|Rx)|ErrorFrame)|CANFD[ \t])", re.M | re.I)
_ASC_HEAD_RE = re.compile(rb"^[ \t]*(date[ \t]+\w+|base[ \t]+(hex|dec)|begin[ \t]+triggerblock)", re.M | re.I)
_TRC_FRAME_RE = re.compile(
    rb"^[ \t]*\d+\)?[ \t]+\d+(\.\d+)?[ \t]+"
    rb"((DT|FD|FB|FE|BI|RR)[ \t]|(Rx|Tx)[ \t]+[0-9A-Fa-f]+[ \t]|[0-9A-Fa-f]{4,8}[ \t]+\d)",
    re.M,
)
_TRC_HEAD_RE = re.compile(rb"^;\$FILEVERSION=", re.M)
_CSV_FRAME_RE = re.compile(rb"^\d+(\.\d*)?,(0x)?[0-9A-Fa-f]+,[01],[01],[01],\d+,[A-Za-z0-9+/=]*\r?$", re.M)
_CSV_HEAD = b"timestamp,arbitration_id,extended,remote,error,dlc,data"
# candump's screen output with a time stamp (-t a: epoch seconds, -t A: local date and time, -t z: from zero), with
# or without -x's direction and flags: ` (1700000000.012002)  can0  300   [8]  9E 40 D0 FF ED FF 00 00`
_CANDUMP_T_STAMP = r"\((\d+\.\d+|\d{4}-\d\d-\d\d \d\d:\d\d:\d\d\.\d+)\)"
_CANDUMP_T_FRAME = (
    r"[ \t]+(\S+)[ \t]+(?:[RT]X[ \t]+\S+[ \t]+\S+[ \t]+)?([0-9A-Fa-f]{3}|[0-9A-Fa-f]{8})[ \t]+\[(\d{1,2})\]"
)
_CANDUMP_T_RE = re.compile((r"^[ \t]*" + _CANDUMP_T_STAMP + _CANDUMP_T_FRAME).encode(), re.M)
_CANDUMP_T_LINE = re.compile(r"^[ \t]*" + _CANDUMP_T_STAMP + _CANDUMP_T_FRAME + r"[ \t]*(.*)$")
# python-can's text (`python -m can.logger -f ride.txt`: `can.Printer`, one `str(Message)` a line), which python-can
# writes and does not read: `Timestamp: 1700000000.012002    ID:      300    S Rx   DL:  8    9e 40 ...  Channel: can0`
_PYCAN_TXT_RE = re.compile(rb"^Timestamp:[ \t]*\d+\.\d+[ \t]+ID:[ \t]*[0-9a-fA-F]+[ \t]+[SX][ \t]", re.M)
_PYCAN_TXT_LINE = re.compile(
    r"^Timestamp:\s*(\S+)\s+ID:\s*([0-9a-fA-F]{1,8})\s+([SX])\s+(.*?)DL:\s*(\d+)\s*((?:[0-9a-fA-F]{2}\s*)*)"
    r"(?:Channel:\s*(\S+))?\s*$"
)
# -t d stamps each frame with the time since the one before: told from the others by stamps that go back
_CANDUMP_T_NUMBER = re.compile(rb"^[ \t]*\((\d+\.\d+)\)", re.M)
# ... and without one (plain `candump can0`): frames with no time, which no replay can clock
_CANDUMP_NO_TIME_RE = re.compile(rb"^[ \t]*\S+[ \t]+([0-9A-Fa-f]{3}|[0-9A-Fa-f]{8})[ \t]+\[\d{1,2}\][ \t]", re.M)


def sniff(head: bytes) -> tuple[list[str], list[str]]:
    """The formats the first bytes of a file show: (those with a frame or a binary signature, those with only
    a header of theirs), each in ``FORMATS`` order."""
    framed: list[str] = []
    headed: list[str] = []
    if head[:4] == b"LOGG":
        framed.append("blf")
    if head[:8] in (b"MDF     ", b"UnFinMF ") and head[8:10] == b"4.":
        framed.append("mf4")
    if head[: len(sqlite_log.MAGIC)] == sqlite_log.MAGIC:
        framed.append("db")
    if framed:
        return framed, headed
    for fmt, frame_re, head_test in (
        ("candump", _CANDUMP_RE, None),
        ("asc", _ASC_FRAME_RE, lambda h: _ASC_HEAD_RE.search(h) is not None),
        ("trc", _TRC_FRAME_RE, lambda h: _TRC_HEAD_RE.search(h) is not None),
        ("csv", _CSV_FRAME_RE, lambda h: h.lstrip().startswith(_CSV_HEAD)),
        ("candump_t", _CANDUMP_T_RE, None),
        ("pycan_txt", _PYCAN_TXT_RE, None),
    ):
        if frame_re.search(head):
            framed.append(fmt)
        elif head_test is not None and head_test(head):
            headed.append(fmt)
    return framed, headed


def detect_format(path: str | Path, max_bytes: int = MAX_LOG_BYTES, *, warn: bool = False) -> tuple[str, int]:
    """(format, size in bytes) of the log at ``path``: the extension's format if the content shows it, else the
    format the content shows (``warn``: say so in a warning). Raises ``CandumpFileError`` (not a regular file,
    too large, unreadable), ``EmptyLogError`` (0 bytes) or ``NotACanLogError``."""
    with compressed.open_log_file(path, max_bytes=max_bytes, what="CAN log", error=CandumpFileError) as fh:
        head = fh.read(SNIFF_BYTES)
        size = file_size(fh)  # the file's: a compressed log's progress counts compressed bytes
    if not head:
        raise EmptyLogError(f"{path}: empty log ({'nothing decompressed' if size else '0 bytes'})")
    framed, headed = sniff(head)
    if "candump_t" in framed and _deltas(head):
        framed[framed.index("candump_t")] = "candump_td"
    by_ext = format_of_extension(path)
    family = FAMILIES.get(by_ext, (by_ext,))
    for found in (framed, headed):
        for fmt in found:
            if fmt in family:
                return fmt, size
        if found:
            if by_ext is not None and warn:
                log.warning(
                    "%s: content is %s, not %s: read as %s", path, FORMATS[found[0]], FORMATS[by_ext], FORMATS[found[0]]
                )
            return found[0], size
    if _CANDUMP_NO_TIME_RE.search(head):
        raise LogFormatError(
            f"{path}: candump output without time stamps: nothing to clock a replay by (record with candump -L, "
            "or candump -ta)"
        )
    names = "/".join(name for fmt, name in FORMATS.items() if fmt != "candump_td")  # -t d is -t's time base
    raise NotACanLogError(f"{path}: not a CAN log (no {names} frame in the first {SNIFF_BYTES >> 10} KiB)")


def _deltas(head: bytes) -> bool:
    """Whether candump -t stamps are -t d's deltas: times that go back at one pair of frames in ten or more (a
    bus's deltas go up and down all the time; -t a and -t z only go back where the clock was stepped, and -t a's
    epoch seconds are no frame's delta)."""
    stamps = [float(m) for m in _CANDUMP_T_NUMBER.findall(head)]
    if len(stamps) < 3 or max(stamps) > 1e6:
        return False
    back = sum(b < a for a, b in zip(stamps, stamps[1:], strict=False))
    return back >= 0.1 * (len(stamps) - 1)


# ---------------------------------------------------------------------- stats


class LogStats:
    """What reading a log found: the time rule's counts (``reader``: ``frames``, ``malformed``, ``rejected``,
    ``reordered``, ``discontinuities``, ``malformed_lines``, ``examples``), the frames skipped because they are
    not classic data frames (``skipped``: kind -> count), the channel of the first frame, the line (record
    number) of the last frame given (``line``) and the progress. The reader's ``warn_discontinuities`` is set
    on ``reader`` (a consumer reporting the discontinuities itself)."""

    def __init__(self, path: Path, fmt: str, size: int, reader: TimeRule) -> None:
        self.path = path
        self.format = fmt
        self.size = size
        self.reader = reader
        self.skipped: dict[str, int] = {}
        self.channel: str | None = None
        self.line = 0

    def __getattr__(self, name: str) -> Any:  # frames, malformed, rejected, ... of the time rule
        if name.startswith("_") or name == "reader":
            raise AttributeError(name)
        return getattr(self.reader, name)

    @property
    def fraction(self) -> float:
        """Share of the log read so far (0..1; by bytes, or records for MF4)."""
        done = getattr(self.reader, "position", 0)
        total = getattr(self.reader, "total", self.size)
        return min(1.0, done / total) if total else 0.0

    def skip(self, kind: str) -> None:
        self.skipped[kind] = self.skipped.get(kind, 0) + 1

    def problems_line(self) -> str | None:
        """One line summarising the records skipped, with a few escaped examples; None if none were."""
        r = self.reader
        if not r.malformed:
            return None
        kinds = ", ".join(f"{k} {n}" for k, n in r.rejected.items() if n)
        examples = "; ".join(r.examples[:_EXAMPLES])
        return f"{self.path}: {r.malformed} {r.unit}s skipped ({kinds}); e.g. {examples}"

    def no_frames_message(self) -> str:
        """The one line for a log that gave no frame at all."""
        r = self.reader
        if r.malformed:
            kinds = ", ".join(f"{k} {n}" for k, n in r.rejected.items() if n)
            return f"{self.path}: no CAN frame could be read ({r.malformed} {r.unit}s skipped: {kinds})"
        skipped = sum(self.skipped.values())
        if skipped:
            kinds = ", ".join(f"{k} {n}" for k, n in sorted(self.skipped.items()))
            return f"{self.path}: no classic CAN data frame in the log ({FORMATS[self.format]}; skipped: {kinds})"
        return f"{self.path}: empty log (no CAN frames in this {FORMATS[self.format]} file)"


# ---------------------------------------------------------------------- readers


def _frame(
    timestamp: float, channel: Any, frame_id: int, data: bytes, record: int, extended: bool
) -> LogFrame | Problem:
    problem = timestamp_problem(timestamp)
    if problem is not None:
        return Problem(record, problem, "", "bad_timestamp")
    if not 0 <= frame_id <= (0x1FFFFFFF if extended else _STD_MAX):
        return Problem(record, f"{'29' if extended else '11'}-bit frame id {frame_id:#x} out of range", "", "malformed")
    return LogFrame(timestamp, str(channel), frame_id, data, record, extended, False)


class _MessageReader(TimeRule):
    """Frames of a python-can ``Message`` source (or parsed here), through the shared time rule."""

    def __init__(self, path: Path, max_bytes: int, **rules: Any) -> None:
        self.path = path
        self._fh = compressed.open_log_file(path, max_bytes=max_bytes, what="CAN log", error=CandumpFileError)
        self.skipped: dict[str, int] = {}
        super().__init__(str(path), **rules)

    @property
    def position(self) -> int:
        return compressed.position(self._fh)

    def _release(self) -> None:
        self._fh.close()

    def _skip(self, kind: str) -> None:
        self.skipped[kind] = self.skipped.get(kind, 0) + 1

    def _skipped(self, error: bool, remote: bool, fd: bool) -> bool:
        """Whether a record is an error, a remote or a CAN FD frame, none of them an input of ours (counted, in
        that order of precedence, whatever the format)."""
        kind = "error" if error else "remote" if remote else "fd" if fd else None
        if kind is not None:
            self._skip(kind)
        return kind is not None

    def _message(self, msg: Any, record: int) -> LogFrame | Problem | None:
        """A python-can Message as a frame; None for a remote, error or CAN FD frame (counted)."""
        if self._skipped(msg.is_error_frame, msg.is_remote_frame, msg.is_fd or len(msg.data) > 8):
            return None
        ts = msg.timestamp
        if not isinstance(ts, float):
            try:
                ts = float(ts)
            except (TypeError, ValueError, OverflowError):
                return Problem(record, f"bad time stamp {ts!r:.40}", "", "bad_timestamp")
        return _frame(ts, msg.channel, int(msg.arbitration_id), bytes(msg.data), record, bool(msg.is_extended_id))

    def _lines(self) -> Iterator[tuple[int, str]]:
        """(line number, line) of a text log, bounded like candump's."""
        fh = self._fh

        def read() -> str:
            return fh.read(_READ_CHUNK).decode("utf-8", "replace")

        n = 0
        for block in text_blocks(read, MAX_TEXT_LINE):
            for line in block:
                n += 1
                yield n, line


def _stripped(lines: Iterator[tuple[int, str]]) -> Iterator[tuple[int, str] | Problem]:
    """(line number, stripped text) of each non-blank line of a text log; a line longer than ``MAX_TEXT_LINE``
    as its Problem (the line-by-line readers of this module: CSV, candump -t)."""
    for n, line in lines:
        if len(line) > MAX_TEXT_LINE:
            yield Problem(n, f"line longer than {MAX_TEXT_LINE} characters", "", "too_long")
            continue
        text = line.strip()
        if text:
            yield n, text


class _LineFeed:
    """The lines of a text log as python-can's text readers iterate ``self.file``; remembers the last one."""

    def __init__(self, lines: Iterator[tuple[int, str]]) -> None:
        self._lines = lines
        self.line_no = 0
        self.line = ""
        self.too_long: list[int] = []

    def __iter__(self) -> _LineFeed:
        return self

    def __next__(self) -> str:
        while True:
            self.line_no, self.line = next(self._lines)
            if len(self.line) <= MAX_TEXT_LINE:
                return self.line + "\n"
            self.too_long.append(self.line_no)  # python-can never sees it; reported by the caller

    def close(self) -> None:
        pass


class _TextReader(_MessageReader):
    """ASC and TRC: python-can's reader parses the header, then its per-line parser is called line by line (a
    line it cannot parse is one skipped line, not the end of the log)."""

    def _pycan(self, feed: _LineFeed) -> Any:
        raise NotImplementedError

    def _parse(self, reader: Any, line: str) -> Any:
        raise NotImplementedError

    def _items(self) -> Iterator[LogFrame | Problem]:
        feed = _LineFeed(self._lines())
        too_long = f"line longer than {MAX_TEXT_LINE} characters"
        try:
            reader, first = self._pycan(feed)
        except StopIteration:
            return
        except Exception as exc:  # noqa: BLE001 - python-can on untrusted content: any error is the file's
            for n in feed.too_long:
                yield Problem(n, too_long, "", "too_long")
            raise LogFormatError(f"{self.path}: unreadable {self.unit.split()[0]} header ({error_text(exc)})") from None
        lines = feed
        if first is not None:
            lines = _prepend(first, feed)
        for raw in lines:
            while feed.too_long:
                yield Problem(feed.too_long.pop(0), too_long, "", "too_long")
            line = raw.strip()
            if not line:
                continue
            n = feed.line_no
            try:
                msg = self._parse(reader, line)
            except Exception as exc:  # noqa: BLE001 - as above
                yield Problem(n, error_text(exc), line, "malformed")
                continue
            if msg is None:
                continue
            out = self._message(msg, n)
            if out is not None:
                yield out
        for n in feed.too_long:
            yield Problem(n, too_long, "", "too_long")


def _prepend(first: str, rest: _LineFeed) -> Iterator[str]:
    yield first
    yield from rest


class _AscReader(_TextReader):
    unit = "ASC line"

    def _pycan(self, feed: _LineFeed) -> tuple[Any, str | None]:
        from can.io.asc import ASCReader

        reader = ASCReader(feed)  # relative time stamps (python-can's default): the measurement starts at 0
        reader._extract_header()  # noqa: SLF001 - python-can's own header parser
        # _extract_header consumes the first line after the header; a frame there must not be lost
        line = feed.line
        return reader, (line + "\n" if feed.line_no and not _is_asc_header(line) else None)

    def _parse(self, reader: Any, line: str) -> Any:
        from can.io.asc import ASC_MESSAGE_REGEX, ASC_TRIGGER_REGEX

        trigger = ASC_TRIGGER_REGEX.match(line)
        if trigger:  # python-can's ASCReader.__iter__, one line
            reader.start_time = (
                0.0 if reader.relative_timestamp else reader._datetime_to_timestamp(trigger.group("datetime_string"))
            )
            return None
        if not ASC_MESSAGE_REGEX.match(line):
            fields = line.split(None, 2)
            if len(fields) == 3 and _ASC_EVENT.match(line) and _ASC_FRAME_REST.match(fields[2]):
                raise ValueError(f"channel {excerpt(fields[1])} is not a number")  # a frame, dropped unsaid before
            if _ASC_EVENT.match(line) or _is_asc_header(line):
                return None  # comments, statistics, events: not frames
            # garbage (or a frame whose stamp is nan, inf, 1e308, -1): was skipped uncounted, half a log lost unsaid
            raise ValueError("neither a frame, an event nor a header line")
        stamp, channel, rest = line.split(None, 2)
        kwargs: dict[str, Any] = {"timestamp": float(stamp) + reader.start_time}
        if channel == "CANFD":
            kwargs["is_fd"] = True
            return reader._process_fd_can_frame(rest, kwargs)
        if not (channel.isascii() and channel.isdigit()):
            if _ASC_FRAME_REST.match(rest):  # a frame's fields after a channel that is no number: not an event line
                raise ValueError(f"channel {excerpt(channel)} is not a number")
            return None
        kwargs["channel"] = int(channel) - 1
        msg = reader._process_classic_can_frame(rest, kwargs)
        if not (msg.is_error_frame or msg.is_remote_frame):
            fields = rest.split(None, 4)  # id, direction, "d", DLC, the data and what follows it
            tokens = fields[4].split() if len(fields) > 4 else []
            _check_data(msg, tokens[: len(msg.data)], reader._converted_base)  # noqa: SLF001 - the header's base
        return msg


def _check_data(msg: Any, tokens: list[str], base: int) -> None:
    """A text record's data as python-can read them, refused (ValueError) where the line does not hold them: python-can
    takes the bytes there are (a logger killed mid-write leaves DLC 7 with 3 bytes) and reads a byte cut to one hex
    digit as that digit (``FC 8`` for ``FC 8F``), where candump's reader counts an odd number of digits."""
    if len(msg.data) != min(msg.dlc, 8):
        raise ValueError(f"DLC {msg.dlc} with {len(msg.data)} data bytes")
    if base == 16 and any(len(t) != 2 for t in tokens):
        raise ValueError(f"a data byte that is not two hex digits in {excerpt(' '.join(tokens))}")


_ASC_EVENT = re.compile(r"\d+\.\d+\s")  # a time-stamped line: a frame, or an event (statistics, status, errors)
# what follows a classic frame's channel: identifier (x: 29-bit), direction, d(ata) or r(emote). Such a line whose
# channel is no number (abc, -1, 0x2, ä) was dropped uncounted; an event line (ErrorFrame, Statistic:) is not one
_ASC_FRAME_REST = re.compile(r"[0-9A-Fa-f]{1,8}x?\s+(Rx|Tx)\s+[dr]\b")


def _is_asc_header(line: str) -> bool:
    s = line.strip().lower()
    return (
        not s
        or s.startswith(("date ", "base ", "//", "begin triggerblock", "end triggerblock"))
        or s.endswith("internal events logged")
        or "start of measurement" in s
    )


_TRC_RECORD = re.compile(r"\d+\)?\s")  # every TRC record starts with its message number ("12)" in version 1.1)


class _TrcReader(_TextReader):
    unit = "TRC line"

    def _pycan(self, feed: _LineFeed) -> tuple[Any, str | None]:
        from can.io.trc import TRCReader

        reader = TRCReader(feed)
        first = reader._extract_header()  # noqa: SLF001 - the first line after the header is a frame
        return reader, (first + "\n" if first and not first.startswith(";") else None)

    def _parse(self, reader: Any, line: str) -> Any:
        if line.startswith(";"):
            return None
        if not _TRC_RECORD.match(line):  # garbage was an "unsupported type" to python-can: skipped uncounted
            raise ValueError("not a TRC record (no message number)")
        cols = tuple(line.split(maxsplit=reader._num_columns))
        msg = reader._parse_cols(cols)
        if msg is not None and not (msg.is_error_frame or msg.is_remote_frame or msg.is_fd):
            _check_data(msg, line.split()[len(line.split()) - len(msg.data) :] if msg.data else [], 16)
        if msg is not None and isinstance(msg.timestamp, float) and math.isfinite(msg.timestamp):
            # start (days since 1899, a double: 0.6 us steps) + offset (ms, 3 decimals): the sum carries float
            # noise below the format's 1 us resolution; rounded to it, the stamps are candump's to the bit
            msg.timestamp = round(msg.timestamp, 6)
        return msg


class _LineReader(_MessageReader):
    """A text log parsed here line by line: ``_line`` turns each non-blank line within bounds into a frame, a
    problem, or nothing (a header, a frame that is no input's kind: counted by ``_skip``)."""

    def _items(self) -> Iterator[LogFrame | Problem]:
        for item in _stripped(self._lines()):
            out = item if isinstance(item, Problem) else self._line(*item)
            if out is not None:
                yield out

    def _line(self, n: int, text: str) -> LogFrame | Problem | None:
        raise NotImplementedError


class _CandumpTextReader(_LineReader):
    """candump's screen output with time stamps (``candump -ta``, ``-tA``, ``-tz``, with or without ``-x``)."""

    unit = "candump -t line"
    deltas = False  # -t d: each stamp the time since the frame before (``_CandumpDeltaReader``)

    def __init__(self, path: Path, max_bytes: int, **rules: Any) -> None:
        super().__init__(path, max_bytes, **rules)
        self._clock = 0.0

    def _line(self, n: int, text: str) -> LogFrame | Problem | None:
        m = _CANDUMP_T_LINE.match(text)
        if m is None:
            return Problem(n, "not a candump -t frame line", text, "malformed")
        stamp, channel, ident, length, rest = m.groups()
        try:
            ts = _candump_t_time(stamp)
        except (ValueError, OverflowError) as exc:
            return Problem(n, error_text(exc), text, "bad_timestamp")
        if self.deltas:  # the time since the frame before: the times are their running sum, from 0
            self._clock += ts
            ts = self._clock
        size = int(length)
        if self._skipped(False, rest.startswith("remote request"), size > 8):
            return None
        try:
            payload = bytes.fromhex(rest)
        except ValueError as exc:
            return Problem(n, error_text(exc), text, "malformed")
        if len(payload) != size:
            return Problem(n, f"[{size}] with {len(payload)} data bytes", text, "malformed")
        return _frame(ts, channel, int(ident, 16), payload, n, len(ident) == 8)


class _CandumpDeltaReader(_CandumpTextReader):
    """``candump -td``: each line stamped with the time since the line before; the times are their running sum
    (from 0, like ``-tz``)."""

    deltas = True


class _PycanTextReader(_LineReader):
    """python-can's text (``can.Printer``: ``str(Message)`` a line), which python-can writes and cannot read."""

    unit = "python-can text line"

    def _line(self, n: int, text: str) -> LogFrame | Problem | None:
        m = _PYCAN_TXT_LINE.match(text)
        if m is None:
            return Problem(n, "not a python-can text frame line", text, "malformed")
        stamp, ident, kind, flags, length, data, channel = m.groups()
        try:
            ts = float(stamp)
        except ValueError as exc:
            return Problem(n, error_text(exc), text, "bad_timestamp")
        marks = flags.split()
        try:  # hex pairs (the line's pattern), but its \s also takes control and non-ASCII spaces fromhex refuses
            payload = bytes.fromhex(data)
        except ValueError as exc:
            return Problem(n, error_text(exc), text, "malformed")
        if self._skipped("E" in marks, "R" in marks, "F" in marks or len(payload) > 8):
            return None
        if len(payload) != int(length):
            return Problem(n, f"DL {length} with {len(payload)} data bytes", text, "malformed")
        return _frame(ts, channel or 0, int(ident, 16), payload, n, kind == "X")


def _candump_t_time(stamp: str) -> float:
    """Seconds since the epoch of candump's ``-ta`` (epoch seconds) or ``-tA`` (local date and time) stamp."""
    if "-" in stamp:
        import datetime

        return datetime.datetime.strptime(stamp, "%Y-%m-%d %H:%M:%S.%f").timestamp()
    return float(stamp)


class _CsvReader(_LineReader):
    """python-can's CSV: ``timestamp,arbitration_id,extended,remote,error,dlc,data`` (data in base64), parsed
    here line by line as ``can.io.csv.CSVReader`` does (it stops at the first bad line)."""

    unit = "CSV line"

    def _line(self, n: int, text: str) -> LogFrame | Problem | None:
        if n == 1 and text.startswith("timestamp,"):
            return None
        fields = text.split(",")
        if len(fields) != 7:
            return Problem(n, f"expected 7 comma-separated fields, got {len(fields)}", text, "malformed")
        stamp, ident, extended, remote, error, dlc, data = fields
        try:
            ts = float(stamp)
            frame_id = int(ident, 16)
            payload = base64.b64decode(data, validate=True)
            length = int(dlc)
        except (ValueError, binascii.Error) as exc:
            return Problem(n, error_text(exc), text, "malformed")
        if remote != "1" and length != len(payload):  # a line cut mid-write can still be base64
            return Problem(n, f"DLC {length} with {len(payload)} data bytes", text, "malformed")
        if self._skipped(error == "1", remote == "1", len(payload) > 8):
            return None
        return _frame(ts, 0, frame_id, payload, n, extended == "1")


class _BlfReader(_MessageReader):
    """Binary Logging Format (Vector), parsed here within bounds (the module docstring says why), with
    python-can's structures: same frames and time stamps as ``can.io.blf.BLFReader`` on a sound file."""

    unit = "BLF object"

    def _items(self) -> Iterator[LogFrame | Problem]:
        from can.io import blf

        fh = self._fh
        header = fh.read(blf.FILE_HEADER_STRUCT.size)
        if len(header) < blf.FILE_HEADER_STRUCT.size or header[:4] != b"LOGG":
            raise LogFormatError(f"{self.path}: not a BLF file (truncated or foreign header)")
        fields = blf.FILE_HEADER_STRUCT.unpack(header)
        header_size = fields[1]
        if not blf.FILE_HEADER_STRUCT.size <= header_size <= 1 << 16:
            raise LogFormatError(f"{self.path}: corrupt BLF header (header size {header_size})")
        self.start = blf.systemtime_to_timestamp(fields[14:22])
        fh.read(header_size - blf.FILE_HEADER_STRUCT.size)
        self._record = 0
        self._forget_tail()
        self._lost = False  # a container was lost: the next one may start inside an object
        base = blf.OBJ_HEADER_BASE_STRUCT
        while True:
            offset = fh.tell()
            head = fh.read(base.size)
            if not head:
                break
            if len(head) < base.size:
                yield Problem(self._record + 1, f"truncated object header at byte {offset}", "", "malformed")
                break
            signature, _, _, obj_size, obj_type = base.unpack(head)
            if signature != b"LOBJ" or not base.size + 16 <= obj_size <= MAX_BLF_OBJECT:
                what = "no object signature" if signature != b"LOBJ" else f"object size {obj_size}"
                yield Problem(self._record + 1, f"{what} at byte {offset}; skipped to the next object", "", "malformed")
                self._forget_tail()
                self._lost = True
                if not self._resync(offset + 1):
                    break
                continue
            body = fh.read(obj_size - base.size)
            if len(body) < obj_size - base.size:
                yield Problem(self._record + 1, f"truncated object at byte {offset} (file ends)", "", "malformed")
                break
            fh.read(obj_size % 4)
            if obj_type != blf.LOG_CONTAINER:
                continue  # python-can reads frames only from containers
            method, _ = blf.LOG_CONTAINER_STRUCT.unpack_from(body)
            payload = body[blf.LOG_CONTAINER_STRUCT.size :]
            if method == blf.ZLIB_DEFLATE:
                unpacker = zlib.decompressobj()
                try:
                    data = unpacker.decompress(payload, MAX_BLF_OBJECT)
                except zlib.error as exc:
                    yield Problem(self._record + 1, f"container at byte {offset}: {exc}", "", "malformed")
                    self._forget_tail()
                    self._lost = True
                    continue
                if unpacker.unconsumed_tail:
                    yield Problem(
                        self._record + 1,
                        f"container at byte {offset} unpacks to more than {MAX_BLF_OBJECT >> 20} MiB",
                        "",
                        "malformed",
                    )
                    self._forget_tail()
                    self._lost = True
                    continue
                if len(data) > MAX_BLF_EXPANSION * len(payload) + 4096:
                    yield Problem(
                        self._record + 1,
                        f"container at byte {offset} unpacks {len(data) / max(len(payload), 1):.0f} times its size "
                        f"(CAN data packs ~4x; at most {MAX_BLF_EXPANSION}x)",
                        "",
                        "malformed",
                    )
                    self._forget_tail()
                    self._lost = True
                    continue
            elif method == blf.NO_COMPRESSION:
                data = payload
            else:
                yield Problem(self._record + 1, f"unknown compression {method} at byte {offset}", "", "malformed")
                self._forget_tail()
                self._lost = True
                continue
            yield from self._container(blf, data)
        if self._tail:
            yield Problem(self._record + 1, "the last object is cut off (file ends)", "", "malformed")

    def _resync(self, offset: int) -> bool:
        """Seek to the next ``LOBJ`` at or after ``offset``; False at the end of the file."""
        fh = self._fh
        fh.seek(offset)
        carry = b""
        while True:
            chunk = fh.read(_READ_CHUNK)
            if not chunk:
                return False
            buf = carry + chunk
            i = buf.find(b"LOBJ")
            if i >= 0:
                fh.seek(offset - len(carry) + i)
                return True
            carry = buf[-3:]
            offset += len(chunk)

    def _forget_tail(self) -> None:
        """No unfinished object carried into the next container."""
        self._tail = b""  # the start of an object the container ended inside
        self._pieces: list[bytes] = []  # the containers after it, held until the object is whole
        self._held = 0  # bytes of the tail and the pieces
        self._need = 0  # bytes the object needs (its declared size, or a header's)

    def _container(self, blf: Any, data: bytes) -> Iterator[LogFrame | Problem]:
        if self._tail:
            self._pieces.append(data)
            self._held += len(data)
            if self._held < self._need and self._held <= MAX_BLF_OBJECT:
                return  # held, not joined: joining at every container was quadratic (8 MB of 32-byte ones: >120 s)
            data = b"".join([self._tail, *self._pieces])
            self._forget_tail()
        base = blf.OBJ_HEADER_BASE_STRUCT
        v1, v2 = blf.OBJ_HEADER_V1_STRUCT, blf.OBJ_HEADER_V2_STRUCT
        can_msg = blf.CAN_MSG_STRUCT
        start = self.start
        end = len(data)
        pos = 0
        while pos + base.size <= end:
            at = data.find(b"LOBJ", pos, pos + 8)  # objects are padded to 4 bytes
            if at < 0:  # garbage (or the end of an object lost with the container before): the next signature
                at = data.find(b"LOBJ", pos + 1)
                self._record += 1
                if not self._lost:
                    yield Problem(self._record, f"garbage inside a container ({(at if at >= 0 else end) - pos} bytes)")
                if at < 0:
                    self._lost = False
                    return
            self._lost = False
            pos = at
            if pos + base.size > end:
                break
            _, _, version, obj_size, obj_type = base.unpack_from(data, pos)
            if obj_size < base.size:
                self._record += 1
                yield Problem(self._record, f"object size {obj_size} inside a container", "", "malformed")
                return
            if pos + obj_size > end:  # continues in the next container
                break
            self._record += 1
            record = self._record
            next_pos = pos + obj_size
            body = pos + base.size
            try:
                if version == 1:
                    flags, _, _, stamp = v1.unpack_from(data, body)
                    body += v1.size
                elif version == 2:
                    flags, _, _, stamp = v2.unpack_from(data, body)
                    body += v2.size
                else:
                    yield Problem(record, f"object header version {version}", "", "malformed")
                    pos = next_pos
                    continue
                ts = stamp / 1e5 if flags == 1 else stamp / 1e9
                if obj_type in (blf.CAN_MESSAGE, blf.CAN_MESSAGE2):
                    channel, msg_flags, dlc, can_id, payload = can_msg.unpack_from(data, body)
                    if msg_flags & blf.REMOTE_FLAG:
                        self._skip("remote")
                    else:
                        ident = can_id & 0x1FFFFFFF
                        extended = bool(can_id & blf.CAN_MSG_EXT)
                        # the channel as python-can gives it (BLF counts from 1): a log of several buses
                        yield _frame(ts + start, channel - 1, ident, payload[:dlc], record, extended)
                elif obj_type == blf.CAN_ERROR_EXT:
                    self._skip("error")
                elif obj_type in (blf.CAN_FD_MESSAGE, blf.CAN_FD_MESSAGE_64):
                    self._skip("fd")
            except struct.error:
                yield Problem(record, f"object type {obj_type} shorter than its fields", "", "malformed")
            pos = next_pos
        tail = data[pos:]
        if len(tail) > MAX_BLF_OBJECT:
            self._record += 1
            yield Problem(self._record, "an object spans more than 16 MiB of containers", "", "malformed")
            return
        if tail:
            self._tail, self._held = tail, len(tail)
            # what the object needs to be whole: its declared size once its header is here, else the header
            self._need = max(base.unpack_from(tail)[3], base.size) if len(tail) >= base.size else base.size


class _RecordReader(_MessageReader):
    """A format another library reads from the path itself, at random offsets (MF4: asammdf; SQLite): the file
    is checked as every log is, then closed; progress counts records (``total`` once the library declares it)."""

    def __init__(self, path: Path, max_bytes: int, **rules: Any) -> None:
        super().__init__(path, max_bytes, **rules)
        self.total = 0
        self._done = 0

    @property
    def position(self) -> int:
        return self._done

    def _declared(self, total: int) -> None:
        self.total = total

    def _hand_over(self) -> int:
        """Close the checked file for the library to open by its path; its size. A compressed one is refused:
        the library cannot read a stream."""
        size = file_size(self._fh)
        gzipped = compressed.is_compressed(self._fh)
        self._fh.close()
        if gzipped:
            name = self.unit.split()[0]
            raise LogFormatError(
                f"{self.path}: {name} inside gzip is not read (read at random offsets): decompress it first"
            )
        return size


class _Mf4Reader(_RecordReader):
    """ASAM MDF 4 through python-can's ``MF4Reader`` (``asammdf``: the ``mf4`` extra)."""

    unit = "MF4 record"

    def _items(self) -> Iterator[LogFrame | Problem]:
        size = self._hand_over()  # the child opens the (checked, regular) file itself
        try:
            for item in mf4_sandbox.read_messages(str(self.path), size, self._declared):
                if isinstance(item, tuple):  # a read error after some records: the rest of the file is lost
                    yield Problem(item[0], item[1], "", "malformed")
                    break
                self._done += 1
                out = self._message(item, self._done)
                if out is not None:
                    yield out
        except mf4_sandbox.SandboxError as exc:
            raise LogFormatError(f"{self.path}: {exc}") from None


class _SqliteReader(_RecordReader):
    """python-can's SQLite log (``ptw_rt.io.sqlite_log``: read-only, a table only, values and time bounded)."""

    unit = "SQLite row"

    def _items(self) -> Iterator[LogFrame | Problem]:
        size = self._hand_over()  # SQLite opens the (checked, regular) file itself
        try:
            for n, item in sqlite_log.rows(self.path, size, self._declared):
                self._done = n
                if isinstance(item, str):
                    yield Problem(n, item, "", "malformed")
                    continue
                ts, frame_id, extended, remote, error, data = item
                if not self._skipped(error, remote, len(data) > 8):
                    yield _frame(ts, 0, frame_id, data, n, extended)
        except sqlite_log.SqliteLogError as exc:
            raise LogFormatError(f"{self.path}: {exc}") from None


_READERS: dict[str, type[_MessageReader]] = {
    "asc": _AscReader,
    "trc": _TrcReader,
    "csv": _CsvReader,
    "blf": _BlfReader,
    "mf4": _Mf4Reader,
    "db": _SqliteReader,
    "candump_t": _CandumpTextReader,
    "candump_td": _CandumpDeltaReader,
    "pycan_txt": _PycanTextReader,
}


def open_log(
    path: str | Path,
    *,
    fmt: str | None = None,
    max_warnings: int | None = None,
    max_bytes: int = MAX_LOG_BYTES,
    bus: BusChoice | None = None,
    **rules: Any,
) -> tuple[Iterator[tuple[float, int, bytes, bool]], LogStats]:
    """The classic CAN data frames of the log at ``path`` as (timestamp, id, data, extended), in file order
    through the time rule, and the ``LogStats`` that fill while the iterator runs.

    ``fmt``: one of ``FORMATS`` (default: ``detect_format``). ``bus``: which bus of a log of several is read
    (``BusChoice``; None: all, as one, counted in the reader's ``other_channel_frames``). ``rules``: the time
    rule's ``max_jump``,
    ``reorder_tolerance``, ``confirm``. Raises ``CandumpFileError``/``LogFormatError`` (one line each) for a
    file that cannot be read at all; never raises on a bad record (counted in the stats) except when the
    iterator meets a header it cannot read at all (``LogFormatError``).
    """
    reader, stats = _open_reader(Path(path), fmt, max_warnings, max_bytes, bus, rules)
    return _frames(reader, stats), stats


def _frames(reader: TimeRule, stats: LogStats) -> Iterator[tuple[float, int, bytes, bool]]:
    try:
        for f in reader:
            if f.is_remote:
                stats.skip("remote")
                continue
            if stats.channel is None:
                stats.channel = f.channel
            stats.line = f.line_no
            yield f.timestamp, f.frame_id, f.data, f.is_extended
    finally:
        reader.close()


def open_log_arrays(
    path: str | Path,
    *,
    fmt: str | None = None,
    max_warnings: int | None = None,
    max_bytes: int = MAX_LOG_BYTES,
    size: int = ARRAY_BLOCK_FRAMES,
    bus: BusChoice | None = None,
    **rules: Any,
) -> tuple[Iterator[FrameArrays], LogStats]:
    """``open_log`` as blocks of columns (``FrameArrays``: the same frames in the same order, with the
    discontinuities of the time stamps that start in each block): a candump log parsed a block of lines at a
    time (``CandumpReader.arrays``), any other format's frames gathered ``size`` at a time."""
    reader, stats = _open_reader(Path(path), fmt, max_warnings, max_bytes, bus, rules)
    if stats.format == "candump":
        return _candump_arrays(reader, stats), stats  # type: ignore[arg-type]
    return _gathered(_frames(reader, stats), stats, size), stats


def _open_reader(
    path: Path, fmt: str | None, max_warnings: int | None, max_bytes: int, bus: BusChoice | None, rules: dict[str, Any]
) -> tuple[TimeRule, LogStats]:
    """The reader of the log's format (``detect_format`` when not given), reading ``bus``, and its stats."""
    if fmt is None:
        fmt, size = detect_format(path, max_bytes, warn=True)
    else:
        size = path.stat().st_size if path.is_file() else 0
    if fmt == "candump":
        reader: TimeRule = CandumpReader(path, max_warnings=max_warnings, max_bytes=max_bytes, **rules)
    else:
        reader = _READERS[fmt](path, max_bytes, max_warnings=max_warnings, **rules)
    reader.bus = bus
    stats = LogStats(path, fmt, size, reader)
    if fmt != "candump":
        stats.skipped = reader.skipped  # type: ignore[attr-defined]
    return reader, stats


def _candump_arrays(reader: CandumpReader, stats: LogStats) -> Iterator[FrameArrays]:
    try:
        for block in reader.arrays():
            if stats.channel is None:
                stats.channel = block.channel
            if reader.remote:
                stats.skipped["remote"] = reader.remote
            yield block
        if reader.remote:
            stats.skipped["remote"] = reader.remote
    finally:
        reader.close()


def _gathered(frames: Iterator[tuple[float, int, bytes, bool]], stats: LogStats, size: int) -> Iterator[FrameArrays]:
    reader = stats.reader
    seen = 0
    try:
        while True:
            batch: list[LogFrame] = []
            jumps: list[Jump] = []
            for timestamp, frame_id, data, extended in frames:
                if reader.discontinuities != seen:  # this frame starts a time base the rule took
                    seen = reader.discontinuities
                    if len(reader.discontinuity_lines) >= seen:
                        jumps.append(Jump(len(batch), *reader.discontinuity_lines[seen - 1]))
                batch.append(LogFrame(timestamp, stats.channel or "", frame_id, bytes(data), 0, extended))
                if len(batch) == size:
                    break
            if not batch:
                return
            yield FrameArrays.of(batch, jumps)
            if len(batch) < size:
                return
    finally:
        frames.close()


# ---------------------------------------------------------------------- writers


class _PycanWriter:
    """A python-can writer behind the candump writer's ``write(timestamp, id, data)``."""

    def __init__(self, path: Path, fmt: str, stream: IO[str] | None = None) -> None:
        import can

        self.name = str(path)
        self.format = fmt
        self._message = can.Message
        self.lines_written = 0
        if fmt == "mf4":
            if _deferred_imports.mf4().asammdf is None:
                raise LogFormatError(
                    f"{path}: writing MF4 needs the 'mf4' extra (asammdf is not installed): pip install 'ptw-rt[mf4]'"
                ) from None
            self._writer = _Mf4BulkWriter(path)
        else:
            from can.io.asc import ASCWriter
            from can.io.blf import BLFWriter
            from can.io.csv import CSVWriter
            from can.io.trc import TRCWriter

            cls = {"asc": ASCWriter, "blf": BLFWriter, "trc": TRCWriter, "csv": CSVWriter}[fmt]
            self._writer = cls(path if stream is None else stream)
        self._on_message = self._writer.on_message_received

    def write(self, timestamp: float, frame_id: int, data: bytes, *, extended: bool | None = None, **_: Any) -> None:
        self._on_message(
            self._message(
                timestamp=timestamp,
                arbitration_id=frame_id,
                is_extended_id=frame_id > _STD_MAX if extended is None else extended,
                data=data,
                dlc=len(data),
                channel=0,
                is_rx=False,
                check=False,
            )
        )
        self.lines_written += 1

    def write_cycle(self, timestamp: float, frames: Sequence[tuple[int, bytes]]) -> None:
        """All frames of one cycle (``CandumpWriter.write_cycle``'s interface)."""
        for frame_id, data in frames:
            self.write(timestamp, frame_id, data)

    def flush(self) -> None:
        pass

    def close(self) -> None:
        if self._writer is not None:
            writer, self._writer = self._writer, None
            writer.stop()

    def __enter__(self) -> _PycanWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def _Mf4BulkWriter(path: Path) -> Any:  # noqa: N802 - a class made on first use (asammdf is optional)
    """python-can's ``MF4Writer`` with the data frames appended in blocks of 4096, not one asammdf call per frame
    (~0.4 ms each: 12 s for a 120 s ride's estimates); the file is the one ``MF4Writer`` writes."""
    import numpy as np

    mf4 = _deferred_imports.mf4()
    STD_DTYPE, MF4Writer = mf4.STD_DTYPE, mf4.MF4Writer  # noqa: N806

    class Writer(MF4Writer):
        BLOCK = 4096

        def __init__(self, file: Any) -> None:
            super().__init__(file)
            self._rows = np.zeros(self.BLOCK, dtype=STD_DTYPE)
            self._stamps = np.zeros(self.BLOCK)
            self._n = 0

        def on_message_received(self, msg: Any) -> None:
            if msg.is_remote_frame or msg.is_error_frame or msg.is_fd:
                self._flush_rows()
                super().on_message_received(msg)
                return
            stamp = msg.timestamp
            self.last_timestamp = max(self.last_timestamp, stamp)
            row = self._rows[self._n]
            row["CAN_DataFrame.BusChannel"] = msg.channel or 0
            row["CAN_DataFrame.ID"] = msg.arbitration_id
            row["CAN_DataFrame.IDE"] = int(msg.is_extended_id)
            row["CAN_DataFrame.Dir"] = 0 if msg.is_rx else 1
            size = len(msg.data)
            row["CAN_DataFrame.DataLength"] = size
            row["CAN_DataFrame.DLC"] = msg.dlc
            row["CAN_DataFrame.DataBytes"][:size] = np.frombuffer(bytes(msg.data), dtype=np.uint8)
            row["CAN_DataFrame.DataBytes"][size:] = 0
            self._stamps[self._n] = stamp - self._start_time
            self._n += 1
            if self._n == self.BLOCK:
                self._flush_rows()

        def _flush_rows(self) -> None:
            if self._n:
                self._mdf.extend(0, [(self._stamps[: self._n].copy(), None), (self._rows[: self._n].copy(), None)])
                self._n = 0

        def stop(self) -> None:
            self._flush_rows()
            super().stop()

    return Writer(path)


def writer_format(path: str | Path) -> str:
    """The format an output log's extension names (none: candump); ``LogFormatError`` for an unknown one."""
    path = Path(path)
    if not path.suffix:
        return "candump"
    if path.name.lower().endswith(GZIP_SUFFIX):
        inner = format_of_extension(path)
        if inner is not None and inner not in GZIP_WRITABLE and inner not in READ_ONLY:
            raise LogFormatError(
                f"{path}: {FORMATS[inner]} is not written compressed (only candump, ASC, TRC and CSV are): name it "
                f"without {GZIP_SUFFIX}"
            )
    if format_of_extension(path) in READ_ONLY:
        raise LogFormatError(f"{path}: text logs are read, not written: name the output .log (candump -L)")
    fmt = format_of_extension(path)
    if fmt is None:
        known = ", ".join(f"{ext} ({FORMATS[f]})" for ext, f in EXTENSIONS.items())
        raise LogFormatError(f"{path}: unknown log format {path.suffix!r} for an output (known: {known})")
    return fmt


def open_writer(path: str | Path, channel: str = "vcan0") -> Any:
    """A writer for the format ``path``'s extension names (no extension: candump), with ``write(timestamp, id,
    data)``, ``close()`` and the context manager protocol. candump is ``CandumpWriter`` (its output is
    byte-identical to what ``ptw-rt replay`` always wrote); the others are python-can's writers (channel 0 of
    their numbering). Raises ``LogFormatError`` for an unknown extension or a missing ``mf4`` extra."""
    path = Path(path)
    fmt = writer_format(path)
    if path.name.lower().endswith(GZIP_SUFFIX):  # a text format (writer_format), written through gzip
        stream = compressed.text_writer(path)
        if fmt == "candump":
            return CandumpWriter(stream, channel=channel)
        return _PycanWriter(path, fmt, stream)
    if fmt == "candump":
        return CandumpWriter(path, channel=channel)
    if fmt == "db":
        return sqlite_log.SqliteLogWriter(path)  # an OSError like every writer's (replay: exit 74)
    return _PycanWriter(path, fmt)
