"""Estimates -> the estimator's output frames (EST_* messages of the DBC), for the shared cycle.

Every cycle: EST_Roll, EST_RiderTorque and EST_Lateral (100 Hz); every ``period`` cycles (10 Hz for a 10 ms
cycle) EST_Status and EST_TireStiffness. This module maps Estimates to signal values (validity bits from
E_VALID and the mode, a non-finite estimate sent as the signal's neutral value and marked invalid, the rolling
counters); the bytes come from the codec's compiled message (``MessageLayout.pack``: bit layout, clipping,
rounding and E2E Profile 11 CRC). ``tests/test_outputs.py`` checks the frames are byte-identical to
``FrameCodec.encode`` and to cantools.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

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
    E_PLAUSIBILITY,
    E_REASONS,
    E_RIDER_TORQUE,
    E_ROLL,
    E_ROLL_RATE,
    E_STEER,
    E_STEER_RATE,
    E_TORQUE_RESIDUAL,
    E_TORQUE_UIO_SENSORS,
    E_TYRE_LEARNING,
    E_TYRE_LOG_SD,
    E_TYRE_NIS,
    E_TYRE_SCALE,
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
    # diagnostics of the tyre estimate: no per-signal validity; the message is valid while the estimator runs
    "EST_TireConfidence": (
        ("TireScale", E_TYRE_SCALE, 0),
        ("TireScaleLogSd", E_TYRE_LOG_SD, 0),
        ("TireModelConsistency", E_TYRE_NIS, 0),
        ("TireLearning", E_TYRE_LEARNING, 0),
    ),
    # the plausibility monitor (issue #16): diagnostics, valid while the estimator runs
    "EST_Plausibility": (
        ("TorqueResidual", E_TORQUE_RESIDUAL, 0),
        ("PlausibilityRatio", E_PLAUSIBILITY, 0),
        ("RiderTorqueUIHOSMO", E_TORQUE_UIO_SENSORS, 0),
    ),
}
# group validity bits of EST_TireStiffness
_STIFFNESS_VALID = (("CorneringStiffness_Valid", V_CORNERING), ("CamberStiffness_Valid", V_CAMBER))
FAST_MESSAGES = ("EST_Roll", "EST_RiderTorque", "EST_Lateral")
SLOW_MESSAGES = ("EST_Status", "EST_TireStiffness", "EST_TireConfidence", "EST_Plausibility")
# slow messages encoded from SIGNAL_MAP (EST_Status has its own encoder)
_SLOW_SIGNAL_MESSAGES = tuple(name for name in SLOW_MESSAGES if name in SIGNAL_MAP)
_STATUS_SIGNALS = ("Mode", "SensorTimeouts", "ReasonBits", "OverrunCount", "CycleTimeUs")


class OutputEncoder:
    """Estimates of one cycle -> the list of ``(frame_id, data)`` to send in that cycle.

    ``sample_time`` is the estimator's cycle (s); the slow messages go out every
    ``round(cycle_time_s / sample_time)`` cycles, starting with cycle index 0.
    """

    def __init__(self, codec: FrameCodec, sample_time: float = 0.01) -> None:
        self.codec = codec
        self.sample_time = float(sample_time)
        # message -> (layout, values list reused every frame, ((Estimates index, V bit, position), ...),
        # ((V bit, position of its *_Valid signal), ...), position of <msg>_Valid, V bits of the message's group,
        # counter position, counter modulus): everything a frame needs, resolved once, not per frame
        self._plans: dict[str, tuple] = {}
        for name, slots in SIGNAL_MAP.items():
            layout = codec.layout(name)
            pos = layout.index
            analog = tuple((e_index, vbit, pos[signal]) for signal, e_index, vbit in slots)
            vflags = [(vbit, pos[f"{signal}_Valid"]) for signal, _, vbit in slots if f"{signal}_Valid" in pos]
            group = 0
            for _, _, vbit in slots:
                group |= vbit
            if name == "EST_TireStiffness":
                for vname, vbit in _STIFFNESS_VALID:
                    vflags.append((vbit, pos[vname]))
                    group |= vbit
            covered = {pos[f"{name}_Valid"], pos[layout.counter_signal]} | {p for *_, p in analog}
            covered |= {p for _, p in vflags} | ({pos[layout.crc_signal]} if layout.crc_signal else set())
            unmapped = set(layout.names) - {layout.names[p] for p in covered}
            if unmapped:
                raise ValueError(f"{name}: signals {sorted(unmapped)} have no source in the Estimates")
            self._plans[name] = (
                layout,
                [0.0] * len(layout.names),
                analog,
                tuple(vflags),
                pos[f"{name}_Valid"],
                group,
                pos[layout.counter_signal],
                layout.counter_modulus,
            )
        self._status = codec.layout("EST_Status")
        self._status_pos = tuple(self._status.index[n] for n in (*_STATUS_SIGNALS, "EST_Status_Valid"))
        self._status_counter = self._status.index[self._status.counter_signal]
        names = (*SIGNAL_MAP, "EST_Status")
        self._modulus = {name: codec.counter_modulus(name) for name in names}
        self.counters = dict.fromkeys(names, 0)
        self.frames_sent = dict.fromkeys(names, 0)
        self.periods = {name: max(1, round(codec.cycle_time_s(name) / self.sample_time)) for name in names}

    # ------------------------------------------------------------------ helpers

    def _next(self, name: str) -> int:
        c = self.counters[name]
        self.counters[name] = c + 1 if c + 1 < self._modulus[name] else 0
        self.frames_sent[name] += 1
        return c

    def _signal_frame(self, name: str, est: list[float], mode_ok: bool, valid: int) -> tuple[int, bytes]:
        layout, values, analog, vflags, msg_valid_pos, group, counter_pos, modulus = self._plans[name]
        for index, vbit, p in analog:
            v = est[index]
            if v - v != 0.0:  # NaN or inf: never a number on the wire; the neutral value, marked invalid
                valid &= ~vbit
                v = math.nan
            values[p] = v
        for vbit, p in vflags:
            values[p] = 1.0 if valid & vbit else 0.0
        # a message of diagnostics (no V_* bit in its group) is valid whenever the estimator runs
        values[msg_valid_pos] = 1.0 if mode_ok and (group == 0 or valid & group) else 0.0
        # the message's rolling counter (as _next, inline)
        counters = self.counters
        c = counters[name]
        counters[name] = c + 1 if c + 1 < modulus else 0
        self.frames_sent[name] += 1
        values[counter_pos] = c
        return layout.frame_id, layout.pack(values)

    def status_frame(
        self,
        estimates: np.ndarray,
        stale_bits: int,
        status: Mapping[str, float],
        *,
        valid: bool = True,
        reasons: int = 0,
    ) -> tuple[int, bytes]:
        """One EST_Status frame (advances its counter). ``valid=False`` for the daemon's last frame at exit.

        ``reasons``: REASON_* bits of the process itself (overrun, send failure), OR-ed into ``ReasonBits``
        beside the estimator's own.
        """
        layout = self._status
        mode = float(estimates[E_MODE])
        core_reasons = float(estimates[E_REASONS])
        values = [0.0] * len(layout.names)
        for p, v in zip(
            self._status_pos,
            (
                mode if math.isfinite(mode) else float(MODE_FAULT),
                float(int(stale_bits) & 0xF),
                float((int(core_reasons) if math.isfinite(core_reasons) else 0) & 0xFFFF | reasons & 0xFFFF),
                float(min(int(status.get("overrun_count", 0)), 65535)),
                float(min(int(status.get("cycle_time_us", 0)), 65535)),
                1.0 if valid else 0.0,
            ),
            strict=True,
        ):
            values[p] = v
        values[self._status_counter] = self._next("EST_Status")
        return layout.frame_id, layout.pack(values)

    # ------------------------------------------------------------------ per cycle

    def frames(
        self,
        estimates: np.ndarray,
        cycle_index: int,
        status: Mapping[str, float] | None = None,
        stale_bits: int = 0,
        reasons: int = 0,
    ) -> list[tuple[int, bytes]]:
        """The frames of cycle ``cycle_index`` (0, 1, ...): the 100 Hz messages, and the 10 Hz ones when due.

        ``status``: ``overrun_count`` and ``cycle_time_us`` (worst over the status period) for EST_Status.
        ``stale_bits``: MSG_* bits of the inputs timed out (``InputTracker.stale_bits()``), EST_Status.SensorTimeouts.
        ``reasons``: REASON_* bits of the process (overrun, send failure) for EST_Status.ReasonBits.
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
            out.append(self.status_frame(estimates, stale_bits, status or {}, reasons=reasons))
        for name in _SLOW_SIGNAL_MESSAGES:
            if cycle_index % periods[name] == 0:
                out.append(self._signal_frame(name, est, mode_ok, valid))
        return out
