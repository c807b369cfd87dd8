"""Worker processes for the parallel commands (the matrix, random rides, a fleet replay): how many, and a map."""

from __future__ import annotations

import os
from collections.abc import Callable

from ptw_rt.progress import Progress


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


def map_in_processes(fn: Callable, jobs: list, workers: int | None, progress: Progress | None, name: Callable) -> list:
    """fn over jobs on `worker_count(workers, ...)` processes (1: in this process), results in job order;
    `progress` steps once per finished job, labelled `name(job)`."""
    workers = worker_count(workers, len(jobs))
    results: list = [None] * len(jobs)
    if workers == 1:
        for i, job in enumerate(jobs):
            results[i] = fn(job)
            if progress:
                progress.step(name(job))
        return results
    from concurrent.futures import ProcessPoolExecutor, as_completed

    with ProcessPoolExecutor(max_workers=workers) as pool:
        futures = {pool.submit(fn, job): i for i, job in enumerate(jobs)}
        for fut in as_completed(futures):
            i = futures[fut]
            results[i] = fut.result()
            if progress:
                progress.step(name(jobs[i]))
    return results
