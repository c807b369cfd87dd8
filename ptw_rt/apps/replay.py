"""``ptw-rt replay``: candump logs through the daemon's cycle, clocked by the log's time stamps.

    log frames -> drive_log(CycleRunner: decode, track, step, encode) -> candump -L output log (+ optional CSV)

The output log holds the estimator's frames (EST_*) stamped with LOG time (the cycle's time), on the channel of
the input log. Nothing depends on the wall clock or the machine, so the same input gives a byte-identical
output: EST_Status.OverrunCount and CycleTimeUs are 0 in a replay (there is no deadline to miss).
Malformed lines of the input are skipped, counted and logged (file and line) by ``ptw_rt.io.candump``.
"""

from __future__ import annotations

import itertools
import json
import logging
import math
import os
import stat
import sys
import time
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import IO, Any

import numpy as np

from ptw_rt.core.layout import E_MODE, ESTIMATE_NAMES, MODE_NAMES
from ptw_rt.edge.cycle import DEFAULT_MAX_GAP_S, CycleRunner, DriveStats, SegmentBreak, build_runner, drive_log
from ptw_rt.errors import EXIT_OK, EXIT_OUTPUT, EXIT_PARTIAL, UserFacingError
from ptw_rt.io.candump import CandumpWriter, read_log
from ptw_rt.paths import DEFAULT_CONFIG
from ptw_rt.untrusted import file_kind

__all__ = ["replay_log", "run_replay"]

log = logging.getLogger(__name__)

DEFAULT_CHANNEL = "vcan0"


class _Feed:
    """The reader's frames for ``drive_log`` as (timestamp, id, data); remote and 29-bit frames counted in
    ``skipped``. Knows the line of the frame it gave last and reports the reader's discontinuities that the
    cycle driver bridges (one line each); those that end a segment are reported by ``on_segment``."""

    def __init__(self, first, reader, name: str, max_gap: float) -> None:
        self.first = first
        self.reader = reader
        self.name = name
        self.max_gap = max_gap
        self.skipped = 0
        self.line = 0
        self._seen = 0  # reader discontinuities seen so far
        self._pending: tuple | None = None  # (line, from, to) of a discontinuity not yet reported

    def __iter__(self) -> Iterator[tuple[float, int, bytes]]:
        reader = self.reader
        for f in itertools.chain((self.first,), reader):
            if self._pending is not None:  # the cycle driver took the last frame without a new segment
                self._report_bridged()
            if f.is_remote or f.is_extended:
                self.skipped += 1
                continue
            if getattr(reader, "discontinuities", 0) != self._seen:
                self._seen = reader.discontinuities
                lines = reader.discontinuity_lines
                if len(lines) >= self._seen:
                    self._pending = lines[self._seen - 1]
            self.line = f.line_no
            yield f.timestamp, f.frame_id, f.data
        if self._pending is not None:
            self._report_bridged()

    def _report_bridged(self) -> None:
        line, t_from, t_to = self._pending
        self._pending = None
        log.warning(
            "%s:%d: time stamps jump %+.3f s (from %.6f to %.6f): bridged, the gap is within --max-gap %g s "
            "(inputs stale meanwhile)",
            self.name,
            line,
            t_to - t_from,
            t_from,
            t_to,
            self.max_gap,
        )

    def on_segment(self, brk: SegmentBreak) -> None:
        self._pending = None
        what = f"a gap longer than --max-gap {self.max_gap:g} s" if brk.kind == "gap" else "the clock going back"
        log.warning(
            "%s:%d: time stamps jump %+.3f s (from %.6f to %.6f), %s: segment %d starts here from reset inputs "
            "(the estimator keeps its learned tyre stiffness)",
            self.name,
            self.line,
            brk.jump,
            brk.t_from,
            brk.t_to,
            what,
            brk.segment,
        )


class ReplayOutputError(UserFacingError):
    """An output of the replay cannot be written (disk full, permission, not a file)."""

    exit_code = EXIT_OUTPUT


def _output_error(path: Path | str, exc: OSError) -> ReplayOutputError:
    return ReplayOutputError(f"cannot write {path}: {exc.strerror or exc}")


