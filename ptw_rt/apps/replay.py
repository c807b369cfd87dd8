"""``ptw-rt replay``: CAN logs through the daemon's cycle, clocked by the log's time stamps.

    log frames -> frame_blocks (decoded per message id) -> drive_blocks (the compiled loop: track, step, encode)
               -> output log written per chunk of cycles (+ optional CSV)

Input and output logs are any format of ``ptw_rt.io.logformats`` (candump ``-L``, ASC, BLF, TRC, CSV, MF4),
the input's found from its extension and content, the output's from its extension (none: candump).
The output log holds the estimator's frames (EST_*) stamped with LOG time (the cycle's time), on the channel of
a candump input log. Nothing depends on the wall clock or the machine, so the same input gives a byte-identical
output: EST_Status.OverrunCount and CycleTimeUs are 0 in a replay (there is no deadline to miss).
Malformed records of the input are skipped and counted by the reader, and summarised in one warning line
with at most three examples, escaped.
"""

from __future__ import annotations

import collections
import gc
import itertools
import json
import logging
import math
import os
import stat
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any

import numpy as np

from ptw_rt._numba_cache import announce_compile
from ptw_rt.apps import fleet
from ptw_rt.core.layout import (
    E_C_ALPHA_FRONT,
    E_C_ALPHA_REAR,
    E_C_GAMMA_FRONT,
    E_C_GAMMA_REAR,
    E_MODE,
    E_REASONS,
    E_TYRE_SCALE,
    E_VALID,
    ESTIMATE_NAMES,
    MODE_NAMES,
    REASON_NAMES,
    V_CAMBER,
    V_CORNERING,
)
from ptw_rt.edge.cycle import (
    DEFAULT_MAX_GAP_S,
    Block,
    Chunk,
    CycleRunner,
    DriveStats,
    SegmentBreak,
    build_runner,
    decode_block,
    drive_blocks,
    shared_runner,
)
from ptw_rt.edge.inputs import InputTracker
from ptw_rt.errors import EXIT_OK, EXIT_PARTIAL, OutputError, UserFacingError, output_error
from ptw_rt.io.candump import MAX_RECORDED, BusChoice, FrameArrays
from ptw_rt.io.logformats import (
    EXTENSIONS,
    FAMILIES,
    GZIP_SUFFIX,
    EmptyLogError,
    LogFormatError,
    detect_format,
    format_of_extension,
    open_log_arrays,
    open_writer,
    output_name,
    writer_format,
)
from ptw_rt.parallel import worker_count
from ptw_rt.paths import DEFAULT_CONFIG
from ptw_rt.progress import Progress
from ptw_rt.untrusted import fifo_has_reader, file_kind, one_line, same_file

__all__ = ["replay_job", "replay_log", "run_replay"]

log = logging.getLogger(__name__)

DEFAULT_CHANNEL = "vcan0"
# REASON_* bits that say an input was faulty this cycle: a fleet row's sensor_fault_cycles counts their cycles
SENSOR_FAULT_BITS = sum(1 << REASON_NAMES.index(name) for name in fleet.SENSOR_FAULT_REASONS)
MAX_TREE_DEPTH = 32  # directory levels searched for logs below a directory given on the command line


