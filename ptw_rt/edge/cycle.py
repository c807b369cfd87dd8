"""The one cycle shared by the daemon, replay, the demo, the bench and evaluation: frames in, frames out.

    frames (since the last cycle) -> InputTracker -> Sample -> Estimator.step -> Estimates -> OutputEncoder -> frames

What differs between uses is only where frames come from, what clocks the cycle (the monotonic clock, or the
log's time stamps) and where the outputs go. ``CycleRunner.run(now)`` is the whole cycle (decode, track, step,
encode); ``cycle(now)`` stops at the Estimates (evaluation, which scores them and sends nothing).

The process around the cycle (the daemon) reports its own health at the edge, never through the estimator:
``status`` (overrun count, worst cycle time) and ``process_reasons`` (REASON_OVERRUN, REASON_SEND_FAILURE) go
straight into EST_Status. `drive_log` is the log-clocked driver (replay, evaluation): a cycle every
`sample_time` of log time; the frames stamped up to a cycle's time belong to it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from pathlib import Path

import numpy as np

from ptw_rt.core.estimator import Estimator
from ptw_rt.core.layout import new_estimates, new_sample
from ptw_rt.design.file import load_design
from ptw_rt.edge.inputs import InputTracker
from ptw_rt.edge.outputs import OutputEncoder
from ptw_rt.io.dbc import FrameCodec
from ptw_rt.paths import DEFAULT_DBC, DEFAULT_DESIGN
from ptw_rt.settings import Settings, load_settings

Frame = tuple[int, bytes]


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
        return self.encoder.frames(estimates, index, self.status, self.tracker.stale_bits(), self.process_reasons)

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


def drive_log(
    frames: Iterable[tuple[float, int, bytes]],
    runner: CycleRunner,
    on_cycle: Callable[[float, np.ndarray], None] | None = None,
    *,
    start: float | None = None,
    on_frames: Callable[[float, list[Frame]], None] | None = None,
) -> int:
    """Run `runner` over time-ordered (timestamp, id, data) frames, clocked by their stamps.

    The first cycle is one sample time after `start` (default: the first frame's stamp); cycles continue until
    the last frame has been consumed. Per cycle, ``on_frames(now, output frames)`` (if given: the whole cycle,
    encoding included) and then ``on_cycle(now, Estimates)``. Returns the number of cycles.
    """
    dt = runner.sample_time
    it = iter(frames)
    pending = next(it, None)
    if pending is None:
        return 0
    t0 = pending[0] if start is None else start
    on_frame = runner.on_frame  # bound once: this loop runs per frame
    k = 1
    n = 0
    while pending is not None:
        now = t0 + k * dt
        while pending is not None and pending[0] <= now:
            on_frame(pending[0], pending[1], pending[2])
            pending = next(it, None)
        if on_frames is not None:
            on_frames(now, runner.run(now))
        else:
            runner.cycle(now)
        if on_cycle is not None:
            on_cycle(now, runner.estimates)
        n += 1
        k += 1
    return n
