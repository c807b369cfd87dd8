"""Replay treats a log's time as untrusted data: segments at long gaps and jumps back, out-of-order frames by
rule and counted, output bounded by the log's content; output errors and bad logs of a directory run in one line.

In-process (one runner for the module): ``test_hostile_cli.py`` runs the same cases as subprocesses.
"""

from __future__ import annotations

import argparse
import io
import json
import logging
import math

import numpy as np
import pytest

from ptw_rt.apps import replay as replay_app
from ptw_rt.apps.replay import ReplayOutputError, replay_log, run_replay
from ptw_rt.edge.cycle import DriveStats, build_runner, drive_log
from ptw_rt.errors import EXIT_OUTPUT, EXIT_PARTIAL, UserFacingError
from ptw_rt.io.candump import read_log
from ptw_rt.paths import DEFAULT_CONFIG

from .conftest import LOG_EPOCH, clean_log_lines, shifted

CLEAN_S = 2.0  # seconds of content of every clean block in the fixtures
CLEAN_CYCLES = int(CLEAN_S * 100)


@pytest.fixture(scope="module")
def runner():
    r = build_runner(DEFAULT_CONFIG)
    r.cycle(0.0)  # compile / load the jitted step once
    return r


def _replay(path, tmp_path, runner, caplog=None, **kw):
    runner.estimator.reset()
    out = tmp_path / f"{path.stem}.out.log"
    return replay_log(path, out, None, DEFAULT_CONFIG, runner=runner, **kw), out


def _args(logs, out, **kw):
    base = dict(logs=list(logs), out=out, csv=None, config=DEFAULT_CONFIG, design_file=None, jobs=2, no_progress=True)
    base.update(kw)
    return argparse.Namespace(**base)


def _lines(caplog, text):
    return [r.getMessage() for r in caplog.records if text in r.getMessage()]


# ---------------------------------------------------------------------- segments


def test_two_hour_gap_is_two_segments_not_720k_cycles(hostile_logs, tmp_path, runner, caplog):
    with caplog.at_level(logging.WARNING):
        s, out = _replay(hostile_logs["gap_2h"], tmp_path, runner)
    assert s["segments"] == 2 and s["discontinuities"] == 1
    assert abs(s["cycles"] - 2 * CLEAN_CYCLES) <= 2  # the log's content, not its 2 h span
    assert out.stat().st_size < 200_000
    assert s["log_duration_s"] == pytest.approx(2 * CLEAN_S, abs=0.05)
    lines = _lines(caplog, "segment 2 starts")
    assert len(lines) == 1 and "+7200.0" in lines[0] and "gap2h.log:601:" in lines[0], lines
    assert not _lines(caplog, "discontinuity of the log")  # the reader's own line is not printed as well
    stamps = [f.timestamp for f in read_log(out)]
    assert stamps == sorted(stamps) and stamps[-1] - stamps[0] > 7200


def test_jump_back_is_a_new_segment(hostile_logs, tmp_path, runner, caplog):
    with caplog.at_level(logging.WARNING):
        s, _ = _replay(hostile_logs["backwards_30s"], tmp_path, runner)
    assert s["segments"] == 2 and abs(s["cycles"] - 2 * CLEAN_CYCLES) <= 2
    (line,) = _lines(caplog, "segment 2 starts")
    assert "clock going back" in line and "-3" in line


def test_gap_within_max_gap_is_bridged_in_one_line(hostile_logs, tmp_path, runner, caplog):
    with caplog.at_level(logging.WARNING):
        s, _ = _replay(hostile_logs["gap_3s"], tmp_path, runner)
    assert s["segments"] == 1 and s["discontinuities"] == 1
    assert abs(s["cycles"] - (2 * CLEAN_CYCLES + 300)) <= 3  # 3 s driven through, cycle by cycle
    (line,) = _lines(caplog, "bridged")
    assert "+3.0" in line and "gap3s.log:601:" in line
    # the same log with a shorter --max-gap: two segments
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        s, _ = _replay(hostile_logs["gap_3s"], tmp_path, runner, max_gap=1.0)
    assert s["segments"] == 2 and abs(s["cycles"] - 2 * CLEAN_CYCLES) <= 2
    assert len(_lines(caplog, "segment 2 starts")) == 1 and not _lines(caplog, "bridged")


