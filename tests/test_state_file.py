"""Persisted tyre stiffness: round trip, atomic replacement, and rejection of every kind of bad file."""

from __future__ import annotations

import json
import os

import pytest

from ptw_rt.io import state_file
from ptw_rt.io.state_file import STIFFNESS_KEYS, LoadedState, load_state, save_state

HASH = "a1b2c3d4e5f6"
STIFF = (21000.0, 1200.5, 27000.0, 1500.25)


def _leftovers(directory):
    return sorted(p.name for p in directory.iterdir() if p.name.endswith(".tmp"))


def test_round_trip(tmp_path):
    path = tmp_path / "state.json"
    assert save_state(path, STIFF, HASH, extra={"adapt_cycles": 1234}) == path
    state, reason = load_state(path, HASH)
    assert reason == "ok"
    assert isinstance(state, LoadedState)
    assert state.stiffness == STIFF
    assert state.config_hash == HASH
    assert state.extra == {"adapt_cycles": 1234}
    assert state.saved_at.endswith("+00:00") and "T" in state.saved_at
    doc = json.loads(path.read_text())
    assert doc["format"] == "ptw-rt-state" and doc["version"] == 1
    assert doc["stiffness"] == dict(zip(STIFFNESS_KEYS, STIFF, strict=True))
    assert _leftovers(tmp_path) == []


def test_numpy_values_and_overwrite(tmp_path):
    np = pytest.importorskip("numpy")
    path = tmp_path / "state.json"
    save_state(path, STIFF, HASH)
    save_state(path, np.array([1.0, 2.0, 3.0, 4.0]), HASH)
    state, _ = load_state(path, HASH)
    assert state is not None and state.stiffness == (1.0, 2.0, 3.0, 4.0)
    assert state.extra == {}


def test_missing_directory_is_created(tmp_path):
    path = tmp_path / "var" / "lib" / "ptw-rt" / "state.json"
    save_state(path, STIFF, HASH)
    assert path.is_file()
    assert load_state(path, HASH)[0] is not None


