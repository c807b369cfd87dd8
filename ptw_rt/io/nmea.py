"""NMEA 0183 GNSS receiver on a serial port, as a stand-in for the CAN ``GPS_Velocity`` message.

:class:`NmeaParser` turns RMC and VTG sentences (any talker: GP, GN, GL, GA, BD, ...) into the signals of
``GPS_Velocity`` with the same meaning: horizontal speed over ground [m/s], course over ground [deg clockwise
from true north, 0..360) and the fix type (0 none, 1 dead reckoning, 2 2D, 3 3D; speed is usable only with 2 or 3):

- RMC: status ``V`` -> 0; status ``A`` -> 2D. The NMEA 2.3+ mode indicator refines it (some receivers, u-blox
  among them, send status ``A`` together with a non-GNSS mode): ``E`` (dead reckoning) -> 1, ``N``/``M``/``S``
  (no fix, manual, simulator) -> 0.
- VTG: FAA mode indicator ``N`` -> 0, ``E`` -> 1, ``A``/``D`` (and RTK ``F``/``R``, precise ``P``) -> 2,
  ``M``/``S`` -> 0; a VTG without mode field (NMEA < 2.3) counts as 2D when it carries a speed.
- GSA (optional, when the receiver sends it): a recent "3D fix" upgrades 2 to 3. RMC/VTG alone cannot say 3D.

A sentence without a speed gives ``speed_mps = nan`` and fix 0; one without a course (receivers leave it empty
when standing still) gives ``course_deg = nan``. Every line is checksum-verified (a sentence without ``*hh`` is
a checksum error too); checksum errors, garbage lines and parsed sentences are counted, never raised.

:class:`SerialGnssReader` runs the parser in a background thread on a pyserial port and survives the receiver
being unplugged and replugged. Needs the optional ``pynmea2`` package: ``pip install 'ptw-rt[gnss]'``.
"""

from __future__ import annotations

import logging
import math
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from ptw_rt.errors import UserFacingError

try:
    import pynmea2
except ImportError:  # optional extra "gnss"
    pynmea2 = None

__all__ = [
    "FIX_2D",
    "FIX_3D",
    "FIX_DR",
    "FIX_NONE",
    "GnssVelocity",
    "NmeaParser",
    "SerialGnssReader",
]

log = logging.getLogger(__name__)

FIX_NONE, FIX_DR, FIX_2D, FIX_3D = 0, 1, 2, 3
KNOT_MPS = 1852.0 / 3600.0
MAX_LINE = 164  # NMEA allows 82 characters; leave room for long proprietary sentences
_RMC_PREFERRED_S = 2.0  # VTG is used only when no RMC came for this long
_GSA_VALID_FOR = 4  # velocity sentences: a GSA older than this no longer upgrades the fix (receiver stopped it)
_MODE_FIX = {"N": FIX_NONE, "M": FIX_NONE, "S": FIX_NONE, "E": FIX_DR}  # anything else (A, D, F, R, P): 2D
_INSTALL_HINT = "pip install 'ptw-rt[gnss]'"
_PRINTABLE = re.compile(r"[\x20-\x7e]+").fullmatch  # NMEA is printable ASCII: anything else is line noise


def _require_pynmea2() -> None:
    if pynmea2 is None:
        raise UserFacingError(
            f"reading a serial NMEA GNSS receiver needs the pynmea2 package, which is not installed: {_INSTALL_HINT} "
            "(or set runtime.gps.source: can)"
        )


@dataclass(frozen=True)
class GnssVelocity:
    """One velocity solution, same meaning as the CAN ``GPS_Velocity`` signals."""

    speed_mps: float
    course_deg: float
    fix_type: int
    sentence: str  # "RMC" or "VTG"


def _number(value: Any) -> float:
    """A field as float: nan when empty; ValueError for anything that is not a finite number."""
    if value is None or value == "":
        return math.nan
    number = float(value)  # pynmea2 hands back the raw text when its own conversion failed: ValueError here
    if not math.isfinite(number):
        raise ValueError(f"not a finite number: {value!r}")
    return number


def _mode_fix(mode: Any) -> int | None:
    mode = (mode or "").strip().upper()[:1]
    if not mode:
        return None
    return _MODE_FIX.get(mode, FIX_2D)


