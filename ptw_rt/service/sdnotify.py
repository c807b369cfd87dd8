"""systemd's sd_notify protocol without a dependency, and a watchdog gate for the fixed-step loop.

The protocol (sd_notify(3)): newline-separated ``KEY=VALUE`` assignments in ONE datagram sent to the
AF_UNIX SOCK_DGRAM socket named by ``$NOTIFY_SOCKET`` (a path, or ``@name`` for an abstract socket).
Outside systemd the variable is unset and every call here is a silent no-op, so the daemon runs the same
from a shell, under pytest and as ``Type=notify`` service.

Nothing here raises into the loop: a failed send (socket gone, systemd busy) is counted in
``SystemdNotifier.send_failures`` and logged at most once a minute.

:class:`WatchdogGate` decides WHEN to send ``WATCHDOG=1``: the loop calls ``gate.cycle_done(healthy, now)``
after every cycle with the monotonic time it already has. That costs two float comparisons; a datagram goes
out at most every ``WatchdogSec/2``, and only while healthy cycles keep completing. A hung loop sends
nothing (the pings come from the loop itself, not from a helper thread that would outlive it), and a loop
that keeps running but has produced no healthy cycle for ``max_unhealthy_s`` withholds the pings too, so
systemd's watchdog kills and restarts the daemon in both cases.
"""

from __future__ import annotations

import logging
import math
import os
import socket
import time
from collections.abc import Mapping

__all__ = ["SystemdNotifier", "WatchdogGate"]

log = logging.getLogger(__name__)

_LOG_EVERY_S = 60.0


class SystemdNotifier:
    """Sends sd_notify messages to ``$NOTIFY_SOCKET``; a no-op when it is unset.

    ``address``: the socket to notify (a path, or ``@name`` for an abstract socket); ``None`` reads
    ``NOTIFY_SOCKET`` from ``environ`` (default ``os.environ``); ``""`` disables notification.
    ``unset_environment``: remove ``NOTIFY_SOCKET``, ``WATCHDOG_USEC`` and ``WATCHDOG_PID`` from ``os.environ``
    after reading them, so child processes do not talk to systemd in the daemon's name (sd_notify's
    ``unset_environment``).
    """

    def __init__(
        self,
        address: str | None = None,
        *,
        environ: Mapping[str, str] | None = None,
        unset_environment: bool = False,
    ) -> None:
        env = os.environ if environ is None else environ
        if address is None:
            address = env.get("NOTIFY_SOCKET", "")
        self._watchdog_usec = env.get("WATCHDOG_USEC")
        self._watchdog_pid = env.get("WATCHDOG_PID")
        if unset_environment:
            for name in ("NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID"):
                os.environ.pop(name, None)
        self.address = address
        self.sent = 0
        self.send_failures = 0
        self.last_error: str | None = None
        self._last_log = -math.inf
        self._sock: socket.socket | None = None
        self._target: str | None = None
        if not address:
            return
        if address.startswith("@"):
            self._target = "\0" + address[1:]
        elif address.startswith("/"):
            self._target = address
        else:
            # vsock:CID:PORT (systemd >= 253, for VMs) and relative paths are not supported by this daemon
            log.warning("NOTIFY_SOCKET=%r is not an AF_UNIX path or @abstract name: not notifying systemd", address)
            return
        try:
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            # never block the loop: a full socket buffer (systemd busy) is a counted failure, not a stall
            self._sock.setblocking(False)
        except OSError as exc:
            self._failed(exc)
            self._sock = None

    @property
    def enabled(self) -> bool:
        """True when there is a systemd to notify."""
        return self._sock is not None

    def notify(self, *assignments: str) -> bool:
        """Send ``KEY=VALUE`` assignments as one datagram; True when systemd got it (False also when disabled)."""
        if self._sock is None:
            return False
        try:
            self._sock.sendto("\n".join(assignments).encode("utf-8", "replace"), self._target)
        except OSError as exc:
            self._failed(exc)
            return False
        self.sent += 1
        return True

    def ready(self, status: str | None = None) -> bool:
        """Start-up (or a reload) is complete: ``READY=1``; systemd arms the watchdog from here."""
        return self.notify("READY=1", *self._status(status))

    def reloading(self, status: str | None = None) -> bool:
        """A reload starts (on SIGHUP); send :meth:`ready` when done. Carries ``MONOTONIC_USEC`` as systemd >= 253
        requires for ``RELOADING=1`` (older versions ignore it)."""
        usec = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
        return self.notify("RELOADING=1", f"MONOTONIC_USEC={usec}", *self._status(status))

    def stopping(self, status: str | None = None) -> bool:
        """Shutdown has begun: ``STOPPING=1``."""
        return self.notify("STOPPING=1", *self._status(status))

    def status(self, text: str) -> bool:
        """Free-form one-line status shown by ``systemctl status``."""
        return self.notify(*self._status(text))

    def watchdog(self) -> bool:
        """One keep-alive ping, ``WATCHDOG=1``. The loop should go through :class:`WatchdogGate` instead."""
        return self.notify("WATCHDOG=1")

    def extend_timeout(self, seconds: float) -> bool:
        """Ask for more time for the current start/stop/reload step (``EXTEND_TIMEOUT_USEC``), e.g. while numba
        compiles the hot path on a cold cache."""
        return self.notify(f"EXTEND_TIMEOUT_USEC={max(0, int(seconds * 1e6))}")

    def watchdog_interval_s(self) -> float | None:
        """``WatchdogSec=`` of the service in seconds, or None when no watchdog is armed for THIS process.

        From ``$WATCHDOG_USEC``; ignored when ``$WATCHDOG_PID`` is set and is not our pid (the variables were
        inherited from a parent), or when the values are malformed.
        """
        if self._watchdog_pid:
            try:
                if int(self._watchdog_pid) != os.getpid():
                    return None
            except ValueError:
                return None
        try:
            usec = int(self._watchdog_usec or "")
        except ValueError:
            return None
        return usec / 1e6 if usec > 0 else None

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def __enter__(self) -> SystemdNotifier:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    @staticmethod
    def _status(text: str | None) -> tuple[str, ...]:
        if text is None:
            return ()
        return ("STATUS=" + " ".join(str(text).splitlines()),)

    def _failed(self, exc: OSError) -> None:
        self.send_failures += 1
        self.last_error = f"{type(exc).__name__}: {exc}"
        now = time.monotonic()
        if now - self._last_log >= _LOG_EVERY_S:
            self._last_log = now
            log.warning(
                "sd_notify to %s failed (%s); %d failure(s) so far", self.address, self.last_error, self.send_failures
            )


