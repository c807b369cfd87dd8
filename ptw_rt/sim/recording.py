"""Writing a ride: candump ``-L`` log (frames from the DBC), truth CSV at 100 Hz, a small JSON sidecar.

Files for ``write_ride(ride, DIR)``:

* ``DIR/NAME.log``        candump -L, channel vcan0, time stamps = ride.epoch + sim time (microseconds)
* ``DIR/NAME.truth.csv``  header row, SI units, columns ``ride.TRUTH_COLUMNS`` (contract columns first)
* ``DIR/NAME.meta.json``  scenario, seed, perturbation, sensor biases/offsets, injected faults

Fault frames: ``raw`` payloads are written as they are; a ``dlc`` override cuts the encoded payload
or pads it with zero bytes; silent periods are simply absent from the log.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Iterable
from dataclasses import asdict
from pathlib import Path

import numpy as np

from ptw_rt.errors import output_error
from ptw_rt.io.candump import CandumpWriter
from ptw_rt.io.dbc import FrameCodec
from ptw_rt.paths import DEFAULT_DBC
from ptw_rt.sim.ride import TRUTH_COLUMNS, TRUTH_UNITS, Ride
from ptw_rt.sim.sensors import SensorFrame
from ptw_rt.untrusted import check_output_file

DEFAULT_CHANNEL = "vcan0"


def frame_payload(codec: FrameCodec, frame: SensorFrame) -> tuple[int, bytes]:
    """(CAN id, payload) of one sensor frame, faults applied."""
    fid = codec.frame_id(frame.message)
    if frame.raw is not None:
        data = bytes(frame.raw)
    else:
        assert frame.signals is not None
        fid, data = codec.encode(frame.message, frame.signals, counter=frame.counter)
    if frame.dlc is not None:
        data = data[: frame.dlc] if frame.dlc <= len(data) else data + bytes(frame.dlc - len(data))
    return fid, data


def encode_frames(ride: Ride, codec: FrameCodec | None = None) -> Iterable[tuple[float, int, bytes]]:
    """(absolute time stamp, CAN id, payload) of every frame, in time order."""
    codec = codec or FrameCodec(DEFAULT_DBC)
    for frame in ride.frames():
        fid, data = frame_payload(codec, frame)
        yield ride.epoch + frame.t, fid, data


def write_log(
    ride: Ride,
    path: str | Path,
    *,
    codec: FrameCodec | None = None,
    channel: str = DEFAULT_CHANNEL,
    progress=None,
) -> int:
    """Write the ride's frames as a candump -L log; returns the number of frames written."""
    codec = codec or FrameCodec(DEFAULT_DBC)
    total = max(1, ride.n_frames())
    n = 0
    with CandumpWriter(path, channel=channel) as w:
        for ts, fid, data in encode_frames(ride, codec):
            # round to the microsecond here so the printed stamp is exactly ride.epoch + t
            w.write(round(ts, 6), fid, data)
            n += 1
            if progress is not None and n % 5000 == 0:
                progress(n / total)
    if progress is not None:
        progress(1.0)
    return n


def write_truth_csv(ride: Ride, path: str | Path) -> None:
    """Truth at 100 Hz: header row of column names, SI units (see TRUTH_UNITS), full float precision."""
    cols = [ride.truth[c] for c in TRUTH_COLUMNS]
    data = np.column_stack(cols)
    with open(path, "w", newline="", encoding="ascii") as fh:
        wr = csv.writer(fh, lineterminator="\n")
        wr.writerow(TRUTH_COLUMNS)
        for row in data:
            wr.writerow([f"{v:.9g}" for v in row])


def read_truth_csv(path: str | Path) -> dict[str, np.ndarray]:
    with open(path, newline="", encoding="ascii") as fh:
        rd = csv.reader(fh)
        header = next(rd)
        rows = np.array([[float(v) for v in r] for r in rd])
    return {name: rows[:, i] for i, name in enumerate(header)}


def ride_metadata(ride: Ride) -> dict[str, object]:
    return {
        "scenario": ride.scenario,
        "description": ride.description,
        "seed": ride.seed,
        "duration_s": ride.duration,
        "epoch_s": ride.epoch,
        "vehicle": ride.vehicle.as_dict(),
        "perturbation": ride.perturbation.as_dict(),
        "sensors": ride.sensor_meta,
        "faults": [asdict(f) for f in ride.faults],
        "crashed_at_s": ride.crashed_at,
        "truth_units": TRUTH_UNITS,
        "frames": {name: int(len(s.t)) for name, s in ride.streams.items()},
    }


def write_ride(
    ride: Ride,
    out_dir: str | Path,
    name: str | None = None,
    *,
    codec: FrameCodec | None = None,
    channel: str = DEFAULT_CHANNEL,
    progress=None,
) -> dict[str, Path]:
    """Write NAME.log, NAME.truth.csv and NAME.meta.json into out_dir (created if needed); one that cannot be
    written: ``OutputError`` (one line, exit code 74)."""
    out = Path(out_dir)
    name = name or ride.scenario
    paths = {
        "log": out / f"{name}.log",
        "truth": out / f"{name}.truth.csv",
        "meta": out / f"{name}.meta.json",
    }
    try:
        out.mkdir(parents=True, exist_ok=True)
        for path in paths.values():  # a FIFO nobody reads there: the open waited for ever
            check_output_file(path)
        write_log(ride, paths["log"], codec=codec, channel=channel, progress=progress)
        write_truth_csv(ride, paths["truth"])
        meta = ride_metadata(ride)
        paths["meta"].write_text(json.dumps(meta, indent=2, default=_json_default) + "\n", encoding="utf-8")
    except OSError as exc:
        raise output_error(out, exc) from None
    return paths


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, float) and not math.isfinite(o):
        return None
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
