"""``ptw-rt run``: the 100 Hz daemon. CAN frames in, estimates out, on absolute deadlines of the monotonic clock.

One cycle (every ``sample_time`` of ``time.monotonic()``, deadlines on a fixed grid so nothing drifts):

    frames received since the last cycle (+ the serial GNSS receiver's newest solution) -> CycleRunner.run -> bus.send

* A reader thread receives the input frames (the bus filters to the DBC's input ids; on the virtual bus python-can
  filters in software, which a ``recv(timeout=0)`` drain would mistake for an empty queue) and stamps them with
  the monotonic clock, so the tracker's timeouts use the loop's clock.
* Overrun: when the loop wakes more than one period late it does not burst through the missed cycles: it
  resynchronises to the grid, counts the missed cycles (EST_Status.OverrunCount) and raises REASON_OVERRUN for
  a status period (in EST_Status.ReasonBits, beside the estimator's own bits: the process's health is reported at
  the edge and never goes through the estimator).
* A failed send (``can.CanError``/``OSError``) is retried ``send_retries`` times, counted, raises
  REASON_SEND_FAILURE for a second, and is never fatal. A bus that disappears (the reader fails) is closed and
  reopened every second while the loop keeps its period.
* SIGTERM/SIGINT stop the loop: a last EST_Status with EST_Status_Valid = 0, the learned stiffness saved.
  SIGHUP reloads the config file (kept running with the old one if the new one is invalid).
* sd_notify: READY after the first published cycle, STATUS every second, WATCHDOG only while cycles are healthy.
* ``runtime.gps.source: serial``: a reader thread (``ptw_rt.io.nmea.SerialGnssReader``, started before the loop
  takes its real-time priority) parses RMC/VTG from ``runtime.gps.serial_port``; each cycle takes its newest
  solution as a GPS_Velocity would be taken (same Sample slots, range checks, timeout). An unplugged receiver
  makes GPS_Velocity stale in the next cycle (EST_Status.SensorTimeouts, DEGRADED), a replugged one is reopened
  every second; checksum errors and garbage lines count as decode errors of GPS_Velocity and are logged.

``Daemon`` is usable in a thread of another program (tests, demo): ``run(duration)`` / ``stop()``; only
``run_daemon`` installs signal handlers.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

import can

from ptw_rt.core.layout import (
    E_MODE,
    E_REASONS,
    E_VALID,
    MODE_NAMES,
    REASON_OVERRUN,
    REASON_SEND_FAILURE,
    V_CAMBER,
    V_CORNERING,
    reason_names,
)
from ptw_rt.edge.cycle import CycleRunner, build_runner
from ptw_rt.errors import UserFacingError
from ptw_rt.io.dbc import DbcError
from ptw_rt.io.nmea import NmeaParser, SerialGnssReader
from ptw_rt.io.state_file import restore_state, save_state, stiffness_bounds
from ptw_rt.paths import DEFAULT_DBC, DEFAULT_DESIGN
from ptw_rt.service.logs import HealthSummary, RateLimitedLog, setup_logging
from ptw_rt.service.realtime import apply_realtime, restore_scheduling, thread_scheduling
from ptw_rt.service.sdnotify import SystemdNotifier, WatchdogGate
from ptw_rt.settings import BusSettings, Settings, load_settings

__all__ = ["Daemon", "load_daemon_settings", "run_daemon"]

log = logging.getLogger("ptw_rt.daemon")

REOPEN_INTERVAL_S = 1.0
SEND_FAILURE_HOLD_S = 1.0
STATUS_NOTIFY_INTERVAL_S = 1.0
_BITRATE_INTERFACES = frozenset({"pcan", "kvaser", "ixxat", "vector", "slcan", "gs_usb", "nican", "canalystii"})
_RX_QUEUE_MAX = 20000


def _open_bus(bus_cfg: BusSettings, filters: list[dict]) -> can.BusABC:
    """Open the configured bus. A bad interface name is a user error; a missing device raises can.CanError/OSError."""
    kwargs: dict[str, Any] = {
        "interface": bus_cfg.interface,
        "channel": bus_cfg.channel,
        "can_filters": filters,
        "receive_own_messages": False,
    }
    if bus_cfg.interface in _BITRATE_INTERFACES:
        kwargs["bitrate"] = bus_cfg.bitrate
    try:
        return can.Bus(**kwargs)
    except (can.CanInterfaceNotImplementedError, ImportError, NotImplementedError) as exc:
        raise UserFacingError(f"CAN interface {bus_cfg.interface!r} is not available: {exc}") from exc


class _Reader(threading.Thread):
    """Receives frames from the bus into a deque as (monotonic time, id, data, extended); flags a lost bus."""

    def __init__(self, bus: can.BusABC, queue: collections.deque) -> None:
        super().__init__(name="ptw-rt-can-rx", daemon=True)
        self.bus = bus
        self.queue = queue
        self.running = True
        self.failed: str | None = None

    def run(self) -> None:
        recv = self.bus.recv
        append = self.queue.append
        clock = time.monotonic
        while self.running:
            try:
                msg = recv(timeout=0.05)
            except (can.CanError, OSError, ValueError) as exc:  # ValueError: bus closed under us
                if self.running:
                    self.failed = f"{type(exc).__name__}: {exc}"
                return
            if msg is not None and not msg.is_error_frame and not msg.is_remote_frame:
                append((clock(), msg.arbitration_id, bytes(msg.data), msg.is_extended_id))


class Daemon:
    """The fixed-step loop. ``settings.runtime`` gives the bus, timeouts, state file and log intervals."""

    def __init__(
        self,
        settings: Settings,
        config_path: str | Path,
        design_file: str | Path | None = None,
        *,
        notifier: SystemdNotifier | None = None,
        dbc: str | Path = DEFAULT_DBC,
        overrides: dict[str, Any] | None = None,
    ) -> None:
        self._overrides = dict(overrides or {})
        self.config_path = Path(config_path)
        self.design_file = design_file
        self.dbc = dbc
        self.settings = settings
        self.runner: CycleRunner = _build(self.config_path, design_file, dbc, settings)
        self.codec = self.runner.codec
        self.dt = self.runner.sample_time
        self.status_period = self.runner.encoder.periods["EST_Status"]
        self.filters = self.codec.can_filters(self.codec.input_messages)
        self.notifier = notifier if notifier is not None else SystemdNotifier()
        self.watchdog = WatchdogGate(self.notifier)
        self.rate_log = RateLimitedLog(log, settings.runtime.log_repeat_interval_s)
        self.bus: can.BusABC | None = None
        self._reader: _Reader | None = None
        self._rx: collections.deque = collections.deque(maxlen=_RX_QUEUE_MAX)
        self._stop = threading.Event()
        self._reload = threading.Event()
        # counters (read by tests, the health log and the status)
        self.cycles = 0
        self.overruns = 0
        self.frames_in = 0
        self.frames_out = 0
        self.send_failures = 0
        self.send_errors = 0  # failed attempts, retries included
        self.bus_reopens = 0
        self.state_saves = 0
        self.worst_cycle_us = 0.0  # since start
        self.estimates = self.runner.estimates
        self.ready = threading.Event()
        # optional hook called in the loop thread after every cycle with (monotonic time, Estimates); for tests
        # and the demo. Must be quick and must not keep the array (it is reused).
        self.on_cycle = None
        self.state_note = "no state file configured"
        self.realtime_warnings: list[str] = []  # what apply_realtime could not put in force at the last run()
        self.gnss: SerialGnssReader | None = None
        if settings.runtime.gps.source == "serial":
            gps = settings.runtime.gps
            self.gnss = SerialGnssReader(gps.serial_port, gps.serial_baudrate)  # UserFacingError without pynmea2
        self._gnss_taken = None  # receive time of the last solution taken into a cycle
        self._gnss_connected = False
        self._gnss_bad = 0  # checksum errors + garbage lines seen so far
        self._saver: threading.Thread | None = None
        self._warm_up()
        self._restore_state()

    # ------------------------------------------------------------------ control

    def stop(self) -> None:
        """Ask the loop to finish (thread-safe, async-signal-safe enough for a Python signal handler)."""
        self._stop.set()

    def request_reload(self) -> None:
        self._reload.set()

    @property
    def mode(self) -> int:
        return int(self.estimates[E_MODE])

    # ------------------------------------------------------------------ bus

    def _try_open(self) -> bool:
        cfg = self.settings.runtime.bus
        try:
            bus = _open_bus(cfg, self.filters)
        except (can.CanError, OSError, ValueError) as exc:
            self.rate_log.warn("bus_open", f"cannot open CAN bus {cfg.interface}:{cfg.channel}: {exc}", 0.0)
            return False
        self.bus = bus
        self._reader = _Reader(bus, self._rx)
        self._reader.start()
        log.info("CAN bus %s:%s open", cfg.interface, cfg.channel)
        return True

    def _close_bus(self) -> None:
        if self._reader is not None:
            self._reader.running = False
        if self.bus is not None:
            try:
                self.bus.shutdown()
            except Exception as exc:  # a dying driver may raise anything; closing must not
                log.debug("bus shutdown: %s", exc)
        if self._reader is not None and self._reader is not threading.current_thread():
            self._reader.join(timeout=0.5)
        self.bus = None
        self._reader = None

    def _send(self, frames: list[tuple[int, bytes]], now: float) -> bool:
        """Send the cycle's frames; False if any could not be sent after the retries."""
        bus = self.bus
        if bus is None:
            return False
        retries = self.settings.runtime.bus.send_retries
        ok = True
        for fid, data in frames:
            msg = can.Message(arbitration_id=fid, data=data, is_extended_id=False)
            for attempt in range(retries + 1):
                try:
                    bus.send(msg, timeout=0.001)
                except (can.CanError, OSError) as exc:
                    self.send_errors += 1
                    if attempt == retries:
                        ok = False
                        self.send_failures += 1
                        self.rate_log.warn("send", f"cannot send frame 0x{fid:03X}: {exc}", now)
                    continue
                self.frames_out += 1
                break
        return ok

    def _poll_gnss(self, runner: CycleRunner, gnss: SerialGnssReader, now: float) -> None:
        """The serial receiver's newest solution into this cycle, its unplug and its bad lines (cheap: no lock)."""
        connected = gnss.connected
        if connected != self._gnss_connected:
            self._gnss_connected = connected
            if not connected:  # unplugged: stale now, not after the timeout
                runner.tracker.lost("GPS_Velocity")
                self.rate_log.error("gnss_lost", f"GNSS receiver {gnss.port} lost: {gnss.last_error}", now)
            else:
                log.info("GNSS receiver %s connected", gnss.port)
        bad = gnss.parser.checksum_errors + gnss.parser.garbage
        if bad != self._gnss_bad:
            for _ in range(bad - self._gnss_bad):
                runner.tracker.decode_error("GPS_Velocity")
            self._gnss_bad = bad
            p = gnss.parser
            self.rate_log.warn(
                "gnss_bad", f"GNSS {gnss.port}: checksum errors {p.checksum_errors}, garbage lines {p.garbage}", now
            )
        latest = gnss.latest()
        if latest is None or latest[0] == self._gnss_taken:
            return
        t, speed, course, fix = latest
        self._gnss_taken = t
        signals = {"FixType": float(fix)}
        if speed == speed:  # no speed in the sentence: the neutral value, with its fix 0
            signals["SpeedOverGround"] = speed
        if course == course:  # receivers leave the course empty at standstill
            signals["CourseOverGround"] = course
        runner.on_values("GPS_Velocity", t, signals)

    def _warm_up(self) -> None:
        """Run the jitted step once before the loop (loading/compiling it takes far longer than a cycle)."""
        est = self.runner.estimator
        est.step(self.runner.sample.copy(), self.runner.estimates.copy())
        est.reset()

    # ------------------------------------------------------------------ state

    def _restore_state(self) -> None:
        path = self.settings.runtime.state_file
        if not path:
            return
        design = self.runner.estimator.design
        loaded = restore_state(
            path, self.settings.config_hash, stiffness_bounds(design.ad_theta_nominal, design.ad_theta_bound)
        )
        if loaded.removed_temp_files:
            log.info("removed %d orphan temporary state files", len(loaded.removed_temp_files))
        state = loaded.state
        if state is None:
            self.state_note = f"starting from nominal tyre stiffness: {loaded.reason}"
            log.log(loaded.level, self.state_note)
            return
        try:
            self.runner.estimator.restore_stiffness(state.stiffness)
        except ValueError as exc:
            self.state_note = f"state file {path} ignored: {exc}"
            log.warning(self.state_note)
            return
        self.state_note = f"restored learned tyre stiffness from {path} (saved {state.saved_at})"
        log.info(self.state_note)

    def _stiffness_to_save(self):
        if not int(self.estimates[E_VALID]) & (V_CORNERING | V_CAMBER):
            return None  # nothing learned (or restored) yet: keep the previous file
        return [float(v) for v in self.runner.estimator.learned_stiffness()]

    def _save_state(self, values, now: float) -> None:
        path = self.settings.runtime.state_file
        if not path or values is None:
            return
        try:
            save_state(path, values, self.settings.config_hash)
            self.state_saves += 1
        except (OSError, ValueError, TypeError) as exc:
            self.rate_log.warn("state_save", f"cannot save state to {path}: {exc}", now)

    def _save_in_background(self, now: float) -> None:
        if self._saver is not None and self._saver.is_alive():
            return
        values = self._stiffness_to_save()
        if values is None:
            return
        self._saver = threading.Thread(target=self._save_state, args=(values, now), name="ptw-rt-save", daemon=True)
        self._saver.start()

    # ------------------------------------------------------------------ reload

    def _do_reload(self) -> None:
        try:
            settings = load_daemon_settings(self.config_path, self._overrides)
            same_model = settings.config_hash == self.settings.config_hash and settings.sensors == self.settings.sensors
            runner = None if same_model else _build(self.config_path, self.design_file, self.dbc, settings)
        except UserFacingError as exc:
            log.error("SIGHUP: config not reloaded, keeping the running one: %s", exc)
            return
        if settings.runtime.bus != self.settings.runtime.bus:
            log.warning("SIGHUP: runtime.bus changed; the bus is reopened with the new settings")
            self.settings = settings
            self._close_bus()
        if runner is not None:
            if settings.config_hash == self.settings.config_hash:
                runner.estimator.restore_stiffness(self.runner.estimator.learned_stiffness())
            # the wire goes on: output counters and the 10 Hz phase continue
            runner.encoder, runner.cycles = self.runner.encoder, self.runner.cycles
            self.runner = runner
            self.estimates = runner.estimates
        self.settings = settings
        self.rate_log.repeat_interval_s = float(settings.runtime.log_repeat_interval_s)
        logging.getLogger().setLevel(settings.runtime.log_level)
        log.info("SIGHUP: config %s reloaded%s", self.config_path, "" if same_model else " (estimator restarted)")

    # ------------------------------------------------------------------ loop

    def run(self, duration: float | None = None) -> int:
        """Run until ``stop()`` (or ``duration`` seconds). Returns 0."""
        if self.gnss is not None:
            self.gnss.start()  # before the real-time priority: the reader thread must not inherit it
        rt = self.settings.runtime.realtime
        scheduling_before = thread_scheduling()
        self.realtime_warnings = apply_realtime(rt.priority, list(rt.cpus) if rt.cpus else None, rt.lock_memory)
        for w in self.realtime_warnings:
            log.warning("real-time setting not applied: %s", w)
        if self.bus is None:
            self._try_open()
        runner = self.runner
        gnss = self.gnss
        rx = self._rx
        dt = self.dt
        clock = time.monotonic
        perf = time.perf_counter
        t_start = clock()
        t_end = math.inf if duration is None else t_start + duration
        k = 1  # index of the next deadline on the grid t_start + k * dt
        next_reopen = t_start + REOPEN_INTERVAL_S
        next_status = t_start
        next_health = t_start + self.settings.runtime.health_log_interval_s
        next_save = t_start + self.settings.runtime.state_save_interval_s
        overrun_until = -math.inf
        send_fail_until = -math.inf
        period_worst_us = 0.0
        try:
            while not self._stop.is_set():
                deadline = t_start + k * dt
                now = clock()
                if now < deadline:
                    time.sleep(deadline - now)
                    now = clock()
                if now >= t_end:
                    break
                if now > deadline + dt:  # woke up more than a period late: resynchronise, no burst
                    k_now = int((now - t_start) / dt)
                    missed = k_now - k
                    self.overruns += missed
                    k = k_now
                    overrun_until = now + self.status_period * dt
                    self.rate_log.warn("overrun", f"cycle overrun: {missed} cycle(s) missed", now)
                k += 1
                t0 = perf()

                # ---- the cycle's work
                if self._reload.is_set():
                    self._reload.clear()
                    self._do_reload()
                    runner = self.runner
                n_rx = len(rx)
                for _ in range(n_rx):
                    ts, fid, data, ext = rx.popleft()
                    runner.on_frame(ts, fid, data, ext)
                self.frames_in += n_rx
                if gnss is not None:
                    self._poll_gnss(runner, gnss, now)
                runner.process_reasons = (REASON_OVERRUN if now < overrun_until else 0) | (
                    REASON_SEND_FAILURE if now < send_fail_until else 0
                )
                runner.status["overrun_count"] = self.overruns
                runner.status["cycle_time_us"] = period_worst_us
                is_status = runner.cycles % self.status_period == 0
                frames = runner.run(now)
                estimates = self.estimates = runner.estimates
                if is_status:
                    period_worst_us = 0.0
                sent = self._send(frames, now)
                if not sent and self.bus is not None:
                    send_fail_until = now + SEND_FAILURE_HOLD_S
                self.cycles += 1
                us = (perf() - t0) * 1e6
                if us > period_worst_us:
                    period_worst_us = us
                if us > self.worst_cycle_us:
                    self.worst_cycle_us = us
                if self.on_cycle is not None:
                    self.on_cycle(now, estimates)

                # ---- housekeeping (cheap unless due)
                healthy = sent and self.bus is not None
                if healthy and not self.ready.is_set():
                    self.ready.set()
                    self.notifier.ready(self._status_text())
                    log.info("publishing on %s; %s", self._bus_name(), self.state_note)
                self.watchdog.cycle_done(healthy, now)
                if self._reader is not None and self._reader.failed:
                    self.rate_log.error("bus_lost", f"CAN bus lost ({self._reader.failed}); reopening", now)
                    self._close_bus()
                if self.bus is None and now >= next_reopen:
                    next_reopen = now + REOPEN_INTERVAL_S
                    if self._try_open():
                        self.bus_reopens += 1
                if now >= next_status:
                    next_status = now + STATUS_NOTIFY_INTERVAL_S
                    self.notifier.status(self._status_text())
                if now >= next_health:
                    next_health = now + self.settings.runtime.health_log_interval_s
                    self._health_log(now)
                if now >= next_save:
                    next_save = now + self.settings.runtime.state_save_interval_s
                    self._save_in_background(now)
        finally:
            self._shutdown()
            restore_scheduling(scheduling_before)
        return 0

    def _shutdown(self) -> None:
        self.notifier.stopping("stopping")
        if self.gnss is not None:
            self.gnss.stop()
        if self.bus is not None:
            self.runner.status.update(overrun_count=self.overruns, cycle_time_us=0)
            self._send([self.runner.final_status()], time.monotonic())
        if self._saver is not None:
            self._saver.join(timeout=5.0)
        self._save_state(self._stiffness_to_save(), time.monotonic())
        self._close_bus()
        self._health_log(time.monotonic())
        log.info("stopped after %d cycles", self.cycles)

    # ------------------------------------------------------------------ reporting

    def _bus_name(self) -> str:
        b = self.settings.runtime.bus
        return f"{b.interface}:{b.channel}"

    def _status_text(self) -> str:
        e = self.estimates
        reasons = ",".join(reason_names(int(e[E_REASONS]))) or "-"
        bus = "open" if self.bus is not None else "LOST"
        gnss = "" if self.gnss is None else f" gnss={'open' if self.gnss.connected else 'LOST'}"
        return (
            f"mode={MODE_NAMES[int(e[E_MODE])]} reasons={reasons} cycles={self.cycles} overruns={self.overruns} "
            f"send_failures={self.send_failures} bus={bus}{gnss}"
        )

    def health(self) -> dict[str, Any]:
        return {
            "mode": MODE_NAMES[int(self.estimates[E_MODE])],
            "cycles": self.cycles,
            "overruns": self.overruns,
            "frames_in": self.frames_in,
            "frames_out": self.frames_out,
            "send_failures": self.send_failures,
            "bus_reopens": self.bus_reopens,
            "worst_cycle_us": round(self.worst_cycle_us, 1),
            "inputs": self.runner.tracker.summary(),
            "gnss": None if self.gnss is None else self.gnss.stats(),
        }

    def _health_log(self, now: float) -> None:
        self.rate_log.flush(now)
        inputs = {}
        for name, h in self.runner.tracker.summary().items():
            if isinstance(h, dict):
                inputs[name] = {
                    "rx": h["frames"],
                    "decode_err": h["decode_errors"],
                    "range": h["out_of_range"],
                    "jumps": h["counter_jumps"],
                    "timeouts": h["timeouts"],
                }
        if self.gnss is not None:
            g = self.gnss.stats()
            keys = ("connected", "opens", "disconnects", "used", "checksum_errors", "garbage")
            inputs["gnss_serial"] = {k: g[k] for k in keys}
        summary = HealthSummary(
            mode=int(self.estimates[E_MODE]),
            reasons=int(self.estimates[E_REASONS]),
            cycles=self.cycles,
            overruns=self.overruns,
            worst_cycle_us=self.worst_cycle_us,
            inputs=inputs,
        )
        summary.log(log)