class _Feed:
    """The log's frames (``open_log_arrays``, any format) for the cycle driver as decoded blocks
    (``decode_block``); 29-bit frames counted in ``skipped`` (remote, error and CAN FD frames in the reader's
    stats). Remembers the reader's discontinuities of the time stamps with the index of the frame where each
    starts: the driver reads ahead in blocks, so what it made of one (a new segment, ``on_segment``, or bridged,
    ``report_bridged`` once the log is driven) is reported, one line each, once it is known. ``progress()`` is
    called after every block.
    """

    def __init__(
        self,
        first: FrameArrays,
        blocks: Iterator[FrameArrays],
        tracker: InputTracker,
        name: str,
        max_gap: float,
        progress: Callable[[], None] | None = None,
    ) -> None:
        self.first = first
        self.blocks = blocks
        self.tracker = tracker
        self.name = name
        self.max_gap = max_gap
        self.progress = progress
        self.skipped = 0
        # 29-bit frames whose id is an 11-bit input's: a logger that flags every frame extended, not another bus
        self.extended_inputs = 0
        self.input_ids = self.input_ids_of(tracker)
        self._jumps: dict[int, tuple[int, float, float]] = {}  # frame index -> (line, from, to), not yet reported
        # segments beyond the first MAX_RECORDED get no line each (a log of short bursts 6 s apart printed one line
        # per burst, 23 000 for 7.7 MB), one count at the end (`report_bridged`), as the readers do for bad lines
        self._segments_unlisted = 0
        self._segments_listed = 0

    @staticmethod
    def input_lengths_of(tracker: InputTracker) -> dict[int, int]:
        """The 11-bit inputs' ids and their DLCs."""
        return {lay.frame_id: lay.length for lay in tracker.layouts if not lay.message.is_extended_frame}

    @staticmethod
    def input_ids_of(tracker: InputTracker) -> np.ndarray:
        """The 11-bit ids of the inputs the tracker decodes, sorted."""
        return np.array(sorted(_Feed.input_lengths_of(tracker)), dtype=np.int64)

    def __iter__(self) -> Iterator[Block]:
        offset = 0
        for frames in itertools.chain((self.first,), self.blocks):
            standard = ~frames.extended
            kept = np.flatnonzero(standard)
            self.skipped += len(frames) - kept.size
            for jump in frames.jumps:  # the index among the frames kept (a 29-bit one: the next kept)
                self._jumps[offset + int(np.searchsorted(kept, jump.index))] = jump[1:]
            if kept.size != len(frames):
                self.extended_inputs += int(np.isin(frames.ids[frames.extended], self.input_ids).sum())
                frames = FrameArrays(*(a[kept] for a in frames[:5]), frames.channel, [])
            yield decode_block(self.tracker, frames.times, frames.ids, frames.lengths, frames.data, offset)
            offset += len(frames)
            if self.progress is not None:
                self.progress()

    def report_bridged(self) -> None:
        """The discontinuities the driver went through without a new segment (the gap within --max-gap), and how
        many segments went unlisted."""
        for line, t_from, t_to in self._jumps.values():
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
        self._jumps.clear()
        if self._segments_unlisted:
            log.warning(
                "%s: %d more segments started where the time stamps jump (not listed: the first %d are)",
                self.name,
                self._segments_unlisted,
                MAX_RECORDED,
            )
            self._segments_unlisted = 0

    def on_segment(self, brk: SegmentBreak) -> None:
        jump = self._jumps.pop(brk.frame, None)
        if self._segments_listed >= MAX_RECORDED:
            self._segments_unlisted += 1
            return
        self._segments_listed += 1
        where = self.name if jump is None else f"{self.name}:{jump[0]}"
        what = f"a gap longer than --max-gap {self.max_gap:g} s" if brk.kind == "gap" else "the clock going back"
        log.warning(
            "%s: time stamps jump %+.3f s (from %.6f to %.6f), %s: segment %d starts here from reset inputs "
            "(the estimator keeps its learned tyre stiffness)",
            where,
            brk.jump,
            brk.t_from,
            brk.t_to,
            what,
            brk.segment,
        )


# a bus's name the candump output can carry: an interface's (IFNAMSIZ 16), printable ASCII without space or '#'
_OUTPUT_CHANNEL_CHARS = frozenset("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_-.:@")


def _output_channel(bus: str | None) -> str:
    """The channel the output log is written on: the input's bus (a candump log's), else DEFAULT_CHANNEL; a name
    candump's ASCII lines cannot carry (non-ASCII, punctuation) is DEFAULT_CHANNEL too (it was a traceback at the
    first line written)."""
    if bus and len(bus) <= 16 and set(bus) <= _OUTPUT_CHANNEL_CHARS:
        return bus
    return DEFAULT_CHANNEL


class ReplayOutputError(OutputError):
    """An output of the replay cannot be written (disk full, permission, not a file)."""


def _output_error(path: Path | str, exc: OSError) -> ReplayOutputError:
    return output_error(path, exc, ReplayOutputError)


def _prepare_output(path: Path, what: str) -> None:
    """Refuse a directory as an output file and create its parent; ReplayOutputError (one line) otherwise."""
    try:
        if path.is_dir():
            raise ReplayOutputError(f"{what} {path} is a directory")
        if path.is_fifo() and not fifo_has_reader(path):  # opening it would wait for one: replay hung, nothing said
            raise ReplayOutputError(f"{what} {path} is a FIFO (named pipe) with no reader; write to a file")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except (FileExistsError, NotADirectoryError):
            raise ReplayOutputError(f"cannot write {path}: a parent of it is not a directory") from None
    except OSError as exc:
        raise _output_error(path, exc) from None


