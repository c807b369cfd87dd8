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
backwards) ends a segment and the next starts from reset inputs. It runs the whole cycle of every frame and
cycle of a block of frames in one compiled loop (``ptw_rt.edge.drive``) on the same state and the same compiled
functions as ``CycleRunner.run``; `frame_blocks` decodes the frames per message identifier at once.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ptw_rt.core.estimator import Estimator
from ptw_rt.core.layout import E_MODE, MODE_CONVERGING, MODE_DEGRADED, MODE_VALID, new_estimates, new_sample
from ptw_rt.design.file import load_design_for
from ptw_rt.edge import drive as dr
from ptw_rt.edge import tracking as tr
from ptw_rt.edge.inputs import InputTracker
from ptw_rt.edge.outputs import OutputEncoder
from ptw_rt.io.candump import payload_rows
from ptw_rt.io.dbc import FrameCodec, FrameDecodeError
from ptw_rt.paths import DEFAULT_DBC, design_file_for
from ptw_rt.settings import Settings, load_settings

Frame = tuple[int, bytes]

_DEGRADABLE = (float(MODE_CONVERGING), float(MODE_VALID))
DEFAULT_MAX_GAP_S = 5.0  # drive_log: a longer gap in a log's time stamps ends a segment
DEFAULT_REORDER_TOLERANCE_S = 0.02  # drive_log: frames up to this much out of order are taken as they come
BLOCK_FRAMES = 32768  # frames decoded at once (drive_log)
BLOCK_CYCLES = 4096  # cycles the compiled loop writes before its outputs are handed on
_BYTES_TYPES = (bytes, bytearray)


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

    def warm_up(self) -> None:
        """Load (or compile) every compiled function of the live cycle, as the daemon calls them, before a
        deadline matters: a frame, a source without counter, a decode error, an unknown id, a cycle with all its
        frames and a last status frame. The inputs, the output counters and the estimator are as before (its
        state reset, as ``Estimator.reset``)."""
        tracker_state, encoder_state = self.tracker.state.copy(), self.encoder.state.copy()
        sample, estimates = self.sample.copy(), self.estimates.copy()
        layout = self.tracker.layouts[0]
        self.tracker.on_frame(0.0, layout.frame_id, bytes(layout.length))
        self.tracker.on_values(self.tracker.layouts[-1].name, 0.0, {})
        self.tracker.decode_error(layout.name)
        self.tracker.on_frame(0.0, -1, b"")
        self.tracker.restart()
        self.tracker.fill(sample, 0.0)
        self.estimator.step(sample, estimates)
        self.estimator.reset()
        self.encoder.frames(estimates, 0, self.status, 0, 0)
        self.encoder.status_frame(estimates, 0, self.status, valid=False)
        self.tracker.state[:] = tracker_state
        self.encoder.state[:] = encoder_state

    def process_figures(self) -> np.ndarray:
        """[degraded, reasons, overrun count, cycle time us] of the process, for the compiled loop."""
        return np.array(
            [
                1.0 if self.process_degraded else 0.0,
                float(self.process_reasons),
                float(int(self.status.get("overrun_count", 0))),
                float(int(self.status.get("cycle_time_us", 0))),
            ]
        )

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
    design = load_design_for(settings, design_file or design_file_for(config), config)
    return CycleRunner(settings, Estimator(settings, design), FrameCodec(dbc))


# What `shared_runner` loaded in this process: {(config, design file, DBC identities): (settings, design, codec)}
_LOADED: dict[tuple, tuple] = {}


def _identity(path: Path) -> tuple:
    """A file as `shared_runner` knows it: a file changed or replaced since it was loaded is another file."""
    st = path.stat()
    return (str(path.resolve()), st.st_size, st.st_mtime_ns, st.st_ino)


def shared_runner(
    config: str | Path, design_file: str | Path | None = None, dbc: str | Path = DEFAULT_DBC
) -> CycleRunner:
    """`build_runner` for a process that runs many logs or rides (a replay or evaluation worker): the config, the
    design file and the DBC are loaded and checked once per process, not per log. Parsing them costs ~60 ms (YAML
    ~19, design file ~19, DBC ~24 ms, measured 2026-11-29) against ~1.3 ms for a runner built from them: 2000
    listed logs that did not exist took 63 s. Every call still returns a runner of its own (estimator, input
    tracker and output counters from nothing, as `build_runner`'s), so a log's result never depends on what the
    process ran before it. Keyed by the three files' identities (path, size, mtime, inode): a file changed
    during the run is loaded again; one that cannot be read is left to `build_runner` to report."""
    design_path = Path(design_file) if design_file else design_file_for(config)
    try:
        key = (_identity(Path(config)), _identity(design_path), _identity(Path(dbc)))
    except OSError:
        return build_runner(config, design_file, dbc)
    parts = _LOADED.get(key)
    if parts is None:  # loaded and checked as `build_runner` does: one way in, the same errors
        runner = build_runner(config, design_path, dbc)
        _LOADED.clear()  # one run's files: a process keeps at most one set
        _LOADED[key] = (runner.settings, runner.estimator.design, runner.codec)
        return runner
    settings, design, codec = parts
    return CycleRunner(settings, Estimator(settings, design), codec)


