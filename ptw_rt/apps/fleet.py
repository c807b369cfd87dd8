"""Many logs at once: where they come from (directory trees, list files), where they run (local processes or a
Dask cluster), and the fleet summary (one row per log) written at the end.

The work per log is ``ptw_rt.apps.replay.replay_job``: the same function in a local process pool and in a Dask
task, so a log replays to the same bytes wherever it runs. A log that fails is a row with its reason and never
stops the others.

Dask (the ``fleet`` extra, ``dask[distributed]``) is imported only when ``--dask`` is given:
``--dask tcp://scheduler:8786`` uses an existing cluster (its workers need ptw-rt installed and the logs and
output directory at the same paths, a shared file system), ``--dask local`` starts a ``LocalCluster`` of
``--jobs`` single-threaded worker processes on this machine.
"""

from __future__ import annotations

import csv
import itertools
import math
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

from ptw_rt.core.layout import MODE_NAMES
from ptw_rt.errors import UserFacingError
from ptw_rt.io.logformats import SNIFF_BYTES, sniff
from ptw_rt.parallel import completed_in_processes
from ptw_rt.untrusted import UntrustedFileError, decode_utf8, read_bounded, replacing, short_text

__all__ = ["FLEET_COLUMNS", "fleet_row", "read_list_file", "run_jobs", "write_fleet_summary"]

MAX_LIST_BYTES = 16 * 1024 * 1024  # a list file of ~100 000 paths
MAX_LIST_ENTRIES = 200_000
MAX_PATH_CHARS = 4096  # PATH_MAX on Linux: a longer entry names no file
DASK_CONNECT_TIMEOUT_S = 10.0  # dask's connect timeout; the handshake gets 5 s more
SENSOR_FAULT_REASONS = ("sensor_stale", "out_of_range", "decode_errors", "counter_jumps", "gyro_step")

FLEET_COLUMNS = (
    "log",
    "status",
    "error",
    "duration_s",
    "cycles",
    "segments",
    *(f"share_{name.lower()}" for name in MODE_NAMES),
    "sensor_fault_cycles",
    "overruns",
    "tyre_scale",
    "c_alpha_front",
    "c_gamma_front",
    "c_alpha_rear",
    "c_gamma_rear",
    "stiffness_valid",
    "wall_s",
)


class ListFileError(UserFacingError):
    pass


def read_list_file(path: Path) -> list[Path]:
    """The logs named by a list file: one path per line, blank lines and ``#`` comments skipped, a relative path
    relative to the list file's directory. Untrusted: a regular file of at most MAX_LIST_BYTES, UTF-8, at most
    MAX_LIST_ENTRIES paths, no NUL in a path."""
    try:
        raw = read_bounded(path, max_bytes=MAX_LIST_BYTES, what="list file", error=ListFileError)
        text = decode_utf8(raw, path, what="list file", error=ListFileError)
    except UntrustedFileError as exc:  # pragma: no cover - read_bounded raises the given error type
        raise ListFileError(str(exc)) from None
    framed, _ = sniff(raw[:SNIFF_BYTES])
    if framed:  # each of a log's lines was a missing log: 3100 error lines and 94 s for a 20 s ride
        raise ListFileError(f"{path}: a CAN log ({framed[0]}), not a list of logs: give it without --list")
    base = path.parent
    logs: list[Path] = []
    for number, line in enumerate(text.splitlines(), 1):
        entry = line.strip()
        if not entry or entry.startswith("#"):
            continue
        if "\0" in entry:
            raise ListFileError(f"{path}:{number}: a path with a NUL character")
        if len(entry) > MAX_PATH_CHARS:  # no file has such a name: echoed in every message, a 16 MB line took 546 MB
            raise ListFileError(f"{path}:{number}: a path of {len(entry)} characters (at most {MAX_PATH_CHARS})")
        logs.append(Path(entry) if Path(entry).is_absolute() else base / entry)
        if len(logs) > MAX_LIST_ENTRIES:
            raise ListFileError(f"{path}: more than {MAX_LIST_ENTRIES} logs")
    if not logs:
        raise ListFileError(f"{path}: list file names no log")
    return logs