def _is_stdout(path: Path | None) -> bool:
    """Whether ``path`` is this process's standard output (``--out /dev/stdout``): the summaries then go to stderr,
    not into the log."""
    if path is None:
        return False
    try:
        return os.path.samestat(os.stat(path), os.fstat(1))
    except (OSError, ValueError):
        return False


def _open_output(path: Path, what: str) -> IO[str]:
    """A text output file, opened for writing; ReplayOutputError (one line) when that is not possible."""
    _prepare_output(path, what)
    try:
        return open(path, "w", encoding="ascii", newline="\n")
    except OSError as exc:
        raise _output_error(path, exc) from None


def _open_log_writer(path: Path, channel: str) -> Any:
    """The output log's writer (``open_writer``: candump or a python-can writer, from the extension);
    ReplayOutputError (one line) when it cannot be opened."""
    _prepare_output(path, "--out")
    try:
        return open_writer(path, channel=channel)
    except OSError as exc:
        raise _output_error(path, exc) from None


def _remove_outputs(paths: list[Path]) -> None:
    """Remove the regular files among ``paths`` (``/dev/null`` and the like stay); failures are ignored: the
    error already being reported is the one the user needs."""
    for path in paths:
        try:
            if path.is_file():
                path.unlink()
        except OSError:
            pass


# one printf-style template per row: "%.6f" / "%.10g" format floats exactly as f"{v:.6f}" / f"{v:.10g}" do
# (inf, nan and -0 included), at a fraction of the cost of one f-string per value
_CSV_TEMPLATE = "%.6f," + ",".join(["%.10g"] * len(ESTIMATE_NAMES)) + "\n"


