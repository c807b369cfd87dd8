"""``ptw-rt run``: the 100 Hz daemon. CAN frames in, estimates out, on absolute deadlines of the monotonic clock.

One cycle (every ``sample_time`` of ``time.monotonic()``, deadlines on a fixed grid so nothing drifts):

    frames received since the last cycle (+ the serial GNSS receiver's newest solution) -> CycleRunner.run
    -> the sender's queue

Nothing that can block or take long runs in the loop's thread; the loop only hands work over and takes results:

* A reader thread receives the input frames (the bus filters to the DBC's input ids; on the virtual bus python-can
  filters in software, which a ``recv(timeout=0)`` drain would mistake for an empty queue) and stamps them with
  the monotonic clock, so the tracker's timeouts use the loop's clock. A receive failure (the bus disappeared)
  closes the bus; the loop reopens it every second while it keeps its period (``bus_reopens``).
* Sending never holds the loop. On SocketCAN (``send(timeout=0)``: python-can polls the socket for room first, a
  full queue or a bus-off controller is an error at once) and python-can's virtual bus the loop sends itself; any
  other driver (which may block in ``send``) gets a sender thread: ``bus.send`` with a bounded timeout, a queue of
  ``SEND_QUEUE_FRAMES`` frames that drops the oldest when the bus cannot keep up (``send_dropped``). Either way a
  frame is tried ``1 + send_retries`` times; failures (any ``can.CanError``/``OSError``) are counted
  (``send_failures``, ``send_errors`` for every failed attempt), logged at most once per
  ``runtime.log_repeat_interval_s``, shown in the status and raise REASON_SEND_FAILURE for a second; never fatal.
  When no frame has gone out for ``SEND_STUCK_REOPEN_S`` while frames failed, the bus is closed and reopened as a
  lost one is (``send_stuck_reopens``; again after as long if it still sends nothing).
* SIGHUP: a reload thread (normal scheduling) re-reads and validates the config and builds the new cycle
  (``RELOADING=1`` to systemd); the loop swaps it in between two cycles and sends ``READY=1``. An invalid config
  is logged and the running one kept (``READY=1`` all the same).
* Overrun: when the loop wakes more than one period late it does not burst through the missed cycles: it
  resynchronises to the grid, counts the missed cycles (EST_Status.OverrunCount) and raises REASON_OVERRUN for a
  status period (EST_Status.ReasonBits, beside the estimator's own bits). The rule for the mode: published
  DEGRADED, with REASON_OVERRUN, while more than ``OVERRUN_DEGRADED_LIMIT`` cycles were missed within the last
  ``OVERRUN_WINDOW_S`` (docs/daemon.md: each missed cycle loses one sample of every input; an isolated overrun
  keeps VALID).
* Watchdog: ``WATCHDOG=1`` means "the loop runs": pinged while cycles complete on time (a cycle that had to
  resynchronise is not on time), whatever the bus does. A hung loop, or one that misses every deadline for
  ``WatchdogSec/2``, stops the pings and systemd restarts it. ``READY=1`` after the first cycle on an open bus.
* Start-up: a bus that cannot be opened is one line and exit code 69 (``BusUnavailableError``), restarted by
  systemd; later losses of the bus are reopened in the loop.
* SIGTERM/SIGINT stop the loop: a last EST_Status with EST_Status_Valid = 0, the learned stiffness saved.
* sd_notify: STATUS every second (mode, counters, bus, send failures).
* ``runtime.gps.source: serial``: a reader thread (``ptw_rt.io.nmea.SerialGnssReader``, started before the loop
  takes its real-time priority) parses RMC/VTG from ``runtime.gps.serial_port``; each cycle takes its newest
  solution as a GPS_Velocity would be taken (same Sample slots, range checks, timeout). An unplugged receiver
  makes GPS_Velocity stale in the next cycle (EST_Status.SensorTimeouts, DEGRADED), a replugged one is reopened
  every second; checksum errors and garbage lines count as decode errors of GPS_Velocity and are logged.

``Daemon`` is usable in a thread of another program (tests, demo): ``run(duration)`` / ``stop()``; only
``run_daemon`` installs signal handlers and ``faulthandler`` (a SIGABRT from systemd's watchdog prints every
thread's stack to the journal).
"""

from __future__ import annotations

import collections
import dataclasses
import faulthandler
import gc
import logging
import math
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

import can
import numpy as np

