"""Received frames -> one Sample per cycle, with the health of every input message.

Frames arrive asynchronously; each cycle takes the newest valid frame of each input
received since the previous cycle. Every kind of bad input is counted per message and
raised as a reason bit of the cycle in which it was seen:
- a frame that cannot be decoded (wrong DLC, garbage)      -> decode_errors
- a signal outside its DBC range or not finite (frame dropped) -> out_of_range
- a rolling counter that skipped or repeated                   -> counter_jumps
- no valid frame within `stale_after_periods` cycle times      -> SensorTimeouts bit + sensor_stale
Unknown identifiers are counted and otherwise ignored (they are someone else's traffic).
Nothing here raises on bad data. Frames are unpacked by the codec's compiled message (``MessageLayout``), counters
checked by ``ptw_rt.io.e2e.CounterChecker``: nothing here knows a bit layout.
``on_values`` takes an input's signals from another source than a CAN frame (a serial GNSS receiver for
``GPS_Velocity``) into the same Sample slots, range checks and timeout.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping
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
    S_GPS_COURSE,
    S_GPS_FIX,
    S_GPS_SPEED,
    S_IMU_AGE,
    S_INPUT_REASONS,
    S_PITCH_RATE_BODY,
    S_ROLL_RATE_BODY,
    S_STALE,
    S_STEER_COUNT,
    S_SUSPECT,
    S_TIME,
    S_YAW_RATE_BODY,
    SAMPLE_SIZE,
)
from ptw_rt.io.dbc import FrameCodec, FrameDecodeError
from ptw_rt.io.e2e import CounterChecker, P11Status

_BYTES_TYPES = (bytes, bytearray)
MAX_IMU_AGE = 0.05  # s
_FLOAT64 = np.dtype(np.float64)  # the native-order dtype instance, for an identity test (== on dtypes is slow)
_SAMPLE_SHAPE = (SAMPLE_SIZE,)

# message -> ((signal, Sample index), ...)
SIGNAL_SLOTS: dict[str, tuple[tuple[str, int], ...]] = {
    "IMU_Rates": (("RollRate", S_ROLL_RATE_BODY), ("PitchRate", S_PITCH_RATE_BODY), ("YawRate", S_YAW_RATE_BODY)),
    "IMU_Accel": (("AccelX", S_ACCEL_X), ("AccelY", S_ACCEL_Y), ("AccelZ", S_ACCEL_Z)),
    "Steer_Encoder": (("SteerCount", S_STEER_COUNT),),
    "GPS_Velocity": (("SpeedOverGround", S_GPS_SPEED), ("FixType", S_GPS_FIX), ("CourseOverGround", S_GPS_COURSE)),
}


@dataclass(slots=True)  # slots: faster attribute updates, several per frame
class MessageHealth:
    """Cumulative counters of one input message (for logs, status and tests)."""

    frames: int = 0
    decode_errors: int = 0
    out_of_range: int = 0
    counter_jumps: int = 0
    timeouts: int = 0  # transitions fresh -> stale
    stale: bool = True
    last_valid_time: float = -math.inf

    def as_dict(self) -> dict:
        return {
            "frames": self.frames,
            "decode_errors": self.decode_errors,
            "out_of_range": self.out_of_range,
            "counter_jumps": self.counter_jumps,
            "timeouts": self.timeouts,
            "stale": self.stale,
        }


_SEQUENCE_OK = (P11Status.OK, P11Status.INITIAL)


@dataclass
class InputTracker:
    codec: FrameCodec
    stale_after_periods: float = 3.0
    unknown_ids: int = 0
    health: dict[str, MessageHealth] = field(default_factory=dict)

    def __post_init__(self) -> None:
        # the cycle's Sample as a plain list: list item writes cost ~20 ns against ~60 ns for a numpy element,
        # and fill() copies it into the Sample in one struct.pack_into (no numpy call per value)
        self._row: list[float] = [0.0] * SAMPLE_SIZE
        self._row_struct = struct.Struct(f"={SAMPLE_SIZE}d")
        self._timeout: dict[str, float] = {}
        self._plans: dict[str, tuple] = {}
        self._by_id: dict[tuple[int, bool], tuple] = {}
        for name in SIGNAL_SLOTS:
            self.health[name] = MessageHealth()
            self._timeout[name] = self.stale_after_periods * self.codec.cycle_time_s(name)
            plan = self._plan(name)
            self._plans[name] = plan
            layout = plan[0]
            self._by_id[(layout.frame_id, bool(layout.message.is_extended_frame))] = plan
        # (health, timeout, MSG_* bit) in health order, for fill()
        self._imu_health = self.health["IMU_Rates"]
        self._stale_plan = tuple((self.health[n], self._timeout[n], INPUT_MESSAGE_BITS[n]) for n in SIGNAL_SLOTS)
        self._stale_bits = sum(bit for h, _, bit in self._stale_plan if h.stale)
        self._fresh = 0
        self._reasons = 0
        self._suspect = 0

    def _plan(self, name: str) -> tuple:
        """``(layout, health, counter checker, counter position or -1, range checks, slots, MSG_* bit)`` of one input.

        ``range checks`` (position, lo, hi) only for the signals whose raw field can decode outside the DBC
        [min, max] (``SignalLayout.can_exceed``): for the others the check could never fail. ``slots``
        (position, Sample index) of the signals copied into the Sample.
        """
        layout = self.codec.layout(name)
        counter = layout.counter_signal
        checker = CounterChecker(layout.counter_modulus) if counter is not None else None
        checks = tuple((k, s.lo, s.hi) for k, s in enumerate(layout.signals) if s.can_exceed)
        slots = tuple((layout.index[signal], slot) for signal, slot in SIGNAL_SLOTS[name])
        pos = -1 if counter is None else layout.index[counter]
        return (layout, self.health[name], checker, pos, checks, slots, INPUT_MESSAGE_BITS[name])

    def on_frame(self, timestamp: float, frame_id: int, data: bytes, *, extended: bool = False) -> None:
        plan = self._by_id.get((frame_id, extended))
        if plan is None:
            self.unknown_ids += 1
            return
        layout = plan[0]
        if type(data) in _BYTES_TYPES and type(frame_id) is int:
            if len(data) != layout.length:
                values = None
            else:
                try:
                    values = layout.unpack(data)
                except Exception:  # the generic (cantools) path on undecodable data
                    values = None
        else:  # exotic argument types (a float id, a list of ints, a memoryview) take the codec's own checks
            try:
                values = list(self.codec.decode(frame_id, data, extended=extended)[1].values())
            except FrameDecodeError:
                values = None
        if values is None:
            plan[1].decode_errors += 1
            self._reasons |= REASON_DECODE_ERRORS
            return
        self._accept(plan, timestamp, values, True)

    def on_values(self, message: str, timestamp: float, signals: Mapping[str, float]) -> None:
        """Signals of input ``message`` from a source other than a CAN frame (no counter). A signal not given is
        taken as its neutral value; the given ones are range checked and copied as a frame's would be."""
        plan = self._plans[message]
        layout = plan[0]
        values = [signals.get(s.name, s.neutral) for s in layout.signals]
        self._accept(plan, timestamp, values, False)

    def _accept(self, plan: tuple, timestamp: float, values: list[float], counted: bool) -> None:
        _, h, checker, counter_pos, checks, slots, bit = plan
        h.frames += 1
        if counted and counter_pos >= 0 and checker.step(int(values[counter_pos])) not in _SEQUENCE_OK:
            h.counter_jumps += 1
            self._reasons |= REASON_COUNTER_JUMPS
            self._suspect |= bit  # repeated, skipped or random counter: the payload may be garbage too
        for k, lo, hi in checks:
            if not lo <= values[k] <= hi:  # also NaN
                h.out_of_range += 1
                self._reasons |= REASON_OUT_OF_RANGE
                return
        row = self._row
        for k, slot in slots:
            row[slot] = values[k]
        h.last_valid_time = timestamp
        self._fresh |= bit

    def restart(self) -> None:
        """Forget every input's state (values, freshness, rolling counters) as at construction; the cumulative
        counters of ``summary`` are kept. For a new segment of a log after a time discontinuity: nothing seen
        before it may be taken as the last value, nor a counter continue across it."""
        self._row[:] = [0.0] * SAMPLE_SIZE
        for plan in self._plans.values():
            h, checker = plan[1], plan[2]
            h.stale = True  # stale again without a timeout transition: nothing has been received yet
            h.last_valid_time = -math.inf
            if checker is not None:
                checker.reset()
        self._stale_bits = sum(bit for _, _, bit in self._stale_plan)
        self._fresh = 0
        self._reasons = 0

    def decode_error(self, message: str) -> None:
        """Something of ``message`` arrived that could not be decoded (a serial line with a bad checksum)."""
        self.health[message].decode_errors += 1
        self._reasons |= REASON_DECODE_ERRORS

    def lost(self, message: str) -> None:
        """The source of ``message`` is gone (a serial receiver unplugged): stale from the next ``fill`` on,
        without waiting for its timeout."""
        self.health[message].last_valid_time = -math.inf

    def fill(self, sample: np.ndarray, now: float) -> None:
        """Write the cycle's Sample at time `now` and start collecting the next cycle."""
        stale_bits = 0
        for h, timeout, bit in self._stale_plan:
            stale = now - h.last_valid_time > timeout
            if stale and not h.stale:
                h.timeouts += 1
            h.stale = stale
            if stale:
                stale_bits |= bit
        self._stale_bits = stale_bits
        row = self._row  # the newest valid value of every input signal is kept from cycle to cycle
        row[S_TIME] = now
        row[S_FRESH] = self._fresh
        row[S_STALE] = stale_bits
        row[S_INPUT_REASONS] = self._reasons
        # how old the IMU's newest sample is at this cycle (bounded: beyond a few cycles the input is stale)
        row[S_IMU_AGE] = min(max(now - self._imu_health.last_valid_time, 0.0), MAX_IMU_AGE)
        row[S_SUSPECT] = self._suspect
        if sample.dtype is _FLOAT64 and sample.shape == _SAMPLE_SHAPE and sample.flags.c_contiguous:
            self._row_struct.pack_into(sample, 0, *row)  # float64 bytes straight into the array's buffer
        else:  # any other array: as numpy assigns it
            sample[:] = 0.0
            sample[:SAMPLE_SIZE] = row
        self._fresh = 0
        self._reasons = 0
        self._suspect = 0

    def stale_bits(self) -> int:
        """MSG_* bits of the inputs stale at the last ``fill`` (all of them before the first)."""
        return self._stale_bits

    def summary(self) -> dict:
        out = {name: h.as_dict() for name, h in self.health.items()}
        out["unknown_ids"] = self.unknown_ids
        return out
