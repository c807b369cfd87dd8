"""The compiled log-clocked cycle (``edge/drive.py`` over ``edge/tracking.py`` and ``edge/encoding.py``) against
the live cycle it must equal: every frame through ``CycleRunner.on_frame`` and every cycle through
``CycleRunner.run``, as the daemon does, driven by the clock rule of ``drive_log``'s docstring written out in
plain Python below (the specification). Same frames in, the same output frames (bytes), Estimates, input health
and clock statistics out, on a ride with every kind of bad input the rule and the tracker handle."""

from __future__ import annotations

import io
import math
import random

import numpy as np
import pytest

from ptw_rt.edge.cycle import (
    DEFAULT_MAX_GAP_S,
    DEFAULT_REORDER_TOLERANCE_S,
    DriveStats,
    SegmentBreak,
    build_runner,
    drive_log,
)
from ptw_rt.io.candump import CandumpReader, CandumpWriter, FrameArrays
from ptw_rt.io.dbc import FrameCodec
from ptw_rt.paths import DEFAULT_CONFIG
from ptw_rt.sim.recording import encode_frames
from ptw_rt.sim.ride import simulate


def reference_drive(frames, runner, max_gap=DEFAULT_MAX_GAP_S, tol=DEFAULT_REORDER_TOLERANCE_S):
    """The clock rule, frame by frame on the live cycle's calls. Returns (cycles [(now, frames, estimates)],
    segment breaks, late frames, bad stamps)."""
    cycles, breaks = [], []
    late = bad = 0
    it = iter(frames)
    pending = next(it, None)
    if pending is None:
        return cycles, breaks, late, bad
    dt = runner.sample_time
    t0 = newest = pending[0]
    k, now, closed, consumed, seg_cycles = 1, t0 + dt, -math.inf, False, 0

    def close(now):
        out = runner.run(now)
        cycles.append((now, out, runner.estimates.copy()))

    while True:
        if pending is not None:
            t = pending[0]
            if not newest - tol <= t <= newest + max_gap:
                if not math.isfinite(t):
                    bad += 1
                    pending = next(it, None)
                    continue
                if consumed or seg_cycles:
                    if consumed:
                        close(now)
                        consumed = False
                    breaks.append(("gap" if t > newest else "backwards", newest, t))
                    runner.restart_segment()
                t0 = newest = t
                k, now, closed, seg_cycles = 1, t0 + dt, -math.inf, 0
            if t <= now:
                runner.on_frame(t, pending[1], pending[2])
                consumed = True
                if t > newest:
                    newest = t
                elif t <= closed:
                    late += 1
                pending = next(it, None)
                continue
        elif not consumed:
            return cycles, breaks, late, bad
        close(now)
        closed, consumed = now, False
        seg_cycles += 1
        k += 1
        now = t0 + k * dt


def hostile_ride(seed: int, seconds: float = 12.0) -> list[tuple[float, int, object]]:
    """A simulated ride's frames with garbage payloads, wrong DLCs, unknown and 29-bit-sized ids, broken
    counters, reordering, late frames, non-finite stamps, exotic argument types, a bridged gap, a gap beyond
    --max-gap and a jump back."""
    rng = random.Random(seed)
    ride = simulate("slalom_30", duration=seconds)
    frames = list(encode_frames(ride, FrameCodec()))
    out: list[tuple[float, int, object]] = []
    shift = 0.0
    n = len(frames)
    for i, (t, fid, data) in enumerate(frames):
        if i == n // 4:
            shift += 2.0  # bridged
        elif i == n // 2:
            shift += 30.0  # a new segment
        elif i == 3 * n // 4:
            shift -= 20.0  # the clock going back
        t += shift
        r = rng.random()
        if r < 0.01:
            data = bytes(rng.randrange(256) for _ in range(len(data)))
        elif r < 0.0125:
            data = data[:-1]
        elif r < 0.015:
            data = data + b"\x00"  # longer than its DBC length: undecodable too
        elif r < 0.02:
            out.append((t, 0x123, b"\x01\x02"))
        elif r < 0.025 and out:
            out.insert(len(out) - 1, (t, fid, data))  # swapped with its predecessor
            continue
        elif r < 0.027:
            out.append((t - 0.015, fid, data))  # late
        elif r < 0.028:
            out.append((rng.choice([math.nan, math.inf]), fid, data))
        elif r < 0.029:
            out.append((t, float(fid), data))  # exotic id type: the codec's own checks
        elif r < 0.030:
            out.append((t, fid, memoryview(bytes(data))))
        elif r < 0.031:
            data = bytes([data[0] ^ 0xFF, *data[1:]]) if data else data
        out.append((t, fid, data))
    return out


