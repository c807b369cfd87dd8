"""``ptw-rt demo``: no hardware needed. A simulated ride is played on a python-can virtual bus into the real daemon.

Three parties share one virtual channel (``ptw-rt-demo-<pid>``), all in this process:

* the **daemon** (``ptw_rt.service.daemon.Daemon``, its real 100 Hz loop, in a thread), publishing EST_* frames;
* a **player** thread sending the ride's sensor frames on an absolute ``time.monotonic`` schedule
  (ride time / ``--speed``, no drift);
* a **listener** thread decoding everything on the wire (``FrameCodec.decode_checked``: CRC and counter range of
  the E2E messages, plus the counter sequence of every output message). The live line on stderr and the accuracy
  summary are computed from these decoded frames, not from the estimator's arrays: the demo shows the wire.

Receive times are mapped to ride time as ``(t_rx - t_start) * speed``; the truth CSV is interpolated there and
scored after ``SETTLE_S``. Files (``--out``, default ``out/demo``): ``NAME.log`` + ``NAME.truth.csv`` +
``NAME.meta.json`` (the ride, as ``ptw-rt simulate`` writes it), ``NAME.outputs.log`` (the received output frames,
candump -L, stamped on the ride's clock), ``state.json`` (the daemon's state file, started afresh for every demo so
runs are reproducible) and ``report/`` (plots of an offline replay of the same log, if matplotlib is installed).

At ``--speed`` above 1 the daemon still runs its 100 Hz loop on the wall clock, so it gets several ride-seconds'
worth of frames per wall second (fewer cycles per ride second): the wire and the E2E checks still mean something,
the accuracy does not.
"""

from __future__ import annotations

import collections
import importlib.util
import logging
import math
import os
import sys
import threading
import time
from pathlib import Path

import can
import numpy as np

from ptw_rt.core.layout import MODE_NAMES, MODE_VALID
from ptw_rt.errors import UserFacingError, output_error
from ptw_rt.io.candump import CandumpWriter
from ptw_rt.io.dbc import FrameCodec, FrameDecodeError
from ptw_rt.io.e2e import CounterChecker, P11Status
from ptw_rt.paths import DEFAULT_CONFIG
from ptw_rt.untrusted import check_output_file, one_line

__all__ = ["run_demo"]

MAX_DEFAULT_DURATION_S = 25.0  # default ride length cap, so the demo takes well under a minute
SETTLE_S = 5.0  # s of ride time not scored
TAIL_S = 0.3  # s the daemon keeps running after the last frame (its last outputs reach the listener)
READY_TIMEOUT_S = 10.0
LIVE_PERIOD_TTY = 0.2
LIVE_PERIOD_PIPE = 1.0
LOG_CHANNEL = "vcan0"
_SEQUENCE_OK = (P11Status.OK, P11Status.INITIAL)

# (output message, signal, truth column, scale to the printed unit, printed name, unit)
_SCORED = (
    ("EST_Roll", "RollAngle", "roll", math.degrees(1.0), "roll RMSE", "deg"),
    ("EST_RiderTorque", "RiderTorque", "rider_torque", 1.0, "rider torque RMSE", "N m"),
    ("EST_Lateral", "FrontLateralForce", "fy_front", 1.0, "front Fy RMSE", "N"),
    ("EST_Lateral", "RearLateralForce", "fy_rear", 1.0, "rear Fy RMSE", "N"),
)