def test_out_of_order_frames_by_rule_and_counted(hostile_logs, tmp_path, runner):
    s, _ = _replay(hostile_logs["swapped_pairs"], tmp_path, runner)
    n = len(clean_log_lines())
    assert s["frames_in"] == n and s["malformed_lines"] == 0  # within 20 ms: taken, not rejected
    assert s["reordered"] >= n // 6 - 1
    assert s["segments"] == 1 and abs(s["cycles"] - CLEAN_CYCLES) <= 2
    # a block stamped 5 s in the past: rejected as out of order, counted by reason
    s, _ = _replay(hostile_logs["block_5s_in_past"], tmp_path, runner)
    assert s["rejected"] == {"out_of_order": 5} and s["segments"] == 1


def test_summary_reports_the_clock(hostile_logs, tmp_path, runner):
    s, _ = _replay(hostile_logs["stray_zero_first"], tmp_path, runner)
    for key in ("rejected", "reordered", "discontinuities", "segments", "late_frames", "segment_breaks"):
        assert key in s
    assert s["rejected"] == {"time_jump": 1} and s["segments"] == 1


# ---------------------------------------------------------------------- drive_log itself


def _frames(t0: float, seconds: float, ids=(0x100, 0x101, 0x102)):
    data = {0x100: bytes(7), 0x101: bytes(7), 0x102: bytes(2)}
    return [(t0 + k * 0.01 + j * 1e-4, fid, data[fid]) for k in range(int(seconds * 100)) for j, fid in enumerate(ids)]


def test_drive_log_segments_keep_learned_stiffness(runner):
    est = runner.estimator
    est.reset()
    learned = est.design.ad_theta_nominal * 1.1
    est.restore_stiffness(learned)
    resets = []
    real_restart = runner.restart_segment

    def restart():
        resets.append(runner.cycles)
        real_restart()

    runner.restart_segment = restart
    try:
        stats = DriveStats()
        frames = _frames(LOG_EPOCH, 1.0) + _frames(LOG_EPOCH + 3600, 1.0) + _frames(LOG_EPOCH + 10, 1.0)
        breaks = []
        n = drive_log(frames, runner, on_segment=breaks.append, stats=stats)
    finally:
        del runner.restart_segment
    assert n == pytest.approx(300, abs=3)
    assert stats.segments == 3 and [b.kind for b in breaks] == ["gap", "backwards"] and len(resets) == 2
    assert breaks[0].jump == pytest.approx(3599.0, abs=0.02)
    np.testing.assert_allclose(est.learned_stiffness(), learned)  # reset() keeps what was learned


def test_drive_log_bounded_and_late_frames(runner):
    runner.estimator.reset()
    stats = DriveStats()
    frames = _frames(LOG_EPOCH, 0.5)
    # one frame 15 ms late: after the cycle its stamp belongs to has closed
    late = (LOG_EPOCH + 0.2 - 0.015, 0x100, bytes(7))
    frames.insert(3 * 20 + 1, late)
    frames.insert(5, (math.nan, 0x100, bytes(7)))
    frames.insert(7, (math.inf, 0x100, bytes(7)))
    n = drive_log(frames, runner, stats=stats)
    assert stats.segments == 1 and stats.bad_stamps == 2
    assert stats.late_frames == 1
    assert n == pytest.approx(50, abs=2)


def test_drive_log_rejects_a_non_positive_max_gap(runner):
    with pytest.raises(ValueError):
        drive_log([], runner, max_gap=0.0)


# ---------------------------------------------------------------------- output errors, directory runs