@dataclass(frozen=True)
class SegmentBreak:
    """Where `drive_log` ended a segment: the log's clock jumped forward by more than ``max_gap`` ("gap") or
    back by more than ``reorder_tolerance`` ("backwards")."""

    kind: str  # "gap" or "backwards"
    t_from: float  # newest stamp of the segment that ends
    t_to: float  # stamp of the first frame of the next segment
    segment: int  # number of the segment that starts here (2, 3, ...)
    cycles_before: int  # cycles driven before it (all segments)
    frame: int = -1  # index of the frame that starts it among the frames driven (from 0)

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


class Block(NamedTuple):
    """Frames decoded for the compiled loop: stamp, what happened to each (``drive.FRAME_*``), its input index
    and its signal values (DBC order, ``tracking.MAX_SIGNALS`` columns)."""

    times: np.ndarray
    kinds: np.ndarray
    inputs: np.ndarray
    values: np.ndarray
    offset: int = 0  # index of its first frame among all the frames of the source


def decode_block(
    tracker: InputTracker,
    times: np.ndarray,
    ids: np.ndarray,
    lengths: np.ndarray,
    data: np.ndarray,
    offset: int = 0,
) -> Block:
    """A block from arrays of standard-identifier frames: stamps, identifiers, DLCs and ``uint8[n, 8]`` bytes
    (zero-padded). Each input message's frames are decoded at once (``MessageLayout.unpack_many``)."""
    n = times.shape[0]
    kinds = np.full(n, dr.FRAME_UNKNOWN, dtype=np.int64)
    inputs = np.zeros(n, dtype=np.int64)
    values = np.zeros((n, tr.MAX_SIGNALS))
    for k, layout in enumerate(tracker.layouts):
        if layout.message.is_extended_frame:
            continue
        mine = ids == layout.frame_id
        if not mine.any():
            continue
        inputs[mine] = k
        kinds[mine] = dr.FRAME_UNDECODABLE
        rows = np.flatnonzero(mine & (lengths == layout.length))
        if rows.size:
            decoded, ok = layout.unpack_many(data[rows])
            good = rows[ok]
            kinds[good] = dr.FRAME_OK
            values[good, : decoded.shape[1]] = decoded[ok]
    return Block(times, kinds, inputs, values, offset)


def frame_blocks(
    frames: Iterable[tuple[float, int, bytes]], tracker: InputTracker, size: int = BLOCK_FRAMES
) -> Iterator[Block]:
    """``(timestamp, id, data)`` frames (standard identifiers) in blocks of ``size``, decoded. A frame whose id
    or data is not a plain int and bytes takes the codec's own checks, as ``InputTracker.on_frame`` does."""
    it = iter(frames)
    offset = 0
    while True:
        times: list[float] = []
        ids: list[int] = []
        chunks: list[bytes] = []
        exotic: list[tuple[int, object, object]] = []
        for timestamp, frame_id, data in it:
            pos = len(times)
            times.append(timestamp)
            if type(frame_id) is int and type(data) in _BYTES_TYPES and len(data) <= 8:
                ids.append(frame_id)
                chunks.append(data)
            else:
                ids.append(-1)
                chunks.append(b"")
                exotic.append((pos, frame_id, data))
            if pos + 1 == size:
                break
        if not times:
            return
        lengths = np.fromiter(map(len, chunks), dtype=np.int64, count=len(chunks))
        data = payload_rows(chunks)
        block = decode_block(
            tracker, np.array(times, dtype=float), np.array(ids, dtype=np.int64), lengths, data, offset
        )
        offset += len(times)
        for pos, frame_id, data_ in exotic:
            _decode_exotic(tracker, block, pos, frame_id, data_)
        yield block
        if len(times) < size:
            return


def _decode_exotic(tracker: InputTracker, block: Block, pos: int, frame_id: object, data: object) -> None:
    plan = tracker.input_of(frame_id)
    if plan is None:
        return  # FRAME_UNKNOWN already
    k, _layout = plan
    block.inputs[pos] = k
    try:
        decoded = list(tracker.codec.decode(frame_id, data)[1].values())
    except FrameDecodeError:
        block.kinds[pos] = dr.FRAME_UNDECODABLE
        return
    block.kinds[pos] = dr.FRAME_OK
    block.values[pos, : len(decoded)] = decoded


class Chunk(NamedTuple):
    """What one call of the compiled loop produced: ``cycles`` cycles (their times and Estimates rows) and
    their frames (``frame_end[c]``: one past cycle c's last frame row; ``messages``: plan index; ``words``)."""

    times: np.ndarray
    samples: np.ndarray  # what each cycle's step received
    estimates: np.ndarray
    frame_end: np.ndarray
    messages: np.ndarray
    words: np.ndarray
    values: np.ndarray

    @property
    def cycles(self) -> int:
        return self.times.shape[0]

    def frames(self, encoder: OutputEncoder, c: int) -> list[Frame]:
        """The ``(frame id, data)`` of cycle ``c`` of the chunk."""
        first = int(self.frame_end[c - 1]) if c else 0
        last = int(self.frame_end[c])
        return [encoder.frame(int(self.messages[i]), int(self.words[i]), self.values[i]) for i in range(first, last)]