def replay_log(
    in_path: str | Path,
    out_log: str | Path,
    csv_path: str | Path | None = None,
    config: str | Path = DEFAULT_CONFIG,
    design_file: str | Path | None = None,
    *,
    runner: CycleRunner | None = None,
    progress: Progress | None = None,
    max_gap: float = DEFAULT_MAX_GAP_S,
    channel: str | None = None,
) -> dict[str, Any]:
    """Replay one CAN log (any format of ``ptw_rt.io.logformats``); write the estimator's frames to ``out_log``
    (format from its extension) and the estimates to ``csv_path``.

    Returns a summary: cycles, segments, frames in/out, rejected records by reason, reordered frames, time
    discontinuities, log and wall duration, x real time, modes seen, input health counters. A gap in the log's
    time stamps longer than ``max_gap`` seconds, or a jump back, ends a segment (``drive_log``), whatever the
    format. A log of several buses is read on one, as the daemon reads one: ``channel``, or the inputs' bus
    (``BusChoice``); the frames on the others are skipped and counted (one warning line). Raises
    UserFacingError if the input cannot be opened, is not a CAN log or holds no frame
    (``EmptyLogError``), ReplayOutputError (exit code ``EXIT_OUTPUT``) if an output cannot be written;
    ``progress`` (if given) is updated with the share of the log read.
    """
    in_path, out_log = Path(in_path), Path(out_log)
    if in_path.is_dir():  # one of several inputs, a directory in which no log was found (`_collect_logs`)
        raise UserFacingError(_no_logs_in(in_path))
    wall0 = time.perf_counter()
    runner = runner or build_runner(config, design_file)
    frames_before = _input_frames(runner.tracker.summary())  # a runner given by the caller may have replayed others
    try:
        bus = BusChoice(_Feed.input_lengths_of(runner.tracker), channel)
        blocks, stats = open_log_arrays(in_path, bus=bus)
        # reported below, one line each, with what the replay did (bridged, or a new segment)
        stats.reader.warn_discontinuities = False
        first = next(blocks, None)
    except OSError as exc:  # FileNotFoundError, permissions, a directory ...
        raise UserFacingError(f"cannot read CAN log {in_path}: {exc.strerror or exc}") from None
    if first is None:
        blocks.close()
        if channel is not None and stats.reader.other_channel_frames:
            raise EmptyLogError(
                f"{in_path}: no frame on --channel {channel} (the log's channels: "
                f"{', '.join(stats.reader.other_channels)})"
            )
        raise EmptyLogError(stats.no_frames_message())
    out_channel = _output_channel(stats.reader.bus_read if stats.format == "candump" else None)
    tick = None if progress is None else (lambda: progress.update(stats.fraction))
    feed = _Feed(first, blocks, runner.tracker, str(in_path), max_gap, tick)
    drive = DriveStats()
    mode_counts = [0] * len(MODE_NAMES)
    sensor_fault_cycles = 0
    last = np.zeros(len(ESTIMATE_NAMES))
    frames_out = 0
    t_first = float(first.times[0])
    t_last = t_first
    duration = 0.0
    csv: IO[str] | None = None
    writer: Any = None
    created: list[Path] = []  # the outputs this replay opened: removed if it fails, never left half written
    finished = False
    try:
        writer = _open_log_writer(out_log, out_channel)
        created.append(out_log)
        if csv_path is not None:
            csv = _open_output(Path(csv_path), "--csv")
            created.append(Path(csv_path))
            try:
                csv.write("time," + ",".join(ESTIMATE_NAMES) + "\n")
            except OSError as exc:
                raise _output_error(csv_path, exc) from None
        encoder = runner.encoder
        bulk_writer = getattr(writer, "write_frames", None)

        def on_chunk(chunk: Chunk) -> None:
            nonlocal frames_out, t_last, sensor_fault_cycles, last
            times = chunk.times
            try:
                frames = encoder.bulk(chunk.messages, chunk.words) if bulk_writer is not None else None
                if frames is not None:
                    ends = chunk.frame_end
                    cycle_of = np.repeat(np.arange(times.size), np.diff(ends, prepend=0))
                    bulk_writer(times, cycle_of, *frames)
                else:
                    for c, now in enumerate(times.tolist()):
                        writer.write_cycle(now, chunk.frames(encoder, c))
            except OSError as exc:
                raise _output_error(out_log, exc) from None
            frames_out += int(chunk.frame_end[-1])
            est = chunk.estimates
            modes = est[:, E_MODE].astype(np.int64)
            seen = np.bincount(modes[(modes >= 0) & (modes < len(MODE_NAMES))], minlength=len(MODE_NAMES))
            for m, n in enumerate(seen.tolist()):
                mode_counts[m] += n
            sensor_fault_cycles += int(np.count_nonzero(est[:, E_REASONS].astype(np.int64) & SENSOR_FAULT_BITS))
            last = est[-1].copy()
            t_last = float(times[-1])
            if csv is not None:
                try:
                    csv.write(
                        "".join(
                            [_CSV_TEMPLATE % (t, *row) for t, row in zip(times.tolist(), est.tolist(), strict=True)]
                        )
                    )
                except OSError as exc:
                    raise _output_error(csv_path, exc) from None

        def on_segment(brk: SegmentBreak) -> None:
            nonlocal duration, t_first
            duration += max(0.0, t_last - t_first)  # the log's content: the gaps between segments do not count
            t_first = brk.t_to
            feed.on_segment(brk)

        try:
            cycles = drive_blocks(
                feed, runner, on_chunk, max_gap=max_gap, on_segment=on_segment,
                stats=drive,
            )  # fmt: skip
        except OSError as exc:  # output errors are ReplayOutputError by now: this is the input failing (EIO ...)
            raise UserFacingError(f"cannot read CAN log {in_path}: {exc.strerror or exc}") from None
        duration += max(0.0, t_last - t_first)
        feed.report_bridged()
        for close, path in ((writer.close, out_log), (None if csv is None else csv.close, csv_path)):
            if close is not None:
                try:
                    close()  # flushes: a full disk shows here
                except OSError as exc:
                    raise _output_error(path, exc) from None
        finished = True
    finally:
        for close in (None if csv is None else csv.close, None if writer is None else writer.close):
            if close is not None:
                try:
                    close()  # a second close is a no-op
                except Exception:  # noqa: BLE001 - already failing: the first error is the one reported
                    pass
        blocks.close()
        if not finished:  # a full disk or an unreadable input mid-log: a truncated output would pass for a ride
            _remove_outputs(created)
    if stats.malformed:
        log.warning("%s", stats.problems_line())
    driven = stats.frames - feed.skipped  # the 29-bit frames skipped never reached a cycle
    if driven >= DENSE_LOG_FRAMES and cycles * DENSE_LOG_FRAMES_PER_CYCLE < driven:
        # all stamps equal, or a whole ride's frames within a millisecond: every frame lands in one cycle or a few
        log.warning(
            "%s: %d frames in %d cycles (%.6f s of time stamps): not the time stamps of a recorded bus",
            in_path,
            driven,
            cycles,
            duration,
        )
    inputs = runner.tracker.summary()
    read = {name: n - frames_before.get(name, 0) for name, n in _input_frames(inputs).items()}
    if not any(read.values()):
        # a log of another bus (29-bit frames, other ids): every cycle FAULT and exit 0 said nothing was wrong
        _remove_outputs(created)
        skipped = feed.skipped + sum(stats.skipped.values())
        raise EmptyLogError(
            f"{in_path}: none of its {stats.frames} frames is one the estimator reads ({', '.join(read)}): "
            f"{inputs.get('unknown_ids', 0)} of other ids, {skipped} skipped (29-bit, remote, error, FD); "
            "a log of another bus?"
            + (
                f" ({feed.extended_inputs} of the 29-bit ones carry an input's 11-bit id)"
                if feed.extended_inputs
                else ""
            )
            + (
                f" ({stats.reader.other_channel_frames} frames on other channels skipped: "
                f"{', '.join(stats.reader.other_channels)}; --channel reads another)"
                if stats.reader.other_channel_frames
                else ""
            )
        )
    if stats.reader.other_channel_frames:  # said here, not before a refusal above (one line, not two)
        log.warning(
            "%s: %d frames on other channels (%s) than the bus read, %s (%s): skipped; --channel reads another",
            in_path,
            stats.reader.other_channel_frames,
            ", ".join(stats.reader.other_channels),
            bus.chosen,
            "--channel" if channel is not None else "the inputs' bus",
        )
    if feed.extended_inputs:
        log.warning(
            "%s: %d frames flagged 29-bit carry the id of an 11-bit input (%s) and were skipped: "
            "a logger that marks every frame extended?",
            in_path,
            feed.extended_inputs,
            ", ".join(f"0x{i:X}" for i in feed.input_ids),
        )
    wall = time.perf_counter() - wall0
    return {
        "log": str(in_path),
        "out": str(out_log),
        "csv": None if csv_path is None else str(csv_path),
        "cycles": cycles,
        "segments": drive.segments,
        "format": stats.format,
        "frames_in": stats.frames,
        "frames_out": frames_out,
        "malformed_lines": stats.malformed,
        "malformed_line_numbers": stats.malformed_lines[:20],
        "rejected": {k: v for k, v in stats.rejected.items() if v},
        "reordered": stats.reordered,
        "late_frames": drive.late_frames,
        "discontinuities": stats.discontinuities,
        "discontinuity_lines": [line for line, _, _ in stats.discontinuity_lines[:20]],
        "segment_breaks": [
            {"kind": b.kind, "from": round(b.t_from, 6), "to": round(b.t_to, 6)} for b in drive.breaks[:20]
        ],
        "skipped_frames": feed.skipped + sum(stats.skipped.values()) + drive.bad_stamps,
        "extended_input_frames": feed.extended_inputs,
        "bus": stats.reader.bus_read,  # the channel read (a log of several buses: the inputs' or --channel)
        "other_bus_frames": stats.reader.other_channel_frames,  # the frames on the others, skipped
        "log_duration_s": round(duration, 3),
        "wall_s": round(wall, 3),
        "x_real_time": round(duration / wall, 1) if wall > 0 else None,
        "modes": {MODE_NAMES[i]: n for i, n in enumerate(mode_counts) if n},
        "sensor_fault_cycles": sensor_fault_cycles,
        "overruns": 0,  # replay is clocked by the log: there is no deadline to miss
        "final": _final_tyres(last),
        "inputs": inputs,
    }


