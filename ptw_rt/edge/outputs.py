"""Estimates -> the estimator's output frames (EST_* messages of the DBC), shared by the daemon and replay.

Every cycle: EST_Roll, EST_RiderTorque and EST_Lateral (100 Hz); every ``period`` cycles (10 Hz for a 10 ms
sample time, from the DBC's ``GenMsgCycleTime``): EST_Status and EST_TireStiffness. Each message has its own
rolling counter 0..14 (wraps 14 -> 0), advanced once per sent frame.

Validity:

* per-signal ``<Signal>_Valid`` bits are the estimator's ``E_VALID`` bits, unchanged;
* the message bit ``<Message>_Valid`` is 1 when the mode is neither INIT nor FAULT AND at least one signal of the
  message is valid (so a consumer checks the message bit first, then the signal bit);
* ``EST_Status_Valid`` is 1 while the loop runs; the daemon's last frame at shutdown carries 0.

Speed: the frames are packed here with a bit layout precomputed from the codec's DBC (Intel byte order, integer
signals, values clipped to the codec's limits, rounded exactly as cantools does) and E2E Profile 11 protection
from ``ptw_rt.io.e2e``. ``tests/test_outputs.py`` checks the result is byte-identical to ``FrameCodec.encode``.
A message whose layout the fast packer does not cover (Motorola order, float signals) falls back to
``FrameCodec.encode``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from ptw_rt.core.layout import (
    E_C_ALPHA_FRONT,
    E_C_ALPHA_REAR,
    E_C_GAMMA_FRONT,
    E_C_GAMMA_REAR,
    E_FY_FRONT,
    E_FY_REAR,
    E_LAT_VEL,
    E_MODE,
    E_REASONS,
    E_RIDER_TORQUE,
    E_ROLL,
    E_ROLL_RATE,
    E_STEER,
    E_STEER_RATE,
    E_VALID,
    MODE_FAULT,
    MODE_INIT,
    V_CAMBER,
    V_CORNERING,
    V_FY_FRONT,
    V_FY_REAR,
    V_LAT_VEL,
    V_RIDER_TORQUE,
    V_ROLL,
    V_ROLL_RATE,
    V_STEER,
    V_STEER_RATE,
)
from ptw_rt.io.dbc import FrameCodec
from ptw_rt.io.e2e import profile11_crc_seeded, profile11_seed

__all__ = ["FAST_MESSAGES", "SLOW_MESSAGES", "OutputEncoder", "SIGNAL_MAP"]

# message -> ((signal, Estimates index, V_* bit of its <signal>_Valid or 0), ...)
SIGNAL_MAP: dict[str, tuple[tuple[str, int, int], ...]] = {
    "EST_Roll": (("RollAngle", E_ROLL, V_ROLL), ("RollRateEst", E_ROLL_RATE, V_ROLL_RATE)),
    "EST_RiderTorque": (
        ("RiderTorque", E_RIDER_TORQUE, V_RIDER_TORQUE),
        ("SteerAngleEst", E_STEER, V_STEER),
        ("SteerRateEst", E_STEER_RATE, V_STEER_RATE),
    ),
    "EST_Lateral": (
        ("LateralVelocity", E_LAT_VEL, V_LAT_VEL),
        ("FrontLateralForce", E_FY_FRONT, V_FY_FRONT),
        ("RearLateralForce", E_FY_REAR, V_FY_REAR),
    ),
    "EST_TireStiffness": (
        ("FrontCorneringStiffness", E_C_ALPHA_FRONT, 0),
        ("RearCorneringStiffness", E_C_ALPHA_REAR, 0),
        ("FrontCamberStiffness", E_C_GAMMA_FRONT, 0),
        ("RearCamberStiffness", E_C_GAMMA_REAR, 0),
    ),
}
# group validity bits of EST_TireStiffness
_STIFFNESS_VALID = (("CorneringStiffness_Valid", V_CORNERING), ("CamberStiffness_Valid", V_CAMBER))
FAST_MESSAGES = ("EST_Roll", "EST_RiderTorque", "EST_Lateral")
SLOW_MESSAGES = ("EST_Status", "EST_TireStiffness")
_STATUS_SIGNALS = ("Mode", "SensorTimeouts", "ReasonBits", "OverrunCount", "CycleTimeUs")


def _neutral(lo: float, hi: float) -> float:
    """What a NaN is sent as: 0 if the range holds it, else the range's lower end."""
    return 0.0 if lo <= 0.0 <= hi else lo