def _open_output(path: Path, what: str) -> IO[str]:
    """A text output file, opened for writing; ReplayOutputError (one line) when that is not possible."""
    try:
        if path.is_dir():
            raise ReplayOutputError(f"{what} {path} is a directory")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except (FileExistsError, NotADirectoryError):
            raise ReplayOutputError(f"cannot write {path}: a parent of it is not a directory") from None
        return open(path, "w", encoding="ascii", newline="\n")
    except OSError as exc:
        raise _output_error(path, exc) from None


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
    max_gap: float = DEFAULT_MAX_GAP_S,
) -> dict[str, Any]:
    """Replay one candump log; write the estimator's frames to ``out_log`` (and the estimates to ``csv_path``).

    Returns a summary: cycles, segments, frames in/out, rejected lines by reason, reordered frames, time
    discontinuities, log and wall duration, x real time, modes seen, input health counters. A gap in the log's
    time stamps longer than ``max_gap`` seconds, or a jump back, ends a segment (``drive_log``). Raises
    UserFacingError if the input cannot be opened, ReplayOutputError (exit code ``EXIT_OUTPUT``) if an output
    cannot be written.
    """
    in_path, out_log = Path(in_path), Path(out_log)
    wall0 = time.perf_counter()
    runner = runner or build_runner(config, design_file)
    try:
        reader = read_log(in_path)
        first = next(reader, None)
    except OSError as exc:  # FileNotFoundError, permissions, a directory ...
        raise UserFacingError(f"cannot read candump log {in_path}: {exc}") from exc
    if hasattr(reader, "warn_discontinuities"):
        reader.warn_discontinuities = False  # reported below, one line each, with what the replay did
    channel = first.channel if first is not None else DEFAULT_CHANNEL
    feed = _Feed(first, reader, str(in_path), max_gap)
    stats = DriveStats()
    mode_counts = [0] * len(MODE_NAMES)
    frames_out = 0
    t_first = first.timestamp if first is not None else 0.0
    t_last = t_first
    duration = 0.0
    csv: IO[str] | None = None
    out: IO[str] | None = None
    try:
        out = _open_output(out_log, "--out")
        writer = CandumpWriter(out, channel=channel)
        if csv_path is not None:
            csv = _open_output(Path(csv_path), "--csv")
        if csv is not None:
            try:
                csv.write("time," + ",".join(ESTIMATE_NAMES) + "\n")
            except OSError as exc:
                raise _output_error(csv_path, exc) from None
        write = writer.write

        def on_frames(now: float, frames: list[tuple[int, bytes]]) -> None:
            nonlocal frames_out
            try:
                for fid, data in frames:
                    write(now, fid, data)
            except OSError as exc:
                raise _output_error(out_log, exc) from None
            frames_out += len(frames)

        def on_cycle(now: float, estimates: np.ndarray) -> None:
            nonlocal t_last
            m = int(estimates[E_MODE])
            if 0 <= m < len(mode_counts):
                mode_counts[m] += 1
            if csv is not None:
                try:
                    csv.write(_csv_row(now, estimates))
                except OSError as exc:
                    raise _output_error(csv_path, exc) from None
            t_last = now

        def on_segment(brk: SegmentBreak) -> None:
            nonlocal duration, t_first
            duration += max(0.0, t_last - t_first)  # the log's content: the gaps between segments do not count
            t_first = brk.t_to
            feed.on_segment(brk)

        try:
            cycles = (
                0
                if first is None
                else drive_log(
                    feed, runner, on_cycle, on_frames=on_frames, max_gap=max_gap, on_segment=on_segment, stats=stats
                )
            )
        except OSError as exc:  # output errors are ReplayOutputError by now: this is the input failing (EIO ...)
            raise UserFacingError(f"cannot read candump log {in_path}: {exc.strerror or exc}") from None
        duration += max(0.0, t_last - t_first)
        for stream, path in ((out, out_log), (csv, csv_path)):
            if stream is not None:
                try:
                    stream.close()  # flushes: a full disk shows here
                except OSError as exc:
                    raise _output_error(path, exc) from None
    finally:
        for stream in (csv, out):
            if stream is not None and not stream.closed:
                try:
                    stream.close()
                except OSError:
                    pass  # already failing: the first error is the one reported
        reader.close()
    wall = time.perf_counter() - wall0
    return {
        "log": str(in_path),
        "out": str(out_log),
        "csv": None if csv_path is None else str(csv_path),
        "cycles": cycles,
        "segments": stats.segments,
        "frames_in": reader.frames,
        "frames_out": frames_out,
        "malformed_lines": reader.malformed,
        "malformed_line_numbers": reader.malformed_lines[:20],
        "rejected": {k: v for k, v in getattr(reader, "rejected", {}).items() if v},
        "reordered": getattr(reader, "reordered", 0),
        "late_frames": stats.late_frames,
        "discontinuities": getattr(reader, "discontinuities", 0),
        "discontinuity_lines": [line for line, _, _ in getattr(reader, "discontinuity_lines", [])[:20]],
        "segment_breaks": [
            {"kind": b.kind, "from": round(b.t_from, 6), "to": round(b.t_to, 6)} for b in stats.breaks[:20]
        ],
        "skipped_frames": feed.skipped + stats.bad_stamps,
        "log_duration_s": round(duration, 3),
        "wall_s": round(wall, 3),
        "x_real_time": round(duration / wall, 1) if wall > 0 else None,
        "modes": {MODE_NAMES[i]: n for i, n in enumerate(mode_counts) if n},
        "inputs": runner.tracker.summary(),
    }