class NmeaParser:
    """Line-by-line NMEA 0183 parser with counters. Raises :class:`UserFacingError` when pynmea2 is missing."""

    def __init__(self) -> None:
        _require_pynmea2()
        self.parsed = 0  # sentences with a valid checksum that pynmea2 understood (any type)
        self.used = 0  # of those, RMC/VTG/GSA sentences that went into a solution
        self.checksum_errors = 0
        self.garbage = 0  # not an NMEA sentence, unknown type, malformed field, over-long line
        self._gsa_fix: int | None = None
        self._since_gsa = 0

    def counters(self) -> dict[str, int]:
        return {
            "parsed": self.parsed,
            "used": self.used,
            "checksum_errors": self.checksum_errors,
            "garbage": self.garbage,
        }

    def feed(self, line: str | bytes) -> GnssVelocity | None:
        """Parse one line; a :class:`GnssVelocity` for RMC/VTG, None otherwise (blank lines are not counted)."""
        if isinstance(line, bytes):
            line = line.decode("ascii", "replace")  # noise becomes U+FFFD, which no sentence matches
        line = line.strip()
        if not line:
            return None
        if not line.startswith("$") or len(line) > MAX_LINE or not _PRINTABLE(line):
            self.garbage += 1
            return None
        try:
            msg = pynmea2.parse(line, check=True)
        except pynmea2.ChecksumError:
            self.checksum_errors += 1
            return None
        except Exception:  # noqa: BLE001 - ParseError/SentenceTypeError and whatever else a bad line provokes
            self.garbage += 1
            return None
        self.parsed += 1
        kind = getattr(msg, "sentence_type", "")
        try:
            if kind == "RMC":
                result = self._rmc(msg)
            elif kind == "VTG":
                result = self._vtg(msg)
            elif kind == "GSA":
                self._gsa(msg)
                self.used += 1
                return None
            else:
                return None
        except (ValueError, TypeError, ArithmeticError):
            self.parsed -= 1
            self.garbage += 1
            return None
        self.used += 1
        return result

    def _rmc(self, msg: Any) -> GnssVelocity:
        speed = _number(msg.spd_over_grnd) * KNOT_MPS
        course = _number(msg.true_course)
        fix = FIX_2D if (msg.status or "").strip().upper() == "A" else FIX_NONE
        mode = _mode_fix(msg.mode_indicator)
        if mode is not None:
            fix = min(fix, mode)
        return self._solution(speed, course, fix, "RMC")

    def _vtg(self, msg: Any) -> GnssVelocity:
        speed = _number(msg.spd_over_grnd_kmph) / 3.6
        if math.isnan(speed):
            speed = _number(msg.spd_over_grnd_kts) * KNOT_MPS
        course = _number(msg.true_track)
        mode = _mode_fix(msg.faa_mode)
        fix = mode if mode is not None else FIX_2D
        return self._solution(speed, course, fix, "VTG")

    def _gsa(self, msg: Any) -> None:
        fix_type = (msg.mode_fix_type or "").strip()
        if fix_type not in ("1", "2", "3"):
            raise ValueError(f"GSA fix type {fix_type!r}")
        # a multi-constellation receiver sends one GSA per system per epoch: keep the best one
        best = int(fix_type) if self._since_gsa else max(int(fix_type), self._gsa_fix or 0)
        self._gsa_fix = best
        self._since_gsa = 0

    def _solution(self, speed: float, course: float, fix: int, kind: str) -> GnssVelocity:
        if speed < 0:
            raise ValueError(f"negative speed {speed}")
        if math.isnan(speed):
            fix = FIX_NONE
        self._since_gsa += 1
        if fix == FIX_2D and self._gsa_fix == FIX_3D and self._since_gsa <= _GSA_VALID_FOR:
            fix = FIX_3D
        if not math.isnan(course):
            course %= 360.0
            if course >= 360.0:  # -1e-300 % 360 rounds to 360.0: the same direction as 0, the range excludes 360
                course = 0.0
        return GnssVelocity(speed, course, fix, kind)


