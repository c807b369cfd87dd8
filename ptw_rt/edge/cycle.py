"""The one cycle shared by the daemon, replay, evaluation and the demo.

    frames (since the last cycle) -> InputTracker -> Sample -> Estimator.step -> Estimates

What differs between uses is only where frames come from, what clocks the cycle
(the monotonic clock, or the log's time stamps) and where the outputs go.
`drive_log` is the log-clocked driver (replay, evaluation): a cycle every
`sample_time` of log time; the frames stamped up to a cycle's time belong to it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from ptw_rt.core.estimator import Estimator
from ptw_rt.core.layout import S_INPUT_REASONS, new_estimates, new_sample
from ptw_rt.design.file import load_design
from ptw_rt.edge.inputs import InputTracker
from ptw_rt.io.dbc import FrameCodec
from ptw_rt.paths import DEFAULT_DBC, DEFAULT_DESIGN
from ptw_rt.settings import Settings, load_settings


class CycleRunner:
    """Input tracking + estimator with preallocated Sample and Estimates."""

    def __init__(self, settings: Settings, estimator: Estimator, codec: FrameCodec) -> None:
        self.settings = settings
        self.estimator = estimator
        self.codec = codec
        self.tracker = InputTracker(codec, stale_after_periods=settings.runtime.stale_after_periods)
        self.sample = new_sample()
        self.estimates = new_estimates()
        self.sample_time = estimator.sample_time
        self.cycles = 0

    def on_frame(self, timestamp: float, frame_id: int, data: bytes, extended: bool = False) -> None:
        self.tracker.on_frame(timestamp, frame_id, data, extended=extended)

    def cycle(self, now: float, extra_reasons: int = 0) -> np.ndarray:
        """Close the cycle at `now`: Sample from the frames seen since the last one, one step.

        `extra_reasons` are REASON_* bits of the runtime itself (overrun, send failure).
        Returns the (reused) Estimates array.
        """
        self.tracker.fill(self.sample, now)
        if extra_reasons:
            self.sample[S_INPUT_REASONS] = int(self.sample[S_INPUT_REASONS]) | extra_reasons
        self.estimator.step(self.sample, self.estimates)
        self.cycles += 1
        return self.estimates


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
    on_cycle: Callable[[float, np.ndarray], None],
    *,
    start: float | None = None,
) -> int:
    """Run `runner` over time-ordered (timestamp, id, data) frames, clocked by their stamps.

    The first cycle is one sample time after `start` (default: the first frame's stamp);
    cycles continue until the last frame has been consumed. Returns the number of cycles.
    """
    dt = runner.sample_time
    it = iter(frames)
    pending = next(it, None)
    if pending is None:
        return 0
    t0 = pending[0] if start is None else start
    on_frame = runner.on_frame  # bound once: this loop runs per frame
    cycle = runner.cycle
    k = 1
    n = 0
    while pending is not None:
        now = t0 + k * dt
        while pending is not None and pending[0] <= now:
            on_frame(pending[0], pending[1], pending[2])
            pending = next(it, None)
        on_cycle(now, cycle(now))
        n += 1
        k += 1
    return n
