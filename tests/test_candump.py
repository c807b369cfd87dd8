"""candump -L logs: format, round trip, interoperability with python-can and cantools, malformed lines."""

from __future__ import annotations

import io
import logging
import math
import subprocess
import sys
from pathlib import Path

import can
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ptw_rt.io.candump import CandumpWriter, LogFrame, format_line, parse_line, read_log
from ptw_rt.io.dbc import FrameCodec
from ptw_rt.paths import DEFAULT_DBC

T0 = 1700000000.0


@pytest.fixture(scope="module")
def codec() -> FrameCodec:
    return FrameCodec()


def _estimator_frames(codec: FrameCodec, n: int = 5) -> list[tuple[float, int, bytes]]:
    out = []
    for i in range(n):
        t = T0 + 0.01 * i
        out.append(
            (t, *codec.encode("IMU_Rates", {"RollRate": 0.1 * i, "PitchRate": -0.02, "YawRate": 0.3}, counter=i % 16))
        )
        out.append(
            (
                t + 0.001,
                *codec.encode(
                    "EST_Roll",
                    {
                        "RollAngle": -0.2 + 0.01 * i,
                        "RollRateEst": 0.05,
                        "RollUIHOSMO": 0.0,
                        "EST_Roll_Valid": 1,
                        "RollAngle_Valid": 1,
                    },
                    counter=i % 15,
                ),
            )
        )
    return out


# ---------------------------------------------------------------- format


def test_format_line_exact() -> None:
    line = format_line(1700000000.123456, "vcan0", 0x123, bytes.fromhex("deadbeef"))
    assert line == "(1700000000.123456) vcan0 123#DEADBEEF"


def test_format_line_variants() -> None:
    assert format_line(0.01, "can0", 0x7, b"") == "(0000000000.010000) can0 007#"
    assert format_line(5, "can1", 0x1ABCDEF, b"\x01") == "(0000000005.000000) can1 01ABCDEF#01"
    assert format_line(5, "can1", 0x10, b"\x01", extended=True) == "(0000000005.000000) can1 00000010#01"


@pytest.mark.parametrize(
    ("args", "kwargs"),
    [
        ((-1.0, "can0", 1, b""), {}),
        ((float("nan"), "can0", 1, b""), {}),
        ((1.0, "can 0", 1, b""), {}),
        ((1.0, "", 1, b""), {}),
        ((1.0, "can0", 1, bytes(9)), {}),
        ((1.0, "can0", 0x800, b""), {"extended": False}),
        ((1.0, "can0", 0x20000000, b""), {}),
    ],
)
def test_format_line_rejects(args, kwargs) -> None:
    with pytest.raises(ValueError):
        format_line(*args, **kwargs)


def test_parse_line_accepts_candump_variants() -> None:
    f = parse_line("(1700000000.123456) vcan0 123#DEADBEEF", 7)
    assert f == LogFrame(1700000000.123456, "vcan0", 0x123, bytes.fromhex("DEADBEEF"), 7, False, False)
    assert parse_line("(1.5) can0 1ABCDEF0#0102").is_extended
    assert parse_line("(1.5) can0 1ABCDEF0#0102").frame_id == 0x1ABCDEF0
    r = parse_line("(1.5) can0 123#R")
    assert r.is_remote and r.data == b""
    assert parse_line("(1.5) can0 123#R8").is_remote
    assert parse_line("(1.5) can0 123#deadbeef R").data == bytes.fromhex("DEADBEEF")  # rx flag, lower-case hex
    assert parse_line("(1.5) can0 123#\r\n").data == b""


# ---------------------------------------------------------------- round trip


