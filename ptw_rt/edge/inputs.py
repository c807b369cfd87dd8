"""Received frames -> one Sample per cycle, with the health of every input message.

Frames arrive asynchronously; each cycle takes the newest valid frame of each input
received since the previous cycle. Every kind of bad input is counted per message and
raised as a reason bit of the cycle in which it was seen:
- a frame that cannot be decoded (wrong DLC, garbage)      -> decode_errors
- a signal outside its DBC range or not finite (frame dropped) -> out_of_range
- a rolling counter that skipped or repeated                   -> counter_jumps
  (a frame that continues the last in-sequence one, counting the frames between, is in sequence)
- no valid frame within `stale_after_periods` cycle times      -> SensorTimeouts bit + sensor_stale
Unknown identifiers are counted and otherwise ignored (they are someone else's traffic).
Nothing here raises on bad data. Frames are unpacked by the codec's compiled message (``MessageLayout``); what
happens to the values is the compiled tracker's (``ptw_rt.edge.tracking``), the one implementation of these
rules that replay's compiled loop also runs: nothing here knows a bit layout.
``on_values`` takes an input's signals from another source than a CAN frame (a serial GNSS receiver for
``GPS_Velocity``) into the same Sample slots, range checks and timeout.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping

import numpy as np

from ptw_rt.core.layout import (
    INPUT_MESSAGE_BITS,
    S_ACCEL_X,
    S_ACCEL_Y,
    S_ACCEL_Z,
    S_GPS_COURSE,
    S_GPS_FIX,
    S_GPS_SPEED,
    S_PITCH_RATE_BODY,
    S_ROLL_RATE_BODY,
    S_STEER_COUNT,
    S_YAW_RATE_BODY,
)
from ptw_rt.edge import tracking as tr
from ptw_rt.io.dbc import FrameCodec, FrameDecodeError, MessageLayout

_BYTES_TYPES = (bytes, bytearray)

# message -> ((signal, Sample index), ...), in input order (the compiled tracker's input k)
SIGNAL_SLOTS: dict[str, tuple[tuple[str, int], ...]] = {
    "IMU_Rates": (("RollRate", S_ROLL_RATE_BODY), ("PitchRate", S_PITCH_RATE_BODY), ("YawRate", S_YAW_RATE_BODY)),
    "IMU_Accel": (("AccelX", S_ACCEL_X), ("AccelY", S_ACCEL_Y), ("AccelZ", S_ACCEL_Z)),
    "Steer_Encoder": (("SteerCount", S_STEER_COUNT),),
    "GPS_Velocity": (("SpeedOverGround", S_GPS_SPEED), ("FixType", S_GPS_FIX), ("CourseOverGround", S_GPS_COURSE)),
}
INPUT_NAMES = tuple(SIGNAL_SLOTS)
assert len(INPUT_NAMES) == tr.N_INPUTS
# inputs whose noise spans many LSBs (gyro 0.002 rad/s rms at 0.0001 rad/s, accelerometer 0.03 m/s^2 at 0.001:
# 20-30 LSB), so a payload repeated this many times is a sensor that stopped measuring, not a value that held (the
# encoder's count and the GPS's speed do hold); a MEMS gyro of a tenth of that noise repeats one in ~10^9 frames
FROZEN_AFTER_FRAMES = {"IMU_Rates": 10, "IMU_Accel": 10}


def tracker_params(codec: FrameCodec, stale_after_periods: float) -> tuple[np.ndarray, tuple[MessageLayout, ...]]:
    """The compiled tracker's parameter vector (``tracking.PARAMS``) for the inputs of ``codec``'s DBC, and the
    inputs' message layouts in input order.

    Range checks only for the signals whose raw field can decode outside the DBC [min, max]
    (``SignalLayout.can_exceed``): for the others the check could never fail."""
    p = np.zeros(tr.PARAMS.size)
    p[tr.TP_COUNTER_POS : tr.TP_COUNTER_POS + tr.N_INPUTS] = -1.0
    p[tr.TP_SLOT : tr.TP_SLOT + tr.N_INPUTS * tr.MAX_SIGNALS] = -1.0
    layouts = []
    for k, name in enumerate(INPUT_NAMES):
        layout = codec.layout(name)
        layouts.append(layout)
        if len(layout.signals) > tr.MAX_SIGNALS:
            raise ValueError(f"{name}: more than {tr.MAX_SIGNALS} signals")
        p[tr.TP_TIMEOUT + k] = stale_after_periods * codec.cycle_time_s(name)
        p[tr.TP_BIT + k] = INPUT_MESSAGE_BITS[name]
        p[tr.TP_N_SIGNALS + k] = len(layout.signals)
        if layout.counter_signal is not None:
            p[tr.TP_COUNTER_POS + k] = layout.index[layout.counter_signal]
            p[tr.TP_MODULUS + k] = layout.counter_modulus
        p[tr.TP_CRC_POS + k] = -1.0 if layout.crc_signal is None else layout.index[layout.crc_signal]
        p[tr.TP_FROZEN_AFTER + k] = FROZEN_AFTER_FRAMES.get(name, 0)
        base = k * tr.MAX_SIGNALS
        for j, s in enumerate(layout.signals):
            p[tr.TP_CHECK + base + j] = 1.0 if s.can_exceed else 0.0
            p[tr.TP_LO + base + j] = s.lo
            p[tr.TP_HI + base + j] = s.hi
        for signal, slot in SIGNAL_SLOTS[name]:
            p[tr.TP_SLOT + base + layout.index[signal]] = slot
    p[tr.TP_IMU] = INPUT_NAMES.index("IMU_Rates")
    p[tr.TP_STEER] = INPUT_NAMES.index("Steer_Encoder")
    p[tr.TP_GPS] = INPUT_NAMES.index("GPS_Velocity")
    return p, tuple(layouts)


class InputTracker:
    """Frames in, one Sample per cycle out: the compiled tracker (``ptw_rt.edge.tracking``) behind the calls of
    a live bus. ``state``/``params`` are its arrays (replay's compiled loop runs on the same ones)."""

    def __init__(self, codec: FrameCodec, stale_after_periods: float = 3.0) -> None:
        self.codec = codec
        self.stale_after_periods = stale_after_periods
        self.params, self.layouts = tracker_params(codec, stale_after_periods)
        self.state = tr.initial_state()
        self._input = {name: k for k, name in enumerate(INPUT_NAMES)}
        # (frame id, extended) -> (input k, layout, values buffer, struct that packs the values into it)
        self._values = np.zeros(tr.MAX_SIGNALS)
        self._by_id: dict[tuple[int, bool], tuple] = {}
        for k, layout in enumerate(self.layouts):
            packer = struct.Struct(f"={len(layout.signals)}d")
            self._by_id[(layout.frame_id, bool(layout.message.is_extended_frame))] = (k, layout, packer)

    def input_of(self, frame_id: object, extended: bool = False) -> tuple[int, MessageLayout] | None:
        """``(input index, layout)`` of the input message with this identifier, None for someone else's."""
        plan = self._by_id.get((frame_id, extended))
        return None if plan is None else plan[:2]

    @property
    def unknown_ids(self) -> int:
        return int(self.state[tr.TR_UNKNOWN_IDS])

    def on_frame(self, timestamp: float, frame_id: int, data: bytes, *, extended: bool = False) -> None:
        plan = self._by_id.get((frame_id, extended))
        if plan is None:
            tr.track_unknown(self.state)
            return
        k, layout, packer = plan
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
            tr.track_decode_error(self.state, k, 1.0)
            return
        packer.pack_into(self._values, 0, *values)  # float64 bytes straight into the buffer (no numpy call)
        tr.track_values(self.state, self.params, k, float(timestamp), self._values, True)

    def on_values(self, message: str, timestamp: float, signals: Mapping[str, float]) -> None:
        """Signals of input ``message`` from a source other than a CAN frame (no counter). A signal not given is
        taken as its neutral value; the given ones are range checked and copied as a frame's would be."""
        k = self._input[message]
        layout = self.layouts[k]
        values = self._values
        for j, s in enumerate(layout.signals):
            values[j] = float(signals.get(s.name, s.neutral))
        tr.track_values(self.state, self.params, k, float(timestamp), values, False)

    def restart(self) -> None:
        """Forget every input's state (values, freshness, rolling counters) as at construction; the cumulative
        counters of ``summary`` are kept. For a new segment of a log after a time discontinuity: nothing seen
        before it may be taken as the last value, nor a counter continue across it."""
        tr.track_restart(self.state)

    def decode_error(self, message: str, count: int = 1) -> None:
        """``count`` records of ``message`` arrived that could not be decoded (serial lines with a bad checksum)."""
        tr.track_decode_error(self.state, self._input[message], float(count))

    def lost(self, message: str) -> None:
        """The source of ``message`` is gone (a serial receiver unplugged): stale from the next ``fill`` on,
        without waiting for its timeout."""
        self.state[tr.TR_LAST_VALID + self._input[message]] = -math.inf

    def fill(self, sample: np.ndarray, now: float) -> None:
        """Write the cycle's Sample at time `now` and start collecting the next cycle."""
        tr.track_fill(self.state, self.params, sample, float(now))

    def stale_bits(self) -> int:
        """MSG_* bits of the inputs stale at the last ``fill`` (all of them before the first)."""
        return int(self.state[tr.TR_STALE_BITS])

    def summary(self) -> dict:
        s = self.state
        out: dict = {}
        for k, name in enumerate(INPUT_NAMES):
            out[name] = {key: int(s[offset + k]) for key, offset in tr.COUNTS}
            out[name]["stale"] = bool(s[tr.TR_STALE + k])
        out["unknown_ids"] = self.unknown_ids
        return out