class _Player(threading.Thread):
    """Sends ``(ride time, id, data)`` frames at ``t_start + t / speed`` of the monotonic clock."""

    def __init__(self, channel: str, frames: list[tuple[float, int, bytes]], speed: float) -> None:
        super().__init__(name="ptw-rt-demo-player", daemon=True)
        self.bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        self.frames = frames
        self.speed = speed
        self.t_start = 0.0
        self.sent = 0
        self.ride_time = 0.0
        self.max_late_s = 0.0
        self.error: str | None = None
        self.running = True

    def run(self) -> None:
        clock = time.monotonic
        t_start, speed, send = self.t_start, self.speed, self.bus.send
        try:
            for t, fid, data in self.frames:
                if not self.running:
                    break
                deadline = t_start + t / speed
                delay = deadline - clock()
                if delay > 0:
                    time.sleep(delay)
                elif -delay > self.max_late_s:
                    self.max_late_s = -delay
                send(can.Message(arbitration_id=fid, data=data, is_extended_id=False))
                self.sent += 1
                self.ride_time = t
        except (can.CanError, OSError) as exc:
            self.error = f"{type(exc).__name__}: {exc}"
        finally:
            self.bus.shutdown()


class _Listener(threading.Thread):
    """Decodes every frame on the channel; keeps the output frames and the latest values of every message."""

    def __init__(self, channel: str, codec: FrameCodec) -> None:
        super().__init__(name="ptw-rt-demo-listener", daemon=True)
        self.bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        self.codec = codec
        self.running = True
        self.lock = threading.Lock()
        self.latest: dict[str, dict[str, float]] = {}
        self.outputs: list[tuple[float, int, bytes]] = []  # (monotonic receive time, id, data)
        self.decoded: dict[str, list[tuple[float, dict[str, float]]]] = collections.defaultdict(list)
        self.received: collections.Counter = collections.Counter()
        self.errors: collections.Counter = collections.Counter()  # decode error reason -> count (outputs)
        self.counter_errors: collections.Counter = collections.Counter()  # message -> counter steps != 1
        self.inputs = 0
        self._checkers = {n: CounterChecker(codec.counter_modulus(n)) for n in codec.output_messages}

    def run(self) -> None:
        clock = time.monotonic
        try:
            while True:
                msg = self.bus.recv(timeout=0.05)
                if msg is None:
                    if not self.running:
                        return  # stopped and drained
                    continue
                if not msg.is_error_frame and not msg.is_remote_frame:
                    self._handle(clock(), msg.arbitration_id, bytes(msg.data), msg.is_extended_id)
        finally:
            self.bus.shutdown()

    def _handle(self, now: float, fid: int, data: bytes, extended: bool) -> None:
        codec = self.codec
        name = None if extended else codec.message_name(fid)
        if name is None or not codec.is_output(name):
            self.inputs += 1
            if name is not None:
                try:
                    _, values = codec.decode(fid, data)
                except FrameDecodeError:
                    return  # injected sensor faults: the daemon's business, not the demo's
                with self.lock:
                    self.latest[name] = values
            return
        self.outputs.append((now, fid, data))
        self.received[name] += 1
        try:
            name, values = codec.decode_checked(fid, data)
        except FrameDecodeError as exc:
            self.errors[exc.reason] += 1
            return
        counter = codec.counter_signal(name)
        if counter is not None and self._checkers[name].step(int(values[counter])) not in _SEQUENCE_OK:
            self.counter_errors[name] += 1
        self.decoded[name].append((now, values))
        with self.lock:
            self.latest[name] = values


class _LiveLog(logging.Handler):
    """Prints the daemon's warnings on their own line without garbling the live line."""

    def __init__(self, tty: bool) -> None:
        super().__init__(logging.WARNING)
        self.tty = tty

    def emit(self, record: logging.LogRecord) -> None:
        prefix = "\r\033[K" if self.tty else ""
        sys.stderr.write(f"{prefix}daemon {record.levelname.lower()}: {record.getMessage()}\n")
        sys.stderr.flush()


