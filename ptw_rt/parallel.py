"""Worker processes for the parallel commands (the matrix, random rides, a fleet replay): how many, and a map."""

from __future__ import annotations

import itertools
import os
from collections.abc import Callable, Generator, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any

from ptw_rt.errors import UserFacingError
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


# Jobs in flight on a pool per worker: enough to keep every worker busy, few enough that a list of 200 000 logs
# does not hold 200 000 futures and their arguments at once (all submitted up front: 915 MB at the peak)
IN_FLIGHT_PER_WORKER = 8


def completed_in_processes(
    fn: Callable, jobs: Iterable[tuple], workers: int
) -> Iterator[tuple[int, Callable[[], Any]]]:
    """``fn(*args)`` for each args tuple of `jobs` on `workers` processes: (index, result getter) as each finishes.
    At most IN_FLIGHT_PER_WORKER per worker are submitted at a time. A worker that dies (killed, out of memory, a job
    that crashes the interpreter) breaks its pool: the getters of the jobs it had in flight raise
    ``BrokenProcessPool`` and a fresh pool takes the rest."""
    queued: Iterator[tuple[int, tuple]] = iter(enumerate(jobs))
    while True:
        unsent = yield from _completed_in_one_pool(fn, queued, workers)
        if unsent is None:
            return
        queued = itertools.chain([unsent], queued)


def _completed_in_one_pool(fn, queued, workers: int) -> Generator[tuple[int, Callable[[], Any]], None, Any]:
    """Run `queued` on one pool until it is done (None) or breaks: then the job it could not take."""
    unsent = None
    pool = ProcessPoolExecutor(max_workers=workers)
    try:
        running: dict[Any, int] = {}
        while True:
            if unsent is None:
                for i, args in queued:
                    try:
                        running[pool.submit(fn, *args)] = i
                    except BrokenProcessPool:
                        unsent = (i, args)
                        break
                    if len(running) >= IN_FLIGHT_PER_WORKER * workers:
                        break
            if not running:
                return unsent
            done, _ = wait(running, return_when=FIRST_COMPLETED)
            for fut in done:
                yield running.pop(fut), fut.result
    finally:
        # a caller that stops early (an error, Ctrl-C) does not wait for the jobs it will never take
        pool.shutdown(wait=True, cancel_futures=True)


def map_in_processes(fn: Callable, jobs: list, workers: int | None, progress: Progress | None, name: Callable) -> list:
    """fn over jobs on `worker_count(workers, ...)` processes (1: in this process), results in job order;
    `progress` steps once per finished job, labelled `name(job)`. A worker that dies is one line (UserFacingError):
    every job's result is needed."""
    workers = worker_count(workers, len(jobs))
    results: list = [None] * len(jobs)
    if workers == 1:
        for i, job in enumerate(jobs):
            results[i] = fn(job)
            if progress:
                progress.step(name(job))
        return results
    for i, result in completed_in_processes(fn, ((job,) for job in jobs), workers):
        try:
            results[i] = result()
        except BrokenProcessPool as exc:
            raise UserFacingError(
                f"a worker process died with {name(jobs[i])} in flight (killed, or out of memory: fewer --jobs use "
                f"less; {exc})"
            ) from None
        if progress:
            progress.step(name(jobs[i]))
    return results
