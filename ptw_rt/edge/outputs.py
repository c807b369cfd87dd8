"""Estimates -> the estimator's output frames (EST_* messages of the DBC), for the shared cycle.

Every cycle: EST_Roll, EST_RiderTorque and EST_Lateral (100 Hz); every ``period`` cycles (10 Hz for a 10 ms
cycle) EST_Status, EST_TireStiffness, EST_TireConfidence and EST_Plausibility. This module says which Estimates
slot and which V_* bit every signal of every EST_* message carries (``SIGNAL_MAP``) and turns that, with the
DBC's bit layouts, into the plan of the compiled encoder (``ptw_rt.edge.encoding``), which does the per-frame
work for the daemon and for replay alike. ``tests/test_outputs.py`` checks the frames are byte-identical to
``FrameCodec.encode`` and to cantools.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, MutableMapping

import numpy as np

from ptw_rt.core.layout import (
    E_C_ALPHA_FRONT,
    E_C_ALPHA_REAR,
    E_C_GAMMA_FRONT,
    E_C_GAMMA_REAR,
    E_FY_FRONT,
    E_FY_REAR,
    E_LAT_VEL,
    E_PITCH_DOUBTED,
    E_PLAUSIBILITY,
    E_RIDER_TORQUE,
    E_ROLL,
    E_ROLL_RATE,
    E_ROLL_UIO_SENSORS,
    E_STEER,
    E_STEER_RATE,
    E_STEER_RESIDUAL,
    E_STEER_ZERO_DOUBTED,
    E_TORQUE_RESIDUAL,
    E_TORQUE_UIO_SENSORS,
    E_TYRE_BALANCE_DOUBTED,
    E_TYRE_CHANGE,
    E_TYRE_LEARNING,
    E_TYRE_LOG_SD,
    E_TYRE_NIS,
    E_TYRE_SCALE,
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
from ptw_rt.edge import encoding as en
from ptw_rt.io.dbc import FrameCodec, MessageLayout
from ptw_rt.io.e2e import profile11_seed

__all__ = ["FAST_MESSAGES", "SLOW_MESSAGES", "OutputEncoder", "SIGNAL_MAP"]

# message -> ((signal, Estimates index, V_* bit of its <signal>_Valid or 0), ...)
SIGNAL_MAP: dict[str, tuple[tuple[str, int, int], ...]] = {
    "EST_Roll": (
        ("RollAngle", E_ROLL, V_ROLL),
        ("RollRateEst", E_ROLL_RATE, V_ROLL_RATE),
        # the UIHOSMO channel's own roll (issue #16): a diagnostic beside the published one, no valid bit
        ("RollUIHOSMO", E_ROLL_UIO_SENSORS, 0),
    ),
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
        ("TireChange", E_TYRE_CHANGE, 0),
        ("PitchDoubted", E_PITCH_DOUBTED, 0),
        ("TireBalanceDoubted", E_TYRE_BALANCE_DOUBTED, 0),
        ("SteerZeroDoubted", E_STEER_ZERO_DOUBTED, 0),
    ),
    # the plausibility monitor (issue #16): diagnostics, valid while the estimator runs
    "EST_Plausibility": (
        ("TorqueResidual", E_TORQUE_RESIDUAL, 0),
        ("PlausibilityRatio", E_PLAUSIBILITY, 0),
        ("RiderTorqueUIHOSMO", E_TORQUE_UIO_SENSORS, 0),
        ("SteerKinematicResidual", E_STEER_RESIDUAL, 0),
    ),
}
# group validity bits of EST_TireStiffness
_STIFFNESS_VALID = (("CorneringStiffness_Valid", V_CORNERING), ("CamberStiffness_Valid", V_CAMBER))
FAST_MESSAGES = ("EST_Roll", "EST_RiderTorque", "EST_Lateral")
SLOW_MESSAGES = ("EST_Status", "EST_TireStiffness", "EST_TireConfidence", "EST_Plausibility")
# slow messages encoded from SIGNAL_MAP (EST_Status has its own encoder)
_SLOW_SIGNAL_MESSAGES = tuple(name for name in SLOW_MESSAGES if name in SIGNAL_MAP)
_STATUS_SIGNALS = ("Mode", "SensorTimeouts", "ReasonBits", "OverrunCount", "CycleTimeUs")


OUTPUT_ORDER = (*FAST_MESSAGES, "EST_Status", *_SLOW_SIGNAL_MESSAGES)  # the order of a cycle's frames
_STATUS_ROLES = dict(
    zip(
        (*_STATUS_SIGNALS, "EST_Status_Valid"),
        (
            en.ROLE_MODE,
            en.ROLE_SENSOR_TIMEOUTS,
            en.ROLE_REASON_BITS,
            en.ROLE_OVERRUN_COUNT,
            en.ROLE_CYCLE_TIME_US,
            en.ROLE_STATUS_VALID,
        ),
        strict=True,
    )
)
assert len(OUTPUT_ORDER) == en.N_OUTPUTS


def _signal_roles(name: str, layout: MessageLayout) -> dict[str, tuple[int, int, int]]:
    """signal -> (role, Estimates index, V_* bit) for every signal of output message ``name``."""
    roles: dict[str, tuple[int, int, int]] = {layout.counter_signal: (en.ROLE_COUNTER, 0, 0)}
    if layout.crc_signal:
        roles[layout.crc_signal] = (en.ROLE_CRC, 0, 0)
    if name == "EST_Status":
        roles.update({signal: (role, 0, 0) for signal, role in _STATUS_ROLES.items()})
        return roles
    roles[f"{name}_Valid"] = (en.ROLE_MESSAGE_VALID, 0, 0)
    for signal, e_index, vbit in SIGNAL_MAP[name]:
        roles[signal] = (en.ROLE_ANALOG, e_index, vbit)
        if f"{signal}_Valid" in layout.index:
            roles[f"{signal}_Valid"] = (en.ROLE_FLAG, 0, vbit)
    if name == "EST_TireStiffness":
        for vname, vbit in _STIFFNESS_VALID:
            roles[vname] = (en.ROLE_FLAG, 0, vbit)
    return roles


def encoder_plan(codec: FrameCodec, sample_time: float) -> tuple[np.ndarray, tuple[MessageLayout, ...]]:
    """The compiled encoder's plan (``encoding.PLAN``, messages in ``OUTPUT_ORDER``) and their layouts.
    Every signal of every output message must have a source (ValueError otherwise)."""
    plan = np.zeros(en.PLAN_SIZE)
    layouts = []
    for m, name in enumerate(OUTPUT_ORDER):
        layout = codec.layout(name)
        layouts.append(layout)
        roles = _signal_roles(name, layout)
        unmapped = set(layout.names) - set(roles)
        if unmapped:
            raise ValueError(f"{name}: signals {sorted(unmapped)} have no source in the Estimates")
        if len(layout.signals) > en.MAX_SIGNALS:
            raise ValueError(f"{name}: more than {en.MAX_SIGNALS} signals")
        b = m * en.BLOCK
        plan[b + en.EM_FRAME_ID] = layout.frame_id
        plan[b + en.EM_LENGTH] = layout.length
        plan[b + en.EM_PERIOD] = max(1, round(codec.cycle_time_s(name) / sample_time))
        plan[b + en.EM_CRC_SEED] = -1 if layout.crc_signal is None else profile11_seed(layout.frame_id)
        plan[b + en.EM_MODULUS] = codec.counter_modulus(name)
        plan[b + en.EM_N_SIGNALS] = len(layout.signals)
        plan[b + en.EM_GROUP] = sum({vbit for role, _, vbit in roles.values() if role == en.ROLE_ANALOG})
        if name == "EST_TireStiffness":
            plan[b + en.EM_GROUP] = int(plan[b + en.EM_GROUP]) | sum(v for _, v in _STIFFNESS_VALID)
        plan[b + en.EM_PLAIN] = 1.0 if layout.plain else 0.0
        for j, s in enumerate(layout.signals):
            row = b + en.MSG_SIZE + j * en.SIGNAL_SIZE
            role, source, vbit = roles[s.name]
            plan[row + en.ES_ROLE] = role
            plan[row + en.ES_SOURCE] = source
            plan[row + en.ES_VBIT] = vbit
            plan[row + en.ES_START] = s.start
            plan[row + en.ES_MASK] = (1 << s.length) - 1
            plan[row + en.ES_SCALE] = s.scale
            plan[row + en.ES_OFFSET] = s.offset
            plan[row + en.ES_LO] = s.lo
            plan[row + en.ES_HI] = s.hi
            plan[row + en.ES_NEUTRAL] = s.neutral
    return plan, tuple(layouts)


_MASK64 = (1 << 64) - 1


class _Counters(MutableMapping):
    """message name -> a column of the compiled encoder's state, as a dict (read and set by name)."""

    def __init__(self, state: np.ndarray, offset: int) -> None:
        self._state, self._offset = state, offset
        self._index = {name: m for m, name in enumerate(OUTPUT_ORDER)}

    def __getitem__(self, name: str) -> int:
        return int(self._state[self._offset + self._index[name]])

    def __setitem__(self, name: str, value: int) -> None:
        self._state[self._offset + self._index[name]] = int(value)

    def __delitem__(self, name: str) -> None:
        raise TypeError("the output messages are fixed")

    def __iter__(self) -> Iterator[str]:
        return iter(OUTPUT_ORDER)

    def __len__(self) -> int:
        return len(OUTPUT_ORDER)