def _input_frames(inputs: dict[str, Any]) -> dict[str, int]:
    """Frames of each input the estimator reads, from an input tracker's summary (its other keys are counters)."""
    return {name: v["frames"] for name, v in inputs.items() if isinstance(v, dict)}


def _final_tyres(estimates: np.ndarray) -> dict[str, Any]:
    """What the log's ride ended with: the learned stiffness, its scale and whether it was VALID."""
    return {
        "tyre_scale": float(estimates[E_TYRE_SCALE]),
        "c_alpha_front": float(estimates[E_C_ALPHA_FRONT]),
        "c_gamma_front": float(estimates[E_C_GAMMA_FRONT]),
        "c_alpha_rear": float(estimates[E_C_ALPHA_REAR]),
        "c_gamma_rear": float(estimates[E_C_GAMMA_REAR]),
        "stiffness_valid": bool(int(estimates[E_VALID]) & (V_CORNERING | V_CAMBER)),
    }


# ---------------------------------------------------------------------- CLI


def _collect_logs(
    paths: list[Path], exclude: Path | None = None, several: bool = False
) -> tuple[list[tuple[Path, Path]], bool]:
    """Input logs as (path, name of its output relative to --out) and whether any directory was given.

    A directory is searched recursively (at most MAX_TREE_DEPTH levels, symbolic links to directories not
    followed, `exclude` -- the output directory -- skipped): every file with a log extension
    (``ptw_rt.io.logformats.EXTENSIONS``, or one of them and ``.gz``) is a log (one that is not fails on its own),
    except ``.csv`` and ``.txt`` files, which are taken only when they are python-can CAN CSV, candump's screen
    output with time stamps or python-can's text: a ride's truth and estimates CSV files sit beside its log. Its
    outputs mirror the tree below it; a file given directly keeps its name (``logformats.output_name``). With
    `several` inputs (more than one, or a --list file) a path that is missing, unreadable or not a regular file, or
    a directory with no log, is kept as a log that fails on its own, like any bad log of a fleet run (its `error:`
    line, exit 1): one stale line of a list of thousands must not stop the others."""
    files: list[tuple[Path, Path]] = []
    any_dir = False
    for p in paths:
        try:
            st = p.stat()
        except OSError as exc:
            if several:
                files.append((p, Path(output_name(p))))
                continue
            if isinstance(exc, FileNotFoundError):
                raise UserFacingError(f"CAN log not found: {p}") from None
            raise UserFacingError(f"cannot read CAN log {p}: {exc.strerror or exc}") from None
        if stat.S_ISDIR(st.st_mode):
            any_dir = True
            found = [(q, q.relative_to(p).with_name(output_name(q))) for q in _logs_below(p, exclude)]
            if not found:
                if several:  # fails on its own (`replay_log`: the same message), the others are replayed
                    files.append((p, Path(output_name(p))))
                    continue
                raise UserFacingError(_no_logs_in(p))
            files.extend(found)
        elif stat.S_ISREG(st.st_mode) or several:
            files.append((p, Path(output_name(p))))
        else:
            raise UserFacingError(f"{p}: CAN log is {file_kind(st.st_mode)}, not a regular file")
    return files, any_dir


