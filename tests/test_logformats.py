"""Every log format python-can reads, in and out (issue #15, part 1): a simulated ride written with python-can's
own writers replays to the same estimates as its candump original; sniffing; not a log, empty, hostile files."""

from __future__ import annotations

import base64
import io
import json
import math
import os
import random
import re
import shutil
import struct
import subprocess
import sys
import time
import tracemalloc
import zlib
from pathlib import Path

import can
import pytest

from ptw_rt.apps.replay import replay_log
from ptw_rt.io.candump import CandumpWriter, read_log
from ptw_rt.io.logformats import (
    EmptyLogError,
    LogFormatError,
    NotACanLogError,
    detect_format,
    open_log,
    open_writer,
    sniff,
)
from ptw_rt.paths import DEFAULT_CONFIG

FORMATS = ("asc", "blf", "trc", "csv", "mf4")


@pytest.fixture(scope="module")
def ride(tmp_path_factory):
    """A 5 s ride as candump (the original) and in every other format, written by python-can's writers."""
    from ptw_rt.sim.recording import write_ride
    from ptw_rt.sim.ride import simulate

    d = tmp_path_factory.mktemp("formats")
    original = write_ride(simulate("dlc_100", duration=5.0), d)["log"]
    messages = list(can.LogReader(str(original)))
    logs = {"candump": original}
    for ext in FORMATS:
        path = d / f"ride.{ext}"
        with can.Logger(str(path)) as writer:
            for msg in messages:
                writer.on_message_received(msg)
        logs[ext] = path
    return logs


@pytest.fixture(scope="module")
def replays(ride, tmp_path_factory):
    """Every format replayed: (output log, estimates CSV)."""
    d = tmp_path_factory.mktemp("replays")
    out = {}
    for fmt, path in ride.items():
        out[fmt] = (d / f"{fmt}.out.log", d / f"{fmt}.out.csv")
        summary = replay_log(path, *out[fmt], DEFAULT_CONFIG)
        assert summary["format"] == fmt and summary["malformed_lines"] == 0
    return out


def _frames(path, **kw):
    it, stats = open_log(path, **kw)
    return list(it), stats


def _estimates(csv_path: Path) -> list[str]:
    """The estimates CSV without its time column."""
    return [line.split(",", 1)[1] for line in csv_path.read_text().splitlines()]


@pytest.mark.parametrize("fmt", FORMATS)
def test_every_format_reads_the_frames_of_the_original(ride, fmt):
    ref, _ = _frames(ride["candump"])
    got, stats = _frames(ride[fmt])
    assert stats.format == fmt and stats.malformed == 0 and not stats.skipped
    assert [f[1:] for f in got] == [f[1:] for f in ref]
    # ASC: python-can reads its time stamps relative to the start of the measurement
    offset = ref[0][0] - got[0][0] if fmt == "asc" else 0.0
    assert max(abs(a[0] - (b[0] + offset)) for a, b in zip(ref, got, strict=True)) < 1e-6
    if fmt in ("blf", "csv", "mf4", "trc"):  # the same doubles: replays are byte-identical (next test)
        assert [f[0] for f in got] == [f[0] for f in ref]


@pytest.mark.parametrize("fmt", ["candump", "asc", "trc", "csv"])
def test_a_byte_order_mark_is_not_part_of_the_first_line(ride, fmt, tmp_path):
    """Windows editors save a UTF-8 BOM: a TRC file with one lost its ";$FILEVERSION" header and every line with it,
    the others their first line (found by fuzzing, 2026-11-26)."""
    bom = tmp_path / ("bom.log" if fmt == "candump" else f"bom.{fmt}")
    bom.write_bytes(b"\xef\xbb\xbf" + ride[fmt].read_bytes())
    ref, _ = _frames(ride[fmt])
    got, stats = _frames(bom)
    assert stats.malformed == 0 and [f[1:] for f in got] == [f[1:] for f in ref]


@pytest.mark.parametrize("fmt", ["blf", "trc", "csv", "mf4"])
def test_replay_of_every_format_equals_the_candump_original(replays, fmt):
    (ref_log, ref_csv), (log, csv) = replays["candump"], replays[fmt]
    assert log.read_bytes() == ref_log.read_bytes()
    assert csv.read_bytes() == ref_csv.read_bytes()


def test_replay_of_asc_equals_the_candump_original_on_its_clock(ride, replays, tmp_path):
    """ASC stamps are relative (0 = start of measurement): the same log in candump with those stamps replays
    to the very same estimates (absolute and relative time bases round some frames on a cycle's boundary
    differently, so the absolute original is not the reference)."""
    frames, _ = _frames(ride["candump"])
    t0 = frames[0][0]
    relative = tmp_path / "relative.log"
    with CandumpWriter(relative, channel="vcan0") as w:
        for t, fid, data, _ in frames:
            w.write(round(t - t0, 6), fid, data)
    replay_log(relative, tmp_path / "r.log", tmp_path / "r.csv", DEFAULT_CONFIG)
    log, csv = replays["asc"]
    assert csv.read_bytes() == (tmp_path / "r.csv").read_bytes()
    assert log.read_bytes() == (tmp_path / "r.log").read_bytes()
    assert _estimates(csv)[1:3] != []


@pytest.mark.parametrize("fmt", FORMATS)
def test_format_found_from_the_content_without_extension(ride, fmt, tmp_path):
    bare = tmp_path / "ride"
    shutil.copy(ride[fmt], bare)
    assert detect_format(bare)[0] == fmt
    as_log = tmp_path / "ride.log"  # .log is what many tools write: the content decides
    shutil.copy(ride[fmt], as_log)
    assert detect_format(as_log)[0] == fmt
    assert len(_frames(as_log)[0]) == len(_frames(ride["candump"])[0])


def test_sniff_needs_a_frame_or_a_signature():
    assert sniff(b"(1700000000.000000) vcan0 100#00\n") == (["candump"], [])
    assert sniff(b"timestamp,arbitration_id,extended,remote,error,dlc,data\n") == ([], ["csv"])
    assert sniff(b"time,roll,steer\n0.01,0.1,0.2\n") == ([], [])
    assert sniff(b"LOGG" + bytes(140))[0] == ["blf"]
    assert sniff(b"hello world\n" * 100) == ([], [])


@pytest.mark.parametrize("out_ext", ["blf", "asc", "trc", "csv", "mf4"])
def test_out_writes_the_format_its_extension_names(ride, replays, out_ext, tmp_path):
    out = tmp_path / f"est.{out_ext}"
    replay_log(ride["candump"], out, None, DEFAULT_CONFIG)
    ref, _ = _frames(replays["candump"][0])
    by_pycan = list(can.LogReader(str(out)))
    got, stats = _frames(out)
    assert stats.format == out_ext
    assert len(by_pycan) == len(got) == len(ref)
    assert [(m.arbitration_id, bytes(m.data)) for m in by_pycan] == [(f[1], f[2]) for f in ref]
    assert [f[1:] for f in got] == [f[1:] for f in ref]
    # the cycle's time: candump prints it to the microsecond, BLF keeps nanoseconds, ASC starts at 0
    offset = ref[0][0] - got[0][0] if out_ext == "asc" else 0.0
    assert max(abs(a[0] - (b[0] + offset)) for a, b in zip(ref, got, strict=True)) < 1.5e-6


