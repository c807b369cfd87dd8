"""Optional real-time settings of the daemon: SCHED_FIFO, CPU affinity, locked memory. Never fatal.

Under systemd, ``ptw-rt.service`` already sets SCHED_FIFO (``CPUSchedulingPolicy=``) and the limits that let the
daemon do the rest itself (``LimitRTPRIO=``, ``LimitMEMLOCK=infinity``); run from a shell on a laptop the same
calls are refused. Either way the daemon keeps running: :func:`apply_realtime` returns (and logs) one warning
per setting it could not apply, and the caller puts them in its status.

Linux semantics worth knowing:
- ``sched_setscheduler``/``sched_setaffinity`` with pid 0 act on the CALLING THREAD, and threads created
  afterwards inherit them. Call :func:`apply_realtime` from the loop's thread; start helper threads (serial
  GNSS reader) before it if they should stay at normal priority.
- ``mlockall(MCL_FUTURE)`` under a finite ``RLIMIT_MEMLOCK`` makes every later allocation beyond the limit fail
  (numpy MemoryError in the middle of a ride), so memory is locked only when the limit is infinite or the
  process has CAP_IPC_LOCK.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import logging
import os
import platform
import resource
from typing import Any

__all__ = ["apply_realtime", "normal_scheduling", "realtime_state", "restore_scheduling", "thread_scheduling"]

log = logging.getLogger(__name__)

_FIFO_MAX = 99
_CAP_IPC_LOCK = 14


def apply_realtime(priority: int | None, cpus: list[int] | None, lock_memory: bool) -> list[str]:
    """Apply SCHED_FIFO ``priority``, CPU affinity ``cpus`` and ``mlockall`` to the calling thread/process.

    ``None``/``False`` skips a setting. Returns the warnings (also logged at WARNING), one per setting that
    could not be applied; an empty list means everything asked for is in force. Never raises.
    """
    warnings: list[str] = []
    if priority is not None:
        _collect(warnings, _guarded(f"SCHED_FIFO priority {priority!r}", lambda: _set_fifo(int(priority))))
    if cpus is not None:
        _collect(warnings, _guarded(f"CPU affinity {cpus!r}", lambda: _set_affinity([int(c) for c in cpus])))
    if lock_memory:
        _collect(warnings, _guarded("mlockall", _lock_memory))
    return warnings


def thread_scheduling() -> tuple[int, int] | None:
    """(policy, priority) of the calling thread, to hand to ``restore_scheduling``; None where unsupported."""
    try:
        return os.sched_getscheduler(0), os.sched_getparam(0).sched_priority
    except (AttributeError, OSError):
        return None


def restore_scheduling(saved: tuple[int, int] | None) -> None:
    """Put the calling thread back to ``saved`` (from ``thread_scheduling``). Never raises.

    A thread that ran the loop at SCHED_FIFO and goes on doing other work (the demo, the bench, tests)
    must not keep the priority: processes it starts would inherit it and could starve the machine.
    """
    if saved is None:
        return
    try:
        os.sched_setscheduler(0, saved[0], os.sched_param(saved[1]))
    except (AttributeError, OSError) as exc:
        log.warning("could not restore the thread's scheduling policy: %s", exc)


def normal_scheduling() -> None:
    """Put the calling thread at normal scheduling (SCHED_OTHER). Never raises.

    For a helper thread created by the real-time loop (it inherits SCHED_FIFO) that does long, unhurried work,
    such as preparing a configuration reload: at the loop's priority it would compete with the loop and starve
    every normal thread of its CPU. Lowering one's own priority needs no privilege.
    """
    try:
        if os.sched_getscheduler(0) != os.SCHED_OTHER:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (AttributeError, OSError) as exc:
        log.debug("could not set normal scheduling: %s", exc)


def realtime_state() -> dict:
    """What is in force for the calling thread: policy, priority, CPUs, locked memory (for status and logs)."""
    state: dict[str, Any] = {}
    try:
        policy = os.sched_getscheduler(0)
        state["policy"] = {os.SCHED_FIFO: "fifo", os.SCHED_RR: "rr", os.SCHED_OTHER: "other"}.get(policy, str(policy))
        state["priority"] = os.sched_getparam(0).sched_priority
    except (AttributeError, OSError):
        state["policy"] = "unknown"
    try:
        state["cpus"] = sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        state["cpus"] = None
    state["locked_kib"] = _status_kib("VmLck")
    return state


def _guarded(what: str, action: Any) -> str | None:
    try:
        return action()
    except Exception as exc:  # noqa: BLE001 - a real-time setting must never stop the daemon
        return f"{what}: not applied ({type(exc).__name__}: {exc})"


def _collect(warnings: list[str], message: str | None) -> None:
    if message:
        log.warning("%s", message)
        warnings.append(message)


def _set_fifo(priority: int) -> str | None:
    what = f"SCHED_FIFO priority {priority}"
    if not hasattr(os, "sched_setscheduler"):
        return f"{what}: not supported on this platform; running with normal scheduling"
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except PermissionError:
        return (
            f"{what}: not permitted (EPERM); running with normal scheduling. Allow it with "
            f"LimitRTPRIO={priority} or CPUSchedulingPolicy=fifo in the service (or CAP_SYS_NICE); under a kernel "
            "with CONFIG_RT_GROUP_SCHED the cgroup needs an RT budget too"
        )
    except OSError as exc:
        return f"{what}: refused ({_err(exc)}); running with normal scheduling"
    log.info("%s applied", what)
    return None


def _set_affinity(cpus: list[int]) -> str | None:
    what = f"CPU affinity {cpus}"
    if not hasattr(os, "sched_setaffinity"):
        return f"{what}: not supported on this platform; affinity unchanged"
    try:
        os.sched_setaffinity(0, cpus)
    except PermissionError:
        return f"{what}: not permitted (EPERM); affinity unchanged"
    except OSError as exc:
        hint = ""
        if exc.errno == errno.EINVAL:
            try:
                hint = f" (online CPUs: {os.cpu_count()}, current affinity {sorted(os.sched_getaffinity(0))})"
            except OSError:
                pass
        return f"{what}: refused ({_err(exc)}){hint}; affinity unchanged"
    except (OverflowError, ValueError) as exc:
        return f"{what}: refused ({exc}); affinity unchanged"
    log.info("%s applied", what)
    return None


def _lock_memory() -> str | None:
    what = "mlockall(MCL_CURRENT|MCL_FUTURE)"
    soft, _hard = resource.getrlimit(resource.RLIMIT_MEMLOCK)
    if soft != resource.RLIM_INFINITY and not _has_capability(_CAP_IPC_LOCK):
        return (
            f"{what}: skipped, RLIMIT_MEMLOCK is {soft} bytes (locking all future allocations under a finite limit "
            "would make them fail later); set LimitMEMLOCK=infinity in the service; memory stays pageable"
        )
    libc = _libc()
    if libc is None:
        return f"{what}: not supported (no C library found); memory stays pageable"
    current, future = _mcl_flags()
    if libc.mlockall(current | future) != 0:
        code = ctypes.get_errno()
        reason = "not permitted (EPERM)" if code == errno.EPERM else f"refused ({errno.errorcode.get(code, code)})"
        return f"{what}: {reason}; memory stays pageable"
    log.info("%s applied (%s KiB locked)", what, _status_kib("VmLck"))
    return None


def _libc() -> Any:
    try:
        lib = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
        lib.mlockall.argtypes = [ctypes.c_int]
        lib.mlockall.restype = ctypes.c_int
        return lib
    except (OSError, AttributeError):
        return None


def _mcl_flags() -> tuple[int, int]:
    """MCL_CURRENT, MCL_FUTURE of this architecture (<asm/mman.h>; Python's os module does not export them)."""
    machine = platform.machine().lower()
    if machine.startswith(("ppc", "powerpc", "sparc", "alpha")):
        return 0x2000, 0x4000
    return 1, 2


def _has_capability(bit: int) -> bool:
    try:
        with open("/proc/self/status", "rb") as fh:  # bytes: no codec lookup, nothing to fail but the read
            for line in fh:
                if line.startswith(b"CapEff:"):
                    return bool(int(line.split()[1], 16) >> bit & 1)
    except (OSError, ValueError, IndexError):
        pass
    return False


def _status_kib(field: str) -> int | None:
    try:
        with open("/proc/self/status", "rb") as fh:
            for line in fh:
                if line.startswith(field.encode() + b":"):
                    return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        pass
    return None


def _err(exc: OSError) -> str:
    name = errno.errorcode.get(exc.errno or 0, str(exc.errno))
    return f"{name}: {exc.strerror or exc}"
