"""Gzip-compressed CAN logs (``ride.log.gz``, ``ride.asc.gz``, ``ride.blf.gz`` ...), read as a stream, within bounds.

python-can reads its text and binary log formats gzip-compressed (``LogReader`` on ``*.EXT.gz``), and loggers
rotate and compress their files: a fleet's logs are often ``.gz``. A compressed log is untrusted twice over: a
few kB can decompress to gigabytes (a "gzip bomb"), and a logger killed mid-write leaves a stream without its end.
So ``open_log_file``, which every reader of ``ptw_rt.io.candump`` and ``ptw_rt.io.logformats`` opens its file
with, gives:

* a file that does not start with gzip's magic bytes: the file itself (``untrusted.open_binary``);
* one that does, whatever its name: ``GzipLog``, its decompressed stream. The bytes it gives are bounded by the
  log's own ``max_bytes`` and by ``MAX_EXPANSION`` times the compressed size (CAN logs compress 4-6 times: a
  candump log 4.1x, its ASC 6.2x with ``gzip -9``; the text readers pay per decompressed byte, so the bound is
  also what a crafted file can cost); beyond, the reader's own file error (one line: the log is refused);
* a stream that ends early or is corrupt (truncated, a bad CRC, garbage after a member) ends where its good data
  ends, with one warning naming the byte (``GzipLog.problem``), as a truncated BLF or candump log does.

Decompression is Python's ``gzip`` (zlib): each ``read(n)`` inflates at most ``n`` bytes, so memory stays bounded
by the reader's chunk and the ``SEEK_BACK_BYTES`` kept for a seek back, whatever the file declares.
"""

from __future__ import annotations

import gzip
import io
import logging
import os
import zlib
from pathlib import Path
from typing import IO

from ptw_rt.untrusted import error_text, file_size, open_binary

log = logging.getLogger(__name__)

GZIP_MAGIC = b"\x1f\x8b"
MAX_EXPANSION = 16  # decompressed bytes per compressed byte, at most (CAN logs: 4-6; readers pay per byte)
EXPANSION_SLACK = 1 << 20  # bytes: a tiny file's header and dictionary are not a bomb
SEEK_BACK_BYTES = 2 << 20  # bytes kept for a seek back (the BLF reader's: at most its 1 MiB read chunk)