@pytest.mark.parametrize("seed", [1, 2])
def test_compiled_drive_equals_the_live_cycle_frame_by_frame(seed):
    frames = hostile_ride(seed)
    live = build_runner(DEFAULT_CONFIG)
    ref_cycles, ref_breaks, ref_late, ref_bad = reference_drive(frames, live)

    compiled = build_runner(DEFAULT_CONFIG)
    got: list = []
    breaks: list[SegmentBreak] = []
    stats = DriveStats()
    n = drive_log(
        frames,
        compiled,
        lambda now, est: got[-1].append(est.copy()),
        on_frames=lambda now, out: got.append([now, out]),
        on_segment=breaks.append,
        stats=stats,
    )
    assert n == len(ref_cycles) == len(got) > 1000
    for (now, out, est), (now2, out2, est2) in zip(ref_cycles, got, strict=True):
        assert now == now2 and out == out2
        np.testing.assert_array_equal(est, est2)
    assert [(b.kind, b.t_from, b.t_to) for b in breaks] == ref_breaks and len(ref_breaks) == 2
    assert stats.late_frames == ref_late and stats.bad_stamps == ref_bad
    assert stats.late_frames > 0 and stats.bad_stamps > 0
    assert compiled.tracker.summary() == live.tracker.summary()
    summary = live.tracker.summary()
    assert summary["unknown_ids"] > 0 and summary["IMU_Rates"]["decode_errors"] > 0
    assert summary["IMU_Rates"]["counter_jumps"] > 0
    assert compiled.encoder.frames_sent == live.encoder.frames_sent
    # the runner is left as the live one: its next cycle is the same
    assert compiled.run(ref_cycles[-1][0] + 0.01) == live.run(ref_cycles[-1][0] + 0.01)


def test_drive_log_gives_each_cycle_its_sample():
    """Evaluation's peer reads the Sample of each cycle from the runner inside the callback."""
    frames = hostile_ride(3, seconds=4.0)
    live = build_runner(DEFAULT_CONFIG)
    expected = []
    real_step = live.estimator.step

    def spy(sample, estimates):
        expected.append(sample.copy())
        real_step(sample, estimates)

    live.estimator.step = spy
    reference_drive(frames, live)
    compiled = build_runner(DEFAULT_CONFIG)
    samples = []
    drive_log(frames, compiled, lambda now, est: samples.append(compiled.sample.copy()))
    np.testing.assert_array_equal(np.array(samples), np.array(expected))


def test_unpack_many_equals_unpack():
    codec = FrameCodec()
    rng = np.random.default_rng(4)
    for name in codec.input_messages:
        layout = codec.layout(name)
        data = rng.integers(0, 256, size=(500, 8), dtype=np.uint8)
        data[:, layout.length :] = 0
        values, ok = layout.unpack_many(data)
        assert ok.all()
        for row, v in zip(data, values, strict=True):
            assert list(v) == layout.unpack(row[: layout.length].tobytes())


@pytest.mark.parametrize("fixed_width", [False, True])
def test_write_frames_equals_write_cycle(tmp_path, fixed_width):
    """Many frames at once, the same bytes as cycle by cycle: any lengths and id widths, and the fixed-width
    block path (all frames 8 bytes, one id width: what replay writes), small stamps included."""
    rng = np.random.default_rng(5)
    times = (3.0 if fixed_width else 1_700_000_000.0) + np.cumsum(rng.uniform(0.0, 0.02, 50))
    counts = rng.integers(0, 4, 50)
    cycle_of = np.repeat(np.arange(50), counts)
    choices = [0x300, 0x301, 0x7FF, 0x0] if fixed_width else [0x300, 0x301, 0x7FF, 0x12345]
    ids = [int(i) for i in rng.choice(choices, cycle_of.size)]
    lengths = [8] * cycle_of.size if fixed_width else [int(n) for n in rng.integers(0, 9, cycle_of.size)]
    data = rng.integers(0, 256, size=(cycle_of.size, 8), dtype=np.uint8)
    a, b = tmp_path / "a.log", tmp_path / "b.log"
    with CandumpWriter(a, channel="vcan0") as w:
        w.write(1.0, 0x123, b"\x01")  # text written before and after the block (bytes to the file's buffer)
        w.write_frames(times, cycle_of, ids, data, lengths)
        w.write_frames(times[:0], cycle_of[:0], [], data[:0], [])
        w.write(2.0, 0x124, b"\x02")
    with CandumpWriter(b, channel="vcan0") as w:
        w.write(1.0, 0x123, b"\x01")
        for c, now in enumerate(times.tolist()):
            rows = np.flatnonzero(cycle_of == c)
            w.write_cycle(now, [(ids[i], data[i, : lengths[i]].tobytes()) for i in rows])
        w.write(2.0, 0x124, b"\x02")
    assert a.read_text() == b.read_text() and a.stat().st_size > 0
    stream = io.StringIO()  # a stream without a byte buffer: the same text
    with CandumpWriter(stream, channel="vcan0") as w:
        w.write(1.0, 0x123, b"\x01")
        w.write_frames(times, cycle_of, ids, data, lengths)
        w.write(2.0, 0x124, b"\x02")
    assert stream.getvalue() == b.read_text()


