"""A sensor that stops measuring behind a live counter: its frames arrive on time, counted right, in range, and
repeat one payload. Daemon fuzzing (2026-11-26) froze the IMU's payloads mid lane change at 100 km/h: roll 10 deg
and the rider torque 25 N m off, VALID, mode VALID, no reason."""

from __future__ import annotations

import numpy as np
import pytest

from ptw_rt.core import layout as L  # noqa: N812
from ptw_rt.edge.cycle import build_runner, drive_log
from ptw_rt.edge.inputs import FROZEN_AFTER_FRAMES, InputTracker
from ptw_rt.paths import DEFAULT_CONFIG
from ptw_rt.sim.recording import encode_frames
from ptw_rt.sim.ride import simulate

FREEZE_AT = 8.0  # s into the ride


def _frozen(frames, epoch: float, ids=(0x100, 0x101)):
    """The frames with every payload of ``ids`` from FREEZE_AT on held at its value then, the counter (byte 6's low
    nibble) still counting."""
    held: dict[int, bytes] = {}
    out = []
    for t, frame_id, data in frames:
        if frame_id in ids and t - epoch >= FREEZE_AT:
            first = held.setdefault(frame_id, bytes(data))
            data = first[:6] + bytes([(first[6] & 0xF0) | (data[6] & 0x0F)])
        out.append((t, frame_id, data))
    return out


def test_a_frozen_imu_behind_a_live_counter_goes_stale_and_drops_valid():
    runner = build_runner(DEFAULT_CONFIG)
    ride = simulate("dlc_100", duration=14.0)
    frames = _frozen(list(encode_frames(ride, runner.codec)), ride.epoch)
    times, rows = [], []
    drive_log(
        frames, runner, lambda now, est: (times.append(now - ride.epoch), rows.append(est.copy())), start=ride.epoch
    )
    t, E = np.asarray(times), np.vstack(rows)
    valid = E[:, L.E_VALID].astype(np.int64)
    before = (t > 6.0) & (t < FREEZE_AT)
    assert (valid[before] & L.V_ROLL).all() and (E[before, L.E_MODE] == L.MODE_VALID).any()
    # 10 repeated frames (0.1 s at 100 Hz), then the input's timeout (3 periods): stale, nothing the IMU feeds VALID
    after = t >= FREEZE_AT + FROZEN_AFTER_FRAMES["IMU_Rates"] * 0.01 + 0.05
    assert after.sum() > 500
    assert not (valid[after] & (L.V_ROLL | L.V_ROLL_RATE | L.V_RIDER_TORQUE)).any()
    assert (E[after, L.E_MODE] != L.MODE_VALID).all()
    assert (E[after, L.E_REASONS].astype(np.int64) & L.REASON_STALE).all()
    assert runner.tracker.summary()["IMU_Rates"]["frozen_frames"] > 500


def test_a_payload_held_is_not_fresh_only_where_noise_makes_repeats_impossible():
    """The encoder's count and the GPS's speed hold their values riding straight: never taken as frozen."""
    runner = build_runner(DEFAULT_CONFIG)
    tracker = InputTracker(runner.codec)
    assert FROZEN_AFTER_FRAMES == {"IMU_Rates": 10, "IMU_Accel": 10}
    for i in range(50):
        tracker.on_values("Steer_Encoder", 0.01 * i, {"SteerCount": 512})
    assert tracker.summary()["Steer_Encoder"]["frozen_frames"] == 0
    for i in range(50):
        tracker.on_values("IMU_Rates", 0.01 * i, {"RollRate": 0.01, "PitchRate": 0.0, "YawRate": 0.02})
    assert tracker.summary()["IMU_Rates"]["frozen_frames"] == 50 - FROZEN_AFTER_FRAMES["IMU_Rates"]


@pytest.mark.parametrize("changed", ["RollRate", "PitchRate", "YawRate"])
def test_one_axis_moving_is_a_live_sensor(changed):
    runner = build_runner(DEFAULT_CONFIG)
    tracker = InputTracker(runner.codec)
    for i in range(50):
        values = {"RollRate": 0.01, "PitchRate": 0.0, "YawRate": 0.02}
        values[changed] += 0.0001 * (i % 2)
        tracker.on_values("IMU_Rates", 0.01 * i, values)
    assert tracker.summary()["IMU_Rates"]["frozen_frames"] == 0