def _live_line(listener: _Listener, ride_t: float) -> str:
    with listener.lock:
        latest = dict(listener.latest)

    def get(message: str, signal: str) -> float:
        return latest.get(message, {}).get(signal, math.nan)

    def fmt(value: float, spec: str, width: int) -> str:
        return format(value, spec) if math.isfinite(value) else "-".rjust(width)

    mode = get("EST_Status", "Mode")
    mode_name = MODE_NAMES[int(mode)] if mode == mode and 0 <= int(mode) < len(MODE_NAMES) else "-"
    return (
        f"t {ride_t:5.1f} s | speed {fmt(get('GPS_Velocity', 'SpeedOverGround') * 3.6, '5.1f', 5)} km/h | "
        f"roll {fmt(math.degrees(get('EST_Roll', 'RollAngle')), '+6.1f', 6)} deg | "
        f"torque {fmt(get('EST_RiderTorque', 'RiderTorque'), '+6.1f', 6)} N m | "
        f"C_alpha f/r {fmt(get('EST_TireStiffness', 'FrontCorneringStiffness') / 1e3, '5.1f', 5)}/"
        f"{fmt(get('EST_TireStiffness', 'RearCorneringStiffness') / 1e3, '5.1f', 5)} kN/rad | {mode_name}"
    )


def _series(listener: _Listener, message: str, signal: str, t_start: float, speed: float):
    """(ride times, values, signal valid) of one decoded output signal."""
    rows = listener.decoded.get(message, [])
    t = np.array([(now - t_start) * speed for now, _ in rows])
    v = np.array([values[signal] for _, values in rows])
    valid_name = f"{signal}_Valid"
    ok = np.array([values.get(valid_name, 1.0) >= 0.5 for _, values in rows], dtype=bool)
    return t, v, ok


def _duration(args, scenario) -> float:
    duration = getattr(args, "duration", None)
    if duration is None:
        return min(float(scenario.duration), MAX_DEFAULT_DURATION_S)
    if not duration > 0:
        raise UserFacingError(f"--duration must be positive, got {duration}")
    return float(duration)


