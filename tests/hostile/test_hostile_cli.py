"""The command line against hostile files: every subcommand that takes a file, as a real subprocess under a
1.5 GiB address-space limit and a timeout: exit code 2, exactly one line on stderr, never "Traceback".

Subprocesses cost 1-2 s each (numba import), so each subcommand meets one or two hostile files here (run three
at a time); the in-process tests (test_hostile_readers.py) put every fixture through every reader.
"""

from __future__ import annotations

import json

import pytest

from .conftest import run_cli, run_many

TIMEOUT = 90.0
# on a cold numba cache the subprocesses would each compile the estimator (and say so on stderr): once, here, first
pytestmark = pytest.mark.usefixtures("warm_numba_cache")


def _assert_one_line_refusal(args, returncode, out, err, seconds, expected_rc=2):
    where = f"ptw-rt {' '.join(map(str, args))}"
    assert returncode is not None, f"{where}: killed after {seconds:.0f} s (timeout)"
    assert "Traceback" not in out + err, f"{where}:\n{err[-3000:]}"
    # demo announces its simulation before it reads the configuration (runtime/demo.py): a progress note, not an error
    lines = [line for line in err.splitlines() if line.strip() and not line.startswith("simulating ")]
    assert len(lines) == 1, f"{where}: stderr has {len(lines)} lines:\n{err[-3000:]}"
    assert len(lines[0]) < 500, f"{where}: a {len(lines[0])}-character message"
    assert lines[0].startswith(f"ptw-rt {args[0]}"), f"{where}: {lines[0]}"
    assert returncode == expected_rc, f"{where}: exit {returncode}, stderr: {err[-500:]}"


def test_every_subcommand_refuses_hostile_files(hostile_configs, hostile_designs, hostile_logs, tmp_path):
    c = hostile_configs
    d = hostile_designs
    log = hostile_logs["digits_400"]
    out = tmp_path
    commands = [
        (["analyze", "--config", c["alias_bomb_as_value"]], 2),
        (["design", "--config", c["nested_brackets"], "--out", out / "d.npz"], 2),
        # a design file to fix first, as `run` and `evaluate` say; exit 1 is "the design is not stable"
        (["design", "--check", "--design-file", d["zip_bomb"]], 2),
        (["simulate", "--scenario", "dlc_50", "--config", c["non_utf8"], "--out", out / "sim"], 2),
        (["simulate", "--scenario", "dlc_50", "--config", c["dev_zero"], "--out", out / "sim"], 2),  # not "not found"
        (["evaluate", "--scenario", "dlc_50", "--config", c["dev_zero"]], 2),
        (["evaluate", "--scenario", "dlc_50", "--design-file", d["shape_lie"]], 2),
        (["report", "--scenario", "dlc_50", "--config", c["fifo"], "--out", out / "rep"], 2),
        (["report", "--scenario", "dlc_50", "--design-file", d["pickle"], "--out", out / "rep"], 2),
        (["run", "--check-config", "--config", c["alias_bomb"]], 2),
        (["run", "--check-config", "--config", c["huge_sparse"]], 2),
        (["run", "--check-config", "--design-file", d["fifo"]], 2),
        (["run", "--check-config", "--config", c["state_file_nul"]], 2),  # was exit 0, then a traceback at run
        (["run", "--check-config", "--state-file", ""], 2),  # was the current directory
        (["run", "--check-config", "--state-file", "s" * 5000], 2),  # runtime.state_file's bound, on the command line
        (["replay", log, "--out", out / "r.log", "--config", c["directory"]], 2),
        (["replay", log, "--out", out / "r.log", "--design-file", d["size_lie"]], 2),
        (["replay", hostile_logs["dev_zero"], "--out", out / "z.log"], 2),
        (["replay", hostile_logs["fifo"], "--out", out / "f.log"], 2),
        # replay's outputs: one line, exit 74 (EX_IOERR)
        (["replay", hostile_logs["gap_2h"], "--out", "/dev/full"], 74),
        (["replay", hostile_logs["gap_2h"], "--out", "/sys/ptw-rt-hostile.log"], 74),
        (["replay", hostile_logs["gap_2h"], "--out", out], 74),
        (["replay", hostile_logs["swapped_pairs"], "--out", out / "c.log", "--csv", "/dev/full"], 74),
        (["replay", log, "--out", out / "g.log", "--max-gap", "nan"], 2),
        (["replay", log, "--out", out / "k.log", "--channel", "vcan0\nerror: forged"], 2),
        (["replay", log, "--out", out / "k.log", "--channel", "c" * 100], 2),
        (["replay", log, "--out", out / "k.log", "--channel", "nosuch"], 2),  # none of the log's buses
        (["demo", "--config", c["long_bad_text"], "--out", out / "demo"], 2),
        # within the schema's ranges, no design / no simulated rider: one line, not numpy's traceback
        (["design", "--config", c["grid_too_fine"], "--out", out / "d.npz"], 2),
        (["design", "--config", c["no_design"], "--out", out / "d.npz"], 2),
        (["simulate", "--scenario", "dlc_50", "--duration", "2", "--config", c["no_design"], "--out", out / "s"], 2),
        (["design", "--config", c["duplicate_key"], "--out", out / "d.npz"], 2),
        (["replay", log, "--out", out / "n.log", "--design-file", d["nan_table"]], 2),
        (["replay", log, "--out", out / "j.log", "--jobs", "0"], 2),
        # arguments that reached numpy or the simulator's first sample as a traceback
        (["simulate", "--scenario", "dlc_50", "--duration", "0.001", "--out", out / "s"], 2),
        (["evaluate", "--scenario", "dlc_50", "--seed", "-1"], 2),
        (["analyze", "--speeds", "nan,inf"], 2),
        # outputs that cannot be written: one line, exit 74 like replay's (a file where a directory is asked for)
        (["simulate", "--scenario", "dlc_50", "--duration", "2", "--out", log], 74),
        (["report", "--scenario", "dlc_50", "--out", log], 74),
        # a rename over a directory (or, as root, a device or a FIFO) replaced it: refused before designing
        (["design", "--out", out], 74),
        (["demo", "--speed", "1e308", "--out", out / "demo"], 2),  # was a traceback
        (["replay", log, "--out", out / "same.log", "--csv", out / "same.log"], 2),  # one overwrote the other
    ]
    results = run_many([args for args, _ in commands], cwd=tmp_path, timeout=TIMEOUT)
    expected = {tuple(map(str, args)): rc for args, rc in commands}
    for args, returncode, stdout, stderr, seconds in results:
        _assert_one_line_refusal(args, returncode, stdout, stderr, seconds, expected[tuple(map(str, args))])