# ---------------------------------------------------------------------- setup / CLI


def _build(config: Path, design_file, dbc, settings: Settings) -> CycleRunner:
    try:
        return build_runner(config, design_file, dbc, settings=settings)
    except DbcError as exc:
        raise UserFacingError(str(exc)) from exc


def load_daemon_settings(config: str | Path, overrides: dict[str, Any] | None = None) -> Settings:
    """Settings of the config file with command-line overrides of ``runtime`` applied."""
    settings = load_settings(config)
    if not overrides:
        return settings
    runtime = settings.runtime
    bus = {k: str(v) for k, v in overrides.items() if k in ("interface", "channel") and v is not None}
    rest = {
        k: str(v) if isinstance(v, Path) else v
        for k, v in overrides.items()
        if k not in ("interface", "channel") and v is not None
    }
    if bus:
        runtime = dataclasses.replace(runtime, bus=dataclasses.replace(runtime.bus, **bus))
    if rest:
        runtime = dataclasses.replace(runtime, **rest)
    return dataclasses.replace(settings, runtime=runtime)


def _overrides_from(args) -> dict[str, Any]:
    return {
        "interface": getattr(args, "interface", None),
        "channel": getattr(args, "channel", None),
        "state_file": getattr(args, "state_file", None),
    }


def run_daemon(args) -> int:
    """``ptw-rt run``: check the config (``--check-config``) or run the loop until SIGTERM/SIGINT/--duration."""
    overrides = _overrides_from(args)
    settings = load_daemon_settings(args.config, overrides)
    design = args.design_file or DEFAULT_DESIGN
    if args.check_config:
        runner = _build(Path(args.config), design, DEFAULT_DBC, settings)
        bus, gps = settings.runtime.bus, settings.runtime.gps
        if gps.source == "serial":
            NmeaParser()  # UserFacingError naming the gnss extra when pynmea2 is missing
        where = f"serial {gps.serial_port} at {gps.serial_baudrate} baud" if gps.source == "serial" else "CAN"
        print(
            f"config OK: {args.config} (hash {settings.config_hash[:12]}), design {design}, "
            f"DBC {runner.codec.dbc_path} ({len(runner.codec.output_messages)} outputs), "
            f"bus {bus.interface}:{bus.channel}, gps {where}, sample time {runner.sample_time * 1e3:g} ms"
        )
        return 0
    if args.duration is not None and not args.duration > 0:
        raise UserFacingError(f"--duration must be positive, got {args.duration}")
    setup_logging(settings.runtime.log_level)
    daemon = Daemon(settings, args.config, design, overrides=overrides)
    previous: dict[int, Any] = {}

    def on_stop(signum, frame) -> None:
        daemon.stop()

    def on_hup(signum, frame) -> None:
        daemon.request_reload()

    if threading.current_thread() is threading.main_thread():
        for sig, handler in ((signal.SIGTERM, on_stop), (signal.SIGINT, on_stop), (signal.SIGHUP, on_hup)):
            previous[sig] = signal.signal(sig, handler)
    try:
        return daemon.run(args.duration)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        sys.stderr.flush()
