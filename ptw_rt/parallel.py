"""How many worker processes a parallel command starts (the matrix, random rides, a fleet replay)."""

from __future__ import annotations

import os


def usable_cores() -> int:
    """The CPUs this process may run on: its affinity (systemd's ``CPUAffinity=``, a container's cpuset), not the
    machine's count, which would oversubscribe a pinned service."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # not Linux
        return max(1, os.cpu_count() or 1)


def worker_count(requested: int | None, jobs: int) -> int:
    """``--jobs`` if given, else every usable core; never more than there are jobs, never fewer than one."""
    return max(1, min(requested or usable_cores(), jobs or 1))