def run_demo(args) -> int:
    """Simulate, play on a virtual bus into the daemon, show the wire live, score it, write logs and report."""
    from ptw_rt.service.daemon import Daemon, load_daemon_settings
    from ptw_rt.sim.recording import encode_frames, read_truth_csv, write_ride
    from ptw_rt.sim.ride import get_scenario, simulate

    speed = getattr(args, "speed", None)
    speed = 1.0 if speed is None else float(speed)
    if not (math.isfinite(speed) and 0.1 <= speed <= 1000.0):  # 1e308 or 1e-300 was a traceback
        raise UserFacingError(f"--speed must be 0.1-1000 (1 = real time), got {speed}")
    config = Path(getattr(args, "config", None) or DEFAULT_CONFIG)
    out = Path(getattr(args, "out", None) or "out/demo")
    scenario = get_scenario(args.scenario)
    duration = _duration(args, scenario)
    tty = sys.stderr.isatty()
    wall0 = time.monotonic()

    def note(text: str) -> None:
        sys.stderr.write(text + "\n")
        sys.stderr.flush()

    outputs_path = out / f"{scenario.name}.outputs.log"
    try:  # written at the end: a FIFO nobody reads there waited for ever after the whole ride
        check_output_file(outputs_path)
    except OSError as exc:
        raise output_error(outputs_path, exc) from None

    # ---- 1. the ride
    note(f"simulating {scenario.name} ({duration:g} s of ride) ...")
    ride = simulate(scenario.name, duration=duration, vehicle=config, progress=tty)
    paths = write_ride(ride, out)
    truth = read_truth_csv(paths["truth"])
    codec = FrameCodec()
    frames = [(ts - ride.epoch, fid, data) for ts, fid, data in encode_frames(ride, codec)]

    # ---- 2. the daemon on a virtual bus (state file under --out, fresh for every run)
    channel = f"ptw-rt-demo-{os.getpid()}"
    state_file = out / "state.json"
    state_file.unlink(missing_ok=True)
    overrides = {"interface": "virtual", "channel": channel, "state_file": state_file}
    settings = load_daemon_settings(config, overrides)
    note("loading the estimator (the first run compiles it, later ones use the cache) ...")
    daemon = Daemon(settings, config, overrides=overrides)

    daemon_log = logging.getLogger("ptw_rt")
    handler = _LiveLog(tty)
    old_propagate = daemon_log.propagate
    daemon_log.addHandler(handler)
    daemon_log.propagate = False
    listener = _Listener(channel, codec)  # opened first: it sees every frame the daemon publishes
    player = _Player(channel, frames, speed)
    result: dict[str, object] = {}

    def daemon_main() -> None:
        try:
            result["rc"] = daemon.run()
        except BaseException as exc:  # reported by the main thread
            result["error"] = exc

    daemon_thread = threading.Thread(target=daemon_main, name="ptw-rt-demo-daemon", daemon=True)
    try:
        listener.start()
        daemon_thread.start()
        if not daemon.ready.wait(READY_TIMEOUT_S):
            daemon.stop()
            daemon_thread.join(timeout=2.0)
            if "error" in result:
                raise result["error"]  # type: ignore[misc]
            note(f"the daemon did not start publishing on virtual:{channel} within {READY_TIMEOUT_S:g} s")
            return 1
        note(
            f"playing {len(frames)} frames on virtual:{channel} at {speed:g}x "
            f"({ride.duration / speed:.1f} s); the daemon publishes at 100 Hz (live view from the decoded frames)"
        )

        # ---- 3./4. play the ride, show the wire
        player.t_start = time.monotonic()
        player.start()
        period = LIVE_PERIOD_TTY if tty else LIVE_PERIOD_PIPE
        next_line = time.monotonic()
        interrupted = False
        try:
            while player.is_alive() and daemon_thread.is_alive():
                now = time.monotonic()
                if now >= next_line:
                    next_line += period
                    ride_t = min((now - player.t_start) * speed, ride.duration)
                    line = _live_line(listener, ride_t)
                    sys.stderr.write(f"\r{line}\033[K" if tty else line + "\n")
                    sys.stderr.flush()
                player.join(timeout=max(0.0, min(period, next_line - time.monotonic())))
        except KeyboardInterrupt:
            interrupted = True
            player.running = False
        if tty:
            sys.stderr.write("\r" + _live_line(listener, min(player.ride_time, ride.duration)) + "\033[K\n")
        time.sleep(TAIL_S)
    finally:
        # ---- 5. stop everything
        player.running = False
        daemon.stop()
        daemon_thread.join(timeout=10.0)
        player.join(timeout=2.0)
        listener.running = False
        listener.join(timeout=2.0)
        daemon_log.removeHandler(handler)
        daemon_log.propagate = old_propagate
    if "error" in result:
        raise result["error"]  # type: ignore[misc]
    if interrupted:
        note("interrupted")

    # ---- the received outputs, on the ride's clock
    t_start = player.t_start
    with CandumpWriter(outputs_path, channel=LOG_CHANNEL) as w:
        for now, fid, data in listener.outputs:
            w.write(round(ride.epoch + (now - t_start) * speed, 6), fid, data)

    rc = _summary(daemon, listener, player, ride, truth, speed)

    # ---- the report (offline replay of the same log through the same cycle code)
    report_dir = out / "report"
    if importlib.util.find_spec("matplotlib") is None:
        print("report: skipped, matplotlib is not installed (pip install 'ptw-rt[plot]')")
        report_dir = None
    else:
        from ptw_rt.eval.evaluate import evaluate_ride
        from ptw_rt.eval.report import write_report

        note("writing the report (offline replay of the same log) ...")
        write_report(evaluate_ride(ride, config), report_dir)

    print(f"ride log:     {one_line(str(paths['log']))}")
    print(f"truth:        {one_line(str(paths['truth']))}")
    print(f"outputs log:  {one_line(str(outputs_path))} (received EST_* frames, candump -L, ride clock)")
    if state_file.exists():
        print(f"state file:   {one_line(str(state_file))} (learned tyre stiffness)")
    else:
        print(
            f"state file:   not written: the tyre stiffness was not published valid when the daemon stopped "
            f"({ride.duration:g} s ride; valid needs the tyre bank to single out one tyre with a consistent model, "
            'docs/estimator.md, "Tyres")'
        )
    if report_dir is not None:
        print(f"report:       {one_line(str(report_dir))}/ (summary.md, *.png)")
    print(f"wall time:    {time.monotonic() - wall0:.1f} s")
    return rc


