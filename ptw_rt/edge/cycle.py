"""The one cycle shared by the daemon, replay, the demo, the bench and evaluation: frames in, frames out.

    frames (since the last cycle) -> InputTracker -> Sample -> Estimator.step -> Estimates -> OutputEncoder -> frames

What differs between uses is only where frames come from, what clocks the cycle (the monotonic clock, or the
log's time stamps) and where the outputs go. ``CycleRunner.run(now)`` is the whole cycle (decode, track, step,
encode); ``cycle(now)`` stops at the Estimates (evaluation, which scores them and sends nothing).

The process around the cycle (the daemon) reports its own health at the edge, never through the estimator:
``status`` (overrun count, worst cycle time) and ``process_reasons`` (REASON_OVERRUN, REASON_SEND_FAILURE) go
straight into EST_Status; ``process_degraded`` publishes a VALID or CONVERGING mode as DEGRADED.

`drive_log` is the log-clocked driver (replay, evaluation): a cycle every `sample_time` of log time; the frames
stamped up to a cycle's time belong to it; a jump of the log's clock (forward by more than `max_gap`, or
backwards) ends a segment and the next starts from reset inputs.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ptw_rt.core.estimator import Estimator
from ptw_rt.core.layout import E_MODE, MODE_CONVERGING, MODE_DEGRADED, MODE_VALID, new_estimates, new_sample
from ptw_rt.design.file import load_design
from ptw_rt.edge.inputs import InputTracker
from ptw_rt.edge.outputs import OutputEncoder
from ptw_rt.io.dbc import FrameCodec
from ptw_rt.paths import DEFAULT_DBC, DEFAULT_DESIGN
from ptw_rt.settings import Settings, load_settings

Frame = tuple[int, bytes]

_DEGRADABLE = (float(MODE_CONVERGING), float(MODE_VALID))
DEFAULT_MAX_GAP_S = 5.0  # drive_log: a longer gap in a log's time stamps ends a segment
DEFAULT_REORDER_TOLERANCE_S = 0.02  # drive_log: frames up to this much out of order are taken as they come


class CycleRunner:
    """Input tracking, estimator and output encoding with preallocated Sample and Estimates."""

    def __init__(self, settings: Settings, estimator: Estimator, codec: FrameCodec) -> None:
        self.settings = settings
        self.estimator = estimator
        self.codec = codec
        self.tracker = InputTracker(codec, stale_after_periods=settings.runtime.stale_after_periods)
        self.sample_time = estimator.sample_time
        self.encoder = OutputEncoder(codec, self.sample_time)
        self.sample = new_sample()
        self.estimates = new_estimates()
        self.cycles = 0
        # the process's own health for EST_Status (the daemon sets them; a replay leaves them at 0: deterministic)
        self.status = {"overrun_count": 0, "cycle_time_us": 0}
        self.process_reasons = 0
        # the process cannot keep its period (the daemon's overrun rule): a VALID or CONVERGING mode is published
        # as DEGRADED while set
        self.process_degraded = False

    def on_frame(self, timestamp: float, frame_id: int, data: bytes, extended: bool = False) -> None:
        self.tracker.on_frame(timestamp, frame_id, data, extended=extended)

    def on_values(self, message: str, timestamp: float, signals: Mapping[str, float]) -> None:
        """An input's signals from a source other than CAN (serial GNSS for GPS_Velocity)."""
        self.tracker.on_values(message, timestamp, signals)

    def cycle(self, now: float) -> np.ndarray:
        """Close the cycle at `now`: Sample from the frames seen since the last one, one step.

        Returns the (reused) Estimates array. ``run`` is this plus the output frames.
        """
        self.tracker.fill(self.sample, now)
        self.estimator.step(self.sample, self.estimates)
        self.cycles += 1
        return self.estimates

    def run(self, now: float) -> list[Frame]:
        """The whole cycle at `now`: decode, track, step, encode. Returns the frames to send in this cycle."""
        index = self.cycles
        estimates = self.cycle(now)
        if self.process_degraded and estimates[E_MODE] in _DEGRADABLE:
            estimates[E_MODE] = MODE_DEGRADED  # the step writes every output each cycle: nothing carries over
        return self.encoder.frames(estimates, index, self.status, self.tracker.stale_bits(), self.process_reasons)

    def restart_segment(self) -> None:
        """A new segment of a log after a time discontinuity: the inputs start from nothing, the estimator from
        its initial state but keeps what it learned (``Estimator.reset``). The output counters go on."""
        self.tracker.restart()
        self.estimator.reset()

    def final_status(self) -> Frame:
        """The EST_Status frame of a stopping process: ``EST_Status_Valid`` = 0."""
        return self.encoder.status_frame(
            self.estimates, self.tracker.stale_bits(), self.status, valid=False, reasons=self.process_reasons
        )


def build_runner(
    config: str | Path,
    design_file: str | Path | None = None,
    dbc: str | Path = DEFAULT_DBC,
    settings: Settings | None = None,
) -> CycleRunner:
    """Load and check config, design file and DBC (clear errors), return a ready runner."""
    settings = settings or load_settings(config)
    design = load_design(design_file or DEFAULT_DESIGN, settings.config_hash, config)
    return CycleRunner(settings, Estimator(settings, design), FrameCodec(dbc))