def _dask_client(address: str, workers: int):
    """A dask.distributed Client on `address` ("local": a LocalCluster of `workers` processes)."""
    from dask.distributed import Client, LocalCluster  # the `fleet` extra; ModuleNotFoundError -> one line

    if address == "local":
        cluster = LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None, silence_logs=40
        )
        return Client(cluster), cluster
    # dask's own timeout covers the connection, not the handshake: a server that accepts and never answers held the
    # command past a minute, and one that answers with something else (HTTP) sent dask allocating exabytes
    outcome: dict[str, Any] = {}

    def connect() -> None:
        try:
            outcome["client"] = Client(address, timeout=f"{DASK_CONNECT_TIMEOUT_S:g}s")
        except BaseException as exc:  # noqa: BLE001 - reported below as one line, whatever dask raised
            outcome["error"] = exc

    thread = threading.Thread(target=connect, name="ptw-rt-dask-connect", daemon=True)
    thread.start()
    thread.join(DASK_CONNECT_TIMEOUT_S + 5.0)
    exc = outcome.get("error")
    if "client" in outcome:
        return outcome["client"], None
    if thread.is_alive():
        raise UserFacingError(
            f"--dask {address}: no Dask scheduler answered within {DASK_CONNECT_TIMEOUT_S + 5.0:g} s (a server that "
            "accepts and says nothing)"
        )
    if isinstance(exc, ValueError):  # an address dask cannot parse
        raise UserFacingError(f"--dask {address}: not a Dask scheduler address ({exc}); e.g. tcp://host:8786") from None
    if isinstance(exc, (OSError, TimeoutError)):
        raise UserFacingError(f"--dask {address}: cannot reach the Dask scheduler ({exc})") from None
    raise UserFacingError(
        f"--dask {address}: what answered is not a Dask scheduler ({type(exc).__name__}: {short_text(str(exc), 80)})"
    ) from None


def run_jobs(
    job: Callable[..., dict[str, Any]],
    jobs: Sequence[tuple],
    *,
    workers: int,
    dask: str | None,
    on_done: Callable[[int, dict[str, Any]], None],
    failure: Callable[[tuple, BaseException], dict[str, Any]],
) -> None:
    """Run ``job(*args)`` for every args tuple of ``jobs`` on `workers` local processes, or on the Dask cluster
    ``dask``; ``on_done(index, result)`` as each finishes. A job whose worker dies gives ``failure(args, exc)``."""
    for index, fut_result in _completed(job, jobs, workers=workers, dask=dask):
        try:
            result = fut_result()
        except Exception as exc:  # the worker itself died (killed, out of memory, lost): this log failed
            result = failure(jobs[index], exc)
        on_done(index, result)


# On a Dask cluster each task's round trip through the scheduler costs milliseconds: more in flight keeps its
# workers busy, and a finished batch's successors go in one message. A `--list` of 20 000 missing logs on 2 local
# workers: all at once 109 s, 561 MB at the peak; one by one, 8 per worker, 172 s; in batches of 64 per worker, 112 s,
# 337 MB (the command's process; 2026-11-29)
DASK_IN_FLIGHT_PER_WORKER = 64


def _completed(job, jobs, *, workers: int, dask: str | None) -> Iterator[tuple[int, Callable[[], Any]]]:
    """(index, result getter) of each job as it finishes, on the local pool or on the Dask cluster ``dask``."""
    if dask is None:
        return completed_in_processes(job, jobs, workers)
    return _completed_on_dask(job, jobs, workers, dask)


# A scheduler lost mid-run: the client cancels what it had given it (those logs fail) and tries to reconnect; what
# it is given meanwhile never runs, and the command waited for ever on it. So a batch goes out only while the client
# is connected, and if it has not reconnected within this long the logs not yet given fail with one reason.
DASK_LOST_AFTER_S = DASK_CONNECT_TIMEOUT_S + 5.0
DASK_POLL_S = 0.5