def _no_logs_in(directory: Path) -> str:
    return f"no CAN logs in directory {directory} ({', '.join(EXTENSIONS)}, each also {GZIP_SUFFIX})"


def _logs_below(top: Path, exclude: Path | None) -> list[Path]:
    found: list[Path] = []
    try:
        for root, dirs, names in os.walk(top, onerror=_raise_walk_error):
            here = Path(root)
            depth = len(here.relative_to(top).parts)
            dirs[:] = sorted(
                d for d in dirs if depth < MAX_TREE_DEPTH and (exclude is None or not same_file(here / d, exclude))
            )
            for name in sorted(names):
                q = here / name
                fmt = format_of_extension(q)
                if fmt is not None and q.is_file() and (fmt not in CONTENT_CHECKED or _content_is(q, fmt)):
                    found.append(q)
    except OSError as exc:
        raise UserFacingError(f"cannot list directory {exc.filename or top}: {exc.strerror or exc}") from None
    return found


def _raise_walk_error(exc: OSError) -> None:
    raise exc


# extensions many other files share: taken from a directory only when the content is the format (a ride's truth
# CSV beside its log, a README.txt)
CONTENT_CHECKED = ("csv", "candump_t")


def _content_is(path: Path, fmt: str) -> bool:
    """Whether the file's content is the format its extension names (or one of its family: a `.txt`)."""
    try:
        return detect_format(path)[0] in FAMILIES.get(fmt, (fmt,))
    except (LogFormatError, UserFacingError, OSError):
        return False


