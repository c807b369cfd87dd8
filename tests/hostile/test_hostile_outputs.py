"""Outputs a user's tree can make hostile (a third fuzzing pass, 2026-12-07): a FIFO nobody reads where a command
writes, a symlink planted at a temporary file's name, an input whose output name is the fleet summary's, a bus
whose name the candump output cannot carry, an option the command would have ignored, a name that forges a line.
Each was a hang, a file overwritten, a traceback or a silent substitution; each is one line now."""

from __future__ import annotations

import argparse
import io
import json
import os
import shutil

import numpy as np
import pytest

from ptw_rt.apps import fleet
from ptw_rt.apps.replay import replay_log, run_replay
from ptw_rt.errors import UserFacingError
from ptw_rt.io.candump import read_log
from ptw_rt.paths import DEFAULT_CONFIG, DEFAULT_DESIGN

from .conftest import run_cli, run_many

pytestmark = pytest.mark.usefixtures("warm_numba_cache")
TIMEOUT = 90.0


@pytest.fixture(scope="module")
def ride_log(tmp_path_factory):
    from ptw_rt.sim.recording import write_ride
    from ptw_rt.sim.ride import simulate

    return write_ride(simulate("dlc_50", duration=3.0), tmp_path_factory.mktemp("ride"))["log"]


def _one_line(args, returncode, out, err, expected):
    where = f"ptw-rt {' '.join(map(str, args))}"
    assert returncode is not None, f"{where}: killed at the timeout (hung)"
    assert "Traceback" not in out + err, f"{where}:\n{err[-2000:]}"
    lines = [line for line in err.splitlines() if line.strip() and not line.startswith("simulating ")]
    assert len(lines) == 1, f"{where}: {err[-2000:]}"
    assert returncode == expected, f"{where}: exit {returncode}: {err[-500:]}"
    return lines[0]


def test_a_fifo_nobody_reads_where_a_command_writes_is_one_line_not_a_hang(ride_log, tmp_path):
    """`simulate`, `report` and `demo` opened their outputs in place and waited for ever on a FIFO nobody reads; the
    fleet summary's parquet file too, after every log was replayed. Exit 74 (EX_IOERR), one line, at once."""
    dirs = {name: tmp_path / name for name in ("sim", "report", "demo", "fleet")}
    for d in dirs.values():
        d.mkdir()
    os.mkfifo(dirs["sim"] / "dlc_50.log")
    os.mkfifo(dirs["report"] / "summary.md")
    os.mkfifo(dirs["demo"] / "dlc_50.outputs.log")
    commands = [
        ["simulate", "--scenario", "dlc_50", "--duration", "2", "--out", dirs["sim"]],
        ["report", "--scenario", "dlc_50", "--out", dirs["report"]],
        ["demo", "--scenario", "dlc_50", "--duration", "2", "--out", dirs["demo"]],
    ]
    for args, returncode, out, err, _ in run_many(commands, cwd=tmp_path, timeout=TIMEOUT):
        line = _one_line(args, returncode, out, err, 74)
        assert "FIFO" in line, line
    os.mkfifo(dirs["fleet"] / "fleet.parquet")
    pytest.importorskip("pyarrow")
    with pytest.raises(OSError, match="FIFO"):
        fleet.write_fleet_summary([], dirs["fleet"])


def test_a_symlink_at_the_design_files_temporary_name_is_not_written_through(tmp_path):
    """`design` wrote its zip into NAME.npz.tmp, following a symlink planted there into its target (and turned the
    output into a link to it), or waited for ever on a FIFO there. The temporary file is a new one of its own now."""
    from ptw_rt.design.file import load_design

    victim = tmp_path / "victim.txt"
    victim.write_text("keep me\n")
    out = tmp_path / "d.npz"
    (tmp_path / "d.npz.tmp").symlink_to(victim)
    os.mkfifo(tmp_path / ".d.npz.tmp")
    load_design(DEFAULT_DESIGN).save(out)
    assert victim.read_text() == "keep me\n"
    assert out.is_file() and not out.is_symlink()
    assert sorted(p.name for p in tmp_path.iterdir()) == [".d.npz.tmp", "d.npz", "d.npz.tmp", "victim.txt"]


def _args(logs, out, **kw):
    base = dict(logs=list(logs), out=out, csv=None, config=DEFAULT_CONFIG, design_file=None, jobs=1, no_progress=True)
    base.update(kw)
    return argparse.Namespace(**base)