@pytest.mark.parametrize(
    "target, text",
    [
        ("/dev/full", "No space left on device"),
        ("{tmp}", "is a directory"),
        ("{log}/x.log", "not a directory"),
        ("/sys/ptw-rt-replay.log", "cannot write /sys/ptw-rt-replay.log"),
    ],
)
def test_output_errors_are_one_line(target, text, hostile_logs, tmp_path, runner):
    log = hostile_logs["gap_3s"]
    out = target.format(tmp=tmp_path, log=log)
    with pytest.raises(ReplayOutputError, match=text) as info:
        run_replay(_args([log], replay_app.Path(out)), out=io.StringIO(), err=io.StringIO())
    assert info.value.exit_code == EXIT_OUTPUT == 74
    assert "\n" not in str(info.value)


def test_csv_output_error_leaves_no_half_written_output(hostile_logs, tmp_path, runner):
    """The CSV fails on a full disk mid-log: the output log, written up to there, was left to pass for a ride."""
    with pytest.raises(ReplayOutputError, match="/dev/full"):
        replay_log(hostile_logs["gap_3s"], tmp_path / "o.log", "/dev/full", DEFAULT_CONFIG, runner=runner)
    assert not (tmp_path / "o.log").exists()
    assert replay_app.Path("/dev/full").exists()  # a device is never removed


def test_an_output_failing_mid_log_is_removed(hostile_logs, tmp_path, runner, monkeypatch):
    """The output log's disk fills after its first chunk: neither it nor the CSV is left behind."""
    real = replay_app.open_writer
    calls = {"n": 0}

    def filling(path, **kw):
        writer = real(path, **kw)
        write = writer.write_frames

        def write_frames(*a):
            calls["n"] += 1
            write(*a)  # written, then the disk is full
            raise OSError(28, "No space left on device")

        writer.write_frames = write_frames
        return writer

    monkeypatch.setattr(replay_app, "open_writer", filling)
    with pytest.raises(ReplayOutputError, match="No space left"):
        replay_log(hostile_logs["gap_3s"], tmp_path / "o.log", tmp_path / "o.csv", DEFAULT_CONFIG, runner=runner)
    assert calls["n"] == 1
    assert not (tmp_path / "o.log").exists() and not (tmp_path / "o.csv").exists()


def test_non_regular_input_named_as_such(hostile_logs, tmp_path):
    for name, kind in (("dev_zero", "character device"), ("fifo", "FIFO")):
        with pytest.raises(UserFacingError, match=f"is a {kind}.*not a regular file"):
            run_replay(_args([hostile_logs[name]], tmp_path / "o.log"))