def test_crash_before_replace_keeps_old_file(tmp_path, monkeypatch):
    path = tmp_path / "state.json"
    save_state(path, STIFF, HASH)
    before = path.read_bytes()

    def boom(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(state_file.os, "replace", boom)
    for _ in range(3):
        with pytest.raises(OSError):
            save_state(path, (1.0, 1.0, 1.0, 1.0), HASH)
    assert path.read_bytes() == before
    assert _leftovers(tmp_path) == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["state.json"]
    state, _ = load_state(path, HASH)
    assert state is not None and state.stiffness == STIFF


def test_crash_during_write_keeps_old_file(tmp_path, monkeypatch):
    path = tmp_path / "state.json"
    save_state(path, STIFF, HASH)
    before = path.read_bytes()

    def boom(fd):
        raise OSError(5, "I/O error")

    monkeypatch.setattr(state_file.os, "fsync", boom)
    with pytest.raises(OSError):
        save_state(path, (1.0, 1.0, 1.0, 1.0), HASH)
    assert path.read_bytes() == before
    assert _leftovers(tmp_path) == []


def test_invalid_values_are_not_written(tmp_path):
    path = tmp_path / "state.json"
    for bad in [(float("nan"), 1, 1, 1), (1, 1, -5, 1), (1, 1, 1), (1, 0, 1, 1), (1, 1, 1, float("inf"))]:
        with pytest.raises(ValueError):
            save_state(path, bad, HASH)
    assert not path.exists()
    assert _leftovers(tmp_path) == []


def test_missing_file(tmp_path):
    state, reason = load_state(tmp_path / "nope.json", HASH)
    assert state is None and "no state file" in reason


def test_unreadable_path(tmp_path):
    state, reason = load_state(tmp_path, HASH)  # a directory
    assert state is None and "is a directory, not a regular file" in reason


@pytest.mark.parametrize(
    "content, expected",
    [
        (b"", "not valid JSON"),
        (b"\x00\xff\xfe garbage", "not valid JSON"),
        (b"[1, 2, 3]", "not a JSON object"),
        (b'{"format": "other", "version": 1}', "wrong format"),
        (b'{"format": "ptw-rt-state", "version": 2, "config_hash": "a1b2c3d4e5f6"}', "unsupported version"),
        (b'{"format": "ptw-rt-state", "version": true, "config_hash": "a1b2c3d4e5f6"}', "unsupported version"),
        (b'{"format": "ptw-rt-state", "version": 1}', "no config_hash"),
        (b'{"format": "ptw-rt-state", "version": 1, "config_hash": "a1b2c3d4e5f6"}', "no stiffness"),
    ],
)
def test_corrupt_content_rejected(tmp_path, content, expected):
    path = tmp_path / "state.json"
    path.write_bytes(content)
    state, reason = load_state(path, HASH)
    assert state is None
    assert expected in reason


def test_truncated_json_rejected(tmp_path):
    path = tmp_path / "state.json"
    save_state(path, STIFF, HASH)
    full = path.read_bytes()
    for n in (1, len(full) // 3, len(full) // 2, len(full) - 3):
        path.write_bytes(full[:n])
        state, reason = load_state(path, HASH)
        assert state is None, n
        assert "not valid JSON" in reason


def test_mismatched_hash_rejected(tmp_path):
    path = tmp_path / "state.json"
    save_state(path, STIFF, HASH)
    state, reason = load_state(path, "ffffffffffff")
    assert state is None
    assert "another configuration" in reason


def test_a_file_saved_with_the_learned_state_hash_is_restored_by_another_payload(tmp_path):
    """A file saved with ``learned_state_hash`` is restored by a configuration whose config hash differs from the
    saved one but whose learned-state hash is the same (the payload changed), and says so; another learned-state
    hash, or a file saved without one, is refused as before."""
    path = tmp_path / "state.json"
    save_state(path, STIFF, HASH, learned_state_hash="0123456789ab", sensor_biases=(0.001, 0.0, -0.001, 0.02))
    assert json.loads(path.read_text())["learned_state_hash"] == "0123456789ab"
    same, reason = load_state(path, HASH, learned_state_hash="0123456789ab")
    assert same is not None and same.same_config, reason
    payload, reason = load_state(path, "ffffffffffff", learned_state_hash="0123456789ab")
    assert payload is not None and not payload.same_config, reason
    assert payload.stiffness == STIFF and payload.sensor_biases == pytest.approx((0.001, 0.0, -0.001, 0.02))
    for key in (None, "ba9876543210"):
        state, reason = load_state(path, "ffffffffffff", learned_state_hash=key)
        assert state is None and "another configuration" in reason
    save_state(path, STIFF, HASH)  # a file of before the key
    state, reason = load_state(path, "ffffffffffff", learned_state_hash="0123456789ab")
    assert state is None and "another configuration" in reason


def _write_doc(path, stiffness):
    doc = {"format": "ptw-rt-state", "version": 1, "config_hash": HASH, "saved_at": "x", "stiffness": stiffness}
    path.write_text(json.dumps(doc))  # json.dumps writes NaN / Infinity tokens, json.loads reads them back


@pytest.mark.parametrize(
    "bad_value",
    [float("nan"), float("inf"), -float("inf"), 0.0, -1.0, "21000", None, True, [1.0], 10**400],
)
def test_bad_values_rejected(tmp_path, bad_value):
    path = tmp_path / "state.json"
    stiffness = dict(zip(STIFFNESS_KEYS, STIFF, strict=True))
    stiffness["rear_camber"] = bad_value
    _write_doc(path, stiffness)
    state, reason = load_state(path, HASH)
    assert state is None
    assert "rear_camber" in reason and "refused whole" in reason


def test_missing_value_rejected(tmp_path):
    path = tmp_path / "state.json"
    stiffness = dict(zip(STIFFNESS_KEYS, STIFF, strict=True))
    del stiffness["front_camber"]
    _write_doc(path, stiffness)
    state, reason = load_state(path, HASH)
    assert state is None and "front_camber" in reason


def test_no_temp_files_accumulate(tmp_path):
    path = tmp_path / "state.json"
    for k in range(20):
        save_state(path, (1.0 + k, 2.0, 3.0, 4.0), HASH)
    assert sorted(os.listdir(tmp_path)) == ["state.json"]
    assert load_state(path, HASH)[0].stiffness[0] == 20.0


def test_sensor_biases_round_trip_and_are_optional(tmp_path):
    from ptw_rt.io.state_file import sensor_bias_bounds

    path = tmp_path / "state.json"
    biases = (0.004, -0.002, 0.0031, -0.05)
    bounds = sensor_bias_bounds(0.1, 0.5)
    save_state(path, [1.0, 2.0, 3.0, 4.0], "h", sensor_biases=biases)
    state, reason = load_state(path, "h", bounds)
    assert reason == "ok" and state.sensor_biases == pytest.approx(biases)
    save_state(path, [1.0, 2.0, 3.0, 4.0], "h")  # a file of before the biases were kept still loads
    state, reason = load_state(path, "h", bounds)
    assert reason == "ok" and state.sensor_biases is None


def test_accel_biases_round_trip_are_optional_and_bounded(tmp_path):
    """b_ax and b_az (new 2026-12-06) are a group of their own: a file with the four sensor biases and without them
    (written before) still loads; a bad one refuses the whole file."""
    from ptw_rt.io.state_file import sensor_bias_bounds

    path = tmp_path / "state.json"
    bounds = sensor_bias_bounds(0.1, 0.5)
    biases, accel = (0.004, -0.002, 0.0031, -0.05), (0.08, -0.06)
    save_state(path, [1.0, 2.0, 3.0, 4.0], "h", sensor_biases=biases, accel_biases=accel)
    state, reason = load_state(path, "h", bounds)
    assert reason == "ok" and state.accel_biases == pytest.approx(accel)
    assert state.sensor_biases == pytest.approx(biases)
    save_state(path, [1.0, 2.0, 3.0, 4.0], "h", sensor_biases=biases)
    state, reason = load_state(path, "h", bounds)
    assert reason == "ok" and state.accel_biases is None and state.sensor_biases == pytest.approx(biases)
    save_state(path, [1.0, 2.0, 3.0, 4.0], "h", sensor_biases=biases, accel_biases=(0.9, 0.0))  # beyond 0.5
    state, reason = load_state(path, "h", bounds)
    assert state is None and "longitudinal_accel" in reason
    with pytest.raises(ValueError):
        save_state(path, [1.0, 2.0, 3.0, 4.0], "h", accel_biases=(float("nan"), 0.0))


@pytest.mark.parametrize("bad", [0.5, "x", None, float("inf")])
def test_a_bad_sensor_bias_refuses_the_whole_file(tmp_path, bad):
    from ptw_rt.io.state_file import sensor_bias_bounds

    path = tmp_path / "state.json"
    save_state(path, [1.0, 2.0, 3.0, 4.0], "h", sensor_biases=(0.0, 0.0, 0.0, 0.0))
    doc = json.loads(path.read_text())
    doc["sensor_biases"]["yaw_gyro"] = bad
    path.write_text(json.dumps(doc))
    state, reason = load_state(path, "h", sensor_bias_bounds(0.1, 0.5))
    assert state is None and "yaw_gyro" in reason
    del doc["sensor_biases"]["yaw_gyro"]
    path.write_text(json.dumps(doc))
    state, reason = load_state(path, "h", sensor_bias_bounds(0.1, 0.5))
    assert state is None and "lacks sensor_biases values: yaw_gyro" in reason


def test_the_steer_zero_round_trips_is_optional_and_bounded(tmp_path):
    from ptw_rt.io.state_file import steer_zero_bounds

    path = tmp_path / "state.json"
    bounds = steer_zero_bounds(0.0077, 1024)
    save_state(path, [1.0, 2.0, 3.0, 4.0], "h", steer_zero=(512.0, -0.006))
    state, reason = load_state(path, "h", bounds)
    assert reason == "ok" and state.steer_zero == (512.0, -0.006)
    save_state(path, [1.0, 2.0, 3.0, 4.0], "h")  # a file of before the steer zero was kept still loads
    state, reason = load_state(path, "h", bounds)
    assert reason == "ok" and state.steer_zero is None
    for key, bad in (("shift", 0.01), ("shift", "x"), ("zero_count", 2000.0), ("zero_count", None)):
        save_state(path, [1.0, 2.0, 3.0, 4.0], "h", steer_zero=(512.0, 0.0))
        doc = json.loads(path.read_text())
        doc["steer_zero"][key] = bad
        path.write_text(json.dumps(doc))
        state, reason = load_state(path, "h", bounds)
        assert state is None and key in reason, (key, bad, reason)
    with pytest.raises(ValueError):
        save_state(path, [1.0, 2.0, 3.0, 4.0], "h", steer_zero=(512.0, float("nan")))


def test_a_save_never_replaces_what_is_not_a_file(tmp_path):
    """A state path that is a FIFO or a device was refused when read and replaced by a regular file when saved (the
    rename of the new file over it; as root, a device node). Saving there is an OSError, the node left alone."""
    import stat

    fifo = tmp_path / "state.json"
    os.mkfifo(fifo)
    with pytest.raises(OSError, match="FIFO"):
        save_state(fifo, STIFF, HASH)
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode) and [p.name for p in tmp_path.iterdir()] == ["state.json"]
    link = tmp_path / "link.json"
    link.symlink_to(tmp_path / "elsewhere.json")  # a symlink is replaced, never what it points to
    save_state(link, STIFF, HASH)
    assert not link.is_symlink() and not (tmp_path / "elsewhere.json").exists()