def _plan(args) -> list[tuple[Path, Path, Path | None]]:
    inputs = list(args.logs)
    list_file = getattr(args, "list", None)
    if list_file is not None:
        inputs.extend(fleet.read_list_file(list_file))
    if not inputs:
        raise UserFacingError("no input log: give logs, directories or --list FILE")
    files, any_dir = _collect_logs(inputs, exclude=args.out, several=len(inputs) > 1 or list_file is not None)
    if args.csv is not None and same_file(args.csv, args.out):  # one would overwrite the other
        raise UserFacingError(f"--out and --csv name the same path {args.out}")
    if len(files) == 1 and not any_dir and list_file is None:
        if args.out.is_dir():
            raise ReplayOutputError(f"--out {args.out} is a directory; with one input log --out names the output file")
        if args.csv is not None and args.csv.is_dir():
            raise ReplayOutputError(f"--csv {args.csv} is a directory; with one input log --csv names a file")
        detect_format(files[0][0])  # not a CAN log, empty: one line now, before the estimator is compiled
        jobs = [(files[0][0], args.out, args.csv)]
    else:
        if args.out.exists() and not args.out.is_dir():
            raise ReplayOutputError(f"--out {args.out} must be a directory when replaying several logs")
        if args.csv is not None and args.csv.exists() and not args.csv.is_dir():
            raise ReplayOutputError(f"--csv {args.csv} must be a directory when replaying several logs")
        dup = _repeated(str(rel) for _, rel in files)  # counted once each: 200 000 listed logs took minutes
        if dup:
            raise UserFacingError(f"several input logs are named {', '.join(dup)}: their outputs would collide")
        dup = _repeated(str(rel.with_suffix("")) for _, rel in files)
        if dup and args.csv is not None:
            raise UserFacingError(f"several input logs are named {', '.join(dup)}.*: their --csv outputs would collide")
        jobs = [
            (f, args.out / rel, None if args.csv is None else args.csv / rel.with_suffix(".csv")) for f, rel in files
        ]
        # the fleet summary's own names in --out: an input called fleet.csv had its output overwritten by the summary
        summary = {args.out / name for name in fleet.SUMMARY_NAMES}
        clash = sorted({str(target) for _, out, csv in jobs for target in (out, csv) if target in summary})
        if clash:
            raise UserFacingError(
                f"the output {clash[0]} would be overwritten by the fleet summary: rename that input log, or replay "
                "it alone"
            )
    for src, out, csv in jobs:
        writer_format(out)  # an unknown extension: one line now
        for target in (out, csv):
            if target is not None and same_file(target, src):
                raise UserFacingError(f"output {target} would overwrite its input log")
    return jobs


def _repeated(names) -> list[str]:
    """The names that come more than once (at most 5 shown), in linear time."""
    counts = collections.Counter(names)
    return sorted(n for n, k in counts.items() if k > 1)[:5]


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
    "skipped_frames",
    "bus",
    "other_bus_frames",
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


def replay_job(
    in_path: Path,
    out: Path,
    csv: Path | None,
    config: Path,
    design_file: Path | None,
    max_gap: float,
    channel: str | None = None,
) -> dict[str, Any]:
    """One log of a run of many, in a worker process or a Dask task: never raises (a bad log must not stop the
    others); the output's directory is made here (outputs mirror the input tree)."""
    try:
        for target in (out, csv):
            if target is not None:
                target.parent.mkdir(parents=True, exist_ok=True)
        # the worker's config, design file and DBC loaded once, a runner of its own for this log (`shared_runner`)
        runner = shared_runner(config, design_file)
        return replay_log(in_path, out, csv, config, design_file, runner=runner, max_gap=max_gap, channel=channel)
    except Exception as exc:
        return _failure(in_path, exc)


# --max-gap's range. A gap within it is driven cycle by cycle (100 per second), so it bounds what one line of a log
# can cost: 10^8 s took 700 MB of output in 20 s and would have run for years. Below the minimum every frame of a
# 100 Hz log would start a segment (one stderr line each).
MAX_GAP_RANGE_S = (0.1, 60.0)
# a log of at least this many frames with more than this many per cycle on average (the contract's inputs send 3.1 a
# cycle; a busy vehicle bus ~20) is said to have no usable time stamps
DENSE_LOG_FRAMES = 100
DENSE_LOG_FRAMES_PER_CYCLE = 200


def _max_gap(args) -> float:
    value = getattr(args, "max_gap", None)
    if value is None:
        return DEFAULT_MAX_GAP_S
    low, high = MAX_GAP_RANGE_S
    if not (math.isfinite(value) and low <= value <= high):
        raise UserFacingError(f"--max-gap must be {low:g}-{high:g} s, got {value}")
    return float(value)


MAX_CHANNEL_CHARS = 64  # a bus's name in any log format: an interface (IFNAMSIZ 16), a number, a python-can name