# ---------------------------------------------------------------------- CLI


def _collect_logs(paths: list[Path]) -> tuple[list[Path], bool]:
    """Input logs (directories expanded to their *.log files, sorted) and whether any directory was given."""
    files: list[Path] = []
    any_dir = False
    for p in paths:
        try:
            st = p.stat()
        except FileNotFoundError:
            raise UserFacingError(f"candump log not found: {p}") from None
        except OSError as exc:
            raise UserFacingError(f"cannot read candump log {p}: {exc.strerror or exc}") from None
        if stat.S_ISDIR(st.st_mode):
            any_dir = True
            try:
                found = sorted(q for q in p.glob("*.log") if q.is_file())
            except OSError as exc:
                raise UserFacingError(f"cannot list directory {p}: {exc.strerror or exc}") from None
            if not found:
                raise UserFacingError(f"no *.log files in directory {p}")
            files.extend(found)
        elif stat.S_ISREG(st.st_mode):
            files.append(p)
        else:
            raise UserFacingError(f"{p}: candump log is {file_kind(st.st_mode)}, not a regular file")
    return files, any_dir


def _plan(args) -> list[tuple[Path, Path, Path | None]]:
    files, any_dir = _collect_logs(list(args.logs))
    if len(files) == 1 and not any_dir:
        if args.out.is_dir():
            raise ReplayOutputError(f"--out {args.out} is a directory; with one input log --out names the output file")
        if args.csv is not None and args.csv.is_dir():
            raise ReplayOutputError(f"--csv {args.csv} is a directory; with one input log --csv names a file")
        jobs = [(files[0], args.out, args.csv)]
    else:
        if args.out.exists() and not args.out.is_dir():
            raise ReplayOutputError(f"--out {args.out} must be a directory when replaying several logs")
        if args.csv is not None and args.csv.exists() and not args.csv.is_dir():
            raise ReplayOutputError(f"--csv {args.csv} must be a directory when replaying several logs")
        names = [f.name for f in files]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise UserFacingError(f"several input logs are named {', '.join(dup)}: their outputs would collide")
        jobs = [(f, args.out / f.name, None if args.csv is None else args.csv / (f.stem + ".csv")) for f in files]
    for src, out, csv in jobs:
        for target in (out, csv):
            if target is not None and target.resolve() == src.resolve():
                raise UserFacingError(f"output {target} would overwrite its input log")
    return jobs


def _progress(done: int, total: int, enabled: bool, stream: IO[str]) -> None:
    if not enabled:
        return
    width = 30
    filled = int(round(width * done / max(1, total)))
    stream.write(f"\rreplay [{'#' * filled}{'.' * (width - filled)}] {done}/{total}")
    if done >= total:
        stream.write("\n")
    stream.flush()


