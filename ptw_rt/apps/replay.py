"""``ptw-rt replay``: CAN logs through the daemon's cycle, clocked by the log's time stamps.

    log frames -> drive_log(CycleRunner: decode, track, step, encode) -> output log (+ optional CSV)

Input and output logs are any format of ``ptw_rt.io.logformats`` (candump ``-L``, ASC, BLF, TRC, CSV, MF4),
the input's found from its extension and content, the output's from its extension (none: candump).
The output log holds the estimator's frames (EST_*) stamped with LOG time (the cycle's time), on the channel of
a candump input log. Nothing depends on the wall clock or the machine, so the same input gives a byte-identical
output: EST_Status.OverrunCount and CycleTimeUs are 0 in a replay (there is no deadline to miss).
Malformed records of the input are skipped and counted by the reader, and summarised in one warning line
with at most three examples, escaped.
"""

from __future__ import annotations

import itertools
import json
import logging
import os
import sys
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import IO, Any

import numpy as np

from ptw_rt._numba_cache import announce_compile
from ptw_rt.core.layout import E_MODE, ESTIMATE_NAMES, MODE_NAMES
from ptw_rt.edge.cycle import CycleRunner, build_runner, drive_log
from ptw_rt.errors import UserFacingError
from ptw_rt.io.logformats import (
    EXTENSIONS,
    EmptyLogError,
    LogFormatError,
    detect_format,
    open_log,
    open_writer,
    writer_format,
)
from ptw_rt.paths import DEFAULT_CONFIG
from ptw_rt.progress import Progress

__all__ = ["replay_log", "run_replay"]

log = logging.getLogger(__name__)

DEFAULT_CHANNEL = "vcan0"


def _frames(
    first, frames: Iterator, skipped: list[int], progress: Callable[[], None] | None = None
) -> Iterator[tuple[float, int, bytes]]:
    """(timestamp, id, data) of the 11-bit data frames; 29-bit frames are counted in skipped[0] (remote, error
    and CAN FD frames in the reader's stats). ``progress()`` is called every 4096 frames."""
    n = 0
    for timestamp, frame_id, data, extended in itertools.chain((first,), frames):
        if extended:
            skipped[0] += 1
            continue
        yield timestamp, frame_id, data
        n += 1
        if progress is not None and not n & 4095:
            progress()


# one printf-style template per row: "%.6f" / "%.10g" format floats exactly as f"{v:.6f}" / f"{v:.10g}" do
# (inf, nan and -0 included), at a fraction of the cost of one f-string per value
_CSV_TEMPLATE = "%.6f," + ",".join(["%.10g"] * len(ESTIMATE_NAMES)) + "\n"


def _csv_row(now: float, estimates: np.ndarray) -> str:
    values = estimates.tolist()
    if len(values) != len(ESTIMATE_NAMES):  # not an Estimates record: format whatever it holds
        return f"{now:.6f}," + ",".join(f"{v:.10g}" for v in values) + "\n"
    return _CSV_TEMPLATE % (now, *values)