class SerialGnssReader:
    """Reads an NMEA receiver on ``port`` in a daemon thread; :meth:`latest` is the newest velocity solution.

    The port is opened as ``serial.Serial(port, baudrate, timeout=0.2)``. When it cannot be opened or fails while
    reading (receiver unplugged: SerialException/OSError), it is closed, the failure counted, and opening is
    retried every ``retry_s`` until it works again; nothing is raised out of the thread. Use a stable path such as
    ``/dev/serial/by-id/...`` so a replugged receiver comes back under the same name.

    Start it BEFORE :func:`ptw_rt.service.realtime.apply_realtime`: threads inherit the SCHED_FIFO policy of the
    thread that creates them, and this one should not compete with the loop.
    Raises :class:`UserFacingError` when pynmea2 (or pyserial) is not installed.
    """

    def __init__(
        self,
        port: str,
        baudrate: int = 9600,
        *,
        retry_s: float = 1.0,
        read_timeout_s: float = 0.2,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.parser = NmeaParser()  # raises UserFacingError without pynmea2
        try:
            import serial
        except ImportError:
            raise UserFacingError(f"reading a serial GNSS receiver needs pyserial: {_INSTALL_HINT}") from None
        self._serial = serial
        self.port = port
        self.baudrate = int(baudrate)
        self.retry_s = float(retry_s)
        self.read_timeout_s = float(read_timeout_s)
        self._clock = clock
        self._latest: tuple[float, float, float, int] | None = None
        self._last_rmc = -math.inf
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._connected = False
        self._opens = 0
        self._open_failures = 0
        self._disconnects = 0
        self._errors = 0
        self._bytes = 0
        self._overlong = 0
        self._last_error: str | None = None
        self._last_log = -math.inf

    # --- public API ------------------------------------------------------------------------------------------

    def start(self) -> SerialGnssReader:
        if self._thread is None or not self._thread.is_alive():
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name=f"gnss-{self.port}", daemon=True)
            self._thread.start()
        return self

    def stop(self, timeout: float = 2.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)

    close = stop

    def __enter__(self) -> SerialGnssReader:
        return self.start()

    def __exit__(self, *exc_info: object) -> None:
        self.stop()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    @property
    def connected(self) -> bool:
        """The port is open (read without the lock: a bool, for the 100 Hz loop)."""
        return self._connected

    @property
    def last_error(self) -> str | None:
        return self._last_error

    def latest(self) -> tuple[float, float, float, int] | None:
        """``(monotonic_time_received, speed_mps, course_deg, fix_type)`` of the newest RMC/VTG, or None yet.

        Kept across a disconnect: judge its age by the receive time, as for a CAN message."""
        return self._latest

    @property
    def bad_lines(self) -> int:
        """Checksum errors, garbage lines and over-long runs without a newline: what the daemon counts as GPS
        decode errors (the over-long ones were left out: megabytes of noise counted as none)."""
        return self.parser.checksum_errors + self.parser.garbage + self._overlong

    def stats(self) -> dict[str, Any]:
        with self._lock:
            return {
                "port": self.port,
                "connected": self._connected,
                "opens": self._opens,
                "open_failures": self._open_failures,
                "disconnects": self._disconnects,
                "errors": self._errors,
                "bytes": self._bytes,
                **self.parser.counters(),
                "garbage": self.parser.garbage + self._overlong,
                "last_error": self._last_error,
            }

    # --- thread ----------------------------------------------------------------------------------------------

    def _run(self) -> None:
        port = None
        buffer = b""
        while not self._stop.is_set():
            try:
                if port is None:
                    port = self._open()
                    buffer = b""
                    if port is None:
                        self._stop.wait(self.retry_s)
                        continue
                chunk = port.read(max(1, port.in_waiting))
                if not chunk:
                    continue
                buffer = self._consume(buffer + chunk)
            except (self._serial.SerialException, OSError) as exc:
                self._close(port)
                port = None
                self._note(exc, disconnect=True)
                self._stop.wait(self.retry_s)
            except Exception as exc:  # noqa: BLE001 - the reader must outlive any surprise; retry from scratch
                self._close(port)
                port = None
                self._note(exc, disconnect=False)
                self._stop.wait(self.retry_s)
        self._close(port)

    def _open(self) -> Any:
        try:
            port = self._serial.Serial(self.port, self.baudrate, timeout=self.read_timeout_s)
        except (self._serial.SerialException, OSError, ValueError) as exc:
            with self._lock:
                self._open_failures += 1
                self._last_error = f"open: {type(exc).__name__}: {exc}"
                first = self._open_failures == 1
            now = time.monotonic()
            if first or now - self._last_log >= 60.0:
                self._last_log = now
                log.warning(
                    "GNSS receiver %s cannot be opened (%s); retrying every %.1f s", self.port, exc, self.retry_s
                )
            return None
        self._last_rmc = -math.inf  # a replugged receiver may be another one, configured otherwise
        with self._lock:
            self._opens += 1
            self._connected = True
        log.info("GNSS receiver %s opened at %d baud", self.port, self.baudrate)
        return port

    def _consume(self, data: bytes) -> bytes:
        """Feed every complete line of ``data`` to the parser; return the incomplete rest.

        One solution per epoch: a receiver that sends RMC and VTG reports the same velocity twice, so a VTG is
        taken only while no RMC has come for ``_RMC_PREFERRED_S`` (a receiver configured for VTG alone).
        """
        *lines, rest = data.split(b"\n")
        now = self._clock()
        for line in lines:
            velocity = self.parser.feed(line)
            if velocity is None:
                continue
            if velocity.sentence == "RMC":
                self._last_rmc = now
            elif now - self._last_rmc < _RMC_PREFERRED_S:
                continue
            self._latest = (now, velocity.speed_mps, velocity.course_deg, velocity.fix_type)
        with self._lock:
            self._bytes += len(data) - len(rest)
        if len(rest) > MAX_LINE:  # no newline in sight: noise at the wrong baud rate, drop it
            with self._lock:
                self._overlong += 1
                self._bytes += len(rest)
            rest = b""
        return rest

    def _close(self, port: Any) -> None:
        with self._lock:
            self._connected = False
        if port is not None:
            try:
                port.close()
            except Exception:  # noqa: BLE001 - closing a vanished device may fail; it is gone either way
                pass

    def _note(self, exc: BaseException, *, disconnect: bool) -> None:
        with self._lock:
            if disconnect:
                self._disconnects += 1
            else:
                self._errors += 1
            self._last_error = f"{type(exc).__name__}: {exc}"
        if disconnect:
            log.warning("GNSS receiver %s lost (%s); reopening every %.1f s", self.port, exc, self.retry_s)
        else:
            log.exception("GNSS reader on %s failed unexpectedly; restarting it", self.port)