def test_write_read_round_trip(tmp_path: Path, codec: FrameCodec) -> None:
    frames = _estimator_frames(codec)
    path = tmp_path / "out.log"
    with CandumpWriter(path, channel="vcan0") as w:
        for t, fid, data in frames:
            w.write(t, fid, data)
    assert w.lines_written == len(frames)
    reader = read_log(path)
    got = list(reader)
    assert reader.malformed == 0 and reader.frames == len(frames)
    assert [(g.frame_id, g.data, g.channel) for g in got] == [(fid, d, "vcan0") for _, fid, d in frames]
    for g, (t, _, _) in zip(got, frames, strict=True):
        assert g.timestamp == pytest.approx(t, abs=1e-6)
    assert [g.line_no for g in got] == list(range(1, len(frames) + 1))
    # decodes back through the codec
    for g in got:
        name, _ = codec.decode_checked(g.frame_id, g.data)
        assert name in ("IMU_Rates", "EST_Roll")


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    rows=st.lists(
        st.tuples(
            st.floats(0, 4e9, allow_nan=False),
            st.one_of(st.integers(0, 0x7FF), st.integers(0x800, 0x1FFFFFFF)),
            st.binary(max_size=8),
            st.sampled_from(["can0", "vcan0", "slcan1"]),
        ),
        max_size=20,
    )
)
def test_round_trip_property(rows) -> None:
    buf = io.StringIO()
    with CandumpWriter(buf) as w:
        for t, fid, data, ch in rows:
            w.write(t, fid, data, channel=ch)
    assert not buf.closed  # a stream passed in is left open
    buf.seek(0)
    reader = read_log(buf, max_jump=math.inf, reorder_tolerance=math.inf)  # random stamps: time rule off
    got = list(reader)
    assert reader.malformed == 0
    assert len(got) == len(rows)
    for g, (t, fid, data, ch) in zip(got, rows, strict=True):
        assert (g.frame_id, g.data, g.channel, g.is_extended) == (fid, data, ch, fid > 0x7FF)
        assert abs(g.timestamp - t) <= 1e-6 + 4e-16 * t


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.floats(0.0, 4e9, allow_nan=False),
    st.lists(
        st.tuples(st.one_of(st.integers(0, 0x7FF), st.integers(0x800, 0x1FFFFFFF)), st.binary(max_size=8)),
        max_size=8,
    ),
)
def test_write_cycle_writes_what_write_writes(t, frames) -> None:
    """Replay's one-write-per-cycle path and the per-frame path give the same lines, byte for byte."""
    per_frame, per_cycle = io.StringIO(), io.StringIO()
    one, bulk = CandumpWriter(per_frame, channel="vcan0"), CandumpWriter(per_cycle, channel="vcan0")
    for fid, data in frames:
        one.write(t, fid, data)
    bulk.write_cycle(t, frames)
    bulk.write_cycle(t, frames)  # the second time from the cached id texts
    assert per_cycle.getvalue() == per_frame.getvalue() * 2
    assert bulk.lines_written == 2 * one.lines_written


def test_write_cycle_rejects_what_write_rejects() -> None:
    w = CandumpWriter(io.StringIO(), channel="vcan0")
    for stamp, frames in ((-1.0, [(1, b"")]), (math.nan, []), (0.0, [(0x20000000, b"")]), (0.0, [(1, b"0" * 9)])):
        with pytest.raises(ValueError):
            w.write_cycle(stamp, frames)


def test_write_frame_copies_log_frames(tmp_path: Path) -> None:
    src = tmp_path / "in.log"
    src.write_text("(1.000000) can0 123#01\n(2.000000) can1 1ABCDEF0#0203\n")
    out = tmp_path / "copy.log"
    with CandumpWriter(out) as w:
        for f in read_log(src):
            w.write_frame(f)
    assert out.read_text() == "(0000000001.000000) can0 123#01\n(0000000002.000000) can1 1ABCDEF0#0203\n"


# ---------------------------------------------------------------- interoperability


def test_python_can_reads_our_log(tmp_path: Path, codec: FrameCodec) -> None:
    frames = _estimator_frames(codec)
    path = tmp_path / "bus.log"
    with CandumpWriter(path, channel="vcan0") as w:
        for t, fid, data in frames:
            w.write(t, fid, data)
        w.write(T0 + 1, 0x1ABCDEF, b"\xaa")
    msgs = list(can.LogReader(path))
    assert len(msgs) == len(frames) + 1
    for m, (t, fid, data) in zip(msgs, frames, strict=False):
        assert isinstance(m, can.Message)
        assert (m.arbitration_id, bytes(m.data), m.is_extended_id, m.channel) == (fid, data, False, "vcan0")
        assert m.timestamp == pytest.approx(t, abs=1e-6)
    assert msgs[-1].is_extended_id and msgs[-1].arbitration_id == 0x1ABCDEF
    # explicit reader class as well
    assert len(list(can.io.CanutilsLogReader(str(path)))) == len(frames) + 1


def test_we_read_python_can_logs(tmp_path: Path) -> None:
    path = tmp_path / "pc.log"
    with can.io.CanutilsLogWriter(str(path), channel="vcan0") as w:
        w.on_message_received(
            can.Message(timestamp=T0 + 0.5, arbitration_id=0x300, data=b"\x01\x02", is_extended_id=False)
        )
        w.on_message_received(can.Message(timestamp=T0 + 0.6, arbitration_id=0x1234567, data=b"", is_extended_id=True))
    reader = read_log(path)
    got = list(reader)
    assert reader.malformed == 0
    assert [(g.frame_id, g.data, g.is_extended) for g in got] == [(0x300, b"\x01\x02", False), (0x1234567, b"", True)]


