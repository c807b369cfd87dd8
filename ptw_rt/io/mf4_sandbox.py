"""An MF4 file read in a child process under limits: asammdf parses untrusted files in native code and whole.

python-can's ``MF4Reader`` hands the file to asammdf, which reads and decodes all of it in its constructor, before
any bound of ours can look. Crafted files of a few kB (fuzzing, 2026-11-26) made it loop forever (a channel group
declaring 0 records), abort the interpreter (a record size of 1: ``malloc(): invalid size``, SIGABRT) or grow past
4 GB (a record size of 2^32 - 1). So the file is read by ``python -m ptw_rt.io.mf4_sandbox PATH SIZE CPU_S``, which sets
its own address-space and CPU-time limits before importing asammdf and streams the messages back on stdout; the
parent bounds the wall-clock time. Whatever ends the child early is the file's, said in one line.

The stream, little-endian, one item after another:
  ``T`` + u64: the records the file declares (after the sanity check of the counts)
  ``F`` + f64 time stamp, u32 id, u8 flags (``FLAG_*``), u8 channel length, u8 data length, channel, data
  ``P`` + u32 record, u16 length, text: a read error after that many records (the rest of the file is lost)
  ``E`` + u16 length, text: the file refused (nothing read)
"""

from __future__ import annotations

import logging
import os
import resource
import struct
import subprocess
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from typing import IO, Any

from ptw_rt.untrusted import short_text

MAX_MF4_EXPANSION = 64  # the records a file declares, in bytes, at most this many times its size (as BLF's)
# the child's address space: Python, numpy, pandas and asammdf read a small file within 768 MiB; asammdf holds a
# group's records unpacked (a deflate bomb of 8.5 MB grew to 2.5 GB before its record count could be checked)
MEMORY_BASE_BYTES, MEMORY_PER_FILE_BYTE = 1 << 30, 8


def memory_limit_bytes(size: int) -> int:
    return MEMORY_BASE_BYTES + MEMORY_PER_FILE_BYTE * size


CPU_S_BASE, CPU_S_PER_MB = 15, 2  # the child's CPU time: 15 s plus 2 s per MB of file (asammdf: ~50 MB/s)
WALL_S_EXTRA = 30  # the parent waits the CPU limit plus this before killing the child

FLAG_EXTENDED, FLAG_REMOTE, FLAG_ERROR, FLAG_FD = 1, 2, 4, 8
_FRAME = struct.Struct("<dIBBB")
_COUNT = struct.Struct("<Q")
_RECORD = struct.Struct("<I")
_TEXT = struct.Struct("<H")
MAX_TEXT = 400


@dataclass(frozen=True)
class Message:
    """What the parent's reader needs of a python-can ``Message``."""

    timestamp: float
    arbitration_id: int
    is_extended_id: bool
    is_remote_frame: bool
    is_error_frame: bool
    is_fd: bool
    channel: str
    data: bytes


def cpu_limit_s(size: int) -> int:
    return CPU_S_BASE + CPU_S_PER_MB * (size >> 20)


# ---------------------------------------------------------------------- child


def _text(kind: bytes, text: str, out: IO[bytes], head: bytes = b"") -> None:
    raw = text.encode("utf-8", "replace")[:MAX_TEXT]
    out.write(kind + head + _TEXT.pack(len(raw)) + raw)


class _CorruptError(Exception):
    pass


def _check_counts(reader: Any, size: int) -> int:
    total = 0
    for i, group in enumerate(reader._mdf.groups):  # noqa: SLF001 - the declared sizes, before any read
        cg = group.channel_group
        records = int(cg.cycles_nr)
        width = max(1, int(getattr(cg, "samples_byte_nr", 1)) + int(getattr(cg, "invalidation_bytes_nr", 0)))
        if records < 0 or records * width > MAX_MF4_EXPANSION * max(size, 1):
            raise _CorruptError(
                f"corrupt MF4 file (channel group {i} declares {records} records of {width} bytes in {size} bytes)"
            )
        total += records
    return total