def _channel(args) -> str | None:
    value = getattr(args, "channel", None)
    if value is None:
        return None
    if not value or len(value) > MAX_CHANNEL_CHARS or not value.isprintable() or value != value.strip():
        raise UserFacingError(f"--channel must be a bus's name as the log writes it, got {one_line(value[:80])}")
    return value


def run_replay(args, *, out: IO[str] | None = None, err: IO[str] | None = None) -> int:
    """``ptw-rt replay``: one log -> ``--out`` is the output file; several logs or a directory -> ``--out`` is a
    directory (same file names), processed in parallel. One JSON summary line per log on stdout (``error``:
    the one-line reason a log was not replayed); on stderr when an output is stdout (``--out /dev/stdout``).

    Exit codes (``ptw_rt.errors``): 0 every log replayed; 1 several logs and some failed (the others were
    replayed); 2 nothing replayed, a problem with the inputs, configuration or arguments; 74 an output cannot be
    written (one log; with several, a log whose output fails is one of the failures).
    """
    err = err or sys.stderr
    max_gap = _max_gap(args)
    channel = _channel(args)
    jobs = _plan(args)
    if out is None:  # the summaries on stdout, unless an output is stdout: a pipe to `cantools decode` (README)
        out = err if any(_is_stdout(target) for _, log, csv in jobs for target in (log, csv)) else sys.stdout
    config = Path(args.config)
    design_file = args.design_file
    # check config, design file and DBC once, here, and compile/load the jitted step before forking workers
    runner = build_runner(config, design_file)
    announce_compile(err)
    runner.cycle(0.0)
    # what the imports and the runner made lives as long as the process: out of the garbage collector's full
    # passes, which otherwise walk it again and again while a log's columns are built (0.4 s of a 20-min log)
    gc.freeze()
    progress = not getattr(args, "no_progress", False)
    failures = 0
    # per log, as each finishes: its summary line and its fleet row, not the whole summary (a fleet of 200 000)
    lines: dict[int, str] = {}
    if len(jobs) == 1:
        src, dst, csv = jobs[0]
        if getattr(args, "dask", None):
            # shipping one log to a cluster would only add the transfer: say so rather than ignore the option
            err.write("replay: one log is replayed in this process; --dask spreads several logs over a cluster\n")
        bar = Progress(1.0, label=f"replay {one_line(src.name)}", stream=err, delay=0.5) if progress else None
        result = replay_log(src, dst, csv, config, design_file, progress=bar, max_gap=max_gap, channel=channel)
        lines[0] = json.dumps(_short(result))
        if bar is not None:
            bar.finish()
    else:
        workers = worker_count(args.jobs, len(jobs))
        bar = Progress(len(jobs), label="replay", stream=err) if progress else None
        rows: dict[int, tuple[Any, ...]] = {}
        riding_s = 0.0

        def done(i: int, result: dict[str, Any]) -> None:
            nonlocal failures, riding_s
            lines[i] = json.dumps(_short(result))
            rows[i] = fleet.fleet_row(result)
            if "error" in result:
                failures += 1
                message = result["error"]
                where = str(jobs[i][0])
                line = message if message.startswith(where) else f"{where}: {message}"
                err.write(("\n" if bar is not None and bar.tty else "") + f"error: {one_line(line)}\n")
            else:
                riding_s += result["log_duration_s"]
            if bar is not None:
                bar.step(one_line(jobs[i][0].name))

        fleet.run_jobs(
            replay_job,
            [(src, dst, csv, config, design_file, max_gap, channel) for src, dst, csv in jobs],
            workers=workers,
            dask=getattr(args, "dask", None),
            on_done=done,
            failure=lambda job, exc: _failure(job[0], exc),
        )
        try:
            written = fleet.write_fleet_summary([rows[i] for i in range(len(jobs))], args.out)
        except OSError as exc:
            raise _output_error(exc.filename or args.out / "fleet.csv", exc) from None
        err.write(
            f"fleet: {len(jobs) - failures} of {len(jobs)} logs replayed, {riding_s / 3600.0:.2f} h of riding, "
            f"summary {', '.join(str(p) for p in written)}\n"
        )
    for i in sorted(lines):  # job order, not completion order: stable output
        out.write(lines[i] + "\n")
    out.flush()
    if failures:
        err.write(f"replay: {failures} of {len(jobs)} logs failed (their summary lines name the error)\n")
        return EXIT_PARTIAL
    return EXIT_OK
