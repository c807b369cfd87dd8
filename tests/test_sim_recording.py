"""Writing rides: candump log round trip through python-can and cantools, truth CSV, seeds, the CLI."""

from __future__ import annotations

import functools
import json

import can
import cantools
import numpy as np
import pytest

from ptw_rt.cli import main
from ptw_rt.io.candump import read_log
from ptw_rt.io.dbc import FrameCodec, FrameDecodeError
from ptw_rt.paths import DEFAULT_DBC
from ptw_rt.sim.recording import read_truth_csv, write_ride
from ptw_rt.sim.ride import TRUTH_COLUMNS, simulate

CONTRACT_COLUMNS = (
    "t, speed, roll, roll_rate, steer, steer_rate, yaw_rate, lat_vel, fy_front, fy_rear, rider_torque, "
    "c_alpha_front, c_alpha_rear, c_gamma_front, c_gamma_rear, mu"
).split(", ")


@functools.cache
def short_ride(name="dlc_50", seed=None, duration=4.0):
    return simulate(name, seed=seed, duration=duration)


def test_log_round_trip_through_python_can_and_cantools(tmp_path):
    ride = short_ride()
    paths = write_ride(ride, tmp_path)
    db = cantools.database.load_file(str(DEFAULT_DBC))
    decoded: dict[str, list] = {name: [] for name in ride.streams}
    stamps: dict[str, list] = {name: [] for name in ride.streams}
    for msg in can.LogReader(str(paths["log"])):
        m = db.get_message_by_frame_id(msg.arbitration_id)
        decoded[m.name].append(m.decode(msg.data, decode_choices=False))
        stamps[m.name].append(msg.timestamp)
        assert msg.channel == "vcan0"
    for name, st in ride.streams.items():
        assert len(decoded[name]) == len(st.t)
        # stamps: epoch + sim time, to the microsecond
        np.testing.assert_allclose(np.array(stamps[name]) - ride.epoch, st.t, atol=1.1e-6)
        msg = db.get_message_by_name(name)
        for sig in msg.signals:
            got = np.array([d[sig.name] for d in decoded[name]], dtype=float)
            if sig.name == st.counter_signal:
                np.testing.assert_array_equal(got, st.counter)
                continue
            want = np.clip(st.signals[sig.name], sig.minimum, sig.maximum)
            assert np.abs(got - want).max() <= sig.scale / 2 + 1e-9, (name, sig.name)


def test_log_reads_back_with_the_project_codec(tmp_path):
    ride = short_ride()
    paths = write_ride(ride, tmp_path)
    codec = FrameCodec()
    frames = list(read_log(paths["log"]))
    assert len(frames) == ride.n_frames()
    assert all(frames[i].timestamp <= frames[i + 1].timestamp for i in range(len(frames) - 1))
    names = [codec.decode(f.frame_id, f.data)[0] for f in frames]
    assert set(names) == {"IMU_Rates", "IMU_Accel", "Steer_Encoder", "GPS_Velocity"}


def test_truth_csv_columns_and_values(tmp_path):
    ride = short_ride()
    paths = write_ride(ride, tmp_path)
    header = paths["truth"].read_text().splitlines()[0].split(",")
    assert header[: len(CONTRACT_COLUMNS)] == CONTRACT_COLUMNS
    assert tuple(header) == TRUTH_COLUMNS
    back = read_truth_csv(paths["truth"])
    assert len(back["t"]) == 401
    np.testing.assert_allclose(np.diff(back["t"]), 0.01, atol=1e-9)
    for k in TRUTH_COLUMNS:
        np.testing.assert_allclose(back[k], ride.truth[k], rtol=1e-8, atol=1e-12)
    meta = json.loads(paths["meta"].read_text())
    assert meta["scenario"] == "dlc_50" and meta["seed"] == ride.seed
    assert meta["frames"]["GPS_Velocity"] == 40


def test_same_seed_same_log_other_seed_other_noise(tmp_path):
    a = write_ride(simulate("dlc_50", seed=7, duration=2.0), tmp_path / "a")
    b = write_ride(simulate("dlc_50", seed=7, duration=2.0), tmp_path / "b")
    c = write_ride(simulate("dlc_50", seed=8, duration=2.0), tmp_path / "c")
    assert a["log"].read_bytes() == b["log"].read_bytes()
    assert a["truth"].read_bytes() == b["truth"].read_bytes()
    la, lc = a["log"].read_text().splitlines(), c["log"].read_text().splitlines()
    assert len(la) == len(lc)
    assert sum(x != y for x, y in zip(la, lc, strict=True)) > 0.9 * len(la)