def test_cantools_decode_cli_reads_our_log(tmp_path: Path, codec: FrameCodec) -> None:
    frames = _estimator_frames(codec, n=3)
    buf = io.StringIO()
    with CandumpWriter(buf, channel="vcan0") as w:
        for t, fid, data in frames:
            w.write(t, fid, data)
    proc = subprocess.run(
        [sys.executable, "-m", "cantools", "decode", str(DEFAULT_DBC)],
        input=buf.getvalue(),
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    out = proc.stdout
    assert out.count("IMU_Rates(") == 3
    assert out.count("EST_Roll(") == 3
    for sig in ("RollRate:", "YawRate:", "IMU_Counter:", "RollAngle:", "RollRateEst:", "EST_Roll_CRC:"):
        assert sig in out, sig
    assert "Unknown frame id" not in out and "Unpack requires" not in out


# ---------------------------------------------------------------- malformed input

MALFORMED = {
    2: "",  # empty
    3: "garbage",
    4: "(abc) vcan0 123#00",  # bad timestamp
    5: "(1.0) vcan0 123#0G",  # bad hex
    6: "(1.0) vcan0 123#ABC",  # odd hex length
    7: "(1.0) vcan0 123#" + "00" * 9,  # > 8 bytes
    8: "(1.0) vcan0 12#00",  # id neither 3 nor 8 digits
    9: "(1.0) vcan0 123##1AABB",  # CAN FD
    10: "(1.0) vcan0 123",  # no '#'
    11: "(nan) vcan0 123#00",
    12: "(1.0) vcan0 800#00",  # 11-bit id out of range
    13: "(1.0) vcan0 20000080#0000000000000000",  # error frame
    14: "1.0 vcan0 123#00",
    15: "(1.0) vcan0 123#00 extra",
}


def _malformed_file(tmp_path: Path) -> Path:
    lines = ["(1.000000) vcan0 100#00112233445566"]
    for n in range(2, 16):
        lines.append(MALFORMED[n])
    lines.append("(2.000000) vcan0 123#R")  # line 16: remote frame, fine
    lines.append("(3.000000) vcan0 1ABCDEF0#01 T")  # line 17: extended + tx flag, fine
    p = tmp_path / "bad.log"
    p.write_text("\n".join(lines) + "\n")
    return p


def test_malformed_lines_counted_and_skipped(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    p = _malformed_file(tmp_path)
    with caplog.at_level(logging.WARNING, logger="ptw_rt.io.candump"):
        reader = read_log(p)
        frames = list(reader)
    assert [f.line_no for f in frames] == [1, 16, 17]
    assert frames[1].is_remote and frames[2].is_extended
    assert reader.malformed == len(MALFORMED)
    assert reader.malformed_lines == sorted(MALFORMED)
    assert [n for n, _ in reader.problems] == sorted(MALFORMED)
    messages = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    for n in MALFORMED:
        assert any(f"{p}:{n}:" in m for m in messages), f"no warning naming line {n}"
    reasons = dict(reader.problems)
    assert "empty" in reasons[2]
    assert "timestamp" in reasons[4]
    assert "hex" in reasons[5]
    assert "odd" in reasons[6]
    assert "8 bytes" in reasons[7]


def test_warning_flood_is_limited(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    p = tmp_path / "flood.log"
    p.write_text("junk\n" * 100 + "(1.0) can0 123#01\n")
    with caplog.at_level(logging.WARNING, logger="ptw_rt.io.candump"):
        reader = read_log(p, max_warnings=5)
        assert len(list(reader)) == 1
    assert reader.malformed == 100
    warnings = [r.getMessage() for r in caplog.records]
    assert len(warnings) == 6
    assert "95 more" in warnings[-1]


def test_binary_garbage_never_raises(tmp_path: Path) -> None:
    p = tmp_path / "bin.log"
    p.write_bytes(bytes(range(256)) * 4 + b"\n(1.0) can0 123#01\n\xff\xfe(2.0) can0 123#02\n")
    reader = read_log(p)
    frames = list(reader)
    assert [f.data for f in frames] == [b"\x01"]
    assert reader.malformed >= 1


@settings(max_examples=300, deadline=None)
@given(text=st.text(alphabet=st.sampled_from(list("()#.0123456789ABCDEFabcdefRTrtxXvcan \t\n-+_e")), max_size=200))
def test_reader_never_raises_on_random_text(text: str) -> None:
    reader = read_log(io.StringIO(text), max_warnings=0)
    frames = list(reader)
    n_lines = len(text.splitlines())
    assert reader.frames == len(frames)
    assert reader.frames + reader.malformed == n_lines
    for f in frames:
        assert len(f.data) <= 8 and 0 <= f.frame_id <= 0x1FFFFFFF


def test_missing_file_raises_file_not_found(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError):
        read_log(tmp_path / "missing.log")
