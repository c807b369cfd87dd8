"""``ptw-rt demo``: the README's first command, end to end on python-can's virtual bus (short ride, sped up)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from ptw_rt.errors import UserFacingError
from ptw_rt.io.candump import read_log
from ptw_rt.io.dbc import FrameCodec


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    proc = subprocess.run(
        [sys.executable, "-m", "ptw_rt", "demo", "--scenario", "slalom_30", "--duration", "8", "--speed", "1",
         "--out", str(out)],
        capture_output=True, text=True, timeout=240,
    )  # fmt: skip
    return out, proc


def test_demo_exits_zero_and_prints_the_accuracy_summary(demo_run):
    _, proc = demo_run
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "Traceback" not in proc.stderr
    assert "== ptw-rt demo: slalom_30, 8 s ride at 1x ==" in proc.stdout
    for label in ("roll RMSE", "rider torque RMSE", "front Fy RMSE", "mode share VALID"):
        assert label in proc.stdout
    assert re.search(r"CRC errors 0, counter errors 0, other decode errors 0", proc.stdout)


def test_demo_live_view_shows_roll_torque_stiffness_and_mode(demo_run):
    _, proc = demo_run
    lines = [line for line in proc.stderr.splitlines() if line.startswith("t ")]
    assert lines, proc.stderr
    assert all(k in lines[-1] for k in ("roll", "torque", "C_alpha", "km/h"))
    assert re.search(r"\| (INIT|CONVERGING|VALID|DEGRADED|FAULT)$", lines[-1])


def test_demo_received_every_output_frame_and_wrote_its_files(demo_run):
    out, proc = demo_run
    counts = re.findall(r"^  (EST_\w+)\s+(\d+) /\s+(\d+)$", proc.stdout, flags=re.M)
    assert {name for name, _, _ in counts} == set(FrameCodec().output_messages)
    for name, received, expected in counts:
        assert int(received) == int(expected) > 0, name
    for name in ("slalom_30.log", "slalom_30.truth.csv", "slalom_30.outputs.log", "report/summary.md"):
        assert (out / name).is_file(), name
    outputs = list(read_log(out / "slalom_30.outputs.log"))
    codec = FrameCodec()
    assert outputs and all(codec.is_output(codec.message_name(frame.frame_id)) for frame in outputs)


def test_demo_accuracy_is_that_of_the_estimator(demo_run):
    _, proc = demo_run
    roll = float(re.search(r"roll RMSE\s+([\d.]+) deg", proc.stdout).group(1))
    assert roll < 2.0


@pytest.mark.parametrize("option", [{"speed": 0.0}, {"speed": float("nan")}, {"duration": -1.0}])
def test_demo_rejects_bad_options_clearly(option, tmp_path):
    from argparse import Namespace

    from ptw_rt.apps.demo import run_demo

    args = Namespace(scenario="slalom_30", speed=1.0, duration=5.0, out=Path(tmp_path), config=None)
    for key, value in option.items():
        setattr(args, key, value)
    with pytest.raises(UserFacingError):
        run_demo(args)