def test_fault_frames_reach_the_log(tmp_path):
    ride = simulate("sensor_faults", duration=12.0)  # faults are placed proportionally to the duration
    paths = write_ride(ride, tmp_path)
    codec = FrameCodec()
    reasons: dict[tuple[str | None, str], int] = {}
    for f in read_log(paths["log"]):
        try:
            codec.decode(f.frame_id, f.data)
        except FrameDecodeError as exc:
            key = (codec.message_name(f.frame_id), exc.reason)
            reasons[key] = reasons.get(key, 0) + 1
    assert reasons.get(("IMU_Rates", "wrong_dlc"), 0) >= 10
    assert reasons.get(("Steer_Encoder", "wrong_dlc"), 0) >= 10
    lines = paths["log"].read_text().splitlines()
    steer_lines = [ln for ln in lines if " 102#" in ln]
    assert any(len(ln.split("#")[1]) == 16 for ln in steer_lines)  # 8 bytes instead of 2


def test_cli_list_and_errors(capsys):
    assert main(["simulate", "--list"]) == 0
    out = capsys.readouterr().out
    for name in ("dlc_50", "dlc_100", "radius_accel", "handling_40_120", "slalom_30", "urban", "mu_drop"):
        assert name in out
    assert main(["simulate", "--scenario", "nope"]) == 2
    err = capsys.readouterr().err
    assert "unknown scenario 'nope'" in err and "dlc_100" in err
    assert main(["simulate", "--scenario", "dlc_50", "--perturb", "weight=3"]) == 2
    assert "unknown key 'weight'" in capsys.readouterr().err
    assert main(["simulate", "--scenario", "dlc_50", "--perturb", "stiffness=lots"]) == 2
    assert "not a number" in capsys.readouterr().err
    assert main(["simulate", "--scenario", "dlc_50", "--perturb", "stiffness"]) == 2
    assert "KEY=VALUE" in capsys.readouterr().err
    assert main(["simulate", "--scenario", "dlc_50", "--perturb", "stiffness=0.5", "--perturb", "stiffness=2"]) == 2
    assert "stiffness given twice (0.5 and 2)" in capsys.readouterr().err


@pytest.mark.parametrize("plot", [False, True])
def test_cli_writes_the_files(tmp_path, capsys, plot):
    args = ["simulate", "--scenario", "urban", "--duration", "3", "--seed", "5", "--out", str(tmp_path)]
    args += ["--perturb", "stiffness=0.8", "--perturb", "imu_noise=2"] + (["--plot"] if plot else [])
    assert main(args) == 0
    out = capsys.readouterr().out
    assert (tmp_path / "urban.log").stat().st_size > 0
    assert (tmp_path / "urban.truth.csv").is_file()
    assert (tmp_path / "urban.png").is_file() == plot
    assert "real-time factor" in out and "stiffness=0.8" in out
    truth = read_truth_csv(tmp_path / "urban.truth.csv")
    assert truth["speed"][0] == 0.0  # urban starts at rest


NO_DESIGN_EXTRA = """
import importlib.abc, sys, tempfile
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name.split(".")[0] in ("scipy", "cvxpy", "matplotlib"):
            raise ImportError("blocked " + name)
sys.meta_path.insert(0, Block())
from ptw_rt.cli import main
out = tempfile.mkdtemp()
assert main(["simulate", "--scenario", "urban", "--duration", "1", "--out", out]) == 0
assert main(["simulate", "--scenario", "urban", "--duration", "1", "--out", out, "--plot"]) == 2
assert not [m for m in sys.modules if m.startswith(("scipy", "cvxpy"))]
print("OK")
"""


def test_simulator_runs_without_scipy_cvxpy_and_matplotlib():
    """The demo has only the runtime dependencies (numba's own np.linalg would need scipy's LAPACK)."""
    import subprocess
    import sys

    res = subprocess.run([sys.executable, "-c", NO_DESIGN_EXTRA], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.strip().endswith("OK")
    assert "needs matplotlib" in res.stderr