def _summary(daemon, listener: _Listener, player: _Player, ride, truth, speed: float) -> int:
    """Print the accuracy and wire summary (stdout); return the exit code."""
    t_start = player.t_start
    print(f"\n== ptw-rt demo: {ride.scenario}, {ride.duration:g} s ride at {speed:g}x ==")
    if speed != 1.0:
        print(
            f"note: at {speed:g}x the daemon's loop still runs at 100 Hz of wall time, so it ran "
            f"{100.0 / speed:.0f} cycles per ride second instead of 100 and got {speed:g} ride-seconds of frames "
            "per wall second; the accuracy below is only meaningful at --speed 1."
        )
    print(
        f"daemon: {daemon.cycles} cycles, {daemon.overruns} overruns, worst cycle {daemon.worst_cycle_us:.0f} us, "
        f"{daemon.frames_in} frames in, {daemon.frames_out} out; player sent {player.sent}/{len(player.frames)} "
        f"(latest {player.max_late_s * 1e3:.1f} ms late)"
    )
    if player.error:
        print(f"player error: {player.error}")

    # accuracy, from the decoded frames
    lo, hi = SETTLE_S, ride.duration
    print(f"accuracy (decoded frames vs truth, ride time {lo:g}..{hi:g} s, signal valid bit set):")
    for message, signal, column, scale, label, unit in _SCORED:
        t, v, ok = _series(listener, message, signal, t_start, speed)
        scored = (t >= lo) & (t <= hi) if t.size else np.zeros(0, dtype=bool)
        use = scored & ok
        if not use.any():
            print(f"  {label:<20} -      {unit:<4} (no valid frames after {lo:g} s)")
            continue
        err = v[use] - np.interp(t[use], truth["t"], truth[column])
        rmse = float(np.sqrt(np.mean(err**2))) * scale
        print(f"  {label:<20} {rmse:8.3f} {unit:<4} ({int(use.sum())} of {int(scored.sum())} frames valid)")
    t, mode, _ = _series(listener, "EST_Status", "Mode", t_start, speed)
    scored = (t >= lo) & (t <= hi) if t.size else np.zeros(0, dtype=bool)
    share = float(np.mean(mode[scored] == MODE_VALID)) if scored.any() else math.nan
    print(f"  mode share VALID     {share:8.3f}      ({int(scored.sum())} EST_Status frames)")

    # the wire
    print("frames received / expected (from the daemon's cycle count):")
    for name in daemon.codec.output_messages:
        period = daemon.runner.encoder.periods.get(name, 1)
        expected = math.ceil(daemon.cycles / period) + (1 if name == "EST_Status" else 0)  # + the last frame
        print(f"  {name:<18} {listener.received[name]:6d} / {expected:6d}")
    crc = listener.errors.get(FrameDecodeError.CRC, 0)
    other = sum(n for reason, n in listener.errors.items() if reason != FrameDecodeError.CRC)
    counters = sum(listener.counter_errors.values())
    print(f"  CRC errors {crc}, counter errors {counters}, other decode errors {other}")
    total = sum(listener.received.values())
    if total == 0:
        print("FAIL: the daemon published nothing")
        return 1
    if crc or other:
        print("FAIL: corrupted output frames on the wire")
        return 1
    return 0