def test_replay_of_hostile_logs_rejects_lines_and_finishes(hostile_logs, tmp_path):
    """A directory of logs with hostile lines: every CAN log replayed, every bad line counted, no traceback; the
    two that are no CAN log fail alone (exit code 1)."""
    names = [
        "digits_400",
        "digits_200_everywhere",
        "inf_first",
        "nan_and_inf",
        "stray_zero_first",
        "far_future_line",
        "year_2286_line",
        "negative",
        "reversed",
        "block_5s_in_past",
        "long_line",
        "random_bytes",
        "empty",
        "gap_2h",
        "gap_3s",
        "backwards_30s",
        "swapped_pairs",
    ]
    src = tmp_path / "logs"
    src.mkdir()
    for name in names:
        (src / f"{name}.log").write_bytes(hostile_logs[name].read_bytes())
    proc = run_cli(["replay", src, "--out", tmp_path / "out", "--jobs", "2", "--no-progress"], tmp_path, TIMEOUT)
    assert "Traceback" not in proc.stdout + proc.stderr, proc.stderr[-3000:]
    # random bytes are not a CAN log, an empty file is no log: each one `error:` line and a summary line with its
    # error, the others replayed; a partial failure of a directory run is exit code 1 (EXIT_PARTIAL)
    assert proc.returncode == 1, proc.stderr[-2000:]
    errors = sorted(line for line in proc.stderr.splitlines() if line.startswith("error: "))
    assert errors == [
        f"error: {src / 'empty.log'}: empty log (0 bytes)",
        f"error: {src / 'random_bytes.log'}: not a CAN log "
        "(no candump/ASC/BLF/TRC/CSV/MF4/SQLite/candump -t/python-can text frame in the first 64 KiB)",
    ], proc.stderr[-2000:]
    summaries = {json.loads(line)["log"].rsplit("/", 1)[-1][:-4]: json.loads(line) for line in proc.stdout.splitlines()}
    assert set(summaries) == set(names)
    failed = {"random_bytes", "empty"}
    assert {name for name, summary in summaries.items() if "error" in summary} == failed
    assert f"2 of {len(names)} logs failed" in proc.stderr, proc.stderr[-2000:]
    clock_only = {"gap_2h", "gap_3s", "backwards_30s", "swapped_pairs"}  # no bad line, a bad clock
    for name, summary in summaries.items():
        if name in failed:
            continue
        if name not in clock_only:
            assert summary["malformed_lines"] >= 1, (name, summary)
        # nothing runs away: cycles bounded by the content (2 s blocks) and the bridged gaps (--max-gap 5 s)
        content_s = {"gap_2h": 4.0, "gap_3s": 7.0, "backwards_30s": 4.0}.get(name, 2.0)
        assert summary["cycles"] <= content_s * 100 + 50, (name, summary)
    assert summaries["gap_2h"]["segments"] == summaries["backwards_30s"]["segments"] == 2
    assert summaries["gap_3s"]["segments"] == 1 and summaries["swapped_pairs"]["reordered"] > 0
    assert proc.stderr.count("segment 2 starts here") == 2


@pytest.mark.parametrize("state", ["fifo", "value_x1000"])
def test_daemon_starts_despite_hostile_state_file(state, hostile_states, tmp_path):
    """A FIFO at the state path must not block start-up; absurd values are refused whole, never saved back."""
    path = hostile_states[state]
    before = path.read_bytes() if path.is_file() else None
    proc = run_cli(
        ["run", "--interface", "virtual", "--channel", f"hostile-{state}", "--state-file", path, "--duration", "0.5"],
        tmp_path,
        TIMEOUT,
    )
    assert "Traceback" not in proc.stdout + proc.stderr, proc.stderr[-3000:]
    assert proc.returncode == 0, proc.stderr[-2000:]
    warnings = [line for line in proc.stderr.splitlines() if "WARNING" in line and "state file" in line]
    assert len(warnings) == 1, proc.stderr[-2000:]
    assert ("FIFO" if state == "fifo" else "refused whole") in warnings[0]
    if before is not None:
        assert path.read_bytes() == before  # the refused values were not "learned" and saved back