def replay_log(
    in_path: str | Path,
    out_log: str | Path,
    csv_path: str | Path | None = None,
    config: str | Path = DEFAULT_CONFIG,
    design_file: str | Path | None = None,
    *,
    runner: CycleRunner | None = None,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Replay one CAN log (any format of ``ptw_rt.io.logformats``); write the estimator's frames to ``out_log``
    (format from its extension) and the estimates to ``csv_path``.

    Returns a summary: cycles, frames in/out, malformed records, log and wall duration, x real time, modes seen,
    input health counters. Raises UserFacingError if the input cannot be opened, is not a CAN log or holds no
    frame (``EmptyLogError``); ``progress`` (if given) is updated with the share of the log read.
    """
    in_path, out_log = Path(in_path), Path(out_log)
    wall0 = time.perf_counter()
    runner = runner or build_runner(config, design_file)
    try:
        frames, stats = open_log(in_path)
        first = next(frames, None)
    except OSError as exc:  # FileNotFoundError, permissions, a directory ...
        raise UserFacingError(f"cannot read CAN log {in_path}: {exc}") from exc
    if first is None:
        frames.close()
        raise EmptyLogError(stats.no_frames_message())
    channel = (stats.channel if stats.format == "candump" else None) or DEFAULT_CHANNEL
    skipped = [0]
    mode_counts = [0] * len(MODE_NAMES)
    frames_out = 0
    t_first = first[0]
    t_last = t_first
    csv: IO[str] | None = None
    out_log.parent.mkdir(parents=True, exist_ok=True)
    try:
        with open_writer(out_log, channel=channel) as writer:
            if csv_path is not None:
                Path(csv_path).parent.mkdir(parents=True, exist_ok=True)
                csv = open(csv_path, "w", encoding="ascii", newline="\n")
                csv.write("time," + ",".join(ESTIMATE_NAMES) + "\n")
            write = writer.write

            def on_frames(now: float, frames: list[tuple[int, bytes]]) -> None:
                nonlocal frames_out
                for fid, data in frames:
                    write(now, fid, data)
                frames_out += len(frames)

            def on_cycle(now: float, estimates: np.ndarray) -> None:
                nonlocal t_last
                m = int(estimates[E_MODE])
                if 0 <= m < len(mode_counts):
                    mode_counts[m] += 1
                if csv is not None:
                    csv.write(_csv_row(now, estimates))
                t_last = now

            tick = None if progress is None else (lambda: progress.update(stats.fraction))
            cycles = drive_log(_frames(first, frames, skipped, tick), runner, on_cycle, on_frames=on_frames)
    finally:
        if csv is not None:
            csv.close()
        frames.close()
    if stats.malformed:
        log.warning("%s", stats.problems_line())
    wall = time.perf_counter() - wall0
    duration = max(0.0, t_last - t_first)
    return {
        "log": str(in_path),
        "out": str(out_log),
        "csv": None if csv_path is None else str(csv_path),
        "cycles": cycles,
        "format": stats.format,
        "frames_in": stats.frames,
        "frames_out": frames_out,
        "malformed_lines": stats.malformed,
        "malformed_line_numbers": stats.malformed_lines[:20],
        "skipped_frames": skipped[0] + sum(stats.skipped.values()),
        "log_duration_s": round(duration, 3),
        "wall_s": round(wall, 3),
        "x_real_time": round(duration / wall, 1) if wall > 0 else None,
        "modes": {MODE_NAMES[i]: n for i, n in enumerate(mode_counts) if n},
        "inputs": runner.tracker.summary(),
    }


# ---------------------------------------------------------------------- CLI


def _collect_logs(paths: list[Path]) -> tuple[list[Path], bool]:
    """Input logs (directories expanded to their CAN logs, sorted) and whether any directory was given.

    In a directory every file with a log extension (``ptw_rt.io.logformats.EXTENSIONS``) is a log (one that is
    not fails on its own), except ``.csv`` files, which are taken only when they are python-can CAN CSV: a
    ride's truth and estimates CSV files sit beside its log."""
    files: list[Path] = []
    any_dir = False
    for p in paths:
        if p.is_dir():
            any_dir = True
            found = sorted(q for q in p.iterdir() if q.suffix.lower() in EXTENSIONS and q.is_file())
            found = [q for q in found if q.suffix.lower() != ".csv" or _is_can_csv(q)]
            if not found:
                raise UserFacingError(f"no CAN logs in directory {p} ({', '.join(EXTENSIONS)})")
            files.extend(found)
        elif p.is_file():
            files.append(p)
        else:
            raise UserFacingError(f"CAN log not found: {p}")
    return files, any_dir


def _is_can_csv(path: Path) -> bool:
    try:
        return detect_format(path)[0] == "csv"
    except (LogFormatError, UserFacingError, OSError):
        return False


def _plan(args) -> list[tuple[Path, Path, Path | None]]:
    files, any_dir = _collect_logs(list(args.logs))
    if len(files) == 1 and not any_dir:
        if args.out.is_dir():
            raise UserFacingError(f"--out {args.out} is a directory; with one input log --out names the output file")
        detect_format(files[0])  # not a CAN log, empty: one line now, before the estimator is compiled
        jobs = [(files[0], args.out, args.csv)]
    else:
        if args.out.exists() and not args.out.is_dir():
            raise UserFacingError(f"--out {args.out} must be a directory when replaying several logs")
        if args.csv is not None and args.csv.exists() and not args.csv.is_dir():
            raise UserFacingError(f"--csv {args.csv} must be a directory when replaying several logs")
        names = [f.name for f in files]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise UserFacingError(f"several input logs are named {', '.join(dup)}: their outputs would collide")
        stems = [f.stem for f in files]
        dup = sorted({n for n in stems if stems.count(n) > 1})
        if dup and args.csv is not None:
            raise UserFacingError(f"several input logs are named {', '.join(dup)}.*: their --csv outputs would collide")
        jobs = [(f, args.out / f.name, None if args.csv is None else args.csv / (f.stem + ".csv")) for f in files]
    for src, out, csv in jobs:
        writer_format(out)  # an unknown extension: one line now
        for target in (out, csv):
            if target is not None and target.resolve() == src.resolve():
                raise UserFacingError(f"output {target} would overwrite its input log")
    return jobs


def _short(summary: dict[str, Any]) -> dict[str, Any]:
    keys = ("log", "out", "cycles", "frames_in", "frames_out", "malformed_lines", "x_real_time", "modes")
    return {k: summary[k] for k in keys}


def _job(in_path: Path, out: Path, csv: Path | None, config: Path, design_file: Path | None) -> dict[str, Any]:
    return replay_log(in_path, out, csv, config, design_file)


def run_replay(args, *, out: IO[str] | None = None, err: IO[str] | None = None) -> int:
    """``ptw-rt replay``: one log -> ``--out`` is the output file; several logs or a directory -> ``--out`` is a
    directory (same file names), processed in parallel. One JSON summary line per log on stdout."""
    out = out or sys.stdout
    err = err or sys.stderr
    jobs = _plan(args)
    config = Path(args.config)
    design_file = args.design_file
    # check config, design file and DBC once, here, and compile/load the jitted step before forking workers
    runner = build_runner(config, design_file)
    announce_compile(err)
    runner.cycle(0.0)
    progress = not getattr(args, "no_progress", False)
    failures = 0
    results: dict[int, dict[str, Any]] = {}
    if len(jobs) == 1:
        src, dst, csv = jobs[0]
        bar = Progress(1.0, label=f"replay {src.name}", stream=err, delay=0.5) if progress else None
        results[0] = replay_log(src, dst, csv, config, design_file, progress=bar)
        if bar is not None:
            bar.finish()
    else:
        workers = max(1, min(args.jobs or os.cpu_count() or 1, len(jobs)))
        bar = Progress(len(jobs), label="replay", stream=err) if progress else None
        with ProcessPoolExecutor(max_workers=workers) as pool:
            futures = {
                pool.submit(_job, src, dst, csv, config, design_file): i for i, (src, dst, csv) in enumerate(jobs)
            }
            for fut in as_completed(futures):
                i = futures[fut]
                try:
                    results[i] = fut.result()
                except UserFacingError as exc:
                    failures += 1
                    message = str(exc)
                    where = str(jobs[i][0])
                    line = message if message.startswith(where) else f"{where}: {message}"
                    err.write(("\n" if bar is not None and bar.tty else "") + f"error: {line}\n")
                if bar is not None:
                    bar.step(jobs[i][0].name)
    for i in sorted(results):  # job order, not completion order: stable output
        out.write(json.dumps(_short(results[i])) + "\n")
    out.flush()
    return 2 if failures else 0