class _Packer:
    """Precomputed bit layout of one message, packing as FrameCodec.encode does (clip, round, E2E CRC).

    ``pack(values, flags, counter)``: ``values`` are the numeric signals in ``analog`` order, ``flags`` an int
    of the already-shifted 1-bit signals (``bit[name]``), ``counter`` the rolling counter.
    """

    def __init__(self, codec: FrameCodec, message: str, analog: Sequence[str]) -> None:
        msg = codec.database.get_message_by_name(message)
        self.codec = codec
        self.message = message
        self.frame_id = codec.frame_id(message)
        self.length = msg.length
        self.crc_signal = codec.crc_signal(message)
        self.counter_signal = codec.counter_signal(message)
        self.analog = tuple(analog)
        sigs = {s.name: s for s in msg.signals}
        self.flag_names = tuple(
            n for n, s in sigs.items() if n not in self.analog and n not in (self.crc_signal, self.counter_signal)
        )
        covered = set(self.analog) | set(self.flag_names) | {self.crc_signal, self.counter_signal} - {None}
        self.fast = (
            all(s.byte_order == "little_endian" and not s.is_float for s in msg.signals)
            and all(sigs[n].length == 1 and sigs[n].scale == 1 and sigs[n].offset == 0 for n in self.flag_names)
            and covered == set(sigs)
        )
        self.bit = {n: 1 << sigs[n].start for n in self.flag_names}
        self.counter_shift = sigs[self.counter_signal].start if self.counter_signal else 0
        # the CRC register after the Data ID, the same for every frame of this message
        self.crc_seed = None if self.crc_signal is None else profile11_seed(self.frame_id)
        limits = codec.signal_limits(message)
        # (start, mask, scale, offset, min, max, value sent for NaN) per analog signal
        self.fields = tuple(
            (
                sigs[n].start,
                (1 << sigs[n].length) - 1,
                float(sigs[n].scale),
                float(sigs[n].offset),
                *limits[n],
                _neutral(*limits[n]),
            )
            for n in self.analog
        )

    def finish(self, word: int) -> bytes:
        """The frame's bytes from its packed integer (counter included), with the Profile 11 CRC in byte 0."""
        data = word.to_bytes(self.length, "little")
        if self.crc_seed is None:
            return data
        # byte 0 is replaced, as protect_p11 does on the frame
        return ((word & ~0xFF) | profile11_crc_seeded(self.crc_seed, data)).to_bytes(self.length, "little")

    def pack(self, values: Sequence[float], flags: int, counter: int) -> bytes:
        if not self.fast:
            signals = dict(zip(self.analog, values, strict=True))
            signals.update({n: 1.0 if flags & b else 0.0 for n, b in self.bit.items()})
            return self.codec.encode(self.message, signals, counter=counter)[1]
        word = flags | (counter << self.counter_shift)
        for v, (start, mask, scale, offset, lo, hi, neutral) in zip(values, self.fields, strict=True):
            if v < lo:
                v = lo
            elif v > hi:
                v = hi
            elif v != v:  # NaN (the caller has marked the signal invalid): send the neutral value
                v = neutral
            if v == 0.0 and offset == 0.0:
                continue
            # FrameCodec.encode's rounding (the same as cantools' numeric_scaled_to_raw: where that takes the
            # divmod quotient, the remainder is 0, so the quotient is an integer and equals the division exactly)
            raw = round((v - offset) / scale)
            word |= (raw & mask) << start
        return self.finish(word)


