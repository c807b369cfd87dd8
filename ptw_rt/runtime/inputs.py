"""Received frames -> one Sample per cycle, with the health of every input message.

Frames arrive asynchronously; each cycle takes the newest valid frame of each input
received since the previous cycle. Every kind of bad input is counted per message and
raised as a reason bit of the cycle in which it was seen:
- a frame that cannot be decoded (wrong DLC, garbage)      -> decode_errors
- a signal outside its DBC range or not finite (frame dropped) -> out_of_range
- a rolling counter that skipped or repeated                   -> counter_jumps
- no valid frame within `stale_after_periods` cycle times      -> SensorTimeouts bit + sensor_stale
Unknown identifiers are counted and otherwise ignored (they are someone else's traffic).
Nothing here raises on bad data.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ptw_rt.core.layout import (
    INPUT_MESSAGE_BITS,
    REASON_COUNTER_JUMPS,
    REASON_DECODE_ERRORS,
    REASON_OUT_OF_RANGE,
    S_ACCEL_X,
    S_ACCEL_Y,
    S_ACCEL_Z,
    S_FRESH,
    S_GPS_FIX,
    S_GPS_SPEED,
    S_INPUT_REASONS,
    S_PITCH_RATE_BODY,
    S_ROLL_RATE_BODY,
    S_STALE,
    S_STEER_COUNT,
    S_TIME,
    S_YAW_RATE_BODY,
)
from ptw_rt.io.dbc import FrameCodec, FrameDecodeError

# message -> ((signal, Sample index), ...)
SIGNAL_SLOTS: dict[str, tuple[tuple[str, int], ...]] = {
    "IMU_Rates": (("RollRate", S_ROLL_RATE_BODY), ("PitchRate", S_PITCH_RATE_BODY), ("YawRate", S_YAW_RATE_BODY)),
    "IMU_Accel": (("AccelX", S_ACCEL_X), ("AccelY", S_ACCEL_Y), ("AccelZ", S_ACCEL_Z)),
    "Steer_Encoder": (("SteerCount", S_STEER_COUNT),),
    "GPS_Velocity": (("SpeedOverGround", S_GPS_SPEED), ("FixType", S_GPS_FIX)),
}


@dataclass
class MessageHealth:
    """Cumulative counters of one input message (for logs, status and tests)."""

    frames: int = 0
    decode_errors: int = 0
    out_of_range: int = 0
    counter_jumps: int = 0
    timeouts: int = 0  # transitions fresh -> stale
    stale: bool = True
    last_valid_time: float = -math.inf
    last_counter: int | None = None

    def as_dict(self) -> dict:
        return {
            "frames": self.frames,
            "decode_errors": self.decode_errors,
            "out_of_range": self.out_of_range,
            "counter_jumps": self.counter_jumps,
            "timeouts": self.timeouts,
            "stale": self.stale,
        }


@dataclass
class InputTracker:
    codec: FrameCodec
    stale_after_periods: float = 3.0
    unknown_ids: int = 0
    health: dict[str, MessageHealth] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self._values = np.zeros(max(i for slots in SIGNAL_SLOTS.values() for _, i in slots) + 1)
        self._timeout: dict[str, float] = {}
        self._modulus: dict[str, int] = {}
        self._counter_signal: dict[str, str | None] = {}
        for name in SIGNAL_SLOTS:
            self.health[name] = MessageHealth()
            self._timeout[name] = self.stale_after_periods * self.codec.cycle_time_s(name)
            self._modulus[name] = self.codec.counter_modulus(name)
            self._counter_signal[name] = self.codec.counter_signal(name)
        self._ids = {self.codec.frame_id(n): n for n in SIGNAL_SLOTS}
        self._fresh = 0
        self._reasons = 0

    def on_frame(self, timestamp: float, frame_id: int, data: bytes, *, extended: bool = False) -> None:
        name = None if extended else self._ids.get(frame_id)
        if name is None:
            self.unknown_ids += 1
            return
        h = self.health[name]
        try:
            _, values = self.codec.decode(frame_id, data)
        except FrameDecodeError:
            h.decode_errors += 1
            self._reasons |= REASON_DECODE_ERRORS
            return
        h.frames += 1
        cname = self._counter_signal[name]
        if cname is not None:
            c = int(values[cname])
            if h.last_counter is not None and (c - h.last_counter) % self._modulus[name] != 1:
                h.counter_jumps += 1
                self._reasons |= REASON_COUNTER_JUMPS
            h.last_counter = c
        bad = self.codec.out_of_range(name, values)
        if bad or not all(math.isfinite(v) for v in values.values()):
            h.out_of_range += 1
            self._reasons |= REASON_OUT_OF_RANGE
            return
        for signal, index in SIGNAL_SLOTS[name]:
            self._values[index] = values[signal]
        h.last_valid_time = timestamp
        self._fresh |= INPUT_MESSAGE_BITS[name]

    def fill(self, sample: np.ndarray, now: float) -> None:
        """Write the cycle's Sample at time `now` and start collecting the next cycle."""
        stale_bits = 0
        for name, h in self.health.items():
            stale = now - h.last_valid_time > self._timeout[name]
            if stale and not h.stale:
                h.timeouts += 1
            h.stale = stale
            if stale:
                stale_bits |= INPUT_MESSAGE_BITS[name]
        sample[:] = 0.0
        sample[: self._values.shape[0]] = self._values
        sample[S_TIME] = now
        sample[S_FRESH] = self._fresh
        sample[S_STALE] = stale_bits
        sample[S_INPUT_REASONS] = self._reasons
        self._fresh = 0
        self._reasons = 0

    def stale_bits(self) -> int:
        return sum(INPUT_MESSAGE_BITS[n] for n, h in self.health.items() if h.stale)

    def summary(self) -> dict:
        out = {name: h.as_dict() for name, h in self.health.items()}
        out["unknown_ids"] = self.unknown_ids
        return out
