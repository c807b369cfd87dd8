"""Replay of a short simulated ride: decodable output, counts, determinism, CSV, malformed lines, parallel runs."""

from __future__ import annotations

import argparse
import csv
import io
import json
import shutil

import pytest

from ptw_rt.apps.replay import replay_log, run_replay
from ptw_rt.core.layout import ESTIMATE_NAMES
from ptw_rt.errors import UserFacingError
from ptw_rt.io.candump import read_log
from ptw_rt.io.dbc import FrameCodec
from ptw_rt.paths import DEFAULT_CONFIG


@pytest.fixture(scope="module")
def ride_log(tmp_path_factory):
    from ptw_rt.sim.recording import write_ride
    from ptw_rt.sim.ride import simulate

    d = tmp_path_factory.mktemp("ride")
    return write_ride(simulate("dlc_100", duration=5.0), d)["log"]


@pytest.fixture(scope="module")
def codec():
    return FrameCodec()


def _args(logs, out, csv_path=None, jobs=None):
    return argparse.Namespace(
        logs=list(logs), out=out, csv=csv_path, config=DEFAULT_CONFIG, design_file=None, jobs=jobs, no_progress=True
    )


def test_replay_output_decodable_and_counts(ride_log, codec, tmp_path):
    out = tmp_path / "out.log"
    csv_path = tmp_path / "out.csv"
    s = replay_log(ride_log, out, csv_path, DEFAULT_CONFIG)
    assert s["cycles"] == pytest.approx(500, abs=2)
    assert s["malformed_lines"] == 0
    frames = list(read_log(out))
    assert len(frames) == s["frames_out"]
    assert {f.channel for f in frames} == {"vcan0"}  # channel of the input log
    counts: dict[str, int] = {}
    for f in frames:
        name, _ = codec.decode_checked(f.frame_id, f.data)
        counts[name] = counts.get(name, 0) + 1
    for name in ("EST_Roll", "EST_RiderTorque", "EST_Lateral"):
        assert counts[name] == s["cycles"]
    assert counts["EST_Status"] == counts["EST_TireStiffness"] == (s["cycles"] + 9) // 10
    # stamped with log time: first cycle one sample time after the first input frame
    first_in = next(iter(read_log(ride_log))).timestamp
    assert frames[0].timestamp == pytest.approx(first_in + 0.01, abs=1e-6)
    assert "VALID" in s["modes"]
    with open(csv_path, newline="") as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["time", *ESTIMATE_NAMES]
    assert len(rows) == s["cycles"] + 1


def test_replay_is_deterministic(ride_log, tmp_path):
    a, b = tmp_path / "a.log", tmp_path / "b.log"
    replay_log(ride_log, a, tmp_path / "a.csv", DEFAULT_CONFIG)
    replay_log(ride_log, b, tmp_path / "b.csv", DEFAULT_CONFIG)
    assert a.read_bytes() == b.read_bytes()
    assert (tmp_path / "a.csv").read_bytes() == (tmp_path / "b.csv").read_bytes()


def test_malformed_lines_skipped_and_counted(ride_log, tmp_path, caplog):
    lines = ride_log.read_text().splitlines(keepends=True)
    bad = tmp_path / "bad.log"
    lines.insert(10, "this is not a candump line\n")
    lines.insert(20, "(1700001000.5) vcan0 100#XYZ\n")
    bad.write_text("".join(lines))
    s = replay_log(bad, tmp_path / "o.log", None, DEFAULT_CONFIG)
    assert s["malformed_lines"] == 2
    assert s["malformed_line_numbers"] == [11, 21]
    assert any("bad.log:11" in r.getMessage() for r in caplog.records)
    assert s["cycles"] == pytest.approx(500, abs=2)


def test_run_replay_single_file(ride_log, tmp_path):
    out = io.StringIO()
    assert run_replay(_args([ride_log], tmp_path / "single.log"), out=out, err=io.StringIO()) == 0
    summary = json.loads(out.getvalue().splitlines()[0])
    assert summary["cycles"] > 0 and (tmp_path / "single.log").is_file()


def test_run_replay_parallel_into_directory(ride_log, tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    for name in ("a.log", "b.log", "c.log"):
        shutil.copy(ride_log, src / name)
    out, err = io.StringIO(), io.StringIO()
    args = _args([src], tmp_path / "out", tmp_path / "csv", jobs=3)
    args.no_progress = False
    assert run_replay(args, out=out, err=err) == 0
    lines = [json.loads(x) for x in out.getvalue().splitlines()]
    assert [lines[i]["log"].rsplit("/", 1)[-1] for i in range(3)] == ["a.log", "b.log", "c.log"]
    assert "3/3" in err.getvalue()
    outs = [(tmp_path / "out" / n).read_bytes() for n in ("a.log", "b.log", "c.log")]
    assert outs[0] == outs[1] == outs[2]  # same input -> same bytes, whatever the process
    assert (tmp_path / "csv" / "a.csv").is_file()
    # ... and the same bytes as a replay in this process
    replay_log(ride_log, tmp_path / "here.log", None, DEFAULT_CONFIG)
    assert (tmp_path / "here.log").read_bytes() == outs[0]


def test_run_replay_user_errors(ride_log, tmp_path):
    with pytest.raises(UserFacingError):
        run_replay(_args([tmp_path / "missing.log"], tmp_path / "x.log"))
    with pytest.raises(UserFacingError):
        run_replay(_args([ride_log], ride_log))  # would overwrite its input
