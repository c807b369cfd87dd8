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
import struct
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
    SAMPLE_SIZE,
)
from ptw_rt.io.dbc import FrameCodec, FrameDecodeError

_BYTES_TYPES = (bytes, bytearray)
_FLOAT64 = np.dtype(np.float64)  # the native-order dtype instance, for an identity test (== on dtypes is slow)
_SAMPLE_SHAPE = (SAMPLE_SIZE,)

# message -> ((signal, Sample index), ...)
SIGNAL_SLOTS: dict[str, tuple[tuple[str, int], ...]] = {
    "IMU_Rates": (("RollRate", S_ROLL_RATE_BODY), ("PitchRate", S_PITCH_RATE_BODY), ("YawRate", S_YAW_RATE_BODY)),
    "IMU_Accel": (("AccelX", S_ACCEL_X), ("AccelY", S_ACCEL_Y), ("AccelZ", S_ACCEL_Z)),
    "Steer_Encoder": (("SteerCount", S_STEER_COUNT),),
    "GPS_Velocity": (("SpeedOverGround", S_GPS_SPEED), ("FixType", S_GPS_FIX)),
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
        # the cycle's Sample as a plain list: list item writes cost ~20 ns against ~60 ns for a numpy element,
        # and fill() copies it into the Sample in one struct.pack_into (no numpy call per value)
        self._row: list[float] = [0.0] * SAMPLE_SIZE
        self._row_struct = struct.Struct(f"={SAMPLE_SIZE}d")
        self._timeout: dict[str, float] = {}
        self._modulus: dict[str, int] = {}
        self._counter_signal: dict[str, str | None] = {}
        for name in SIGNAL_SLOTS:
            self.health[name] = MessageHealth()
            self._timeout[name] = self.stale_after_periods * self.codec.cycle_time_s(name)
            self._modulus[name] = self.codec.counter_modulus(name)
            self._counter_signal[name] = self.codec.counter_signal(name)
        self._ids = {self.codec.frame_id(n): n for n in SIGNAL_SLOTS}
        # frame id -> everything on_frame needs for that message, resolved once here instead of per frame
        self._plans = {fid: self._plan(name) for fid, name in self._ids.items()}
        # (health, timeout, MSG_* bit) in health order, for fill()
        self._stale_plan = tuple((self.health[n], self._timeout[n], INPUT_MESSAGE_BITS[n]) for n in SIGNAL_SLOTS)
        self._stale_bits = sum(bit for h, _, bit in self._stale_plan if h.stale)
        self._fresh = 0
        self._reasons = 0

    def _plan(self, name: str) -> tuple:
        """``(name, health, DLC, counter shift or -1, counter mask, modulus, fields, MSG_* bit)`` of one input message.

        ``fields`` (None: the message is not plain Intel integers, decode through the codec) lists only the
        signals that matter here: the ones copied into the Sample and the ones that can be out of range.
        A signal whose whole raw field maps into its DBC [min, max] cannot be (``raw * scale + offset`` is
        monotonic in raw, so the two ends of the raw range bound it, and an integer gives a finite value):
        the per-frame range check skips it, with the same outcome as ``FrameCodec.out_of_range``.
        """
        codec = self.codec
        health = self.health[name]
        bit = INPUT_MESSAGE_BITS[name]
        modulus = self._modulus[name]
        layout = codec.plain_layout(name)
        if layout is None:
            return (name, health, codec.expected_length(name), -1, 0, modulus, None, bit)
        slot_of = dict(SIGNAL_SLOTS[name])
        counter = self._counter_signal[name]
        shift, cmask = -1, 0
        fields = []
        for signal, start, n, signed, scale, offset, lo, hi in layout:
            if signal == counter:
                if scale != 1.0 or offset != 0.0:  # the codec rejects such a counter; keep the generic path then
                    return (name, health, codec.expected_length(name), -1, 0, modulus, None, bit)
                shift, cmask = start, (1 << n) - 1
            sign_bit = 1 << (n - 1) if signed else 0
            raw_lo, raw_hi = (-(1 << (n - 1)), (1 << (n - 1)) - 1) if signed else (0, (1 << n) - 1)
            ends = (raw_lo * scale + offset, raw_hi * scale + offset)
            check = not (all(math.isfinite(v) for v in ends) and lo <= min(ends) and max(ends) <= hi)
            slot = slot_of.get(signal, -1)
            if check or slot >= 0:
                fields.append((start, (1 << n) - 1, sign_bit, 1 << n, scale, offset, lo, hi, check, slot))
        if counter is not None and shift < 0:
            return (name, health, codec.expected_length(name), -1, 0, modulus, None, bit)
        return (name, health, codec.expected_length(name), shift, cmask, modulus, tuple(fields), bit)

    def on_frame(self, timestamp: float, frame_id: int, data: bytes, *, extended: bool = False) -> None:
        plan = None if extended else self._plans.get(frame_id)
        if plan is None:
            self.unknown_ids += 1
            return
        name, h, length, shift, cmask, modulus, fields, bit = plan
        # exotic argument types (a float id, a list of ints, a memoryview) take the codec's own checks
        if fields is None or type(data) not in _BYTES_TYPES or type(frame_id) is not int:
            self._on_frame_generic(name, timestamp, frame_id, data)
            return
        # the codec's decode, unrolled for this message: DLC check, then integer unpacking of only the
        # signals needed (plain Intel integers cannot be garbage once the length is right)
        if len(data) != length:
            h.decode_errors += 1
            self._reasons |= REASON_DECODE_ERRORS
            return
        h.frames += 1
        word = int.from_bytes(data, "little")
        if shift >= 0:
            c = (word >> shift) & cmask
            last = h.last_counter
            if last is not None and (c - last) % modulus != 1:
                h.counter_jumps += 1
                self._reasons |= REASON_COUNTER_JUMPS
            h.last_counter = c
        values = []
        for start, mask, sign_bit, full, scale, offset, lo, hi, check, slot in fields:
            raw = (word >> start) & mask
            if raw & sign_bit:
                raw -= full
            v = raw * scale + offset
            if check and not lo <= v <= hi:
                h.out_of_range += 1
                self._reasons |= REASON_OUT_OF_RANGE
                return
            if slot >= 0:
                values.append((slot, v))
        row = self._row
        for slot, v in values:
            row[slot] = v
        h.last_valid_time = timestamp
        self._fresh |= bit

    def _on_frame_generic(self, name: str, timestamp: float, frame_id: int, data: bytes) -> None:
        """Any frame through ``FrameCodec.decode`` (data not bytes, or a message layout not unpacked here)."""
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
            self._row[index] = values[signal]
        h.last_valid_time = timestamp
        self._fresh |= INPUT_MESSAGE_BITS[name]

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
        if sample.dtype is _FLOAT64 and sample.shape == _SAMPLE_SHAPE and sample.flags.c_contiguous:
            self._row_struct.pack_into(sample, 0, *row)  # float64 bytes straight into the array's buffer
        else:  # any other array: as numpy assigns it
            sample[:] = 0.0
            sample[:SAMPLE_SIZE] = row
        self._fresh = 0
        self._reasons = 0

    def stale_bits(self) -> int:
        """MSG_* bits of the inputs stale at the last ``fill`` (all of them before the first)."""
        return self._stale_bits

    def summary(self) -> dict:
        out = {name: h.as_dict() for name, h in self.health.items()}
        out["unknown_ids"] = self.unknown_ids
        return out