def test_out_candump_is_byte_identical_to_the_candump_writer(ride, replays, tmp_path):
    """--out x.log and --out x (no extension): the candump writer, as always."""
    replay_log(ride["candump"], tmp_path / "noext", None, DEFAULT_CONFIG)
    assert (tmp_path / "noext").read_bytes() == replays["candump"][0].read_bytes()
    with pytest.raises(LogFormatError, match="unknown log format '.xyz'"):
        open_writer(tmp_path / "x.xyz")


def test_asc_round_trip_through_out(ride, tmp_path):
    """ASC in, ASC out, ASC in again: the estimates of the second pass are the estimator's frames of the first."""
    first = tmp_path / "est.asc"
    replay_log(ride["asc"], first, None, DEFAULT_CONFIG)
    frames, stats = _frames(first)
    assert stats.format == "asc" and stats.malformed == 0 and len(frames) > 1000
    assert frames[0][0] == pytest.approx(0.0, abs=1e-9)  # an ASC's clock starts at its first frame


def test_bad_lines_in_text_formats_are_counted_and_skipped(ride, tmp_path):
    for fmt, bad in (
        # (an ASC line that does not look like a frame is an event python-can skips, as here: not counted)
        ("asc", ["  0.100000 1  10Z             Rx   d 2 00 GG", "  0.200000 1  FFFF  Rx   d 2 00 11"]),
        ("trc", ["      5       1.000 DT  1     01ZZ Rx -  2    00 11", "x" * 5000]),
        ("csv", ["1700003000.5,0x100,0,0,0,2,!!!", "1,2,3"]),
    ):
        lines = ride[fmt].read_text().splitlines()
        k = len(lines) // 2
        path = tmp_path / f"bad.{fmt}"
        path.write_text("\n".join(lines[:k] + bad + lines[k:]) + "\n")
        good, _ = _frames(ride[fmt])
        got, stats = _frames(path)
        assert len(got) == len(good), fmt
        assert stats.malformed == 2, (fmt, stats.rejected)
        line = stats.problems_line()
        assert line.startswith(f"{path}: 2 ") and "\x00" not in line and "\xff" not in line and len(line) < 600


def _spanning_containers(count: int) -> bytes:
    """An object declaring nearly 16 MiB, then `count` containers of 32 bytes: the unfinished object was joined with
    every container's data, quadratic (131072 of them, an 8 MB file: more than 120 s; fuzzing, 2026-11-26)."""
    from can.io import blf

    def plain(payload: bytes) -> bytes:
        body = blf.LOG_CONTAINER_STRUCT.pack(blf.NO_COMPRESSION, len(payload)) + payload
        return blf.OBJ_HEADER_BASE_STRUCT.pack(b"LOBJ", 16, 1, 16 + len(body), blf.LOG_CONTAINER) + body

    spanning = blf.OBJ_HEADER_BASE_STRUCT.pack(b"LOBJ", 16, 1, (16 << 20) - 64, blf.CAN_MESSAGE) + bytes(16)
    return plain(spanning) + plain(bytes(32)) * count