def _completed_on_dask(job, jobs, workers: int, dask: str) -> Iterator[tuple[int, Callable[[], Any]]]:
    from dask.distributed import as_completed as dask_completed

    client, cluster = _dask_client(dask, workers)
    try:
        # the same bound as the local pool's, per worker of the cluster (a remote one may have more than --jobs):
        # a list of 200 000 logs is submitted as the cluster works through it, not as 200 000 tasks at once
        limit = DASK_IN_FLIGHT_PER_WORKER * max(workers, sum(client.nthreads().values()))
        queued = iter(enumerate(jobs))
        running: dict[Any, int] = {}
        pending = dask_completed()
        lost = False

        def submit(count: int) -> None:
            nonlocal lost
            deadline = time.monotonic() + DASK_LOST_AFTER_S
            while not lost and client.status != "running":
                lost = time.monotonic() >= deadline
                time.sleep(DASK_POLL_S)
            chunk = [] if lost else list(itertools.islice(queued, count))
            if chunk:
                # one message for the batch; pure=False: two logs with the same arguments are still two tasks
                columns = zip(*(args for _, args in chunk), strict=True)  # job(*args) per log: one list per argument
                futures = client.map(job, *columns, pure=False)
                running.update(zip(futures, (i for i, _ in chunk), strict=True))
                pending.update(futures)

        submit(limit)
        for batch in pending.batches():
            submit(len(batch))  # before handing these back: the cluster keeps working while the caller writes
            for fut in batch:
                yield running.pop(fut), fut.result
        if lost:
            reason = UserFacingError(f"the Dask scheduler {dask} was lost during the run; not replayed")
            for i, _ in queued:
                yield i, _raiser(reason)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _raiser(exc: BaseException) -> Callable[[], Any]:
    def result() -> Any:
        raise exc

    return result


def fleet_row(r: dict[str, Any]) -> tuple[Any, ...]:
    """One log's row, in FLEET_COLUMNS order, from its replay summary (``replay_log``'s, or a failure's). A tuple,
    made as each log finishes: with its summary line, ~1 kB a log is what a fleet keeps, not the whole summary."""
    row: dict[str, Any] = dict.fromkeys(FLEET_COLUMNS, "")
    row["log"] = r.get("log", "")
    if "error" in r:
        row.update(status="failed", error=r["error"])
        return tuple(row.values())
    cycles = int(r.get("cycles", 0))
    modes = r.get("modes", {})
    final = r.get("final", {})
    row.update(
        status="ok",
        duration_s=r.get("log_duration_s", ""),
        cycles=cycles,
        segments=r.get("segments", ""),
        sensor_fault_cycles=r.get("sensor_fault_cycles", ""),
        overruns=r.get("overruns", 0),
        wall_s=r.get("wall_s", ""),
    )
    for name in MODE_NAMES:
        row[f"share_{name.lower()}"] = round(modes.get(name, 0) / cycles, 4) if cycles else ""
    for key in ("tyre_scale", "c_alpha_front", "c_gamma_front", "c_alpha_rear", "c_gamma_rear"):
        value = final.get(key)
        row[key] = "" if value is None or not math.isfinite(value) else round(value, 4)
    row["stiffness_valid"] = int(bool(final.get("stiffness_valid", False)))
    return tuple(row.values())


SUMMARY_NAMES = ("fleet.csv", "fleet.parquet")  # what `write_fleet_summary` writes in its directory


def write_fleet_summary(rows: Sequence[tuple[Any, ...]], directory: Path) -> list[Path]:
    """``fleet.csv`` (and ``fleet.parquet`` when pyarrow is installed) in `directory` from `fleet_row`'s rows; the
    paths written."""
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / "fleet.csv"
    with replacing(path, "w", newline="", encoding="utf-8") as fh:  # a FIFO or a planted symlink: refused, not hung
        writer = csv.writer(fh)
        writer.writerow(FLEET_COLUMNS)
        writer.writerows(rows)
    written = [path]
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ModuleNotFoundError:
        return written
    columns = {c: [None if row[k] == "" else row[k] for row in rows] for k, c in enumerate(FLEET_COLUMNS)}
    table = pa.table(
        {c: pa.array(v, type=pa.string() if c in ("log", "status", "error") else None) for c, v in columns.items()}
    )
    with replacing(directory / "fleet.parquet") as fh:
        pq.write_table(table, fh)
    written.append(directory / "fleet.parquet")
    return written