_SHORT_KEYS = (
    "log",
    "out",
    "cycles",
    "segments",
    "frames_in",
    "frames_out",
    "malformed_lines",
    "rejected",
    "reordered",
    "late_frames",
    "discontinuities",
    "x_real_time",
    "modes",
)


def _short(summary: dict[str, Any]) -> dict[str, Any]:
    if "error" in summary:
        return {"log": summary["log"], "error": summary["error"]}
    return {k: summary[k] for k in _SHORT_KEYS}


def _failure(in_path: Path, exc: BaseException) -> dict[str, Any]:
    """The summary of a log that could not be replayed: its error in one line."""
    if isinstance(exc, UserFacingError):
        text = str(exc)
    else:  # a bug or an exhausted resource: named, without a traceback, and the other logs go on
        text = f"internal error: {type(exc).__name__}: {exc}"
    return {"log": str(in_path), "error": " ".join(text.split())[:500]}


def _job(
    in_path: Path, out: Path, csv: Path | None, config: Path, design_file: Path | None, max_gap: float
) -> dict[str, Any]:
    """One log of a parallel run, in a worker process: never raises (a bad log must not stop the others)."""
    try:
        return replay_log(in_path, out, csv, config, design_file, max_gap=max_gap)
    except Exception as exc:
        return _failure(in_path, exc)


def _max_gap(args) -> float:
    value = getattr(args, "max_gap", None)
    if value is None:
        return DEFAULT_MAX_GAP_S
    if not (math.isfinite(value) and value > 0.0):
        raise UserFacingError(f"--max-gap must be a positive number of seconds, got {value}")
    return float(value)


def run_replay(args, *, out: IO[str] | None = None, err: IO[str] | None = None) -> int:
    """``ptw-rt replay``: one log -> ``--out`` is the output file; several logs or a directory -> ``--out`` is a
    directory (same file names), processed in parallel. One JSON summary line per log on stdout (``error``:
    the one-line reason a log was not replayed).

    Exit codes (``ptw_rt.errors``): 0 every log replayed; 1 several logs and some failed (the others were
    replayed); 2 nothing replayed, a problem with the inputs, configuration or arguments; 74 an output cannot be
    written (one log; with several, a log whose output fails is one of the failures).
    """
    out = out or sys.stdout
    err = err or sys.stderr
    max_gap = _max_gap(args)
    jobs = _plan(args)
    config = Path(args.config)
    design_file = args.design_file
    # check config, design file and DBC once, here, and compile/load the jitted step before forking workers
    runner = build_runner(config, design_file)
    runner.cycle(0.0)
    progress = not getattr(args, "no_progress", False)
    failures = 0
    results: dict[int, dict[str, Any]] = {}
    if len(jobs) == 1:
        src, dst, csv = jobs[0]
        results[0] = replay_log(src, dst, csv, config, design_file, max_gap=max_gap)
    else:
        workers = max(1, min(args.jobs or os.cpu_count() or 1, len(jobs)))
        _progress(0, len(jobs), progress, err)
        with ProcessPoolExecutor(max_workers=workers) as pool:
            futures = {
                pool.submit(_job, src, dst, csv, config, design_file, max_gap): i
                for i, (src, dst, csv) in enumerate(jobs)
            }
            for n, fut in enumerate(as_completed(futures), start=1):
                i = futures[fut]
                try:
                    results[i] = fut.result()
                except Exception as exc:  # the worker itself died (killed, out of memory): this log failed
                    results[i] = _failure(jobs[i][0], exc)
                if "error" in results[i]:
                    failures += 1
                _progress(n, len(jobs), progress, err)
    for i in sorted(results):  # job order, not completion order: stable output
        out.write(json.dumps(_short(results[i])) + "\n")
    out.flush()
    if failures:
        err.write(f"replay: {failures} of {len(jobs)} logs failed (their summary lines name the error)\n")
        return EXIT_PARTIAL
    return EXIT_OK