class GzipLog:
    """The decompressed stream of a gzip file, bounded (module docstring). File-like for the log readers:
    ``read``, ``tell`` and ``seek`` (in decompressed bytes), ``close``/``closed``, ``fileno`` (the compressed
    file's), ``compressed_position`` (bytes of the file consumed: the progress).

    A seek back goes to the last ``SEEK_BACK_BYTES`` inflated, kept in memory: the BLF reader steps back within
    one read chunk when it resynchronises on garbage, and a stream re-inflated from its start at every such step
    would be quadratic (a crafted ``.blf.gz`` with garbage every kilobyte). Further back is refused (OSError)."""

    def __init__(self, raw: IO[bytes], name: str, max_bytes: int, error: type[Exception]) -> None:
        self._raw = raw
        self.name = name
        self._error = error
        self.compressed_size = file_size(raw)
        self.limit = min(max_bytes, MAX_EXPANSION * self.compressed_size + EXPANSION_SLACK)
        self._gz = gzip.GzipFile(fileobj=raw, mode="rb")
        self._pos = 0  # the reader's position in the data
        self._inflated = 0  # bytes inflated so far: the data's end as known
        self._window = bytearray()  # the last SEEK_BACK_BYTES inflated: data[_inflated - len(_window):_inflated]
        self.problem: str | None = None  # why the stream ended before its end, once it did

    @property
    def closed(self) -> bool:
        return self._raw.closed

    def fileno(self) -> int:
        return self._raw.fileno()

    def tell(self) -> int:
        return self._pos

    @property
    def compressed_position(self) -> int:
        try:
            return self._raw.tell()
        except (OSError, ValueError):
            return 0

    def read(self, n: int = -1) -> bytes:
        want = self.limit + 1 - self._pos if n is None or n < 0 else n
        out = b""
        behind = self._inflated - self._pos  # bytes a seek back left to give again, from the window
        if behind > 0:
            start = len(self._window) - behind
            out = bytes(self._window[start : start + want])
            self._pos += len(out)
            want -= len(out)
        if want > 0:  # a short read is the end of the data to every reader: the rest is inflated now
            data = self._inflate(want)
            self._pos += len(data)
            out += data
        return out

    def _inflate(self, want: int) -> bytes:
        if self.problem is not None:
            return b""
        want = min(want, self.limit + 1 - self._inflated)
        # read1 inflates one input block at a time: an error loses none of what the blocks before it gave
        # (GzipFile.read(n) drops what it had gathered for the call when the stream turns out truncated)
        parts: list[bytes] = []
        got = 0
        while got < want:
            try:
                part = self._gz.read1(want - got)
            except (EOFError, gzip.BadGzipFile, zlib.error, OSError) as exc:
                # a truncated or corrupt stream: what came before is good data; the rest is lost, said once
                self.problem = (
                    f"compressed stream ends early at byte {self._inflated + got} of its data ({error_text(exc)})"
                )
                log.warning("%s: %s: read up to there", self.name, self.problem)
                break
            if not part:
                break
            parts.append(part)
            got += len(part)
        data = b"".join(parts)
        self._inflated += len(data)
        if self._inflated > self.limit:
            raise self._error(
                f"{self.name}: decompresses beyond {self.limit} bytes ({MAX_EXPANSION} times its "
                f"{self.compressed_size} compressed bytes, or the log size bound): a gzip bomb, not a CAN log"
            )
        self._window += data
        if len(self._window) > SEEK_BACK_BYTES:
            del self._window[: len(self._window) - SEEK_BACK_BYTES]
        return data

    def seek(self, offset: int, whence: int = os.SEEK_SET) -> int:
        if whence != os.SEEK_SET or offset < 0:
            raise OSError("GzipLog seeks to absolute positions only")
        if offset < self._inflated - len(self._window):
            raise OSError(f"GzipLog seeks back at most {SEEK_BACK_BYTES} bytes")
        self._pos = min(offset, self._inflated)
        while self._pos < offset and self.read(min(offset - self._pos, 1 << 20)):
            pass
        return self._pos

    def close(self) -> None:
        try:
            self._gz.close()
        finally:
            self._raw.close()

    def __enter__(self) -> GzipLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_log_file(path: str | Path, *, max_bytes: int, what: str, error: type[Exception]) -> IO[bytes] | GzipLog:
    """``open_binary`` of a CAN log, or its bounded decompressed stream when it is gzip-compressed."""
    fh = open_binary(path, max_bytes=max_bytes, what=what, error=error)
    try:
        magic = fh.read(2)
        fh.seek(0)
    except OSError:
        fh.close()
        raise
    if magic != GZIP_MAGIC:
        return fh
    return GzipLog(fh, str(path), max_bytes, error)


def text_writer(path: str | Path) -> IO[str]:
    """A text stream written gzip-compressed to ``path`` (an output log named ``.gz``), reproducible: no time
    in its header. Errors are ``OSError``s, as a plain file's."""
    return io.TextIOWrapper(gzip.GzipFile(path, "wb", mtime=0), encoding="utf-8", newline="\n")


def is_compressed(fh: object) -> bool:
    return isinstance(fh, GzipLog)


def position(fh: IO[bytes] | GzipLog | None) -> int:
    """Bytes of the file read so far (the compressed file's, for a gzip log): a progress bar's numerator over
    the file's size. 0 for no file, a closed one, or one that cannot tell (a pipe): a progress bar, not an error."""
    if fh is None or fh.closed:
        return 0
    try:
        return fh.compressed_position if isinstance(fh, GzipLog) else fh.tell()
    except (OSError, ValueError):
        return 0
