"""``ptw-rt monitor``: a live decoder of the estimator's own output frames, for bench and vehicle checks.

``Monitor`` is fed ``(timestamp, frame_id, data)`` of the output frames and checks what a receiving ECU
would check, from the DBC alone:

* E2E Profile 11 CRC of the 100 Hz messages (EST_Roll, EST_RiderTorque, EST_Lateral),
* counter continuity of every output (0..14, wrapping 14 -> 0): a jump (frames lost) or a repeated
  counter (sender stuck) is an error; after a frame rejected for its CRC/DLC one lost frame is expected,
* per-message receive rates over a sliding window,
* a FROZEN estimator: a 100 Hz message whose payload, apart from counter and CRC, stays identical for more
  than ``frozen_after_s`` while EST_Status reports Mode VALID (a live estimate always moves a little),
* a SILENT estimator: an output message not received for more than ``silent_after_periods`` cycle times.

``text_line`` / ``snapshot`` give the one-line view and the ``--json`` dict. ``run_monitor(args)`` runs it on
a CAN bus and returns 0, or 1 if any CRC/counter/decode error or frozen/silent condition was seen.
"""

from __future__ import annotations

import json
import math
import signal
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, TextIO

from ptw_rt.core.layout import MODE_NAMES, MODE_VALID, reason_names
from ptw_rt.errors import UserFacingError
from ptw_rt.io.dbc import DbcError, FrameCodec, FrameDecodeError
from ptw_rt.io.e2e import CounterChecker, P11Status

__all__ = ["FROZEN_AFTER_S", "SILENT_AFTER_PERIODS", "MessageStats", "Monitor", "run_monitor"]

FROZEN_AFTER_S = 1.0
SILENT_AFTER_PERIODS = 3.0
MIN_WATCH_PERIODS = 3.0  # the shortest --duration, in the slowest output's periods: what a silence takes to be said
RATE_WINDOW_S = 1.0
_RAD2DEG = 180.0 / math.pi


@dataclass
class MessageStats:
    """Receive statistics of one output message."""

    name: str
    frame_id: int
    cycle_time_s: float
    e2e: bool
    counter_signal: str | None
    modulus: int
    frames: int = 0  # frames that passed decoding (and the CRC check for E2E messages)
    crc_errors: int = 0
    decode_errors: int = 0  # wrong DLC, undecodable, E2E counter 15
    counter_jumps: int = 0  # counter advanced by more than expected: frames lost
    counter_repeats: int = 0  # counter did not advance: sender stuck or frame duplicated
    silent_events: int = 0
    frozen_events: int = 0
    silent: bool = False
    frozen: bool = False
    last_rx: float | None = None
    values: dict[str, float] = field(default_factory=dict)
    content: tuple | None = None  # payload values without counter and CRC
    content_since: float | None = None
    arrivals: deque = field(default_factory=deque)
    checker: CounterChecker | None = None  # the counter sequence (frames that failed their checks count as lost)

    def __post_init__(self) -> None:
        if self.counter_signal is not None and self.checker is None:
            self.checker = CounterChecker(self.modulus)

    @property
    def errors(self) -> int:
        return self.crc_errors + self.decode_errors + self.counter_jumps + self.counter_repeats

    def rate_hz(self, now: float, window_s: float, start: float) -> float:
        span = min(window_s, now - start)
        if span <= 0:
            return 0.0
        lo = now - window_s
        return sum(1 for t in self.arrivals if t > lo) / span