def _short(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {str(exc)[:200]}"


def child(path: str, size: int, cpu: int, out: IO[bytes]) -> int:
    """Read ``path`` and stream it to ``out`` (see the module docstring), within ``cpu`` s of CPU time."""
    memory = memory_limit_bytes(size)
    resource.setrlimit(resource.RLIMIT_AS, (memory, memory))
    resource.setrlimit(resource.RLIMIT_CPU, (cpu, cpu + 5))
    logging.getLogger("asammdf").setLevel(logging.CRITICAL)  # every oddity of a foreign file: counted instead
    from ptw_rt import _deferred_imports

    mf4 = _deferred_imports.mf4()
    if mf4.asammdf is None:
        _text(b"E", "reading MF4 needs the 'mf4' extra (asammdf is not installed): pip install 'ptw-rt[mf4]'", out)
        return 0
    try:
        reader = mf4.MF4Reader(path)
        total = _check_counts(reader, size)
    except _CorruptError as exc:
        _text(b"E", str(exc), out)
        return 0
    except Exception as exc:  # noqa: BLE001 - asammdf on untrusted content: any error is the file's
        _text(b"E", f"unreadable MF4 file ({_short(exc)})", out)
        return 0
    out.write(b"T" + _COUNT.pack(total))
    n = 0
    messages = iter(reader)
    while True:
        try:
            msg = next(messages)
        except StopIteration:
            break
        except Exception as exc:  # noqa: BLE001 - as above: the rest of the file is lost, said once
            _text(b"P", f"MF4 read error after {n} records: {_short(exc)}", out, _RECORD.pack(n + 1))
            break
        n += 1
        flags = (
            FLAG_EXTENDED * bool(msg.is_extended_id)
            | FLAG_REMOTE * bool(msg.is_remote_frame)
            | FLAG_ERROR * bool(msg.is_error_frame)
            | FLAG_FD * bool(msg.is_fd)
        )
        data = bytes(msg.data)[:64]
        channel = ("" if msg.channel is None else str(msg.channel)).encode("utf-8", "replace")[:64]
        try:
            ts = float(msg.timestamp)
        except (TypeError, ValueError, OverflowError):
            ts = float("nan")  # the parent's time rule says "bad time stamp"
        out.write(b"F" + _FRAME.pack(ts, int(msg.arbitration_id) & 0xFFFFFFFF, flags, len(channel), len(data)))
        out.write(channel + data)
    return 0


# ---------------------------------------------------------------------- parent


class SandboxError(Exception):
    """The file is refused, or the child reading it ended early; the message is one line about the file."""


def _read_exact(stream: IO[bytes], n: int) -> bytes:
    data = stream.read(n)
    if len(data) != n:
        raise EOFError
    return data


def read_messages(path: str, size: int, on_total: Any = None) -> Iterator[Message | tuple[int, str]]:
    """The messages of the MF4 file ``path`` (``size`` bytes, a checked regular file), read by a child process;
    ``(record, text)`` for a read error after some records; SandboxError when nothing can be read. ``on_total``
    is called with the number of records the file declares."""
    cpu = cpu_limit_s(size)
    proc = subprocess.Popen(  # noqa: S603 - our own module, run by our own interpreter
        [sys.executable, "-m", "ptw_rt.io.mf4_sandbox", path, str(size), str(cpu)],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        close_fds=True,
    )
    killed = threading.Event()

    def kill() -> None:
        killed.set()
        proc.kill()

    wall = cpu + WALL_S_EXTRA
    timer = threading.Timer(wall, kill)
    timer.daemon = True
    timer.start()
    n = 0
    stream = proc.stdout
    try:
        while True:
            kind = stream.read(1)
            if not kind:
                break
            try:
                if kind == b"F":
                    ts, frame_id, flags, chan_len, data_len = _FRAME.unpack(_read_exact(stream, _FRAME.size))
                    channel = _read_exact(stream, chan_len).decode("utf-8", "replace")
                    data = _read_exact(stream, data_len)
                    n += 1
                    yield Message(
                        ts,
                        frame_id,
                        bool(flags & FLAG_EXTENDED),
                        bool(flags & FLAG_REMOTE),
                        bool(flags & FLAG_ERROR),
                        bool(flags & FLAG_FD),
                        channel,
                        data,
                    )
                elif kind == b"T":
                    (total,) = _COUNT.unpack(_read_exact(stream, _COUNT.size))
                    if on_total is not None:
                        on_total(total)
                elif kind in (b"P", b"E"):
                    record = _RECORD.unpack(_read_exact(stream, _RECORD.size))[0] if kind == b"P" else 0
                    (length,) = _TEXT.unpack(_read_exact(stream, _TEXT.size))
                    # one line, ASCII, whatever asammdf's message held (a newline in it would split the refusal)
                    text = short_text(_read_exact(stream, min(length, MAX_TEXT)).decode("utf-8", "replace"), MAX_TEXT)
                    if kind == b"E":
                        raise SandboxError(text)
                    yield (record, text)
                    return
                else:
                    raise EOFError
            except EOFError:
                break
        code = proc.wait()
        if code != 0 or killed.is_set():
            if killed.is_set():
                why = f"its reader did not finish within {wall} s"
            elif code < 0:
                why = f"its reader was ended by signal {-code} (a crash, or the {cpu} s CPU limit)"
            else:
                why = f"its reader failed (exit {code}; out of memory within {memory_limit_bytes(size) >> 20} MiB?)"
            if n == 0:
                raise SandboxError(f"unreadable MF4 file ({why})")
            yield (n + 1, f"MF4 read error after {n} records: {why}")
    finally:
        timer.cancel()
        if proc.poll() is None:
            proc.kill()
        proc.wait()
        stream.close()


if __name__ == "__main__":  # the child
    _path, _size, _cpu = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    # the stream gets a descriptor of its own, and fd 1 goes to /dev/null: a print of asammdf's (or of its native
    # code) on stdout would otherwise be read as items
    _out = os.fdopen(os.dup(1), "wb", buffering=1 << 16)
    os.dup2(os.open(os.devnull, os.O_WRONLY), 1)
    sys.stdout = open(os.devnull, "w")  # noqa: SIM115 - for the life of the child
    try:
        sys.exit(child(_path, _size, _cpu, _out))
    finally:
        _out.flush()