def test_an_input_whose_output_is_the_fleet_summarys_name_is_refused(ride_log, tmp_path):
    """A tree holding fleet.csv (a CAN log in python-can's CSV) had its replayed output overwritten by the fleet
    summary, exit 0, the summary line naming the lost file (found by fuzzing)."""
    import can

    tree = tmp_path / "in"
    tree.mkdir()
    shutil.copy(ride_log, tree / "a.log")
    with can.Logger(str(tree / "fleet.csv")) as writer:
        for msg in list(can.LogReader(str(ride_log)))[:50]:
            writer.on_message_received(msg)
    with pytest.raises(UserFacingError, match="would be overwritten by the fleet summary"):
        run_replay(_args([tree], tmp_path / "out"), out=io.StringIO(), err=io.StringIO())


@pytest.mark.parametrize("bus", ["cän0", "can/0", "a" * 17])
def test_a_bus_name_the_candump_output_cannot_carry_is_written_as_vcan0(ride_log, tmp_path, bus):
    """The output log is written on the input's bus; a name with non-ASCII (or a character candump lines cannot
    carry) was a UnicodeEncodeError traceback at the first line written, the output removed."""
    path = tmp_path / "odd_bus.log"
    path.write_text(ride_log.read_text().replace(" vcan0 ", f" {bus} "), encoding="utf-8")
    out = tmp_path / "odd_bus.out.log"
    summary = replay_log(path, out, None, DEFAULT_CONFIG)
    assert summary["bus"] == bus and summary["cycles"] > 0
    assert {f.channel for f in read_log(out)} == {"vcan0"}


def test_the_summary_line_names_the_bus_read(ride_log, tmp_path):
    out = io.StringIO()
    assert run_replay(_args([ride_log], tmp_path / "one.log"), out=out, err=io.StringIO()) == 0
    line = json.loads(out.getvalue().splitlines()[0])
    assert line["bus"] == "vcan0" and line["other_bus_frames"] == 0


def test_options_a_command_would_ignore_are_refused(tmp_path):
    """`evaluate --matrix` with --scenario, --all or --perturb ran the nominal matrix and exited 0: not what was
    asked. And names with a newline or ESC forged lines on stdout (`simulate`'s "wrote" lines)."""
    commands = [
        ["evaluate", "--matrix", "--scenario", "dlc_50"],
        ["evaluate", "--matrix", "--all"],
        ["evaluate", "--matrix", "--perturb", "stiffness=0.7"],
        ["simulate", "--scenario", "dlc_50", "--out", ""],
    ]
    for args, returncode, out, err, _ in run_many(commands, cwd=tmp_path, timeout=TIMEOUT):
        _one_line(args, returncode, out, err, 2)
    forged = tmp_path / "a\nerror: b\x1b[31m"
    proc = run_cli(["simulate", "--scenario", "dlc_50", "--duration", "2", "--out", forged], tmp_path)
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout
    assert "\x1b" not in out and not any(line.startswith("error: b") for line in out.splitlines()), out
    assert np.all([line.isprintable() for line in out.splitlines()])


def test_a_channel_of_other_frames_alone_is_one_line(ride_log, tmp_path):
    """`--channel` naming a bus that carries none of the inputs: the other-bus warning, then the refusal, two lines
    where one is promised; the refusal now says what was skipped."""
    path = tmp_path / "two.log"
    stamp = ride_log.read_text().split(")")[0] + ")"
    path.write_text(ride_log.read_text() + f"{stamp} can7 7F0#01\n")
    proc = run_cli(["replay", path, "--out", tmp_path / "x.log", "--channel", "can7", "--no-progress"], tmp_path)
    assert proc.returncode == 2, proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "frames on other channels skipped: vcan0" in lines[0], proc.stderr


def test_a_ride_shorter_than_the_settling_time_is_scored_without_numpy_warnings():
    """`demo --duration 2` printed numpy's "Mean of empty slice": the share of time VALID over no scored frame."""
    import warnings

    from ptw_rt.eval.evaluate import evaluate_ride
    from ptw_rt.sim.ride import simulate

    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        ev = evaluate_ride(simulate("dlc_50", duration=2.0))
    assert ev.result["metrics"]["valid_share"] is None