def drive_blocks(
    blocks: Iterable[Block],
    runner: CycleRunner,
    on_chunk: Callable[[Chunk], None],
    *,
    start: float | None = None,
    max_gap: float = DEFAULT_MAX_GAP_S,
    reorder_tolerance: float = DEFAULT_REORDER_TOLERANCE_S,
    on_segment: Callable[[SegmentBreak], None] | None = None,
    stats: DriveStats | None = None,
    capacity: int = BLOCK_CYCLES,
) -> int:
    """`drive_log` on decoded blocks: ``on_chunk(Chunk)`` after every call of the compiled loop (its buffers are
    reused: copy what must outlive the call). Returns the number of cycles."""
    if not max_gap > 0.0:
        raise ValueError(f"max_gap must be > 0, got {max_gap!r}")
    stats = stats if stats is not None else DriveStats()
    it = iter(blocks)
    block = next(it, None)
    while block is not None and block.times.shape[0] == 0:
        block = next(it, None)
    if block is None:
        return 0
    dt = runner.sample_time
    t0 = float(block.times[0]) if start is None else float(start)
    state = dr.initial_state(t0, dt, runner.cycles)
    cycles0 = runner.cycles
    out = dr.Outputs(capacity)
    tracker, encoder = runner.tracker, runner.encoder
    s, si, t, ti = runner.estimator.buffers()
    process = runner.process_figures()
    stats.segments = 1
    while block is not None:
        following = next(it, None)
        while following is not None and following.times.shape[0] == 0:
            following = next(it, None)
        position = 0
        while True:
            result = dr.drive_block(
                state, dt, max_gap, reorder_tolerance,
                block.times, block.kinds, block.inputs, block.values, position, following is None,
                tracker.state, tracker.params, runner.sample, runner.estimates, s, si, t, ti,
                encoder.plan, encoder.state, process,
                out.cycle_times, out.samples, out.estimates, out.frame_end, out.messages, out.words, out.values,
                out.counts,
            )  # fmt: skip
            position, c, f = (int(x) for x in out.counts)
            runner.cycles = int(state[dr.DR_CYCLES])
            if c:
                on_chunk(
                    Chunk(
                        out.cycle_times[:c], out.samples[:c], out.estimates[:c], out.frame_end[:c], out.messages[:f],
                        out.words[:f],
                        out.values[:f],
                    )
                )  # fmt: skip
            if result == dr.BREAK:
                segments = int(state[dr.DR_SEGMENTS])
                brk = SegmentBreak(
                    "backwards" if state[dr.DR_BREAK_KIND] else "gap",
                    float(state[dr.DR_BREAK_FROM]),
                    float(state[dr.DR_BREAK_TO]),
                    segments,
                    int(state[dr.DR_BREAK_CYCLES]) - cycles0,
                    block.offset + position,
                )
                if len(stats.breaks) < MAX_BREAKS_KEPT:
                    stats.breaks.append(brk)
                if on_segment is not None:
                    on_segment(brk)
                runner.restart_segment()
            elif result == dr.DONE:
                break
        block = following
    stats.segments = int(state[dr.DR_SEGMENTS])
    stats.late_frames += int(state[dr.DR_LATE_FRAMES])
    stats.bad_stamps += int(state[dr.DR_BAD_STAMPS])
    return runner.cycles - cycles0


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
      ``on_frames(now, output frames)`` (if given) and then ``on_cycle(now, Estimates)``; both are called after
      the compiled loop has run a chunk of cycles, in cycle order (the Estimates given are a row of the chunk,
      ``runner.sample`` holds the Sample that cycle's step received).
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
    * A frame with a non-finite stamp is dropped and counted in ``stats.bad_stamps``.

    A ``max_gap`` that is not > 0 is a ValueError (``drive_blocks``), before any frame is read.
    """
    encoder = runner.encoder

    def on_chunk(chunk: Chunk) -> None:
        if on_frames is None and on_cycle is None:
            return
        sample = runner.sample
        for c, now in enumerate(chunk.times.tolist()):
            sample[:] = chunk.samples[c]  # in the callbacks, the runner's Sample is the cycle's, as in a live cycle
            if on_frames is not None:
                on_frames(now, chunk.frames(encoder, c))
            if on_cycle is not None:
                on_cycle(now, chunk.estimates[c])

    return drive_blocks(
        frame_blocks(frames, runner.tracker),
        runner,
        on_chunk,
        start=start,
        max_gap=max_gap,
        reorder_tolerance=reorder_tolerance,
        on_segment=on_segment,
        stats=stats,
    )