class Monitor:
    """Checks of the estimator's output frames; feed frames in time order, then ``check(now)``."""

    def __init__(
        self,
        codec: FrameCodec | None = None,
        *,
        start: float | None = None,
        frozen_after_s: float | None = None,
        silent_after_periods: float | None = None,
        rate_window_s: float = RATE_WINDOW_S,
    ) -> None:
        self.codec = codec if codec is not None else FrameCodec()
        self.frozen_after_s = FROZEN_AFTER_S if frozen_after_s is None else float(frozen_after_s)
        self.silent_after_periods = SILENT_AFTER_PERIODS if silent_after_periods is None else silent_after_periods
        self.rate_window_s = float(rate_window_s)
        self.start = start
        self.now = start
        self.unknown_frames = 0
        self.stats: dict[str, MessageStats] = {}
        self._by_id: dict[int, MessageStats] = {}
        c = self.codec
        for name in c.output_messages:
            st = MessageStats(
                name=name,
                frame_id=c.frame_id(name),
                cycle_time_s=c.cycle_time_s(name),
                e2e=c.is_e2e(name),
                counter_signal=c.counter_signal(name),
                modulus=c.counter_modulus(name),
            )
            self.stats[name] = st
            self._by_id[st.frame_id] = st
        self._skip = {st.name: {st.counter_signal, c.crc_signal(st.name)} - {None} for st in self.stats.values()}

    # ------------------------------------------------------------------ input

    @property
    def frame_ids(self) -> tuple[int, ...]:
        return tuple(self._by_id)

    def _set_time(self, t: float) -> None:
        if self.start is None:
            self.start = t
        if self.now is None or t > self.now:
            self.now = t

    def feed(self, timestamp: float, frame_id: int, data: bytes, *, extended: bool = False) -> str | None:
        """Process one received frame; returns the message name, or None if it is not a valid output frame."""
        self._set_time(timestamp)
        st = None if extended else self._by_id.get(frame_id)
        if st is None:
            self.unknown_frames += 1
            return None
        st.last_rx = timestamp  # the sender is alive even if the frame is damaged
        st.arrivals.append(timestamp)
        lo = timestamp - self.rate_window_s
        while st.arrivals and st.arrivals[0] <= lo:
            st.arrivals.popleft()
        if st.silent:
            st.silent = False
        try:
            _, values = self.codec.decode_checked(frame_id, data)
        except FrameDecodeError as exc:
            if exc.reason == FrameDecodeError.CRC:
                st.crc_errors += 1
            else:
                st.decode_errors += 1
            if st.checker is not None:
                st.checker.frame_lost()
            return None
        st.frames += 1
        if st.checker is not None:
            counter = int(values[st.counter_signal])
            if counter >= st.modulus:
                st.decode_errors += 1  # counter 15 on a 0..14 counter
                st.checker.frame_lost()
                return None
            status = st.checker.step(counter)
            if status == P11Status.REPEATED:
                st.counter_repeats += 1
            elif status == P11Status.WRONGSEQUENCE:
                st.counter_jumps += 1
        st.values = values
        skip = self._skip[st.name]
        content = tuple(v for k, v in values.items() if k not in skip)
        if content != st.content:
            st.content = content
            st.content_since = timestamp
            st.frozen = False
        self._update_frozen(st, timestamp)
        return st.name

    # ------------------------------------------------------------------ conditions

    @property
    def mode(self) -> int | None:
        v = self.stats["EST_Status"].values.get("Mode") if "EST_Status" in self.stats else None
        return None if v is None else int(v)

    def _update_frozen(self, st: MessageStats, now: float) -> None:
        if not st.e2e or st.content_since is None:
            return
        frozen = self.mode == MODE_VALID and now - st.content_since > self.frozen_after_s
        if frozen and not st.frozen:
            st.frozen_events += 1
        st.frozen = frozen

    def check(self, now: float | None = None) -> None:
        """Evaluate the time-based conditions (silent, frozen) at ``now`` (default: the latest frame time)."""
        if now is not None:
            self._set_time(now)
        if self.now is None:
            return
        now = self.now
        for st in self.stats.values():
            ref = st.last_rx if st.last_rx is not None else self.start
            silent = now - ref > self.silent_after_periods * st.cycle_time_s
            if silent and not st.silent:
                st.silent_events += 1
            st.silent = silent
            if silent:
                st.frozen = False
            else:
                self._update_frozen(st, now)

    @property
    def frozen(self) -> list[str]:
        return [st.name for st in self.stats.values() if st.frozen]

    @property
    def silent(self) -> list[str]:
        return [st.name for st in self.stats.values() if st.silent]

    def totals(self) -> dict[str, int]:
        keys = ("crc_errors", "decode_errors", "counter_jumps", "counter_repeats", "frozen_events", "silent_events")
        return {k: sum(getattr(st, k) for st in self.stats.values()) for k in keys}

    @property
    def problems_seen(self) -> bool:
        """Any CRC, decode or counter error, or a frozen or silent condition, since the start."""
        return any(self.totals().values())

    # ------------------------------------------------------------------ views

    def _value(self, message: str, signal: str, valid_signal: str | None = None) -> float | None:
        st = self.stats.get(message)
        if st is None or not st.values or st.silent:
            return None
        if not st.values.get(st.name + "_Valid", 1.0):
            return None
        if valid_signal is not None and not st.values.get(valid_signal, 1.0):
            return None
        return st.values.get(signal)

    def snapshot(self, now: float | None = None) -> dict[str, Any]:
        """Everything the monitor knows, JSON-serialisable (what ``--json`` prints)."""
        if now is not None:
            self._set_time(now)
        t = self.now if self.now is not None else 0.0
        start = self.start if self.start is not None else t
        mode = self.mode
        status = self.stats.get("EST_Status")
        sv = status.values if status is not None else {}
        roll = self._value("EST_Roll", "RollAngle", "RollAngle_Valid")
        stiff_names = {
            "front_cornering": ("FrontCorneringStiffness", "CorneringStiffness_Valid"),
            "front_camber": ("FrontCamberStiffness", "CamberStiffness_Valid"),
            "rear_cornering": ("RearCorneringStiffness", "CorneringStiffness_Valid"),
            "rear_camber": ("RearCamberStiffness", "CamberStiffness_Valid"),
        }
        messages = {}
        for st in self.stats.values():
            messages[st.name] = {
                "rate_hz": round(st.rate_hz(t, self.rate_window_s, start), 1),
                "frames": st.frames,
                "crc_errors": st.crc_errors,
                "decode_errors": st.decode_errors,
                "counter_jumps": st.counter_jumps,
                "counter_repeats": st.counter_repeats,
                "silent": st.silent,
                "frozen": st.frozen,
            }
        totals = self.totals()
        return {
            "t": round(t - start, 3),
            "mode": None if mode is None else (MODE_NAMES[mode] if 0 <= mode < len(MODE_NAMES) else str(mode)),
            "reasons": reason_names(int(sv["ReasonBits"])) if "ReasonBits" in sv else [],
            "sensor_timeouts": int(sv["SensorTimeouts"]) if "SensorTimeouts" in sv else None,
            "overruns": int(sv["OverrunCount"]) if "OverrunCount" in sv else None,
            "cycle_time_us": int(sv["CycleTimeUs"]) if "CycleTimeUs" in sv else None,
            "roll_deg": None if roll is None else round(roll * _RAD2DEG, 2),
            "rider_torque_nm": self._value("EST_RiderTorque", "RiderTorque", "RiderTorque_Valid"),
            "stiffness": {k: self._value("EST_TireStiffness", s, v) for k, (s, v) in stiff_names.items()},
            "frozen": self.frozen,
            "silent": self.silent,
            "errors": totals,
            "problems_seen": any(totals.values()),
            "unknown_frames": self.unknown_frames,
            "messages": messages,
        }

    def text_line(self, now: float | None = None) -> str:
        """One-line view: mode, roll, torque, stiffness, reasons, rates, error counts, FROZEN/SILENT."""
        s = self.snapshot(now)

        def num(v: float | None, fmt: str) -> str:
            return "--" if v is None else format(v, fmt)

        st = s["stiffness"]
        stiff = "/".join(
            num(st[k], ".0f") for k in ("front_cornering", "front_camber", "rear_cornering", "rear_camber")
        )
        rates = "/".join(f"{m['rate_hz']:.0f}" for m in s["messages"].values())
        e = s["errors"]
        parts = [
            f"t={s['t']:7.1f}s",
            f"{s['mode'] or '?':<10}",
            f"roll={num(s['roll_deg'], '+6.1f')}deg",
            f"torque={num(s['rider_torque_nm'], '+7.2f')}Nm",
            f"C[af/gf/ar/gr]={stiff}N/rad",
            f"reasons={','.join(s['reasons']) or '-'}",
            f"rates={rates}Hz",
            f"crc={e['crc_errors']} cnt={e['counter_jumps'] + e['counter_repeats']} dec={e['decode_errors']}",
        ]
        if s["frozen"]:
            parts.append("FROZEN:" + ",".join(s["frozen"]))
        if s["silent"]:
            parts.append("SILENT:" + ",".join(s["silent"]))
        return " ".join(parts)


