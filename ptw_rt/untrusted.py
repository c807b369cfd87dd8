"""Reading files the product does not control: bounded, typed, never blocking, never a traceback.

Every file ptw-rt reads (configuration YAML, design ``.npz``, state JSON, candump logs) may be hostile or simply
wrong: a FIFO (opening it for reading would block until a writer appears), a device (``/dev/zero`` never ends),
a directory, a 10 GB file, bytes that are not UTF-8, nesting deep enough to exhaust Python's recursion limit.
The readers share these helpers so each case gets the same answer: one line naming the file and the problem,
raised as the reader's own error class (``error=``), which the CLI prints with exit code 2.

* ``open_regular``: ``os.open(O_RDONLY | O_NONBLOCK)`` (a FIFO opens at once instead of blocking), then
  ``fstat`` on the open descriptor (no check-then-open race): anything but a regular file is refused, so is one
  above the size limit.
* ``read_bounded``: the whole file, at most ``max_bytes`` (a file growing while read is cut and refused).
* ``decode_utf8``: strict UTF-8 with the line and column of the first bad byte.
* ``check_nesting``: the bracket depth of JSON-like text, before a recursive parser sees it.
* ``excerpt``: a short, escaped, single-line rendering of a bad value for an error message.
"""

from __future__ import annotations

import contextlib
import errno
import os
import reprlib
import stat
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

__all__ = [
    "UntrustedFileError",
    "check_nesting",
    "decode_utf8",
    "excerpt",
    "file_kind",
    "one_line",
    "open_regular",
    "read_bounded",
    "same_file",
    "short_text",
]

EXCERPT_CHARS = 60


class UntrustedFileError(ValueError):
    """Default error of these helpers when the caller names none (a ``ValueError``: bad input, not a bug)."""


def file_kind(mode: int) -> str:
    """Human name of a file type from ``st_mode``."""
    for test, name in (
        (stat.S_ISDIR, "a directory"),
        (stat.S_ISFIFO, "a FIFO (named pipe)"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISSOCK, "a socket"),
        (stat.S_ISREG, "a regular file"),
    ):
        if test(mode):
            return name
    return "not a regular file"


def check_replaceable(path: str | Path) -> None:
    """An output written by renaming a new file over ``path`` must find a regular file, a symlink (the link is
    replaced, never what it points to) or nothing there: a rename replaces a device, a FIFO or an empty directory
    with a file (as root, ``design --out /dev/full`` turned the device into a regular file). Else ``OSError``."""
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return
    if not (stat.S_ISREG(mode) or stat.S_ISLNK(mode)):
        raise OSError(errno.EEXIST, f"exists and is {file_kind(mode)}, not a file to replace", str(path))


def check_output_file(path: str | Path) -> None:
    """An output opened for writing in place (not renamed over) must not be a FIFO nobody reads, which the open
    waits on for ever (`simulate`, `report` and `demo` hung on one), or a directory; ``OSError`` (one line)
    otherwise. A pipe someone reads (``/dev/stdout | ...``) and a device such as ``/dev/null`` are written."""
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):
        return  # nothing there (or a path the open itself will refuse, in one line)
    if stat.S_ISDIR(mode):
        raise OSError(errno.EISDIR, "is a directory", str(path))
    if stat.S_ISFIFO(mode) and not fifo_has_reader(path):
        raise OSError(errno.ENXIO, "is a FIFO (named pipe) with no reader; write to a file", str(path))


def fifo_has_reader(fifo: str | Path) -> bool:
    """Whether a FIFO has a reader: the open of one someone reads succeeds at once, of one nobody reads it would
    block (ENXIO without blocking)."""
    try:
        fd = os.open(fifo, os.O_WRONLY | os.O_NONBLOCK)
    except OSError:
        return False
    os.close(fd)
    return True


