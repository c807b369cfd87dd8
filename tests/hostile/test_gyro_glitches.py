"""Single IMU_Rates frames whose roll rate is off by 0.02-0.4 rad/s, counted right and within every input check (a
glitch of the sensor, or garbage whose rolling counter happened to match): the roll-gyro step check
(ptw_rt.core.attitude, `_roll_gyro_step`) must not take them for steps of the gyro's bias. A glitch jumps and comes
back; taken as a step it would leave the bias 1.5 times the glitch off, and the roll drifting with it."""

from __future__ import annotations

import random
import struct

import numpy as np
import pytest

from ptw_rt.core import layout as L  # noqa: N812
from ptw_rt.edge.cycle import build_runner, drive_log
from ptw_rt.paths import DEFAULT_CONFIG
from ptw_rt.sim.recording import encode_frames
from ptw_rt.sim.ride import simulate

ROLL_RATE_SCALE = 1e-4  # rad/s per count of IMU_Rates.RollRate (dbc/, bits 0-15, little endian, signed)


def _run(ride, frames):
    rows = []
    drive_log(
        frames,
        build_runner(DEFAULT_CONFIG),
        lambda now, e: rows.append((now - ride.epoch, e[L.E_ROLL], int(e[L.E_VALID]), e[L.E_ROLL_GYRO_BIAS])),
    )
    return (np.array(c) for c in zip(*rows, strict=True))


@pytest.mark.slow
@pytest.mark.parametrize(("scenario", "seed"), [("handling_40_120", 7), ("urban", 8), ("slalom_30", 9)])
def test_isolated_gyro_glitches_are_no_bias_steps(scenario, seed):
    ride = simulate(scenario, duration=60.0)
    frames = list(encode_frames(ride, build_runner(DEFAULT_CONFIG).codec))
    rates = 0x100
    rng = random.Random(seed)
    glitched, next_at, count = list(frames), 10.0, 0
    for i, (t, frame_id, data) in enumerate(frames):
        if frame_id == rates and t - ride.epoch >= next_at:
            off = rng.choice([-1, 1]) * rng.uniform(0.02, 0.4)
            raw = struct.unpack_from("<h", data, 0)[0] + round(off / ROLL_RATE_SCALE)
            payload = bytearray(data)
            struct.pack_into("<h", payload, 0, max(-30000, min(30000, raw)))
            glitched[i] = (t, frame_id, bytes(payload))
            next_at += rng.uniform(1.5, 3.0)
            count += 1
    assert count >= 20
    _, _, valid, bias = _run(ride, frames)
    t, roll, valid_g, bias_g = _run(ride, glitched)
    roll_valid = (valid_g & L.V_ROLL) != 0
    error = np.degrees(np.abs(roll - np.interp(t, ride.truth["t"], ride.truth["roll"])))
    assert error[roll_valid & (t > 5.0)].max() < 1.5  # the promise is 3 deg; the clean rides reach 0.5
    assert abs(bias_g[-1] - bias[-1]) < 0.005  # no glitch left in the bias
    assert roll_valid.mean() >= ((valid & L.V_ROLL) != 0).mean() - 0.02
    assert np.isfinite(roll).all()