def _hostile_blfs(blf_bytes: bytes, d: Path) -> dict[str, Path]:
    from can.io import blf

    rng = random.Random(5)
    junk = bytes(rng.randrange(256) for _ in range(20000))
    files = {
        "truncated": blf_bytes[: len(blf_bytes) // 2],
        "garbage_body": blf_bytes[:144] + junk,
        "garbage_inside": blf_bytes[: len(blf_bytes) // 3] + junk[:3000] + blf_bytes[len(blf_bytes) // 3 :],
        "header_only": blf_bytes[:144],
        "header_cut": blf_bytes[:50],
        "zero_size_object": blf_bytes[:144]
        + blf.OBJ_HEADER_BASE_STRUCT.pack(b"LOBJ", 16, 1, 0, blf.LOG_CONTAINER)
        + blf_bytes[144:],
        "huge_size_object": blf_bytes[:144]
        + blf.OBJ_HEADER_BASE_STRUCT.pack(b"LOBJ", 16, 1, 0xFFFFFFF0, blf.LOG_CONTAINER)
        + blf_bytes[144:],
        "header_size_lie": blf_bytes[:4] + (0xFFFFFF00).to_bytes(4, "little") + blf_bytes[8:],
    }
    # a container unpacking to 64 MiB of zeros (64 kB on disk)
    packed = zlib.compress(bytes(64 << 20), 9)
    body = blf.LOG_CONTAINER_STRUCT.pack(blf.ZLIB_DEFLATE, 64 << 20) + packed
    obj = blf.OBJ_HEADER_BASE_STRUCT.pack(b"LOBJ", 16, 1, 16 + len(body), blf.LOG_CONTAINER) + body
    files["zip_bomb"] = blf_bytes[:144] + obj + bytes(-len(obj) % 4) + blf_bytes[144:]
    # a container within the size bound whose CAN objects, repeated, pack 100s of times (an expansion bomb: 200 of
    # them made 10 MB of file take minutes)
    size = blf.OBJ_HEADER_BASE_STRUCT.unpack_from(blf_bytes, 144)[3]
    first = blf_bytes[144 + 16 + blf.LOG_CONTAINER_STRUCT.size : 144 + size]
    objects = zlib.decompress(first)
    unpacked = objects * ((8 << 20) // len(objects))
    packed = zlib.compress(unpacked, 9)
    body = blf.LOG_CONTAINER_STRUCT.pack(blf.ZLIB_DEFLATE, len(unpacked)) + packed
    obj = blf.OBJ_HEADER_BASE_STRUCT.pack(b"LOBJ", 16, 1, 16 + len(body), blf.LOG_CONTAINER) + body
    files["expansion_bomb"] = blf_bytes[:144] + obj + bytes(-len(obj) % 4) + blf_bytes[144:]
    files["object_spanning_containers"] = blf_bytes + _spanning_containers(131072)
    out = {}
    for name, data in files.items():
        (d / f"{name}.blf").write_bytes(data)
        out[name] = d / f"{name}.blf"
    return out


def test_an_object_spanning_many_containers_reads_in_linear_time(ride, tmp_path):
    """Four times the containers take about four times as long (sixteen when the reader was quadratic). A ratio,
    not a wall time: the absolute bound (5 s for 131072 containers, 0.4 s measured) failed under tracemalloc on a
    host in its slow state (5.9 s, `.ci/run`, 2026-11-27)."""
    header = ride["blf"].read_bytes()[:144]
    best = {}
    for count in (32768, 131072):
        path = tmp_path / f"spanning_{count}.blf"
        path.write_bytes(header + _spanning_containers(count))
        best[count] = math.inf
        for _ in range(3):
            t0 = time.perf_counter()
            _, stats = _frames(path)
            best[count] = min(best[count], time.perf_counter() - t0)
        assert stats.malformed >= 1
    assert best[131072] / best[32768] < 8.0, best


def test_hostile_blf_never_hangs_raises_or_balloons(ride, tmp_path):
    small = tmp_path / "small_containers.blf"  # many containers: garbage in one loses that one only
    writer = can.BLFWriter(str(small))
    writer.max_container_size = 2048
    for msg in can.LogReader(str(ride["candump"])):
        writer.on_message_received(msg)
    writer.stop()
    n_good = len(_frames(small)[0])
    assert n_good == len(_frames(ride["blf"])[0])
    for name, path in _hostile_blfs(small.read_bytes(), tmp_path).items():
        tracemalloc.start()
        t0 = time.perf_counter()
        try:
            frames, stats = _frames(path)
        except LogFormatError as exc:  # a header that cannot be read at all: one line
            assert name in ("header_cut", "header_size_lie"), (name, exc)
            assert "\n" not in str(exc)
            continue
        finally:
            peak = tracemalloc.get_traced_memory()[1]
            tracemalloc.stop()
        assert time.perf_counter() - t0 < 20, name  # under tracemalloc; the spanning object's time: the test below
        assert peak < 80 << 20, (name, peak)
        assert len(frames) <= n_good, name
        if name != "header_only":
            assert stats.malformed >= 1, (name, stats.rejected)
        if name in ("zero_size_object", "huge_size_object", "zip_bomb", "expansion_bomb", "object_spanning_containers"):
            assert len(frames) == n_good, name  # the bad object skipped, every frame after it read
        if name == "garbage_inside":
            assert len(frames) > n_good // 2, name


def test_hostile_mf4_is_one_line(ride, tmp_path):
    data = ride["mf4"].read_bytes()
    rng = random.Random(9)
    for name, content in (
        ("truncated", data[: len(data) // 2]),
        ("garbage", data[:64] + bytes(rng.randrange(256) for _ in range(20000))),
    ):
        path = tmp_path / f"{name}.mf4"
        path.write_bytes(content)
        err = io.StringIO()
        hook, sys.unraisablehook = sys.unraisablehook, lambda u, err=err: err.write(repr(u))
        try:
            with pytest.raises(LogFormatError, match="unreadable MF4") as caught:
                _frames(path)
        finally:
            sys.unraisablehook = hook
        assert "\n" not in str(caught.value) and err.getvalue() == ""


def _with_channel_group_field(data: bytes, offset: int, value: int) -> bytes:
    """The MF4 file with one field of its first channel group block (``##CG``) overwritten: 80 the record count
    (u64), 96 the record size (u32)."""
    b = bytearray(data)
    i = b.find(b"##CG")
    fmt = "<Q" if offset == 80 else "<I"
    b[i + offset : i + offset + struct.calcsize(fmt)] = struct.pack(fmt, value)
    return bytes(b)


def test_crafted_mf4_files_are_one_line_within_bounds(ride, tmp_path, monkeypatch):
    """asammdf parses a file whole in its constructor: crafted files of 43 kB (fuzzing, 2026-11-26) looped forever
    (a record count of 0), aborted the interpreter with malloc(): invalid size (a record size of 1: SIGABRT, exit
    134) or grew to 4.4 GB (a record size of 2^32 - 1). Read in a child process under limits: one line each."""
    from ptw_rt.io import mf4_sandbox

    monkeypatch.setattr(mf4_sandbox, "cpu_limit_s", lambda size: 4)  # the child's CPU limit comes from the parent
    data = ride["mf4"].read_bytes()
    cases = {
        "endless": (_with_channel_group_field(data, 80, 0), "unreadable MF4 file \\(its reader was ended by signal"),
        "abort": (_with_channel_group_field(data, 96, 1), "unreadable MF4 file \\(its reader was ended by signal"),
        "huge_records": (_with_channel_group_field(data, 96, 2**32 - 1), "corrupt MF4 file \\(channel group 0"),
    }
    for name, (content, message) in cases.items():
        path = tmp_path / f"{name}.mf4"
        path.write_bytes(content)
        t0 = time.monotonic()
        with pytest.raises(LogFormatError, match=message) as caught:
            _frames(path)
        assert "\n" not in str(caught.value) and time.monotonic() - t0 < 4 + mf4_sandbox.WALL_S_EXTRA, name


@pytest.mark.parametrize("fmt", ["asc", "trc"])
def test_garbage_lines_of_asc_and_trc_are_counted_and_their_events_are_not(ride, tmp_path, fmt):
    """Half an ASC or TRC log replaced by garbage (or by frames stamped nan, 1e308, -1e9) read as a log of half the
    frames, malformed 0, nothing said: python-can's parsers skip a line they do not know. Garbage is counted now;
    an ASC event (statistics, status, an error frame) or a TRC status record is still not a problem."""
    lines = ride[fmt].read_text().splitlines()
    first = next(i for i, line in enumerate(lines) if ("Rx" in line and not line.startswith(";")))
    ref, _ = _frames(ride[fmt])
    bad = ["hello world this is garbage", "nan 1 100 Rx d 2 00 32", "1e308 1 100 Rx d 2 00 32", "-1e9 1 100 Rx d 1 0"]
    events = (
        [" 0.001000 1 Statistic: D 2 R 0 XD 0 XR 0 E 0 O 0 B 0.05%", " 0.002000 CAN 1 Status:chip status error active"]
        if fmt == "asc"
        else []
    )
    mixed = lines[:first] + events + [bad[k % len(bad)] if k % 2 else line for k, line in enumerate(lines[first:])]
    path = tmp_path / f"mixed.{fmt}"
    path.write_text("\n".join(mixed) + "\n")
    frames, stats = _frames(path)
    assert stats.malformed == len(lines[first:]) // 2 and len(frames) == len(ref) - stats.malformed


def test_the_mf4_readers_message_reaches_the_user_on_one_line(monkeypatch):
    """The child's refusal is asammdf's exception text: a newline (or any control character) in it split the one-line
    refusal. Whatever the child sends is made one ASCII line by the parent."""
    from ptw_rt.io import mf4_sandbox

    text = "unreadable MF4 file (KeyError: 'a\nb\x1b[2J\u00e9')".encode()

    class Child:
        stdout = io.BytesIO(b"E" + struct.pack("<H", len(text)) + text)

        def poll(self):
            return 0

        def wait(self):
            return 0

        def kill(self):
            pass

    monkeypatch.setattr(mf4_sandbox.subprocess, "Popen", lambda *a, **kw: Child())
    with pytest.raises(mf4_sandbox.SandboxError) as caught:
        list(mf4_sandbox.read_messages("x.mf4", 100))
    message = str(caught.value)
    assert message.startswith("unreadable MF4 file (KeyError:") and message.isascii() and message.isprintable()


def test_not_a_log_and_empty(tmp_path):
    rng = random.Random(3)
    (tmp_path / "x.asc").write_bytes(bytes(rng.randrange(256) for _ in range(5000)))
    names = "candump/ASC/BLF/TRC/CSV/MF4/SQLite/candump -t/python-can text"
    with pytest.raises(NotACanLogError, match=rf"x.asc: not a CAN log \(no {names} frame"):
        detect_format(tmp_path / "x.asc")
    (tmp_path / "e.log").write_bytes(b"")
    with pytest.raises(EmptyLogError, match="empty log"):
        detect_format(tmp_path / "e.log")
    (tmp_path / "h.csv").write_text("timestamp,arbitration_id,extended,remote,error,dlc,data\n")
    with pytest.raises(EmptyLogError, match="empty log"):
        replay_log(tmp_path / "h.csv", tmp_path / "o.log", None, DEFAULT_CONFIG)


def _cli(args, cwd):
    return subprocess.run(
        [sys.executable, "-m", "ptw_rt", *map(str, args)],
        cwd=cwd,
        capture_output=True,
        text=True,
        errors="replace",
        timeout=300,
        env={**os.environ, "NUMBA_NUM_THREADS": "1"},
    )


def test_cli_refuses_not_a_log_and_empty_in_one_line(ride, tmp_path):
    rng = random.Random(4)
    (tmp_path / "x.log").write_bytes(bytes(rng.randrange(256) for _ in range(5000)))
    (tmp_path / "empty.log").write_bytes(b"")
    shutil.copy(ride["blf"], tmp_path / "ok.blf")
    cases = [
        (["replay", "x.log", "--out", "o.log"], "ptw-rt replay: x.log: not a CAN log (no candump/ASC/BLF/TRC/CSV/MF4/"),
        (["replay", "empty.log", "--out", "o.log"], "ptw-rt replay: empty.log: empty log (0 bytes)"),
        (["replay", "ok.blf", "--out", "o.bin"], "ptw-rt replay: o.bin: unknown log format '.bin'"),
        (["replay", "ok.blf", "--out", "o.txt"], "ptw-rt replay: o.txt: text logs are read, not written"),
    ]
    for args, start in cases:
        proc = _cli(args, tmp_path)
        assert proc.returncode == 2, (args, proc.stderr)
        assert proc.stderr.splitlines() == [proc.stderr.strip()] and proc.stderr.startswith(start), proc.stderr
        assert proc.stdout == ""


def test_directory_replay_takes_every_format_and_lists_failures(ride, tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    for fmt in ("candump", "blf", "csv"):
        shutil.copy(ride[fmt], src / f"r_{fmt}{ride[fmt].suffix}")
    (src / "truth.csv").write_text("time,roll\n0.0,0.1\n")  # not a CAN CSV: not taken from a directory
    (src / "junk.asc").write_bytes(b"\x00\x01 not a log\n" * 10)
    proc = _cli(["replay", src, "--out", tmp_path / "out", "--jobs", "2", "--no-progress"], tmp_path)
    # a bad log of a directory run is a partial failure (exit 1, EXIT_PARTIAL), not a bad command (2)
    assert proc.returncode == 1, proc.stderr
    names = "candump/ASC/BLF/TRC/CSV/MF4/SQLite/candump -t/python-can text"
    junk = f"{src / 'junk.asc'}: not a CAN log (no {names} frame in the first 64 KiB)"
    assert [line for line in proc.stderr.splitlines() if line.startswith("error: ")] == [f"error: {junk}"]
    assert "1 of 4 logs failed" in proc.stderr, proc.stderr
    summaries = [json.loads(line) for line in proc.stdout.splitlines()]
    assert [s.get("error") for s in summaries] == [junk, None, None, None]  # job order: junk.asc sorts first
    outs = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert outs == ["fleet.csv", "fleet.parquet", "r_blf.blf", "r_candump.log", "r_csv.csv"]  # + the fleet summary


def test_the_command_line_loads_mf4_support_only_for_an_mf4_log(ride, tmp_path):
    """python-can imports asammdf (and pandas) with ``can.io``: 0.2 s and ~60 MB at every start. The command line
    defers it (``ptw_rt._deferred_imports``) until a log needs it, and then MF4 still reads and writes."""
    probe = (
        "import sys; from ptw_rt.cli import main; code = main(sys.argv[1:]); "
        "print('PANDAS', 'pandas' in sys.modules, 'ASAMMDF', 'asammdf' in sys.modules); sys.exit(code)"
    )

    def run(*args, code=0):
        done = subprocess.run(
            [sys.executable, "-c", probe, "replay", *map(str, args), "--no-progress"],
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert done.returncode == code, done.stderr
        return done.stdout + done.stderr

    assert "PANDAS False ASAMMDF False" in run(ride["candump"], "--out", tmp_path / "a.log")
    assert "ASAMMDF True" in run(ride["candump"], "--out", tmp_path / "a.mf4")
    # read back: the estimator's own frames, none of them an input (one line, exit 2), but every one read, by a
    # child process (``ptw_rt.io.mf4_sandbox``): asammdf is never loaded into the replay itself to read
    again = run(tmp_path / "a.mf4", "--out", tmp_path / "b.log", code=2)
    assert "PANDAS False ASAMMDF False" in again and re.search(
        r"none of its [1-9]\d* frames is one the estimator reads", again
    )
    candump, _ = _frames(tmp_path / "a.log")
    mf4, _ = _frames(tmp_path / "a.mf4")
    assert len(candump) > 100 and [f[1:] for f in mf4] == [f[1:] for f in candump]  # the same frames written


# ---------------------------------------------------------------------- gzip-compressed logs


@pytest.mark.parametrize("fmt", ["candump", "asc", "blf", "trc", "csv"])
def test_a_gzip_compressed_log_replays_like_its_original(ride, replays, fmt, tmp_path):
    """Loggers rotate and compress their files; python-can reads ``*.EXT.gz``. Same frames, same replay."""
    import gzip

    packed = tmp_path / (ride[fmt].name + ".gz")
    packed.write_bytes(gzip.compress(ride[fmt].read_bytes()))
    assert detect_format(packed)[0] == fmt
    ref, _ = _frames(ride[fmt])
    frames, stats = open_log(packed)
    got = [next(frames)]
    assert 0.0 < stats.fraction <= 1.0  # the progress counts the compressed file's bytes, not the data's
    got += list(frames)
    assert stats.format == fmt and stats.malformed == 0 and got == ref
    if fmt != "asc":  # the ASC's own clock (above)
        log, csv = tmp_path / "o.log", tmp_path / "o.csv"
        replay_log(packed, log, csv, DEFAULT_CONFIG)
        assert log.read_bytes() == replays[fmt][0].read_bytes() and csv.read_bytes() == replays[fmt][1].read_bytes()


def test_a_truncated_or_corrupt_gzip_log_gives_what_it_holds(ride, tmp_path, caplog):
    """A logger killed mid-write leaves a stream without its end; a bad CRC or garbage after the stream: the frames
    before are read, the rest is said lost in one warning."""
    import gzip

    whole = gzip.compress(ride["candump"].read_bytes())
    ref, _ = _frames(ride["candump"])
    cases = {
        "cut.log.gz": whole[: len(whole) // 2],
        "crc.log.gz": whole[:-8] + bytes(b ^ 0xFF for b in whole[-8:-4]) + whole[-4:],
        "tail.log.gz": whole + b"garbage after the stream",
    }
    for name, data in cases.items():
        (tmp_path / name).write_bytes(data)
        caplog.clear()
        got, stats = _frames(tmp_path / name)
        assert 0 < len(got) <= len(ref) and got == ref[: len(got)], name
        assert name == "cut.log.gz" or len(got) == len(ref)  # a CRC or trailing garbage loses no frame
        assert [r.message for r in caplog.records if "compressed stream ends early" in r.message], name


def test_a_gzip_bomb_is_refused_within_bounds(tmp_path):
    """A few hundred kB that inflate to gigabytes: refused once the data exceed 16 times the file, in one line,
    without holding the data."""
    import gzip

    from ptw_rt.io.candump import CandumpFileError
    from ptw_rt.io.compressed import MAX_EXPANSION

    bomb = tmp_path / "bomb.log.gz"
    line = b"(1700000000.000000) can0 300#0000000000000000\n"
    bomb.write_bytes(gzip.compress(line * (200_000_000 // len(line)), 9))
    assert bomb.stat().st_size * MAX_EXPANSION < 200_000_000
    tracemalloc.start()
    t0 = time.perf_counter()
    with pytest.raises(CandumpFileError, match="decompresses beyond .* a gzip bomb"):
        for _ in open_log(bomb)[0]:
            pass
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert time.perf_counter() - t0 < 30.0 and peak < 64 << 20


def test_gzip_logs_in_a_directory_and_their_outputs(ride, tmp_path):
    """A directory of ``.log.gz`` / ``.blf.gz`` logs replays like one of plain logs; each output is compressed
    when its input was and its format is written compressed (a text one: ``.log.gz`` yes, ``.blf.gz`` becomes
    ``.blf``); a BLF output named ``.gz`` is refused; MF4 inside gzip is one line."""
    import gzip

    src = tmp_path / "in"
    src.mkdir()
    for fmt in ("candump", "blf"):
        (src / (ride[fmt].name + ".gz")).write_bytes(gzip.compress(ride[fmt].read_bytes()))
    (src / "truth.csv.gz").write_bytes(gzip.compress(b"time,roll\n0.0,0.1\n"))  # not a CAN CSV: not taken
    proc = _cli(["replay", src, "--out", tmp_path / "out", "--jobs", "1", "--no-progress"], tmp_path)
    assert proc.returncode == 0, proc.stderr
    outs = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert outs == sorted(["fleet.csv", "fleet.parquet", ride["blf"].name, ride["candump"].name + ".gz"])
    (tmp_path / "r.mf4.gz").write_bytes(gzip.compress(ride["mf4"].read_bytes()))
    cases = [
        (["replay", src / (ride["candump"].name + ".gz"), "--out", "o.blf.gz"], "BLF is not written compressed"),
        (["replay", "r.mf4.gz", "--out", "o.log"], "MF4 inside gzip is not read"),
    ]
    for args, text in cases:
        proc = _cli(args, tmp_path)
        assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and text in proc.stderr, proc.stderr


# ---------------------------------------------------------------------- SQLite (python-can's .db)


def test_sqlite_logs_in_and_out(ride, replays, tmp_path):
    """python-can's SQLite log: written here (python-can's reader reads it back frame for frame), read here (the
    candump original's frames and estimates). python-can's own writer is not used: its thread stops before it has
    written what is queued (18 600 frames logged, 501 rows in the file; python-can 4.6)."""
    from ptw_rt.io.sqlite_log import SqliteLogWriter

    ref, _ = _frames(ride["candump"])
    db = tmp_path / "ride.db"
    with SqliteLogWriter(db) as writer:
        for ts, frame_id, data, extended in ref:
            writer.write(ts, frame_id, data, extended=extended)
    back = [(m.timestamp, m.arbitration_id, bytes(m.data), m.is_extended_id) for m in can.LogReader(str(db))]
    assert back == ref
    assert detect_format(db)[0] == "db"
    got, stats = _frames(db)
    assert stats.format == "db" and stats.malformed == 0 and got == ref
    log, csv = tmp_path / "o.log", tmp_path / "o.csv"
    replay_log(db, log, csv, DEFAULT_CONFIG)
    assert (
        log.read_bytes() == replays["candump"][0].read_bytes()
        and csv.read_bytes() == replays["candump"][1].read_bytes()
    )
    # --out .db: a replay's estimates as rows python-can reads (an existing file is replaced, not appended to)
    out = tmp_path / "est.db"
    out.write_bytes(db.read_bytes())
    replay_log(ride["candump"], out, None, DEFAULT_CONFIG)
    est, _ = _frames(replays["candump"][0])  # candump's stamps are rounded to the microsecond
    rows = [(m.timestamp, m.arbitration_id, bytes(m.data)) for m in can.LogReader(str(out))]
    assert [r[1:] for r in rows] == [e[1:3] for e in est]
    assert max(abs(r[0] - e[0]) for r, e in zip(rows, est, strict=True)) < 1e-6


def _sqlite(path: Path, statements: list[str], rows: list[tuple] = ()) -> Path:
    import sqlite3

    conn = sqlite3.connect(path)
    for statement in statements:
        conn.execute(statement)
    if rows:
        conn.executemany("INSERT INTO messages VALUES (?, ?, ?, ?, ?, ?, ?)", rows)
    conn.commit()
    conn.close()
    return path


_TABLE = (
    "CREATE TABLE messages (ts REAL, arbitration_id INTEGER, extended INTEGER, remote INTEGER, error INTEGER, "
    "dlc INTEGER, data BLOB)"
)


def test_hostile_sqlite_logs_are_one_line_or_counted(ride, tmp_path, monkeypatch):
    """An SQLite file is a program as much as data: a view whose recursive query never ends, a blob of megabytes,
    text where numbers belong, corrupt pages, a table of another shape. Each is one line (LogFormatError) or its
    bad rows counted, in bounded time, and nothing is written to the file."""
    import random

    from ptw_rt.io import sqlite_log

    good = [(1700000000.0 + k * 0.01, 0x300 + k % 3, 0, 0, 0, 8, bytes(8)) for k in range(20)]
    endless = (
        "CREATE VIEW messages AS WITH RECURSIVE r(x) AS (SELECT 1 UNION ALL SELECT x + 1 FROM r) SELECT x AS ts, "
        "768 AS arbitration_id, 0 AS extended, 0 AS remote, 0 AS error, 8 AS dlc, zeroblob(8) AS data FROM r"
    )
    refused = {
        "view.db": ([endless], [], "is a view, not a table"),
        "other_table.db": (["CREATE TABLE other (a)"], [], "without python-can's table 'messages'"),
        "other_columns.db": (["CREATE TABLE messages (a, b, c, d, e, f, g)"], [], "is not python-can's (no column ts"),
    }
    for name, (statements, rows, text) in refused.items():
        path = _sqlite(tmp_path / name, statements, rows)
        before = path.read_bytes()
        with pytest.raises(LogFormatError, match=re.escape(text)):
            _frames(path)
        assert path.read_bytes() == before, name  # read-only, immutable: not even a journal
    (tmp_path / "header_only.db").write_bytes(sqlite_log.MAGIC + bytes(100))
    with pytest.raises(LogFormatError, match="unreadable SQLite file"):
        _frames(tmp_path / "header_only.db")
    # bad rows are counted, the good ones read
    typed = good[:5] + [("abc", 0x300, 0, 0, 0, 8, bytes(8)), (1.0, "x", 0, 0, 0, 8, bytes(8))] + good[5:]
    got, stats = _frames(_sqlite(tmp_path / "types.db", [_TABLE], typed))
    assert len(got) == len(good) and stats.malformed == 2
    # a value beyond the bound ends the log there, said; the rows before it are read (but the last: Python's sqlite3
    # cursor steps one row ahead, and the step that fails is the one that would have returned it)
    big = good + [(1700000001.0, 0x300, 0, 0, 0, 8, bytes(10 << 20))] + good
    got, stats = _frames(_sqlite(tmp_path / "blob.db", [_TABLE], big))
    assert len(got) == len(good) - 1 and stats.malformed == 1 and "rest of the file is not read" in stats.examples[0]
    # corrupt pages: one line, or the rows before them
    path = _sqlite(
        tmp_path / "corrupt.db",
        [_TABLE],
        [(1700000000.0 + k * 1e-3, 0x300, 0, 0, 0, 8, bytes(8)) for k in range(20000)],
    )
    data = bytearray(path.read_bytes())
    rng = random.Random(1)
    for i in range(4096, len(data), 997):
        data[i] = rng.randrange(256)
    path.write_bytes(data)
    got, stats = _frames(path)
    assert stats.malformed >= 1
    # the time budget: a slow file is cut off, said
    monkeypatch.setattr(sqlite_log, "TIME_BUDGET_S", 0.0)
    monkeypatch.setattr(sqlite_log, "TIME_PER_MB_S", 0.0)
    got, stats = _frames(_sqlite(tmp_path / "slow.db", [_TABLE], good * 500))
    assert stats.malformed == 1 and "the time budget is spent" in stats.examples[0]


def test_replay_to_a_pipe_for_cantools_decode(ride, replays, tmp_path):
    """``ptw-rt replay ride.log --out /dev/stdout | python -m cantools decode dbc/ptw_rt.dbc``: the log on stdout
    (a pipe with its reader), the JSON summary on stderr; a FIFO nobody reads is one line, not a hang."""
    proc = _cli(["replay", ride["candump"], "--out", "/dev/stdout", "--no-progress"], tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout == replays["candump"][0].read_text()
    assert json.loads(proc.stderr.strip().splitlines()[-1])["out"] == "/dev/stdout"
    fifo = tmp_path / "nobody"
    os.mkfifo(fifo)
    t0 = time.monotonic()
    proc = _cli(["replay", ride["candump"], "--out", fifo, "--no-progress"], tmp_path)
    assert proc.returncode == 74 and "is a FIFO (named pipe) with no reader" in proc.stderr, proc.stderr
    assert proc.stderr.count("\n") == 1 and time.monotonic() - t0 < 60


# ---------------------------------------------------------------------- candump's screen output (-ta, -tA, -tz)


def _candump_t(frames, path: Path, stamp, extra: str = "") -> Path:
    with open(path, "w") as f:
        for ts, frame_id, data, extended in frames:
            ident = f"{frame_id:08X}" if extended else f"{frame_id:03X}"
            f.write(f" ({stamp(ts)})  can0  {extra}{ident}   [{len(data)}]  {' '.join(f'{b:02X}' for b in data)}\n")
    return path


def test_candump_screen_output_with_time_stamps_replays_like_the_log(ride, replays, tmp_path):
    """What `candump -ta can0 > ride.txt` (or -tA, with -x) leaves: the same frames and the same replay; without
    time stamps (`candump can0`) there is nothing to clock a replay by: one line."""
    import datetime

    ref, _ = _frames(ride["candump"])
    epoch = _candump_t(ref, tmp_path / "ta.txt", lambda ts: f"{ts:.6f}")

    def local(ts: float) -> str:
        d = datetime.datetime.fromtimestamp(ts)
        return f"{d:%Y-%m-%d %H:%M:%S}.{d.microsecond:06d}"

    dated = _candump_t(ref, tmp_path / "tA.txt", local, extra="RX - -  ")
    for path in (epoch, dated):
        assert detect_format(path)[0] == "candump_t"
        got, stats = _frames(path)
        assert stats.malformed == 0 and [f[1:] for f in got] == [f[1:] for f in ref]
        assert max(abs(a[0] - b[0]) for a, b in zip(got, ref, strict=True)) < 2e-6
    log = tmp_path / "o.log"
    replay_log(epoch, log, None, DEFAULT_CONFIG)
    assert log.read_bytes() == replays["candump"][0].read_bytes()
    # -t z: from zero; -t d: each frame's time since the one before (their running sum, from zero)
    t0 = ref[0][0]
    zero = _candump_t(ref, tmp_path / "tz.txt", lambda ts: f"{ts - t0:010.6f}")
    previous = iter([t0] + [f[0] for f in ref])
    delta = _candump_t(ref, tmp_path / "td.txt", lambda ts: f"{ts - next(previous):010.6f}")
    assert (detect_format(zero)[0], detect_format(delta)[0]) == ("candump_t", "candump_td")
    for path, tolerance in ((zero, 2e-6), (delta, 1e-6 * len(ref))):  # -t d's rounding adds up
        got, stats = _frames(path)
        assert stats.malformed == 0 and [f[1:] for f in got] == [f[1:] for f in ref]
        assert max(abs(a[0] - (b[0] - t0)) for a, b in zip(got, ref, strict=True)) < tolerance
    bad = epoch.read_text().splitlines()
    bad[3] = bad[3][:-3]  # a byte fewer than its [n]
    bad[5] = " (12:00)  can0  300   [8]  00"
    (tmp_path / "bad.txt").write_text("\n".join(bad) + "\n")
    got, stats = _frames(tmp_path / "bad.txt")
    assert len(got) == len(ref) - 2 and stats.malformed == 2
    (tmp_path / "notime.txt").write_text("".join(line.split(")", 1)[1] + "\n" for line in bad[6:]))
    with pytest.raises(LogFormatError, match="candump output without time stamps"):
        detect_format(tmp_path / "notime.txt")
    (tmp_path / "readme.txt").write_text("notes about the ride\n")
    src = tmp_path / "dir"
    src.mkdir()
    shutil.copy(epoch, src / "ride.txt")
    shutil.copy(tmp_path / "readme.txt", src / "readme.txt")  # not a log: not taken from a directory
    proc = _cli(["replay", src, "--out", tmp_path / "out", "--jobs", "1", "--no-progress"], tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["ride.log"]  # one log: no fleet summary


def test_a_gzip_stream_seeks_back_within_its_window_only(tmp_path):
    """The BLF reader steps back within a read chunk when it resynchronises on garbage: served from the last
    2 MiB inflated, never by re-inflating from the start (quadratic on a crafted file); further back is an
    OSError."""
    import gzip

    from ptw_rt.io.compressed import SEEK_BACK_BYTES, GzipLog

    rng = random.Random(1)
    data = rng.randbytes(3 * SEEK_BACK_BYTES)
    packed = tmp_path / "x.gz"
    packed.write_bytes(gzip.compress(data, 1))
    stream = GzipLog(open(packed, "rb"), "x", 1 << 40, ValueError)  # noqa: SIM115 - closed by GzipLog
    for _ in range(3000):
        if rng.random() < 0.3:
            stream.seek(max(0, stream.tell() - rng.randrange(1 << 20)))
        start, n = stream.tell(), rng.randrange(60_000)
        assert stream.read(n) == data[start : start + n]
    start = stream.tell()
    assert stream.read(-1) == data[start:]
    with pytest.raises(OSError, match="seeks back at most"):
        stream.seek(0)
    stream.close()


def test_a_gzip_compressed_blf_with_garbage_reads_like_the_plain_file(tmp_path):
    """Garbage every 500 bytes of an uncompressed-container BLF: the same frames and counts, gzipped or not."""
    import gzip

    from can.io.blf import BLFWriter

    plain = tmp_path / "raw.blf"
    writer = BLFWriter(str(plain), compression_level=0)
    for k in range(20_000):
        writer.on_message_received(can.Message(timestamp=1.7e9 + k * 0.01, arbitration_id=0x100, data=bytes(8)))
    writer.stop()
    data = plain.read_bytes()
    junk = data[:144] + b"".join(data[i : i + 500] + b"JUNK" for i in range(144, len(data), 500))
    (tmp_path / "junk.blf").write_bytes(junk)
    (tmp_path / "junk.blf.gz").write_bytes(gzip.compress(junk))
    got, stats = _frames(tmp_path / "junk.blf")
    got_gz, stats_gz = _frames(tmp_path / "junk.blf.gz")
    assert stats.malformed > 20 and got_gz == got and stats_gz.rejected == stats.rejected


def test_python_can_text_replays_like_the_log(ride, replays, tmp_path):
    """`python -m can.logger -f ride.txt` writes `str(Message)` a line (`can.Printer`), a format python-can cannot
    read back: read here, the same frames and replay; remote, error and FD frames counted as skipped."""
    text = tmp_path / "pycan.txt"
    with can.Printer(str(text)) as printer:
        for msg in can.LogReader(str(ride["candump"])):
            printer.on_message_received(msg)
        printer.on_message_received(can.Message(timestamp=1e9, arbitration_id=0x123, is_remote_frame=True, dlc=8))
        printer.on_message_received(can.Message(timestamp=1e9, arbitration_id=0x123, is_fd=True, data=bytes(12)))
    assert detect_format(text)[0] == "pycan_txt"
    ref, _ = _frames(ride["candump"])
    got, stats = _frames(text)
    assert stats.malformed == 0 and stats.skipped == {"remote": 1, "fd": 1}
    assert [f[1:3] for f in got] == [f[1:3] for f in ref]
    assert max(abs(a[0] - b[0]) for a, b in zip(got, ref, strict=True)) < 1e-6
    log = tmp_path / "o.log"
    replay_log(text, log, None, DEFAULT_CONFIG)
    assert log.read_bytes() == replays["candump"][0].read_bytes()


@pytest.mark.parametrize("ext", ["log", "asc", "trc", "csv"])
def test_an_output_named_gz_is_written_compressed(ride, replays, ext, tmp_path):
    """``--out est.log.gz``: the text formats written through gzip, what python-can's and this reader read back."""
    import gzip

    packed, plain = tmp_path / f"est.{ext}.gz", tmp_path / f"est.{ext}"
    replay_log(ride["candump"], packed, None, DEFAULT_CONFIG)
    replay_log(ride["candump"], plain, None, DEFAULT_CONFIG)
    if ext == "log":
        assert gzip.decompress(packed.read_bytes()) == replays["candump"][0].read_bytes()
    assert _frames(packed)[0] == _frames(plain)[0]
    assert len(list(can.LogReader(str(packed)))) == len(list(can.LogReader(str(plain))))


def test_a_text_record_cut_mid_write_is_counted_not_read_as_other_bytes(ride, tmp_path):
    """python-can takes the data bytes a line has (a logger killed mid-write: DLC 7 with 3 bytes) and reads a byte
    cut to one hex digit as that digit ('FC 8' for 'FC 8F'); such a record is a malformed line, as candump's odd
    number of hex digits is (found by fuzzing: accepted, uncounted, and the last cycle's estimate changed)."""
    for fmt, cut in (
        ("asc", lambda line: line.rsplit(None, 1)[0] + " " + line.rsplit(None, 1)[1][0]),  # last byte, one digit
        ("asc", lambda line: " ".join(line.split()[:-3])),  # three bytes short of its DLC
        ("trc", lambda line: " ".join(line.split()[:-2])),
        ("csv", lambda line: ",".join(line.split(",")[:-1] + [base64.b64encode(b"\x01\x02").decode()])),
    ):
        lines = ride[fmt].read_text().splitlines()
        k = next(i for i in range(len(lines) // 2, len(lines)) if _data_line(fmt, lines[i]))
        path = tmp_path / f"cut.{fmt}"
        path.write_text("\n".join(lines[:k] + [cut(lines[k])] + lines[k + 1 :]) + "\n")
        good, _ = _frames(ride[fmt])
        got, stats = _frames(path)
        assert stats.malformed == 1 and len(got) == len(good) - 1, (fmt, lines[k], cut(lines[k]), stats.rejected)


def _data_line(fmt: str, line: str) -> bool:
    """A frame record of at least four data bytes."""
    if fmt == "csv":
        fields = line.split(",")
        return len(fields) == 7 and fields[5].isdigit() and int(fields[5]) >= 4
    words = line.split()
    if fmt == "asc":
        return len(words) > 8 and words[4] == "d" and int(words[5], 16) >= 4
    return len(words) > 8 and not line.startswith(";") and words[-5:] and all(len(w) == 2 for w in words[-4:])


def test_a_python_can_text_line_with_a_control_character_between_its_bytes_is_one_malformed_line(ride, tmp_path):
    """The line pattern's \\s takes \\x1c-\\x1f and non-ASCII spaces, which bytes.fromhex refuses: a ValueError that
    escaped as a traceback (found by fuzzing)."""
    text = tmp_path / "ride.txt"  # python-can's text: str(Message) a line (can.Printer's)
    text.write_text("\n".join(str(m) for m in can.LogReader(str(ride["candump"]))) + "\n")
    lines = text.read_text().splitlines()
    pair = re.compile(r"DL:\s+\d+\s+[0-9a-fA-F]{2}( )[0-9a-fA-F]{2}")
    k = next(i for i in range(len(lines) // 2, len(lines)) if pair.search(lines[i]))
    at = pair.search(lines[k]).start(1)
    bad = lines[k][:at] + "\x1c" + lines[k][at + 1 :]
    path = tmp_path / "ctrl.txt"
    path.write_text("\n".join(lines[:k] + [bad] + lines[k + 1 :]) + "\n")
    good, _ = _frames(text)
    got, stats = _frames(path)
    assert stats.malformed == 1 and len(got) == len(good) - 1


def _on_two_buses(ride, fmt: str, path: Path) -> None:
    """The ride on two buses, every frame on both, and a third bus's frame after the first input."""
    if fmt.startswith("candump"):
        lines = ride["candump"].read_text().splitlines()
        both = [x for line in lines for x in (line, line.replace(" vcan0 ", " vcan1 "))]
        stamp = lines[0].split(")")[0] + ")"
        both.insert(2, f"{stamp} can9 7F0#01")
        if fmt == "candump_records":  # a bad line: the block goes record by record, not as columns
            both.insert(0, "not a candump line")
        path.write_text("\n".join(both) + "\n")
        return
    messages = list(can.LogReader(str(ride["candump"])))
    with can.Logger(str(path)) as writer:
        for k, msg in enumerate(messages):
            for channel in (0, 1):
                msg.channel = channel
                writer.on_message_received(msg)
            if k == 0:
                writer.on_message_received(can.Message(timestamp=msg.timestamp, arbitration_id=0x7F0, channel=9))


@pytest.mark.parametrize("fmt", ["candump", "candump_records", "asc", "blf", "mf4", "trc"])
def test_a_log_of_two_buses_is_replayed_on_the_inputs_bus(ride, replays, fmt, tmp_path, caplog):
    """`candump -L any` of two buses: read as one bus, every frame came twice and every cycle stayed INIT. The bus
    of the first input frame is read (the daemon reads one bus), the others' frames skipped, counted and said in
    one line; ``--channel`` reads another; a channel the log lacks is one line."""
    ext = "log" if fmt.startswith("candump") else fmt
    path = tmp_path / f"two_buses.{ext}"
    _on_two_buses(ride, fmt, path)
    reference = _estimates(replays[fmt.split("_")[0]][1])
    frames = len(ride["candump"].read_text().splitlines())
    # the channels as the format names them (TRC counts buses from 1, python-can's ASC, BLF and MF4 from 0)
    *names, third = {"log": ("vcan0", "vcan1", "can9"), "trc": ("1", "2", "10")}.get(ext, ("0", "1", "9"))
    for channel in (None, *names):
        caplog.clear()
        csv = tmp_path / f"{channel}.csv"
        out = tmp_path / f"{channel}.out.log"
        summary = replay_log(path, out, csv, DEFAULT_CONFIG, channel=channel)
        assert _estimates(csv) == reference, channel
        said = [r.getMessage() for r in caplog.records if "other channels" in r.getMessage()]
        assert len(said) == 1 and f"{frames + 1} frames on other channels" in said[0], said
        read = channel or names[0]
        assert f"than the bus read, {read}" in said[0] and f", {third})" in said[0], said
        if ext == "log":
            assert {f.channel for f in read_log(out)} == {read}
        assert summary["frames_in"] >= frames
        assert summary["bus"] == read and summary["other_bus_frames"] == frames + 1
    with pytest.raises(EmptyLogError, match="no frame on --channel nosuch"):
        replay_log(path, tmp_path / "none.log", None, DEFAULT_CONFIG, channel="nosuch")


@pytest.mark.parametrize(
    "stray",
    ["can9 100#3000D1FF22000C", "can9 100#1F00DEFF45", "can9 00000100#3000D1FF22000C", "can9 100#R"],
    ids=["an input frame", "a short one", "a 29-bit one", "a remote one"],
)
def test_one_stray_frame_ahead_of_the_ride_does_not_choose_the_bus(ride, replays, stray, tmp_path):
    """The bus was the one of the first frame with an input's id: one such frame of another bus ahead of a ride (a
    valid-looking one, a short one, a 29-bit or a remote one) had the whole ride skipped as another bus, or the log
    refused (found by fuzzing). The bus is the one with the most input frames of the inputs' lengths."""
    lines = ride["candump"].read_text().splitlines()
    stamp = lines[0].split(")")[0] + ")"
    path = tmp_path / "stray.log"
    path.write_text("\n".join([f"{stamp} {stray}", *lines]) + "\n")
    csv = tmp_path / "stray.csv"
    summary = replay_log(path, tmp_path / "stray.out.log", csv, DEFAULT_CONFIG)
    assert summary["bus"] == "vcan0" and summary["frames_in"] == len(lines)
    assert _estimates(csv) == _estimates(replays["candump"][1])


@pytest.mark.parametrize("token", ["abc", "-1", "0x2", "1e3", "ä"])
def test_an_asc_frame_whose_channel_is_no_number_is_counted(ride, replays, token, tmp_path):
    """A frame line of an ASC file whose channel is not a number was dropped without a word (python-can's reader
    skips it as it skips events): a second channel written as `abc` lost every frame on it, uncounted, and a file of
    only such lines was "empty" (found by fuzzing). Such lines are malformed now; event lines are not."""
    lines = ride["asc"].read_text(encoding="utf-8").splitlines()
    out_lines, frames = [], 0
    for line in lines:
        out_lines.append(line)
        fields = line.split(None, 2)
        if len(fields) == 3 and fields[1] == "1" and " Rx " in line:
            out_lines.append(f" {fields[0]} {token}  {fields[2]}")
            frames += 1
    out_lines.insert(6, " 0.000100 ErrorFrame")  # an event: not a frame, not malformed
    path = tmp_path / "odd_channel.asc"
    path.write_text("\n".join(out_lines) + "\n", encoding="utf-8")
    csv = tmp_path / "odd.csv"
    summary = replay_log(path, tmp_path / "odd.out.log", csv, DEFAULT_CONFIG)
    assert summary["malformed_lines"] == frames
    assert _estimates(csv) == _estimates(replays["asc"][1])