class OutputEncoder:
    """Estimates of one cycle -> the list of ``(frame_id, data)`` to send in that cycle.

    ``sample_time`` is the estimator's cycle (s); the slow messages go out every
    ``round(cycle_time_s / sample_time)`` cycles, starting with cycle index 0.
    """

    def __init__(self, codec: FrameCodec, sample_time: float = 0.01) -> None:
        self.codec = codec
        self.sample_time = float(sample_time)
        self._packers: dict[str, _Packer] = {}
        # message -> (packer, ((Estimates index, V bit, *packer field), ...), ((V bit, shifted <signal>_Valid bit),
        # ...), <msg>_Valid bit, group, counter modulus): everything a frame needs, resolved once, not per frame
        self._plans: dict[str, tuple] = {}
        for name, slots in SIGNAL_MAP.items():
            p = _Packer(codec, name, [signal for signal, _, _ in slots])
            self._packers[name] = p
            vbits = [(vbit, p.bit[f"{signal}_Valid"]) for signal, _, vbit in slots if f"{signal}_Valid" in p.bit]
            group = 0
            for _, _, vbit in slots:
                group |= vbit
            if name == "EST_TireStiffness":
                for vname, vbit in _STIFFNESS_VALID:
                    vbits.append((vbit, p.bit[vname]))
                    group |= vbit
            fields = tuple((e_index, vbit, *f) for (_, e_index, vbit), f in zip(slots, p.fields, strict=True))
            modulus = codec.counter_modulus(name)
            self._plans[name] = (p, fields, tuple(vbits), p.bit[f"{name}_Valid"], group, modulus)
        self._status = _Packer(codec, "EST_Status", _STATUS_SIGNALS)
        self._packers["EST_Status"] = self._status
        self._modulus = {name: codec.counter_modulus(name) for name in self._packers}
        self.counters = dict.fromkeys(self._packers, 0)
        self.frames_sent = dict.fromkeys(self._packers, 0)
        self.periods = {name: max(1, round(codec.cycle_time_s(name) / self.sample_time)) for name in self._packers}

    # ------------------------------------------------------------------ helpers

    def _next(self, name: str) -> int:
        c = self.counters[name]
        self.counters[name] = c + 1 if c + 1 < self._modulus[name] else 0
        self.frames_sent[name] += 1
        return c

    def _signal_frame(self, name: str, est: list[float], mode_ok: bool, valid: int) -> tuple[int, bytes]:
        p, fields, vbits, msg_valid_bit, group, modulus = self._plans[name]
        if not p.fast:
            return self._signal_frame_codec(name, est, mode_ok, valid)
        # the hot path: clip and pack each signal into one integer right here (what _Packer.pack does, without
        # the intermediate list and calls)
        word = 0
        for index, vbit, start, mask, scale, offset, lo, hi, neutral in fields:
            v = est[index]
            if not lo <= v <= hi:  # rare: clip, or (NaN, inf) never a number on the wire: neutral value, invalid
                if not math.isfinite(v):
                    valid &= ~vbit
                    v = neutral
                elif v < lo:
                    v = lo
                else:
                    v = hi
            word |= (round((v - offset) / scale) & mask) << start  # rounding: see _Packer.pack
        for vbit, bit in vbits:
            if valid & vbit:
                word |= bit
        if mode_ok and valid & group:
            word |= msg_valid_bit
        # the message's rolling counter (as _next, inline)
        counters = self.counters
        c = counters[name]
        counters[name] = c + 1 if c + 1 < modulus else 0
        self.frames_sent[name] += 1
        return p.frame_id, p.finish(word | (c << p.counter_shift))

    def _signal_frame_codec(self, name: str, est: list[float], mode_ok: bool, valid: int) -> tuple[int, bytes]:
        """``_signal_frame`` through ``_Packer.pack`` (a layout the fast packer does not cover)."""
        p, fields, vbits, msg_valid_bit, group, _ = self._plans[name]
        values = [est[f[0]] for f in fields]
        for k, v in enumerate(values):
            if not math.isfinite(v):  # never a number on the wire: neutral value, signal invalid
                values[k] = math.nan
                valid &= ~fields[k][1]
        flags = 0
        for vbit, bit in vbits:
            if valid & vbit:
                flags |= bit
        if mode_ok and valid & group:
            flags |= msg_valid_bit
        return p.frame_id, p.pack(values, flags, self._next(name))

    def status_frame(
        self, estimates: np.ndarray, stale_bits: int, status: Mapping[str, float], *, valid: bool = True
    ) -> tuple[int, bytes]:
        """One EST_Status frame (advances its counter). ``valid=False`` for the daemon's last frame at exit."""
        p = self._status
        mode = float(estimates[E_MODE])
        reasons = float(estimates[E_REASONS])
        values = (
            mode if math.isfinite(mode) else float(MODE_FAULT),
            float(int(stale_bits) & 0xF),
            float(int(reasons) & 0xFFFF) if math.isfinite(reasons) else 0.0,
            float(min(int(status.get("overrun_count", 0)), 65535)),
            float(min(int(status.get("cycle_time_us", 0)), 65535)),
        )
        flags = p.bit["EST_Status_Valid"] if valid else 0
        return p.frame_id, p.pack(values, flags, self._next("EST_Status"))

    # ------------------------------------------------------------------ per cycle

    def frames(
        self,
        estimates: np.ndarray,
        cycle_index: int,
        status: Mapping[str, float] | None = None,
        stale_bits: int = 0,
    ) -> list[tuple[int, bytes]]:
        """The frames of cycle ``cycle_index`` (0, 1, ...): the 100 Hz messages, and the 10 Hz ones when due.

        ``status``: ``overrun_count`` and ``cycle_time_us`` (worst over the status period) for EST_Status.
        ``stale_bits``: MSG_* bits of the inputs timed out (``InputTracker.stale_bits()``), EST_Status.SensorTimeouts.
        """
        est = estimates.tolist()
        mode = est[E_MODE]
        mode_ok = mode == mode and int(mode) not in (MODE_INIT, MODE_FAULT)
        v = est[E_VALID]
        valid = int(v) if v == v else 0
        periods = self.periods
        out = [
            self._signal_frame(name, est, mode_ok, valid) for name in FAST_MESSAGES if cycle_index % periods[name] == 0
        ]
        if cycle_index % periods["EST_Status"] == 0:
            out.append(self.status_frame(estimates, stale_bits, status or {}))
        if cycle_index % periods["EST_TireStiffness"] == 0:
            out.append(self._signal_frame("EST_TireStiffness", est, mode_ok, valid))
        return out