from ptw_rt.core.estimator import Estimator
from ptw_rt.core.layout import (
    E_C_ALPHA_FRONT,
    E_C_GAMMA_REAR,
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
from ptw_rt.errors import EXIT_UNAVAILABLE, UserFacingError
from ptw_rt.io.dbc import DbcError
from ptw_rt.io.nmea import NmeaParser, SerialGnssReader
from ptw_rt.io.state_file import (
    group_within_bounds,
    restore_state,
    save_state,
    sensor_bias_bounds,
    steer_zero_bounds,
    stiffness_bounds,
)
from ptw_rt.paths import DEFAULT_DBC, design_file_for
from ptw_rt.service.logs import HealthSummary, RateLimitedLog, setup_logging
from ptw_rt.service.realtime import apply_realtime, normal_scheduling, restore_scheduling, thread_scheduling
from ptw_rt.service.sdnotify import SystemdNotifier, WatchdogGate
from ptw_rt.settings import BusSettings, Settings, load_settings

__all__ = ["BusUnavailableError", "Daemon", "OverrunRule", "load_daemon_settings", "run_daemon"]

log = logging.getLogger("ptw_rt.daemon")

REOPEN_INTERVAL_S = 1.0
RESTART_ONLY = ("gps", "realtime")  # runtime sections a SIGHUP cannot put in force (the next start does)
SEND_FAILURE_HOLD_S = 1.0
# Nothing sent for this long while frames failed: the bus is closed and reopened like a lost one. A wedged adapter or
# a driver's dead handle fails every send and never its receive; a bus-off controller that the kernel restarts
# (`restart-ms`) loses nothing by a new socket. Longer than any transient (3 s of ENOBUFS are counted, not reopened)
SEND_STUCK_REOPEN_S = 5.0
STATUS_NOTIFY_INTERVAL_S = 1.0
SEND_TIMEOUT_S = 0.005  # one bus.send may wait this long for room in the transmit queue (in the sender thread)
SEND_QUEUE_FRAMES = 64  # ~13 cycles of output: beyond, the oldest frames are dropped (stale estimates are useless)
OVERRUN_WINDOW_S = 1.0  # the overrun rule: DEGRADED while more than OVERRUN_DEGRADED_LIMIT cycles were missed
OVERRUN_DEGRADED_LIMIT = 2  # within the last OVERRUN_WINDOW_S (docs/daemon.md, "Overruns")
# a persisted sensor bias beyond this many times its configured uncertainty a priori (the accelerometers': the wider,
# the level road's) is not one the filter learned
MAX_BIAS_SHARES = 10.0
_BITRATE_INTERFACES = frozenset({"pcan", "kvaser", "ixxat", "vector", "slcan", "gs_usb", "nican", "canalystii"})
_RX_QUEUE_MAX = 20000
# CanError, OSError, ValueError (a bus closed under the sender), and a driver's bug (a RuntimeError from send):
# counted, the frame given up; it ended the sender thread (nothing published again, the watchdog fed) or the loop
_SEND_ERRORS = (Exception,)


class BusUnavailableError(UserFacingError):
    """The CAN bus cannot be opened at start-up (exit code 69: systemd restarts the daemon, the link may come)."""

    exit_code = EXIT_UNAVAILABLE


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
    except TypeError as exc:  # a back end whose constructor needs arguments the configuration has no place for
        raise UserFacingError(
            f"CAN interface {bus_cfg.interface!r} needs settings runtime.bus does not carry ({exc}); "
            "give them in python-can's configuration file (~/.canrc)"
        ) from exc


# the input message a serial GNSS receiver stands for (its solutions are fed as this message's signals)
SERIAL_GPS_MESSAGE = "GPS_Velocity"


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
            except Exception as exc:  # noqa: BLE001 - CanError, OSError, ValueError (closed under us), a driver's bug
                if self.running:  # the loop reopens the bus: a dead reader left it FAULT for good, STATUS bus=open
                    self.failed = f"{type(exc).__name__}: {exc}"
                return
            # error, remote and CAN FD frames are no input (the DBC's are classic frames), as in a replay: an FD frame
            # of an input's id with a classic payload was decoded live and skipped by the replay of the same traffic
            if msg is not None and not (msg.is_error_frame or msg.is_remote_frame or msg.is_fd):
                append((clock(), msg.arbitration_id, bytes(msg.data), msg.is_extended_id))


def _shutdown_quietly(bus: can.BusABC) -> None:
    try:
        bus.shutdown()
    except Exception as exc:  # noqa: BLE001 - a dying driver may raise anything; closing must not
        log.debug("bus shutdown: %s", exc)


class _Opener(threading.Thread):
    """Opens a bus off the loop (``Daemon._reopen``): ``bus`` once open, or the ``error`` that stopped it."""

    def __init__(self, cfg: BusSettings, filters: list[dict]) -> None:
        super().__init__(name="ptw-rt-can-open", daemon=True)
        self.cfg, self.filters = cfg, filters
        self.bus: can.BusABC | None = None
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            self.bus = _open_bus(self.cfg, self.filters)
        except Exception as exc:  # noqa: BLE001 - whatever the driver raised: reported by the loop, retried
            self.error = exc


class _Sender(threading.Thread):
    """Sends the loop's frames on ``daemon.bus`` (whatever bus is open at the time) so the loop never waits for it.

    ``put`` (the loop) appends to a queue of at most ``SEND_QUEUE_FRAMES`` frames, dropping the oldest when full
    (``daemon.send_dropped``); the thread sends each with ``bus.send(msg, timeout=SEND_TIMEOUT_S)`` and
    ``send_retries`` retries, counting into the daemon's ``frames_out``, ``send_errors`` (failed attempts) and
    ``send_failures`` (frames given up), and logs failures rate-limited. Started by the loop's thread, it shares
    the loop's real-time priority: frames go out as soon as the loop sleeps.
    """

    def __init__(self, daemon: Daemon) -> None:
        super().__init__(name="ptw-rt-can-tx", daemon=True)
        self.d = daemon
        self.queue: collections.deque = collections.deque()
        self.cond = threading.Condition(threading.Lock())
        self.running = True
        self.rate_log = RateLimitedLog(log, daemon.settings.runtime.log_repeat_interval_s)

    def put(self, frames: list[tuple[int, bytes]]) -> None:
        with self.cond:
            queue = self.queue
            for frame in frames:
                if len(queue) >= SEND_QUEUE_FRAMES:
                    queue.popleft()
                    self.d.send_dropped += 1
                queue.append(frame)
            self.cond.notify()

    def stop(self, timeout: float) -> None:
        """Send what is queued (for at most ``timeout`` s), then end the thread."""
        with self.cond:
            self.running = False
            self.cond.notify()
        self.join(timeout)

    def run(self) -> None:
        cond = self.cond
        queue = self.queue
        while True:
            with cond:
                while not queue and self.running:
                    cond.wait()
                if not queue:
                    return
                fid, data = queue.popleft()
            self._send(fid, data)

    def _send(self, fid: int, data: bytes) -> None:
        bus = self.d.bus
        if bus is not None:  # lost meanwhile: the loop reopens it; frames of a lost bus are not failures
            _send_frame(self.d, bus, fid, data, SEND_TIMEOUT_S, self.rate_log)


def _send_frame(d: Daemon, bus: can.BusABC, fid: int, data: bytes, timeout: float, rate_log: RateLimitedLog) -> None:
    """One frame with ``send_retries`` retries; the outcome counted into the daemon's counters. Never raises."""
    msg = can.Message(arbitration_id=fid, data=data, is_extended_id=False)
    retries = d.settings.runtime.bus.send_retries
    for attempt in range(retries + 1):
        try:
            bus.send(msg, timeout=timeout)
        except _SEND_ERRORS as exc:
            d.send_errors += 1
            if attempt == retries:
                d.send_failures += 1
                d.last_send_error = f"{type(exc).__name__}: {exc}"
                rate_log.warn(
                    "send",
                    f"cannot send frame 0x{fid:03X}: {d.last_send_error} ({d.send_failures} frames failed, "
                    f"{d.send_dropped} dropped so far; the loop keeps its period)",
                    time.monotonic(),
                )
            continue
        d.frames_out += 1
        return


def _never_blocks(bus: can.BusABC) -> bool:
    """True for the buses the loop may send on itself with ``timeout=0``: SocketCAN (python-can polls the socket
    for room with a zero timeout before it sends, so the send cannot wait; a full queue or a bus-off controller is
    an immediate error) and python-can's in-process virtual bus. Every other driver (USB adapters, serial slcan,
    anything unknown) may block in ``send``: the sender thread's job."""
    try:
        from can.interfaces.virtual import VirtualBus

        if type(bus) is VirtualBus:
            return True
        from can.interfaces.socketcan import SocketcanBus

        if type(bus) is SocketcanBus:
            return True
    except ImportError:
        pass
    return False


class OverrunRule:
    """When missed cycles make the published mode DEGRADED: while more than ``limit`` cycles were missed within
    the last ``window_s`` seconds (docs/daemon.md, "Overruns"). An isolated overrun of up to ``limit`` cycles is
    counted (OverrunCount, REASON_OVERRUN) and keeps the mode."""

    def __init__(self, limit: int = OVERRUN_DEGRADED_LIMIT, window_s: float = OVERRUN_WINDOW_S) -> None:
        self.limit = int(limit)
        self.window_s = float(window_s)
        self.missed = 0  # cycles missed within the window
        self._events: collections.deque = collections.deque()  # (time, missed cycles)

    def add(self, now: float, missed: int) -> None:
        self._events.append((now, missed))
        self.missed += missed

    def degraded(self, now: float) -> bool:
        events = self._events
        while events and events[0][0] <= now - self.window_s:
            self.missed -= events.popleft()[1]
        return self.missed > self.limit


@dataclasses.dataclass
class _Reload:
    """What the reload thread prepared for the loop to swap in (``error`` set: keep the running config)."""

    settings: Settings | None = None
    runner: CycleRunner | None = None  # None: same model, the running cycle goes on
    error: str | None = None
    seconds: float = 0.0


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
        # with the GPS on a serial receiver, GPS_Velocity frames on the bus are not ours to trust: taken beside it,
        # they kept a receiver that had gone silent from ever being flagged (found by fuzzing, 2026-11-26)
        serial_gps = settings.runtime.gps.source == "serial"
        self.filters = self.codec.can_filters(
            [m for m in self.codec.input_messages if not (serial_gps and m == SERIAL_GPS_MESSAGE)]
        )
        self.notifier = notifier if notifier is not None else SystemdNotifier()
        self.watchdog = WatchdogGate(self.notifier)
        self.rate_log = RateLimitedLog(log, settings.runtime.log_repeat_interval_s)
        self.bus: can.BusABC | None = None
        self._inline = False  # the loop sends itself (a bus that never blocks), else through the sender thread
        self._reader: _Reader | None = None
        self._sender: _Sender | None = None
        self._rx: collections.deque = collections.deque(maxlen=_RX_QUEUE_MAX)
        self._stop = threading.Event()
        self._reload = threading.Event()
        self._reloader: threading.Thread | None = None
        self._prepared: _Reload | None = None  # set by the reload thread, taken by the loop
        self._next_reopen = -math.inf
        self._opener: _Opener | None = None
        # counters (read by tests, the health log and the status)
        self.cycles = 0
        self.overruns = 0  # missed cycles since start
        self.frames_in = 0
        self.frames_out = 0  # sent (by the sender thread)
        self.send_failures = 0  # frames given up after the retries
        self.send_errors = 0  # failed attempts, retries included
        self.send_dropped = 0  # frames dropped from a full send queue (the bus could not keep up)
        self.last_send_error: str | None = None
        self.last_open_error: str | None = None
        self.bus_reopens = 0
        self.send_stuck_reopens = 0  # buses closed (to be reopened) because nothing could be sent on them
        self.reloads = 0  # configurations swapped in
        self.reload_failures = 0
        self.state_saves = 0
        self.worst_cycle_us = 0.0  # since start
        self.overrun_degraded_cycles = 0  # cycles published DEGRADED by the overrun rule
        self.overrun_rule = OverrunRule()
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
        # the stiffness last published VALID in this run (copied by the loop each VALID cycle: a stop saves it)
        self._kept_stiffness = np.zeros(E_C_GAMMA_REAR + 1 - E_C_ALPHA_FRONT)
        self._stiffness_kept = False
        # the last sensor biases and steer zero known good (restored, or learned and saved): a save while the
        # attitude filter doubts its biases (an alarm) or before the zero is re-learned keeps them, never drops them
        self._kept_biases: tuple[float, ...] | None = None
        self._kept_accel_biases: tuple[float, ...] | None = None  # (b_ax, b_az) with them, if known
        self._kept_steer_zero: tuple[float, float] | None = None
        self._warm_up()
        self._restore_state()
        # everything built so far lives as long as the daemon: out of the garbage collector's full passes,
        # which would otherwise walk it (numba's and cantools' objects) from inside the loop
        gc.freeze()

    # ------------------------------------------------------------------ control

    def stop(self) -> None:
        """Ask the loop to finish (thread-safe, async-signal-safe enough for a Python signal handler)."""
        self._stop.set()

    def request_reload(self) -> None:
        """Re-read the configuration (SIGHUP): prepared in another thread, swapped in between two cycles."""
        self._reload.set()

    @property
    def mode(self) -> int:
        return int(self.estimates[E_MODE])

    # ------------------------------------------------------------------ bus

    def _try_open(self) -> bool:
        """Open the configured bus before the loop starts and start its reader; False when it cannot be opened
        (a configuration problem, an interface python-can lacks: ``UserFacingError``, exit 2)."""
        cfg = self.settings.runtime.bus
        try:
            bus = _open_bus(cfg, self.filters)
        except (can.CanError, OSError, ValueError) as exc:
            self.last_open_error = f"{type(exc).__name__}: {exc}"
            return False
        self._install(bus, cfg)
        return True

    def _install(self, bus: can.BusABC, cfg: BusSettings) -> None:
        self.bus = bus
        self._inline = _never_blocks(bus)
        self._reader = _Reader(bus, self._rx)
        self._reader.start()
        log.info("CAN bus %s:%s open", cfg.interface, cfg.channel)

    def _reopen(self, now: float) -> None:
        """While running, the bus is reopened off the loop, once a second until it opens: a driver's open may block
        for seconds (python-can's slcan sleeps 2 s after opening a replugged adapter: from the loop, 200 missed
        cycles and a 2.1 s gap in the watchdog's pings, a kill under WatchdogSec=2)."""
        opener = self._opener
        if opener is None:
            if now >= self._next_reopen:
                self._next_reopen = now + REOPEN_INTERVAL_S
                self._opener = _Opener(self.settings.runtime.bus, self.filters)
                self._opener.start()
            return
        if opener.is_alive():
            return
        self._opener = None
        cfg = opener.cfg
        if opener.bus is not None and cfg == self.settings.runtime.bus:
            self._install(opener.bus, cfg)
            self.bus_reopens += 1
            return
        if opener.bus is not None:  # opened with the settings of before a reload: not the bus wanted now
            _shutdown_quietly(opener.bus)
            self._next_reopen = now
            return
        exc = opener.error
        if isinstance(exc, UserFacingError):  # the driver would not load: its cause says why
            exc = exc.__cause__ or exc
        self.last_open_error = f"{type(exc).__name__}: {exc}"
        self.rate_log.warn("bus_open", f"cannot open CAN bus {cfg.interface}:{cfg.channel}: {exc}", now)

    def open_bus(self) -> None:
        """Open the bus before the loop starts; ``BusUnavailableError`` (one line, exit code 69) if impossible."""
        if self.bus is not None:
            return
        if not self._try_open():
            cfg = self.settings.runtime.bus
            raise BusUnavailableError(
                f"cannot open CAN bus {cfg.interface}:{cfg.channel} ({self.last_open_error}); "
                "is the interface up? (systemd restarts the daemon)"
            )

    def _close_bus(self, wait: bool = False) -> None:
        """Close the bus. The reader notices within its receive timeout; ``wait`` joins it (not from the loop)."""
        reader = self._reader
        if reader is not None:
            reader.running = False
        if self.bus is not None:
            _shutdown_quietly(self.bus)
        if wait and reader is not None and reader is not threading.current_thread():
            reader.join(timeout=0.5)
        self.bus = None
        self._reader = None

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
        bad = gnss.bad_lines
        if bad != self._gnss_bad:
            runner.tracker.decode_error("GPS_Velocity", bad - self._gnss_bad)  # one call, however many lines
            self._gnss_bad = bad
            p = gnss.parser
            self.rate_log.warn(
                "gnss_bad",
                f"GNSS {gnss.port}: checksum errors {p.checksum_errors}, garbage lines {bad - p.checksum_errors}",
                now,
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
        runner.on_values(SERIAL_GPS_MESSAGE, t, signals)

    def _warm_up(self, runner: CycleRunner | None = None) -> None:
        """Load every compiled function of the cycle before the loop (loading/compiling takes far longer than a
        cycle): ``CycleRunner.warm_up``."""
        (runner or self.runner).warm_up()

    # ------------------------------------------------------------------ state

    def _restore_state(self) -> None:
        path = self.settings.runtime.state_file
        if not path:
            return
        design = self.runner.estimator.design
        bounds = (
            stiffness_bounds(design.ad_theta_nominal, design.ad_theta_bound)
            | self._bias_bounds()
            | steer_zero_bounds(
                self.runner.estimator.steer_zero_max_shift(), self.settings.sensors.steer_counts_per_rev
            )
        )
        loaded = restore_state(path, self.settings.config_hash, bounds, self.settings.learned_state_hash)
        if loaded.removed_temp_files:
            log.info("removed %d orphan temporary state files", len(loaded.removed_temp_files))
        state = loaded.state
        if state is None:
            self.state_note = f"starting from nominal tyre stiffness: {loaded.reason}"
            log.log(loaded.level, self.state_note)
            return
        est = self.runner.estimator
        steer_zero = False
        try:
            est.restore_stiffness(state.stiffness)
            if state.sensor_biases is not None:
                est.restore_sensor_biases(state.sensor_biases, state.accel_biases)
            if state.steer_zero is not None:
                steer_zero = est.restore_steer_zero(*state.steer_zero)
        except ValueError as exc:
            self.state_note = f"state file {path} ignored: {exc}"
            log.warning(self.state_note)
            return
        what = ["tyre stiffness"]
        if state.sensor_biases is not None:
            what.append("sensor biases")
            self._kept_biases = tuple(state.sensor_biases)
            self._kept_accel_biases = state.accel_biases
        if steer_zero:
            what.append("steer zero")
            self._kept_steer_zero = tuple(state.steer_zero)
        listed = what[0] if len(what) == 1 else f"{', '.join(what[:-1])} and {what[-1]}"
        self.state_note = f"restored learned {listed} from {path} (saved {state.saved_at})"
        if not state.same_config:
            self.state_note += "; saved with another payload (vehicle.added_mass): the same tyres and sensors"
        if state.sensor_biases is None and state.accel_biases is not None:
            # the daemon saves them with the four sensor biases only: a file edited or written elsewhere; they are
            # the filter's offsets against those, so restored alone they would be learned values out of context
            self.state_note += "; its accelerometer biases not restored: saved without the sensor biases"
        if state.steer_zero is not None and not steer_zero:
            self.state_note += (
                f"; its steer zero was learned against count {state.steer_zero[0]:g}, the configuration now has "
                f"{self.settings.sensors.steer_zero_count:g}: re-learned riding straight"
            )
        log.info(self.state_note)

    def _bias_bounds(self):
        """The state file's bounds of the sensor biases: the largest a start takes from it."""
        tuning = self.settings.estimator.attitude
        accel_prior = max(tuning.initial_accel_bias_sd, tuning.level_road_accel_bias_sd)
        return sensor_bias_bounds(MAX_BIAS_SHARES * tuning.initial_gyro_bias_sd, MAX_BIAS_SHARES * accel_prior)

    def _stiffness_to_save(self):
        """(stiffness, sensor biases or None, steer zero or None) worth keeping, or None: the file is written only
        once the tyres are learned (VALID), never with the prior as if it had been learned: the stiffness last
        published VALID in this run (the tyres are never VALID at a stop, where SIGTERM comes: a stop there saved
        nothing of a ride's learning). Biases or a steer zero not sound at this moment (the attitude monitor's
        alarm; not yet re-learned) are the last known good ones."""
        if not self._stiffness_kept:  # the loop keeps it, each cycle the tyres are VALID
            return None  # nothing learned (or restored) yet: keep the previous file
        est = self.runner.estimator
        biases, steer_zero = est.learned_sensor_biases(), est.learned_steer_zero()
        accel_biases = est.learned_accel_biases() if biases is not None else None
        bounds = self._bias_bounds()
        if (  # what the next start would take, else the last known good ones (the tyres with them)
            biases is not None
            and group_within_bounds("sensor_biases", biases, bounds)
            and (accel_biases is None or group_within_bounds("accel_biases", accel_biases, bounds))
        ):
            self._kept_biases, self._kept_accel_biases = biases, accel_biases
        self._kept_steer_zero = steer_zero = steer_zero if steer_zero is not None else self._kept_steer_zero
        biases = (self._kept_biases, self._kept_accel_biases)
        return [float(v) for v in self._kept_stiffness], biases, steer_zero

    def _save_state(self, values, now: float, final: bool = False) -> None:
        """Write the learned values; a failure is a rate-limited warning while riding (the next save retries), always
        a line at the stop (`final`): the last save's failure was swallowed by the limiter when it came within its
        interval of the one before, and the ride's newest learning was lost unsaid (found by fuzzing)."""
        path = self.settings.runtime.state_file
        if not path or values is None:
            return
        stiffness, (biases, accel_biases), steer_zero = values
        try:
            save_state(
                path,
                stiffness,
                self.settings.config_hash,
                sensor_biases=biases,
                steer_zero=steer_zero,
                accel_biases=accel_biases,
                learned_state_hash=self.settings.learned_state_hash,
            )
            self.state_saves += 1
        except (OSError, ValueError, TypeError) as exc:
            if final:
                log.error("cannot save state to %s at stop: %s (the file keeps what an earlier save wrote)", path, exc)
            else:
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

    def _start_reload(self) -> None:
        """SIGHUP seen by the loop: tell systemd, prepare the new configuration in a thread of its own."""
        self._reload.clear()
        self.notifier.reloading(f"reloading {self.config_path}")
        self._reloader = threading.Thread(target=self._prepare_reload, name="ptw-rt-reload", daemon=True)
        self._reloader.start()

    def _prepare_reload(self) -> None:
        """The reload thread: parse, validate and build everything the loop will swap in; never raises."""
        normal_scheduling()  # created by the real-time loop: do the slow work at normal priority
        switch = sys.getswitchinterval()
        sys.setswitchinterval(min(switch, 0.0005))  # hand the GIL back to the loop within 0.5 ms, not 5 ms
        t0 = time.perf_counter()
        try:
            settings = load_daemon_settings(self.config_path, self._overrides)
            same_model = (
                settings.config_hash == self.settings.config_hash
                and settings.sensors == self.settings.sensors
                and settings.runtime.stale_after_periods == self.settings.runtime.stale_after_periods  # the tracker's
            )
            runner = None
            if not same_model:
                runner = _build(self.config_path, self.design_file, self.dbc, settings)
                self._warm_up(runner)
            prepared = _Reload(settings, runner)
        except UserFacingError as exc:
            prepared = _Reload(error=str(exc))
        except Exception as exc:  # noqa: BLE001 - a reload must never take the daemon down
            log.exception("SIGHUP: unexpected error while preparing the reload")
            prepared = _Reload(error=f"internal error: {type(exc).__name__}: {exc}")
        finally:
            sys.setswitchinterval(switch)
        prepared.seconds = time.perf_counter() - t0
        self._prepared = prepared

    def _carry_learning(self, old: Estimator, new: Estimator) -> None:
        """A reload that restarts the estimator on the same vehicle (its sensor settings or its payload changed:
        ``Settings.learned_state_hash``) starts the new one from what a restart would: what the state file would
        keep now (the tyres last published VALID, the biases and steer zero known good), else the running tyres.
        Only the tyres were carried before 2026-12-06, and only for the same config hash: a rider's payload set
        while the daemon ran dropped the tyres, and every such reload re-learned the biases from their prior."""
        keep = self._stiffness_to_save()
        new.restore_stiffness(keep[0] if keep is not None else old.learned_stiffness())
        if self._kept_biases is not None:
            new.restore_sensor_biases(self._kept_biases, self._kept_accel_biases)
        if self._kept_steer_zero is not None:
            try:
                carried = new.restore_steer_zero(*self._kept_steer_zero)
            except ValueError as exc:  # beyond what the new sensors section lets the conditioning learn
                log.warning("SIGHUP: the learned steer zero is not carried: %s", exc)
                carried = False
            if not carried:  # re-zeroed or bounded anew: re-learned riding straight, as after a restart, and not
                self._kept_steer_zero = None  # saved (the next start's bounds would refuse the whole file)

    def _apply_reload(self, prepared: _Reload, now: float) -> CycleRunner:
        """Between two cycles (the loop's thread): swap in what the reload thread prepared. Returns the runner."""
        self._prepared = None
        if prepared.error is not None:
            self.reload_failures += 1
            log.error("SIGHUP: config not reloaded, keeping the running one: %s", prepared.error)
            self.notifier.ready(f"reload failed, running the previous config; {self._status_text()}")
            return self.runner
        settings, runner = prepared.settings, prepared.runner
        assert settings is not None
        # what a running daemon cannot change (the GNSS reader's port and source, the scheduling it was started
        # with): kept, and said, rather than reported reloaded and silently not in force
        at_start = [k for k in RESTART_ONLY if getattr(settings.runtime, k) != getattr(self.settings.runtime, k)]
        if at_start:
            kept = {k: getattr(self.settings.runtime, k) for k in at_start}
            settings = dataclasses.replace(settings, runtime=dataclasses.replace(settings.runtime, **kept))
            log.warning(
                "SIGHUP: runtime.%s changed: it takes effect at the next start (systemctl restart ptw-rt); the "
                "running one is kept",
                ", runtime.".join(at_start),
            )
        if settings.runtime.bus != self.settings.runtime.bus:
            log.warning("SIGHUP: runtime.bus changed; the bus is reopened with the new settings")
            self._close_bus()
            self._next_reopen = now  # at the next cycle
        old = self.runner
        if runner is not None:
            if settings.learned_state_hash == self.settings.learned_state_hash:
                self._carry_learning(old.estimator, runner.estimator)
            else:  # another vehicle or tuning: what the old one learned is not this one's to save
                self._stiffness_kept = False
                self._kept_biases = self._kept_accel_biases = self._kept_steer_zero = None
            # the wire goes on: output counters and the 10 Hz phase continue; so do the inputs when they can
            runner.encoder, runner.cycles = old.encoder, old.cycles
            if settings.runtime.stale_after_periods == self.settings.runtime.stale_after_periods:
                runner.tracker = old.tracker
            runner.process_degraded = old.process_degraded
            self.runner = runner
            self.estimates = runner.estimates
        self.settings = settings
        self.rate_log.repeat_interval_s = float(settings.runtime.log_repeat_interval_s)
        if self._sender is not None:
            self._sender.rate_log.repeat_interval_s = self.rate_log.repeat_interval_s
        logging.getLogger().setLevel(settings.runtime.log_level)
        self.reloads += 1
        log.info(
            "SIGHUP: config %s reloaded%s (prepared in %.0f ms off the loop)",
            self.config_path,
            "" if runner is None else " (estimator restarted)",
            prepared.seconds * 1e3,
        )
        self.notifier.ready(self._status_text())
        return self.runner

    # ------------------------------------------------------------------ loop

    def run(self, duration: float | None = None) -> int:
        """Run until ``stop()`` (or ``duration`` seconds). Returns 0.

        Raises ``BusUnavailableError`` (before anything else happens) if the bus cannot be opened.
        """
        self.open_bus()
        if self.gnss is not None:
            self.gnss.start()  # before the real-time priority: the reader thread must not inherit it
        rt = self.settings.runtime.realtime
        scheduling_before = thread_scheduling()
        self.realtime_warnings = apply_realtime(rt.priority, list(rt.cpus) if rt.cpus else None, rt.lock_memory)
        for w in self.realtime_warnings:
            log.warning("real-time setting not applied: %s", w)
        self._sender = sender = _Sender(self)
        sender.start()  # after the real-time priority: it inherits it
        runner = self.runner
        gnss = self.gnss
        rx = self._rx
        dt = self.dt
        clock = time.monotonic
        perf = time.perf_counter
        t_start = clock()
        t_end = math.inf if duration is None else t_start + duration
        k = 1  # index of the next deadline on the grid t_start + k * dt
        self._next_reopen = t_start + REOPEN_INTERVAL_S
        next_status = t_start
        next_health = t_start + self.settings.runtime.health_log_interval_s
        next_save = t_start + self.settings.runtime.state_save_interval_s
        overrun_until = -math.inf
        send_fail_until = -math.inf
        send_problems = 0  # send_failures + send_dropped seen so far
        frames_out_seen = 0
        last_sent = t_start  # when a frame last went out (or there was no bus to send on)
        problems_at_last_sent = 0
        overrun_rule = self.overrun_rule = OverrunRule()
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
                on_time = now <= deadline + dt
                if not on_time:  # woke up more than a period late: resynchronise, no burst
                    k_now = int((now - t_start) / dt)
                    missed = k_now - k
                    self.overruns += missed
                    k = k_now
                    overrun_until = now + self.status_period * dt
                    overrun_rule.add(now, missed)
                    self.rate_log.warn("overrun", f"cycle overrun: {missed} cycle(s) missed", now)
                k += 1
                t0 = perf()

                # ---- the cycle's work
                prepared = self._prepared
                if prepared is not None:
                    runner = self._apply_reload(prepared, now)
                n_rx = len(rx)
                for _ in range(n_rx):
                    ts, fid, data, ext = rx.popleft()
                    runner.on_frame(ts, fid, data, ext)
                self.frames_in += n_rx
                if gnss is not None:
                    self._poll_gnss(runner, gnss, now)
                problems = self.send_failures + self.send_dropped
                if problems != send_problems:
                    send_problems = problems
                    send_fail_until = now + SEND_FAILURE_HOLD_S
                degraded = runner.process_degraded = overrun_rule.degraded(now)
                # the overrun bit for a status period after each overrun, and as long as it makes the mode DEGRADED
                runner.process_reasons = (REASON_OVERRUN if now < overrun_until or degraded else 0) | (
                    REASON_SEND_FAILURE if now < send_fail_until else 0
                )
                runner.status["overrun_count"] = self.overruns
                runner.status["cycle_time_us"] = period_worst_us
                is_status = runner.cycles % self.status_period == 0
                frames = runner.run(now)
                estimates = self.estimates = runner.estimates
                if is_status:
                    period_worst_us = 0.0
                bus = self.bus
                if bus is not None:
                    if self._inline:
                        for fid, data in frames:
                            _send_frame(self, bus, fid, data, 0.0, self.rate_log)
                    else:
                        sender.put(frames)
                self.cycles += 1
                if runner.process_degraded:
                    self.overrun_degraded_cycles += 1
                us = (perf() - t0) * 1e6
                if us > period_worst_us:
                    period_worst_us = us
                if us > self.worst_cycle_us:
                    self.worst_cycle_us = us
                if self.on_cycle is not None:
                    self.on_cycle(now, estimates)
                if int(estimates[E_VALID]) & (V_CORNERING | V_CAMBER):  # what a stop (never VALID) will save
                    np.copyto(self._kept_stiffness, estimates[E_C_ALPHA_FRONT : E_C_GAMMA_REAR + 1])
                    self._stiffness_kept = True

                # ---- housekeeping (cheap unless due)
                if not self.ready.is_set():
                    self.ready.set()
                    self.notifier.ready(self._status_text())
                    log.info("publishing on %s; %s", self._bus_name(), self.state_note)
                self.watchdog.cycle_done(on_time, now)
                if self._reload.is_set() and (self._reloader is None or not self._reloader.is_alive()):
                    self._start_reload()
                if self._reader is not None and self._reader.failed:
                    self.rate_log.error("bus_lost", f"CAN bus lost ({self._reader.failed}); reopening", now)
                    self._close_bus()
                if self.frames_out != frames_out_seen or self.bus is None:  # sending, or nothing to send on
                    frames_out_seen = self.frames_out
                    last_sent = now
                    problems_at_last_sent = send_problems
                elif send_problems > problems_at_last_sent and now - last_sent >= SEND_STUCK_REOPEN_S:
                    why = self.last_send_error or f"{self.send_dropped} frames dropped, the sender stuck"
                    self.rate_log.error(
                        "send_stuck", f"nothing sent for {now - last_sent:.1f} s ({why}); reopening the CAN bus", now
                    )
                    self.send_stuck_reopens += 1
                    self._close_bus()
                    last_sent = now
                    problems_at_last_sent = send_problems
                if self.bus is None:
                    self._reopen(now)
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
        sender = self._sender
        last = None
        if self.bus is not None:
            self.runner.status.update(overrun_count=self.overruns, cycle_time_us=0)
            last = self.runner.final_status()
        if sender is not None:
            if last is not None and not self._inline:
                sender.put([last])
            sender.stop(timeout=0.5)  # what is queued goes out first, the last EST_Status last
        if last is not None and self._inline and self.bus is not None:
            _send_frame(self, self.bus, *last, SEND_TIMEOUT_S, self.rate_log)
        if self._saver is not None:
            self._saver.join(timeout=5.0)
        self._save_state(self._stiffness_to_save(), time.monotonic(), final=True)
        self._close_bus(wait=True)
        opener, self._opener = self._opener, None
        if opener is not None:  # a reopen under way: its bus, if it comes, is closed, not left open
            opener.join(timeout=2.0)
            if opener.bus is not None:
                _shutdown_quietly(opener.bus)
        self._health_log(time.monotonic())
        log.info("stopped after %d cycles", self.cycles)

    # ------------------------------------------------------------------ reporting

    def _bus_name(self) -> str:
        b = self.settings.runtime.bus
        return f"{b.interface}:{b.channel}"

    def _status_text(self) -> str:
        e = self.estimates
        reasons = ",".join(reason_names(int(e[E_REASONS]) | self.runner.process_reasons)) or "-"
        bus = "open" if self.bus is not None else "LOST"
        gnss = "" if self.gnss is None else f" gnss={'open' if self.gnss.connected else 'LOST'}"
        return (
            f"mode={MODE_NAMES[int(e[E_MODE])]} reasons={reasons} cycles={self.cycles} overruns={self.overruns} "
            f"send_failures={self.send_failures} send_dropped={self.send_dropped} bus={bus}{gnss}"
        )

    def health(self) -> dict[str, Any]:
        return {
            "mode": MODE_NAMES[int(self.estimates[E_MODE])],
            "cycles": self.cycles,
            "overruns": self.overruns,
            "overrun_degraded_cycles": self.overrun_degraded_cycles,
            "frames_in": self.frames_in,
            "frames_out": self.frames_out,
            "send_failures": self.send_failures,
            "send_errors": self.send_errors,
            "send_dropped": self.send_dropped,
            "last_send_error": self.last_send_error,
            "bus_reopens": self.bus_reopens,
            "send_stuck_reopens": self.send_stuck_reopens,
            "reloads": self.reloads,
            "reload_failures": self.reload_failures,
            "watchdog_pings": self.watchdog.pings,
            "worst_cycle_us": round(self.worst_cycle_us, 1),
            "inputs": self.runner.tracker.summary(),
            "gnss": None if self.gnss is None else self.gnss.stats(),
        }

    def _health_log(self, now: float) -> None:
        self.rate_log.flush(now)
        if self._sender is not None:
            self._sender.rate_log.flush(now)
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
        inputs["send"] = {
            "out": self.frames_out,
            "failed": self.send_failures,
            "dropped": self.send_dropped,
            "bus_reopens": self.bus_reopens,
            "send_stuck_reopens": self.send_stuck_reopens,
        }
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
    """Settings of the config file with command-line overrides of ``runtime`` applied; a CAN interface python-can
    does not have is refused here (a SIGHUP with a typo in it closed the bus and ended the daemon, exit 2, never
    restarted by systemd)."""
    settings = _with_overrides(load_settings(config), overrides)
    interface = settings.runtime.bus.interface
    if interface not in can.VALID_INTERFACES:
        raise UserFacingError(
            f"{config}: runtime.bus.interface {interface!r} is not a python-can interface "
            f"({', '.join(sorted(can.VALID_INTERFACES))})"
        )
    return settings


def _with_overrides(settings: Settings, overrides: dict[str, Any] | None) -> Settings:
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
    """``ptw-rt run``: check the config (``--check-config``) or run the loop until SIGTERM/SIGINT/--duration.

    Exit codes: 0 stopped; 2 configuration error; 69 the bus cannot be opened at start-up (``ptw_rt.errors``).
    """
    overrides = _overrides_from(args)
    settings = load_daemon_settings(args.config, overrides)
    design = args.design_file or design_file_for(args.config)
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
    # systemd's watchdog kills a hung loop with SIGABRT: print every thread's stack first (to the journal)
    try:
        faulthandler.enable(file=sys.stderr, all_threads=True)
    except (AttributeError, ValueError, OSError) as exc:  # a stderr without a file descriptor (embedded use)
        log.debug("faulthandler not enabled: %s", exc)
    setup_logging(settings.runtime.log_level)
    # the design file named, or none: then each build (start, SIGHUP) reads the config's own if there is one by
    # then (`paths.design_file_for`): a rider's mass set and designed while it runs is taken by a reload
    daemon = Daemon(settings, args.config, args.design_file, overrides=overrides)
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