@contextlib.contextmanager
def replacing(path: str | Path, mode: str = "wb", **open_kw: Any) -> Iterator[IO[Any]]:
    """A new file to write, renamed over ``path`` when the block ends (``check_replaceable``: a regular file, a
    symlink or nothing there), removed if it raises. The temporary file is a new one of a unique name
    (``tempfile.mkstemp``, O_EXCL): a fixed ``NAME.tmp`` followed a symlink planted there (`design` wrote its zip
    into the link's target) and waited for ever on a FIFO."""
    path = Path(path)
    check_replaceable(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, mode, **open_kw) as fh:
            yield fh
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def same_file(a: str | Path, b: str | Path) -> bool:
    """Whether two paths name one file: the same path once symlinks are followed, or the same device and inode (a
    hard link, a bind mount: writing one would truncate the other while it is read). Never raises: a path that
    cannot be resolved (a symlink loop, a component that is not a directory) is compared as written, made
    absolute (``Path.resolve`` raised RuntimeError on a loop, a traceback in every command that compared paths)."""
    try:
        if os.path.samefile(a, b):
            return True
    except (OSError, ValueError):  # one does not exist (an output not yet written), a loop, a NUL in the name
        pass
    try:
        return os.path.realpath(a) == os.path.realpath(b)
    except (OSError, ValueError):
        return os.path.abspath(a) == os.path.abspath(b)