class WatchdogGate:
    """Sends ``WATCHDOG=1`` from the loop, at most every ``interval_s / 2``, only while it stays healthy.

    ``interval_s``: systemd's watchdog timeout; ``None`` takes :meth:`SystemdNotifier.watchdog_interval_s`
    (no watchdog armed -> the gate never sends). ``max_unhealthy_s``: how long the loop may keep completing
    only unhealthy cycles before the pings stop (default ``interval_s / 2``: systemd then restarts the daemon
    within about 1.5 watchdog intervals of the last healthy cycle). ``stall_after_s``: a gap between two
    ``cycle_done`` calls longer than this is counted in ``stalls`` (diagnostics; default ``interval_s / 4``).

    "Healthy" is for the daemon to define; ``ptw-rt run``'s: the cycle completed on time (docs/daemon.md), whatever
    the bus does. A missing sensor is a DEGRADED mode on the bus and a failing send a counted fault, not reasons to
    restart; a loop that completes no cycle on time for ``max_unhealthy_s`` (hung in a cycle, or late at every
    deadline) is. A loop merely slower than its period (15 ms cycles) resynchronises and meets every other
    deadline: it is published DEGRADED by the overrun rule and keeps its pings, since a restart would not make the
    machine faster (docs/daemon.md).
    """

    def __init__(
        self,
        notifier: SystemdNotifier,
        interval_s: float | None = None,
        *,
        max_unhealthy_s: float | None = None,
        stall_after_s: float | None = None,
    ) -> None:
        if interval_s is None:
            interval_s = notifier.watchdog_interval_s()
        self.notifier = notifier
        self.interval_s = interval_s
        active = interval_s is not None and interval_s > 0 and notifier.enabled
        self.period_s = interval_s / 2.0 if active else math.inf
        self.max_unhealthy_s = max_unhealthy_s if max_unhealthy_s is not None else self.period_s
        self.stall_after_s = stall_after_s if stall_after_s is not None else self.period_s / 2.0
        self._next_due = -math.inf if active else math.inf
        self._last_healthy = -math.inf
        self._last_cycle = math.nan
        self.pings = 0
        self.withheld = 0
        self.stalls = 0
        self.last_ping_at: float | None = None

    @property
    def active(self) -> bool:
        return self._next_due != math.inf

    def cycle_done(self, healthy: bool, now: float) -> bool:
        """Call once per loop cycle with the cycle's monotonic time [s]. True when a ping was sent."""
        if now - self._last_cycle > self.stall_after_s:
            self.stalls += 1
        self._last_cycle = now
        if healthy:
            self._last_healthy = now
        if now < self._next_due:
            return False
        # a ping is due: send it only if a healthy cycle completed recently
        if now - self._last_healthy > self.max_unhealthy_s:
            self.withheld += 1
            self._next_due = now + self.period_s / 8.0  # re-check soon, not every cycle
            return False
        self._next_due = now + self.period_s
        self.last_ping_at = now
        self.pings += 1
        return self.notifier.watchdog()