def _as_columns(frames):
    return FrameArrays.of([f for f in frames if not f.is_remote], [])


def test_candump_columns_equal_the_frame_by_frame_reader(tmp_path):
    """CandumpReader.arrays (whole blocks of plain lines as columns) gives what iterating the reader gives:
    frames, order, counts, discontinuities, on a log of plain lines with outliers, reordering, gaps and jumps
    back, and on one with malformed lines among them."""
    rng = random.Random(7)
    lines = []
    t = 1_700_000_000.0
    for i in range(60000):
        t += 0.0033
        if i % 9000 == 8999:
            t += rng.choice([3.0, -25.0, 0.5, 40.0])
        r = rng.random()
        stamp = t
        if r < 0.003:
            stamp = t + rng.choice([100.0, -100.0, 2.0, -0.01, 0.015])
        fid = rng.choice(["100", "101", "102", "110", "12345678"])
        lines.append(f"({stamp:.6f}) vcan0 {fid}#{rng.randbytes(rng.randrange(9)).hex().upper()}")
        if r > 0.998:
            lines.append(lines[-1])
    plain = tmp_path / "plain.log"
    plain.write_text("\n".join(lines) + "\n")
    mixed = tmp_path / "mixed.log"
    mixed.write_text("\n".join(line if k % 997 else "garbage \x00" for k, line in enumerate(lines)) + "\n")
    for path in (plain, mixed):
        one_by_one = CandumpReader(path, max_warnings=None)
        frames = list(one_by_one)
        columns = CandumpReader(path, max_warnings=None)
        blocks = list(columns.arrays())
        assert len(blocks) > 1
        whole = blocks[0]
        for block in blocks[1:]:
            whole = whole.concat(block)
        expected = _as_columns(frames)
        for a, b in zip(whole[:5], expected[:5], strict=True):
            np.testing.assert_array_equal(a, b)
        for count in ("frames", "malformed", "rejected", "reordered", "discontinuities", "discontinuity_lines"):
            assert getattr(columns, count) == getattr(one_by_one, count), count
        assert one_by_one.discontinuities > 2 and one_by_one.reordered > 0
        # each discontinuity starts at the frame it names
        assert [(j.line_no, j.t_to) for j in whole.jumps] == [
            (line, to) for line, _, to in one_by_one.discontinuity_lines
        ]
        assert all(whole.times[j.index] == j.t_to for j in whole.jumps)


_ENCODE_SCRIPT = """
import json, sys
import numpy as np
from ptw_rt.edge.outputs import OutputEncoder
from ptw_rt.io.dbc import FrameCodec
rng = np.random.default_rng(11)
enc = OutputEncoder(FrameCodec())
out = []
for k in range(300):
    est = rng.uniform(-5e4, 5e4, SIZE) * rng.choice([1e-5, 1e-3, 1.0], SIZE)
    est[MODE] = rng.integers(0, 5)
    est[VALID] = rng.integers(0, 1 << 12)
    status = {"overrun_count": k, "cycle_time_us": 3 * k}
    out.append([[fid, data.hex()] for fid, data in enc.frames(est, k, status, k % 16)])
print(json.dumps(out))
"""


def test_the_encoder_is_the_same_with_numba_off():
    """The compiled functions are plain Python when numba is off (NUMBA_DISABLE_JIT=1: debugging, the bench's
    no-JIT figure): the same frames, bit for bit, the 64-bit words included."""
    import json
    import os
    import subprocess
    import sys

    from ptw_rt.core.layout import E_MODE, E_VALID, ESTIMATES_SIZE

    script = _ENCODE_SCRIPT.replace("MODE", str(E_MODE)).replace("VALID", str(E_VALID))
    script = script.replace("SIZE", str(ESTIMATES_SIZE))
    runs = []
    for off in ("0", "1"):
        env = dict(os.environ, NUMBA_DISABLE_JIT=off)
        done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=300)
        assert done.returncode == 0, done.stderr[-2000:]
        runs.append(json.loads(done.stdout))
    assert runs[0] == runs[1] and len(runs[0]) == 300