def test_bad_log_in_a_directory_run_never_stops_the_others(hostile_logs, tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    for name in ("gap_2h", "gap_3s", "swapped_pairs"):
        (src / f"{name}.log").write_bytes(hostile_logs[name].read_bytes())
    out_dir = tmp_path / "out"
    (out_dir / "gap_3s.log").mkdir(parents=True)  # its output cannot be written
    out, err = io.StringIO(), io.StringIO()
    assert run_replay(_args([src], out_dir), out=out, err=err) == EXIT_PARTIAL == 1
    summaries = [json.loads(line) for line in out.getvalue().splitlines()]
    by_name = {s["log"].rsplit("/", 1)[-1]: s for s in summaries}
    assert set(by_name) == {"gap_2h.log", "gap_3s.log", "swapped_pairs.log"}
    assert "is a directory" in by_name["gap_3s.log"]["error"]
    assert by_name["gap_2h.log"]["segments"] == 2 and by_name["swapped_pairs.log"]["cycles"] > 0
    assert "1 of 3 logs failed" in err.getvalue()


def test_a_stale_line_of_a_list_never_stops_the_others(hostile_logs, tmp_path):
    """A fleet's --list of thousands with one missing, one FIFO: those two fail on their own (exit 1), the rest
    are replayed (it stopped the whole run with exit 2; found by fuzzing, 2026-11-26)."""
    good = tmp_path / "good.log"
    good.write_bytes(hostile_logs["gap_3s"].read_bytes())
    listing = tmp_path / "logs.txt"
    listing.write_text(f"{good}\n{tmp_path / 'gone.log'}\n{hostile_logs['fifo']}\n")
    out, err = io.StringIO(), io.StringIO()
    args = _args([], tmp_path / "out")
    args.list = listing
    assert run_replay(args, out=out, err=err) == EXIT_PARTIAL
    by_name = {s["log"].rsplit("/", 1)[-1]: s for s in map(json.loads, out.getvalue().splitlines())}
    assert by_name["good.log"]["cycles"] > 0
    assert "not found" in by_name["gone.log"]["error"]
    assert "not a regular file" in by_name[hostile_logs["fifo"].name]["error"]
    assert "2 of 3 logs failed" in err.getvalue()


def test_worker_exception_becomes_the_logs_error(monkeypatch, tmp_path):
    def boom(*a, **kw):
        raise RuntimeError("simulated bug\nsecond line")

    monkeypatch.setattr(replay_app, "replay_log", boom)
    result = replay_app.replay_job(tmp_path / "a.log", tmp_path / "o.log", None, DEFAULT_CONFIG, None, 5.0)
    expected = "internal error: RuntimeError: simulated bug second line"  # one line
    assert result == {"log": str(tmp_path / "a.log"), "error": expected}


def test_max_gap_option_checked(hostile_logs, tmp_path):
    # beyond 60 s a gap is driven cycle by cycle without bound (1e9: 700 MB in 20 s); below 0.1 s a segment per frame
    for bad in (0.0, -1.0, math.nan, math.inf, 1e9, 61.0, 1e-300, 0.05):
        with pytest.raises(UserFacingError, match="--max-gap"):
            run_replay(_args([hostile_logs["gap_3s"]], tmp_path / "o.log", max_gap=bad))


@pytest.mark.parametrize(
    ("kind", "rewrite"),
    [
        ("29-bit", lambda line: line.replace(" 10", " 0000010", 1)),  # the same frames with 29-bit ids
        ("other ids", lambda line: line.replace(" 10", " 70", 1)),  # frames of another bus
    ],
)
def test_a_log_of_no_frame_the_estimator_reads_is_refused_not_replayed_as_all_fault(kind, rewrite, tmp_path, runner):
    """It exited 0, every cycle FAULT (or no cycle at all), nothing said: one line, exit 2, no output left."""
    path = tmp_path / "another_bus.log"
    path.write_text("\n".join(rewrite(line) for line in clean_log_lines()) + "\n")
    with pytest.raises(UserFacingError, match="none of its 600 frames is one the estimator reads") as info:
        _replay(path, tmp_path, runner)
    assert info.value.exit_code == 2 and "\n" not in str(info.value)
    assert not (tmp_path / "another_bus.out.log").exists()
    assert ("600 of the 29-bit ones carry an input's 11-bit id" in str(info.value)) == (kind == "29-bit")


def test_inputs_flagged_29_bit_on_part_of_a_log_are_said_once(tmp_path, runner, caplog):
    """A logger that flags some frames extended: half the inputs skipped, the ride DEGRADED, only a count in the
    JSON. Now one warning line names it (and the 29-bit frames never count as time stamps of the bus)."""
    lines = clean_log_lines()
    path = tmp_path / "half_extended.log"
    path.write_text("\n".join(ln.replace(" 10", " 0000010", 1) if k % 2 else ln for k, ln in enumerate(lines)) + "\n")
    with caplog.at_level(logging.WARNING):
        s, _ = _replay(path, tmp_path, runner)
    assert s["extended_input_frames"] == 300 and s["skipped_frames"] == 300
    (line,) = _lines(caplog, "flagged 29-bit carry the id of an 11-bit input")
    assert "300 frames" in line and "0x100" in line
    assert not _lines(caplog, "not the time stamps of a recorded bus")
    clean = tmp_path / "clean.log"
    clean.write_text("\n".join(lines) + "\n")
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        s, _ = _replay(clean, tmp_path, runner)
    assert s["extended_input_frames"] == 0 and not _lines(caplog, "flagged 29-bit")


def test_a_log_whose_time_stamps_are_all_equal_is_said(tmp_path, runner, caplog):
    """Every frame in one cycle, exit 0 and nothing said: now one warning line (the replay itself is bounded)."""
    path = tmp_path / "one_instant.log"
    path.write_text("\n".join(f"({LOG_EPOCH:017.6f}) {line.split(') ', 1)[1]}" for line in clean_log_lines()) + "\n")
    with caplog.at_level(logging.WARNING):
        s, _ = _replay(path, tmp_path, runner)
    assert s["cycles"] <= 2 and s["frames_in"] == 600
    (line,) = _lines(caplog, "not the time stamps of a recorded bus")
    assert "600 frames in" in line


def test_an_output_that_is_a_fifo_is_refused_not_waited_on(hostile_logs, tmp_path):
    """Opening a FIFO for writing waits for a reader: replay hung with nothing said. One line, exit 74."""
    import os

    fifo = tmp_path / "out.log"
    os.mkfifo(fifo)
    with pytest.raises(ReplayOutputError, match="FIFO") as info:
        run_replay(_args([hostile_logs["gap_3s"]], fifo))
    assert info.value.exit_code == EXIT_OUTPUT


# ---------------------------------------------------------------------- paths (found by fuzzing, 2026-12-07)


def test_an_output_hard_linked_to_its_input_is_refused_and_the_input_kept(hostile_logs, tmp_path):
    """The overwrite check compared resolved paths only: a hard link (or a bind mount) of the input as --out or
    --csv was truncated while read, 25 139 of 93 000 frames replayed, exit 0, the recording gone."""
    src = tmp_path / "ride.log"
    src.write_bytes(hostile_logs["gap_3s"].read_bytes())
    before = src.read_bytes()
    (tmp_path / "out.log").hardlink_to(src)
    (tmp_path / "est.csv").hardlink_to(src)
    for out, csv in ((tmp_path / "out.log", None), (tmp_path / "other.log", tmp_path / "est.csv")):
        with pytest.raises(UserFacingError, match="would overwrite its input log"):
            run_replay(_args([src], out, csv=csv), out=io.StringIO(), err=io.StringIO())
    assert src.read_bytes() == before


def test_a_symlink_loop_is_one_line_wherever_a_path_is_compared(hostile_logs, tmp_path):
    """Path.resolve() raised RuntimeError on a loop: a traceback from replay's output checks, the directory walk,
    `design --out` and `--design-file` (found by fuzzing)."""
    from ptw_rt.untrusted import same_file

    (tmp_path / "loop_a").symlink_to(tmp_path / "loop_b")
    (tmp_path / "loop_b").symlink_to(tmp_path / "loop_a")
    src = tmp_path / "ride.log"
    src.write_bytes(hostile_logs["gap_3s"].read_bytes())
    assert not same_file(tmp_path / "loop_a", src) and same_file(tmp_path / "loop_a", tmp_path / "loop_a")
    with pytest.raises(UserFacingError, match="Too many levels of symbolic links"):  # an output error: exit 74
        run_replay(_args([src], tmp_path / "loop_a"), out=io.StringIO(), err=io.StringIO())
    out, err = io.StringIO(), io.StringIO()
    assert run_replay(_args([src, tmp_path / "loop_b"], tmp_path / "out"), out=out, err=err) == EXIT_PARTIAL


def test_a_listed_directory_without_logs_fails_on_its_own(hostile_logs, tmp_path):
    """It stopped the whole fleet (exit 2, nothing replayed) though the README says a bad entry fails alone."""
    good = tmp_path / "good.log"
    good.write_bytes(hostile_logs["gap_3s"].read_bytes())
    (tmp_path / "empty").mkdir()
    listing = tmp_path / "logs.txt"
    listing.write_text("good.log\nempty\n")
    out, err = io.StringIO(), io.StringIO()
    args = _args([], tmp_path / "out")
    args.list = listing
    assert run_replay(args, out=out, err=err) == EXIT_PARTIAL
    by_name = {s["log"].rsplit("/", 1)[-1]: s for s in map(json.loads, out.getvalue().splitlines())}
    assert by_name["good.log"]["cycles"] > 0 and "no CAN logs in directory" in by_name["empty"]["error"]


def test_a_list_line_longer_than_any_path_is_refused_in_one_line(tmp_path):
    """A 16 MB line was echoed whole in the error line and the fleet CSV (546 MB peak)."""
    listing = tmp_path / "logs.txt"
    listing.write_text("a.log\n" + "x" * 100_000 + "\n")
    args = _args([], tmp_path / "out")
    args.list = listing
    with pytest.raises(UserFacingError, match=r"logs.txt:2: a path of 100000 characters") as info:
        run_replay(args, out=io.StringIO(), err=io.StringIO())
    assert len(str(info.value)) < 300


def test_a_log_named_with_a_newline_cannot_forge_an_error_line(tmp_path):
    """A file in a replayed directory named "bad<newline>error: a.log: ..." printed a line of its own that read as
    another log's error."""
    src = tmp_path / "in"
    src.mkdir()
    (src / "a.log").write_text("\n".join(clean_log_lines(1.0)) + "\n")
    (src / "bad\nerror: a.log: forged.log").write_text("not a log\n")
    out, err = io.StringIO(), io.StringIO()
    assert run_replay(_args([src], tmp_path / "out"), out=out, err=err) == EXIT_PARTIAL
    lines = err.getvalue().splitlines()
    assert not any(line.startswith("error: a.log") for line in lines), lines
    assert sum(line.startswith("error: ") for line in lines) == 1


def test_segment_lines_are_capped_like_the_readers_bad_lines(tmp_path, runner, caplog):
    """A log of short bursts 6 s apart printed one warning per segment (23 000 lines for 7.7 MB)."""
    from ptw_rt.io.candump import MAX_RECORDED

    lines = []
    for k in range(MAX_RECORDED + 50):
        lines += shifted(clean_log_lines(0.05), 6.0 * k)  # 15 frames: the time rule confirms a new base after 8
    path = tmp_path / "bursts.log"
    path.write_text("\n".join(lines) + "\n")
    with caplog.at_level(logging.WARNING):
        s, _ = _replay(path, tmp_path, runner)
    assert s["segments"] == MAX_RECORDED + 50
    segment_lines = _lines(caplog, "segment")
    assert len(segment_lines) == MAX_RECORDED + 1 and "49 more segments" in segment_lines[-1]


def test_a_log_of_two_buses_says_so(tmp_path, runner, caplog):
    """Every frame again on a second channel (`candump -L any` of two buses): read as one bus, every cycle stayed
    INIT, exit 0 and nothing said (found by fuzzing). Now the inputs' bus is read and one line names the other
    channel and how to pick one (`test_logformats.py`: the estimates those of the one bus, in every format)."""
    lines = []
    for line in clean_log_lines(1.0):
        lines += [line, shifted([line], 0.0001)[0].replace(" vcan0 ", " vcan1 ")]
    path = tmp_path / "two_buses.log"
    path.write_text("\n".join(lines) + "\n")
    with caplog.at_level(logging.WARNING):
        _replay(path, tmp_path, runner)
    said = _lines(caplog, "other channels")
    assert len(said) == 1 and "300 frames on other channels (vcan1) than the bus read, vcan0" in said[0], said
    caplog.clear()
    single = tmp_path / "one_bus.log"
    single.write_text("\n".join(clean_log_lines(1.0)) + "\n")
    with caplog.at_level(logging.WARNING):
        _replay(single, tmp_path, runner)
    assert not _lines(caplog, "other channels")