# ---------------------------------------------------------------------- CLI


def _open_bus(interface: str, channel: str, filters: list[dict]):
    import can

    try:
        return can.Bus(interface=interface, channel=channel, receive_own_messages=False, can_filters=filters)
    except (can.CanError, OSError, ValueError, ImportError, NotImplementedError) as exc:
        raise UserFacingError(f"cannot open CAN bus {interface}:{channel}: {exc}") from exc
    except TypeError as exc:  # a back end whose constructor needs more than an interface and a channel (socketcand)
        raise UserFacingError(
            f"cannot open CAN bus {interface}:{channel}: the interface needs more settings ({exc}); "
            "give them in python-can's configuration file (~/.canrc)"
        ) from exc


def _interrupt(signum, frame) -> None:  # noqa: ANN001 - signal's handler protocol
    raise KeyboardInterrupt


def _stop_on_sigterm():  # noqa: ANN202 - signal's previous handler, whatever it was
    """SIGTERM raises KeyboardInterrupt in the watch loop; returns the handler to restore (None off the main thread,
    where Python cannot install one)."""
    if threading.current_thread() is not threading.main_thread():
        return None
    return signal.signal(signal.SIGTERM, _interrupt)


def run_monitor(args, *, out: TextIO | None = None) -> int:
    """``ptw-rt monitor``: decode the estimator's frames live until ``--duration`` or Ctrl-C.

    Prints a line every EST_Status period (0.1 s): refreshed in place on a terminal, one line each otherwise,
    a JSON object per line with ``--json``. Returns 0, or 1 if any error or frozen/silent condition was seen.
    """
    out = sys.stdout if out is None else out
    as_json = bool(getattr(args, "json", False))
    duration = getattr(args, "duration", None)
    if duration is not None and not duration > 0:
        raise UserFacingError(f"--duration must be positive, got {duration}")
    try:
        codec = FrameCodec()
    except DbcError as exc:
        raise UserFacingError(str(exc)) from exc
    # shorter than a silent estimator takes to be called silent, the verdict "ok" would be of nothing watched
    needed = MIN_WATCH_PERIODS * max((codec.cycle_time_s(m) for m in codec.output_messages), default=0.1)
    if duration is not None and duration < needed:
        raise UserFacingError(f"--duration must be at least {needed:g} s (a silent estimator is said after that)")
    tty = not as_json and out.isatty()
    period = codec.cycle_time_s("EST_Status") if "EST_Status" in codec.output_messages else 0.1
    bus = _open_bus(args.interface, args.channel, codec.can_filters(codec.output_messages))

    start = time.monotonic()
    monitor = Monitor(codec, start=start)
    deadline = math.inf if duration is None else start + float(duration)
    next_print = start + period
    width = 0
    printed = False

    def feed(msg) -> None:
        if msg.is_error_frame or msg.is_remote_frame:
            return
        monitor.feed(time.monotonic(), msg.arbitration_id, bytes(msg.data), extended=msg.is_extended_id)

    def show(now: float, final: bool = False) -> None:
        nonlocal width, printed
        if as_json:
            doc = monitor.snapshot(now)
            if final:
                doc["final"] = True
            out.write(json.dumps(doc) + "\n")
        elif tty:
            line = monitor.text_line(now)
            out.write("\r" + line.ljust(width) + ("\n" if final else ""))
            width = len(line)
        elif not final or not printed:  # plain lines: the last periodic line is already the final state
            out.write(monitor.text_line(now) + "\n")
        printed = True
        out.flush()

    # SIGTERM (`timeout 60 ptw-rt monitor`, systemd, a supervisor) ends the watch like Ctrl-C: with the final line
    # and the verdict, not killed in the middle of a line
    previous = _stop_on_sigterm()
    try:
        while True:
            now = time.monotonic()
            if now >= deadline:
                break
            msg = bus.recv(timeout=max(0.0, min(next_print, deadline) - now))
            if msg is not None:
                feed(msg)
            now = time.monotonic()
            if now >= next_print:
                for _ in range(10000):  # frames queued while we were busy count before the silence check
                    msg = bus.recv(timeout=0.0)
                    if msg is None:
                        break
                    feed(msg)
                now = time.monotonic()
                monitor.check(now)
                show(now)
                next_print += period
                if next_print <= now:
                    next_print = now + period
    except KeyboardInterrupt:
        pass
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
        bus.shutdown()
    now = time.monotonic()
    monitor.check(now)
    show(now, final=True)
    if not as_json:
        totals = monitor.totals()
        verdict = "problems seen" if monitor.problems_seen else "ok"
        print(f"monitor: {verdict}: " + " ".join(f"{k}={v}" for k, v in totals.items()), file=sys.stderr)
    return 1 if monitor.problems_seen else 0
