"""`shared_runner`: a worker of many logs loads the config, design file and DBC once, and every log still gets a
runner of its own (nothing one log did reaches the next)."""

from __future__ import annotations

import argparse
import io
import json
import shutil

import numpy as np
import pytest

from ptw_rt.apps.replay import replay_log, run_replay
from ptw_rt.edge import cycle
from ptw_rt.edge.cycle import build_runner, drive_log, shared_runner
from ptw_rt.paths import DEFAULT_CONFIG
from ptw_rt.sim.recording import encode_frames, write_ride
from ptw_rt.sim.ride import simulate


def _loads(monkeypatch) -> list[str]:
    calls: list[str] = []
    real = cycle.load_settings

    def counting(path):
        calls.append(str(path))
        return real(path)

    monkeypatch.setattr(cycle, "load_settings", counting)
    cycle._LOADED.clear()
    return calls


def test_the_files_are_loaded_once_and_each_call_gets_a_runner_of_its_own(monkeypatch):
    calls = _loads(monkeypatch)
    first, second = shared_runner(DEFAULT_CONFIG), shared_runner(DEFAULT_CONFIG)
    assert len(calls) == 1
    assert first.settings is second.settings and first.codec is second.codec
    for part in ("estimator", "tracker", "encoder", "sample", "estimates"):
        assert getattr(first, part) is not getattr(second, part)
    # a ride run on the first leaves the second as a runner built from nothing
    ride = simulate("slalom_30", duration=8.0)
    drive_log(list(encode_frames(ride, first.codec)), first, start=ride.epoch)
    fresh = build_runner(DEFAULT_CONFIG)
    state, _, _, _ = second.estimator.buffers()
    assert np.array_equal(state, fresh.estimator.buffers()[0])
    assert not np.array_equal(first.estimator.buffers()[0], state)


def test_a_changed_config_file_is_loaded_again(monkeypatch, tmp_path):
    calls = _loads(monkeypatch)
    config = tmp_path / "scooter.yaml"
    shutil.copy(DEFAULT_CONFIG, config)  # no design file of its own: the shipped one fits an unchanged copy
    shared_runner(config)
    shared_runner(config)
    config.write_text(config.read_text() + "\n# edited\n")
    shared_runner(config)
    assert len(calls) == 2


def test_a_missing_config_is_reported_as_build_runner_reports_it(monkeypatch, tmp_path):
    _loads(monkeypatch)
    with pytest.raises(Exception) as shared:
        shared_runner(tmp_path / "none.yaml")
    with pytest.raises(Exception) as direct:
        build_runner(tmp_path / "none.yaml")
    assert type(shared.value) is type(direct.value) and str(shared.value) == str(direct.value)


def test_logs_replayed_one_after_another_by_one_worker_equal_each_alone(tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    a = write_ride(simulate("slalom_30", duration=8.0), tmp_path / "a")["log"]
    b = write_ride(simulate("dlc_100", duration=8.0, seed=3), tmp_path / "b")["log"]
    for name, log in (("1.log", a), ("2.log", b), ("3.log", a)):
        shutil.copy(log, src / name)
    args = argparse.Namespace(
        logs=[src], out=tmp_path / "out", csv=None, config=DEFAULT_CONFIG, design_file=None, jobs=1, no_progress=True
    )
    out = io.StringIO()
    assert run_replay(args, out=out, err=io.StringIO()) == 0
    assert len([json.loads(x) for x in out.getvalue().splitlines()]) == 3
    replay_log(a, tmp_path / "a_alone.log", None, DEFAULT_CONFIG)
    replay_log(b, tmp_path / "b_alone.log", None, DEFAULT_CONFIG)
    got = {n: (tmp_path / "out" / n).read_bytes() for n in ("1.log", "2.log", "3.log")}
    assert got["1.log"] == got["3.log"] == (tmp_path / "a_alone.log").read_bytes()
    assert got["2.log"] == (tmp_path / "b_alone.log").read_bytes()