def _size(n: int) -> str:
    for unit, scale in (("GiB", 1 << 30), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if n >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{n} bytes"


def open_regular(
    path: str | Path, *, max_bytes: int, what: str = "file", error: type[Exception] = UntrustedFileError
) -> tuple[int, os.stat_result]:
    """Open ``path`` for reading without ever blocking; refuse non-regular files and files above ``max_bytes``.

    Returns ``(fd, stat)``; the caller owns ``fd`` (``os.fdopen(fd, "rb")`` or ``os.close``). Raises ``error``
    with a one-line message ``"<path>: <what> ..."`` for a missing, unreadable, non-regular or too large file.
    """
    flags = os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_NOCTTY", 0)
    try:
        fd = os.open(path, flags)
    except FileNotFoundError:
        raise error(f"{path}: {what} not found") from None
    except OSError as exc:
        raise error(f"{path}: cannot open {what} ({exc.strerror or exc})") from None
    except ValueError:  # a NUL in the name: no system call takes one
        raise error(f"{path!r}: cannot open {what} (a NUL character in its name)") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise error(f"{path}: {what} is {file_kind(st.st_mode)}, not a regular file")
        if st.st_size > max_bytes:
            raise error(f"{path}: {what} too large ({_size(st.st_size)}; the limit is {_size(max_bytes)})")
        os.set_blocking(fd, True)  # a regular file: reads never block anyway, and buffered I/O expects this
    except BaseException:
        os.close(fd)
        raise
    return fd, st


def read_bounded(
    path: str | Path, *, max_bytes: int, what: str = "file", error: type[Exception] = UntrustedFileError
) -> bytes:
    """The content of the regular file ``path``, at most ``max_bytes`` (else ``error``; see ``open_regular``)."""
    fd, _ = open_regular(path, max_bytes=max_bytes, what=what, error=error)
    try:
        with os.fdopen(fd, "rb") as fh:
            raw = fh.read(max_bytes + 1)
    except OSError as exc:
        raise error(f"{path}: cannot read {what} ({exc.strerror or exc})") from None
    if len(raw) > max_bytes:  # grew after fstat
        raise error(f"{path}: {what} too large (more than {_size(max_bytes)})")
    return raw


def open_binary(
    path: str | Path, *, max_bytes: int, what: str = "file", error: type[Exception] = UntrustedFileError
) -> IO[bytes]:
    """``open_regular`` as a buffered binary file object (for streaming readers)."""
    fd, _ = open_regular(path, max_bytes=max_bytes, what=what, error=error)
    return os.fdopen(fd, "rb")


def decode_utf8(
    raw: bytes, path: str | Path, *, what: str = "file", error: type[Exception] = UntrustedFileError
) -> str:
    """Strict UTF-8 decoding; the error names the line, column and value of the first bad byte."""
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        column = exc.start - (raw.rfind(b"\n", 0, exc.start) + 1) + 1
        raise error(
            f"{path}: {what} is not UTF-8 text (byte 0x{raw[exc.start]:02x} at line {line}, column {column})"
        ) from None


def check_nesting(
    text: str,
    max_depth: int,
    path: str | Path,
    *,
    what: str = "file",
    error: type[Exception] = UntrustedFileError,
    quoted: bool = True,
) -> int:
    """Raise ``error`` if ``[``/``{`` nest deeper than ``max_depth`` in ``text``; returns the depth found.

    With ``quoted=True`` (JSON) brackets inside double-quoted strings are ignored. Linear time, no recursion.
    """
    depth = deepest = 0
    in_string = escaped = False
    if not quoted and "[" not in text and "{" not in text:
        return 0
    for ch in text:
        if in_string:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == '"':
                in_string = False
            continue
        if ch == "[" or ch == "{":
            depth += 1
            if depth > deepest:
                deepest = depth
                if deepest > max_depth:
                    raise error(f"{path}: {what} nests deeper than {max_depth} levels")
        elif ch == "]" or ch == "}":
            depth -= 1
        elif ch == '"' and quoted:
            in_string = True
    return deepest


_REPR = reprlib.Repr()
_REPR.maxlevel = 2
_REPR.maxstring = EXCERPT_CHARS
_REPR.maxother = EXCERPT_CHARS
_REPR.maxlong = 24
for _name in ("maxlist", "maxtuple", "maxdict", "maxset", "maxfrozenset", "maxdeque", "maxarray"):
    setattr(_REPR, _name, 4)


def excerpt(value: Any, limit: int = EXCERPT_CHARS) -> str:
    """A short, escaped, one-line ``repr`` of ``value`` (bounded work for any size or depth), for messages."""
    try:
        text = _REPR.repr(value)
    except Exception:  # a hostile __repr__ or an int too long to convert: say what it is, not what it holds
        text = f"<{type(value).__name__}>"
    text = text.encode("ascii", "backslashreplace").decode("ascii")
    text = text.replace("\n", "\\n").replace("\r", "\\r")
    return text if len(text) <= limit else text[: limit - 3] + "..."


# the ASCII control characters ``str.split`` leaves in place (ESC, BEL, NUL ...) as escapes: an ESC sequence in a
# message is a terminal command to whoever reads the log
_CONTROL_ESCAPES = {c: f"\\x{c:02x}" for c in (*range(32), 127)}


def error_text(exc: object, limit: int = 80) -> str:
    """An exception's message (its type's name when it has none) as a message fragment (``short_text``: a
    parser's error quotes the untrusted bytes it choked on)."""
    return short_text(str(exc) or type(exc).__name__, limit)


def file_size(fh: IO[bytes]) -> int:
    """The size of an open file, 0 when it has none (a pipe, a closed file)."""
    try:
        return os.fstat(fh.fileno()).st_size
    except (OSError, ValueError):
        return 0


def one_line(text: str, limit: int = 2000) -> str:
    """A message as one line, its own spaces kept: control characters (a newline in a file's name forged a line
    of its own, an ESC sequence is a terminal command) and non-ASCII escaped, at most ``limit`` chars."""
    text = str(text).encode("ascii", "backslashreplace").decode("ascii").translate(_CONTROL_ESCAPES)
    return text if len(text) <= limit else text[: limit - 3] + "..."


# ``_CONTROL_ESCAPES`` and the C1 controls (U+0080-U+009F, a terminal's CSI among them), CR and LF as ``\r``, ``\n``
_LINE_ESCAPES = {**_CONTROL_ESCAPES, **{c: f"\\x{c:02x}" for c in range(0x80, 0xA0)}, 10: "\\n", 13: "\\r"}


def log_line(text: str) -> str:
    """A log record as one line for the journal: control characters escaped (C0, DEL, C1: one in a message made
    journalctl show the line as a blob, an ESC sequence is a terminal command), other text kept (the daemon's
    messages say deg and us in UTF-8)."""
    return text.translate(_LINE_ESCAPES)


def short_text(text: str, limit: int = 120) -> str:
    """A message fragment (e.g. a parser's problem text) on one line, ASCII-escaped (control characters too), at
    most ``limit`` chars."""
    return one_line(" ".join(str(text).split()), limit)