class OutputEncoder:
    """Estimates of one cycle -> the list of ``(frame_id, data)`` to send in that cycle, through the compiled
    encoder (``ptw_rt.edge.encoding``). ``plan``/``state`` are its arrays (replay's compiled loop runs on them).

    ``sample_time`` is the estimator's cycle (s); the slow messages go out every
    ``round(cycle_time_s / sample_time)`` cycles, starting with cycle index 0.
    """

    def __init__(self, codec: FrameCodec, sample_time: float = 0.01) -> None:
        self.codec = codec
        self.sample_time = float(sample_time)
        self.plan, self.layouts = encoder_plan(codec, self.sample_time)
        self.state = np.zeros(en.STATE.size)
        self.counters = _Counters(self.state, en.EN_COUNTERS)  # the next counter of each message
        self.frames_sent = _Counters(self.state, en.EN_SENT)
        self.periods = {name: int(self.plan[m * en.BLOCK + en.EM_PERIOD]) for m, name in enumerate(OUTPUT_ORDER)}
        self._status_index = OUTPUT_ORDER.index("EST_Status")
        # per message: (frame id, length, plain, layout) to turn the encoder's rows into frames
        self._frame_of = tuple((layout.frame_id, layout.length, layout.plain, layout) for layout in self.layouts)
        self._all_plain = all(layout.plain for layout in self.layouts)
        self._ids = np.array([layout.frame_id for layout in self.layouts], dtype=np.int64)  # bulk's, per message
        self._lengths = np.array([layout.length for layout in self.layouts], dtype=np.int64)
        self._messages = np.zeros(en.N_OUTPUTS, dtype=np.int64)
        self._words = np.zeros(en.N_OUTPUTS, dtype=np.uint64)
        self._values = np.zeros((en.N_OUTPUTS, en.MAX_SIGNALS))

    def frame(self, m: int, word: int, values: np.ndarray) -> tuple[int, bytes]:
        """The ``(frame id, data)`` of plan message ``m`` from the encoder's word (plain) or values (not plain)."""
        frame_id, length, plain, layout = self._frame_of[m]
        if plain:
            return frame_id, (word & _MASK64).to_bytes(8, "little")[:length]
        return frame_id, layout.pack(values[: len(layout.signals)].tolist())

    def bulk(self, messages: np.ndarray, words: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """Many frames of the compiled encoder at once: ``(ids, uint8[n, 8] data, lengths)`` (arrays), or None when
        some message is not plain (its bytes come from ``frame``, one by one)."""
        if not self._all_plain:
            return None
        return (
            self._ids[messages],
            words.astype("<u8", copy=False).view(np.uint8).reshape(-1, 8),
            self._lengths[messages],
        )

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
        m = self._status_index
        word = en.encode_message(
            self.plan,
            self.state,
            m,
            estimates,
            int(stale_bits),
            int(reasons),
            int(status.get("overrun_count", 0)),
            int(status.get("cycle_time_us", 0)),
            bool(valid),
            self._values[0],
        )
        return self.frame(m, word, self._values[0])

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
        status = status or {}
        n = en.encode_cycle(
            self.plan,
            self.state,
            estimates,
            int(cycle_index),
            int(stale_bits),
            int(reasons),
            int(status.get("overrun_count", 0)),
            int(status.get("cycle_time_us", 0)),
            self._messages,
            self._words,
            self._values,
            0,
        )
        frame = self.frame
        values = self._values
        return [
            frame(m, w, values[i])
            for i, (m, w) in enumerate(zip(self._messages[:n].tolist(), self._words[:n].tolist(), strict=True))
        ]