@dataclass(frozen=True)
class SegmentBreak:
    """Where `drive_log` ended a segment: the log's clock jumped forward by more than ``max_gap`` ("gap") or
    back by more than ``reorder_tolerance`` ("backwards")."""

    kind: str  # "gap" or "backwards"
    t_from: float  # newest stamp of the segment that ends
    t_to: float  # stamp of the first frame of the next segment
    segment: int  # number of the segment that starts here (2, 3, ...)
    cycles_before: int  # cycles driven before it (all segments)

    @property
    def jump(self) -> float:
        return self.t_to - self.t_from


@dataclass
class DriveStats:
    """What `drive_log` saw of the log's clock (pass one in to read it back)."""

    segments: int = 0  # segments driven: 1 for a log without breaks, 0 for an empty one
    breaks: list[SegmentBreak] = field(default_factory=list)  # the first MAX_BREAKS_KEPT
    late_frames: int = 0  # frames stamped at or before a cycle already closed: given to the next cycle
    bad_stamps: int = 0  # frames with a non-finite stamp, dropped


MAX_BREAKS_KEPT = 1000


def drive_log(
    frames: Iterable[tuple[float, int, bytes]],
    runner: CycleRunner,
    on_cycle: Callable[[float, np.ndarray], None] | None = None,
    *,
    start: float | None = None,
    on_frames: Callable[[float, list[Frame]], None] | None = None,
    max_gap: float = DEFAULT_MAX_GAP_S,
    reorder_tolerance: float = DEFAULT_REORDER_TOLERANCE_S,
    on_segment: Callable[[SegmentBreak], None] | None = None,
    stats: DriveStats | None = None,
) -> int:
    """Run `runner` over (timestamp, id, data) frames, clocked by their stamps. Returns the number of cycles.

    The stamps are data, not a trusted clock. The rule:

    * Cycles every sample time from `start` (default: the first frame's stamp); the frames stamped up to a
      cycle's time belong to it; cycles go on until the last frame has been consumed. Per cycle,
      ``on_frames(now, output frames)`` (if given: the whole cycle, encoding included) and then
      ``on_cycle(now, Estimates)``.
    * A frame stamped at most `reorder_tolerance` before the newest stamp seen (out of order, as a CAN log of
      several nodes has) is taken as it comes: into the cycle being collected, as a late frame on the live bus
      would be; if that cycle's predecessor already closed at or after its stamp it is counted in
      ``stats.late_frames``.
    * A gap of at most `max_gap` between two frames is driven through cycle by cycle (the inputs go stale and
      the estimator reports it, as it would live), so a log's cycles stay at most ``max_gap / sample time``
      per gap beyond its content.
    * A frame stamped more than `max_gap` after the newest one, or more than `reorder_tolerance` before it,
      ends the segment: the cycle being collected is closed, ``on_segment(SegmentBreak)`` is called, the
      inputs are reset (``CycleRunner.restart_segment``: the estimator keeps its learned tyre stiffness) and
      the next segment's cycles start from that frame's stamp. Output counters and the 10 Hz phase go on.
    """
    if not max_gap > 0.0:
        raise ValueError(f"max_gap must be > 0, got {max_gap!r}")
    stats = stats if stats is not None else DriveStats()
    dt = runner.sample_time
    it = iter(frames)
    pending = next(it, None)
    if pending is None:
        return 0
    t0 = pending[0] if start is None else start
    newest = t0
    on_frame = runner.on_frame  # bound once: this loop runs per frame
    k = 1
    n = 0
    now = t0 + dt
    closed = -math.inf  # time of the last closed cycle
    consumed = False  # frames taken in since the last closed cycle
    seg_cycles = 0
    stats.segments = 1
    while True:
        if pending is not None:
            t = pending[0]
            if not newest - reorder_tolerance <= t <= newest + max_gap:
                if not math.isfinite(t):  # no clock to run on: dropped, counted
                    stats.bad_stamps += 1
                    pending = next(it, None)
                    continue
                if consumed or seg_cycles:
                    if consumed:  # close the cycle being collected: its frames belong to this segment
                        n += _close(runner, now, on_frames, on_cycle)
                        consumed = False
                    stats.segments += 1
                    brk = SegmentBreak("gap" if t > newest else "backwards", newest, t, stats.segments, n)
                    if len(stats.breaks) < MAX_BREAKS_KEPT:
                        stats.breaks.append(brk)
                    if on_segment is not None:
                        on_segment(brk)
                    runner.restart_segment()
                t0 = newest = t
                k = 1
                now = t0 + dt
                closed = -math.inf
                seg_cycles = 0
            if t <= now:
                on_frame(t, pending[1], pending[2])
                consumed = True
                if t > newest:
                    newest = t
                elif t <= closed:
                    stats.late_frames += 1
                pending = next(it, None)
                continue
        elif not consumed:
            return n
        n += _close(runner, now, on_frames, on_cycle)
        closed = now
        consumed = False
        seg_cycles += 1
        k += 1
        now = t0 + k * dt


def _close(runner: CycleRunner, now: float, on_frames, on_cycle) -> int:
    """One cycle at `now` for `drive_log`; returns 1."""
    if on_frames is not None:
        on_frames(now, runner.run(now))
    else:
        runner.cycle(now)
    if on_cycle is not None:
        on_cycle(now, runner.estimates)
    return 1
