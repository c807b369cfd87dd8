"""`ptw-rt bench`: speed figures measured in one run on this machine, printed as one JSON object.

- step_us: the jitted estimator step called from Python (as the daemon calls it), p50/p99, and the
  same code in a second process with NUMBA_DISABLE_JIT=1 (the ratio is what numba buys);
- cycle_cpu_us: one daemon cycle's CPU work: decode the cycle's frames, condition, step, encode
  the outputs;
- replay_x_realtime: a recorded ride replayed through the shared cycle (decode, step, encode), frames
  pre-read in memory, one log on one core and several logs on all cores;
- replay_command_x_realtime: the real command, `ptw-rt replay LOG --out OUT` (and with `--csv`) as a user runs
  it, on a 20-minute candump log on disk (ten 120 s rides back to back), wall clock from process start,
  numba cache warm; replay_startup_s: the same command on a 1 s log (imports, cache load, design);
- replay_core_x_realtime: the replay work of that command alone (`replay_log` in this process, runner
  built: read, decode, step, encode, write);
- start_s: process start to the first completed cycle, numba cache cold and warm;
- rss_mb: peak resident memory of the warm-start process (started as `ptw-rt run` starts: MF4 support deferred).
- jitter_us / latency_us / input_to_output_us: the real daemon loop on python-can's virtual bus for
  30 s, idle and with one busy process per core beside it (`measure_loop`).
"""

from __future__ import annotations

import gc
import json
import math
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from ptw_rt.paths import DEFAULT_CONFIG

ROOT = Path(__file__).resolve().parent.parent


def _percentiles(samples_ns: np.ndarray) -> dict:
    us = samples_ns / 1000.0
    return {"p50": round(float(np.percentile(us, 50)), 2), "p99": round(float(np.percentile(us, 99)), 2)}


def _riding_frames(seconds: float = 20.0):
    from ptw_rt.edge.cycle import build_runner
    from ptw_rt.sim.recording import encode_frames
    from ptw_rt.sim.ride import simulate

    ride = simulate("dlc_100", duration=seconds)
    runner = build_runner(DEFAULT_CONFIG)
    return ride, list(encode_frames(ride, runner.codec))


def measure_step(n: int) -> dict:
    """Per-call time of Estimator.step on a realistic stream of Samples (run in this process)."""
    from ptw_rt.core.layout import new_estimates
    from ptw_rt.edge.cycle import build_runner, drive_log

    ride, frames = _riding_frames(12.0)
    runner = build_runner(DEFAULT_CONFIG)
    samples = []
    drive_log(frames, runner, lambda now, e: samples.append(runner.sample.copy()), start=ride.epoch)
    est = runner.estimator
    out = new_estimates()
    est.reset()
    for s in samples[:50]:
        est.step(s, out)  # compile / warm up
    times = np.empty(n, dtype=np.int64)
    m = len(samples)
    clock = time.perf_counter_ns
    for k in range(n):
        s = samples[k % m]
        t0 = clock()
        est.step(s, out)
        times[k] = clock() - t0
    return _percentiles(times)


def _step_in_subprocess(n: int, disable_jit: bool) -> dict:
    env = dict(os.environ)
    if disable_jit:
        env["NUMBA_DISABLE_JIT"] = "1"
    code = f"import json; from ptw_rt.apps.bench import measure_step; print(json.dumps(measure_step({n})))"
    p = subprocess.run([sys.executable, "-c", code], env=env, cwd=ROOT, capture_output=True, text=True, check=True)
    return json.loads(p.stdout.strip().splitlines()[-1])


def measure_cycle(n_cycles: int = 2000) -> dict:
    """decode + step + encode of one cycle's frames (the daemon's CPU work per cycle, I/O excluded): ``run``."""
    from ptw_rt.edge.cycle import build_runner

    ride, frames = _riding_frames(12.0)
    runner = build_runner(DEFAULT_CONFIG)
    dt = runner.sample_time
    t_next = frames[0][0] + dt
    i = 0
    times = []
    clock = time.perf_counter_ns
    while i < len(frames) and len(times) < n_cycles:
        t0 = clock()
        while i < len(frames) and frames[i][0] <= t_next:
            runner.on_frame(frames[i][0], frames[i][1], frames[i][2])
            i += 1
        runner.run(t_next)
        times.append(clock() - t0)
        t_next += dt
    return _percentiles(np.asarray(times[100:], dtype=np.int64))


def _replay_one(seconds: float) -> tuple[float, float]:
    """(ride seconds, wall seconds) of replaying one simulated log through the whole cycle (decode, step, encode)."""
    from ptw_rt.edge.cycle import build_runner, drive_log

    ride, frames = _riding_frames(seconds)
    runner = build_runner(DEFAULT_CONFIG)
    drive_log(frames[:200], runner, on_frames=lambda now, out: None, start=ride.epoch)  # warm
    runner = build_runner(DEFAULT_CONFIG)
    t0 = time.perf_counter()
    drive_log(frames, runner, on_frames=lambda now, out: None, start=ride.epoch)
    return ride.duration, time.perf_counter() - t0


def _long_log(directory: Path, copies: int = 10) -> tuple[Path, float]:
    """A candump log of `copies` 120 s rides (handling_40_120) back to back, time stamps continuous; its length."""
    from ptw_rt.sim.recording import write_ride
    from ptw_rt.sim.ride import simulate

    one = write_ride(simulate("handling_40_120"), directory)["log"]
    lines = one.read_text().splitlines()
    stamps = [float(line[1 : line.index(")")]) for line in (lines[0], lines[-1])]
    span = stamps[1] - stamps[0] + 0.01
    path = directory / "twenty_minutes.log"
    with open(path, "w") as fh:
        for k in range(copies):
            for line in lines:
                i = line.index(")")
                fh.write(f"({float(line[1:i]) + k * span:.6f}){line[i + 1 :]}\n")
    tiny = directory / "one_second.log"
    tiny.write_text("\n".join(line for line in lines if float(line[1 : line.index(")")]) < stamps[0] + 1.0) + "\n")
    return path, copies * span


def measure_replay_command() -> dict:
    """The whole `ptw-rt replay` command on a 20-minute log, wall from process start; start-up alone; the work."""
    from ptw_rt.apps.replay import replay_log
    from ptw_rt.edge.cycle import build_runner

    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        log, seconds = _long_log(d)
        command = [sys.executable, "-m", "ptw_rt", "replay", str(log), "--out", str(d / "out.log"), "--no-progress"]

        def wall(args) -> float:
            t0 = time.perf_counter()
            subprocess.run(args, cwd=ROOT, capture_output=True, check=True)
            return time.perf_counter() - t0

        tiny = command[:4] + [str(d / "one_second.log")] + command[5:]
        wall(tiny)  # the numba cache warm
        startup = statistics.median(wall(tiny) for _ in range(3))
        plain = statistics.median(wall(command) for _ in range(3))
        with_csv = wall(command + ["--csv", str(d / "out.csv")])
        # the work alone, as the command does it: compiled code loaded (a 1 s log first), the collector frozen
        replay_log(d / "one_second.log", d / "warm.log", None, runner=build_runner(DEFAULT_CONFIG))
        gc.freeze()
        runner = build_runner(DEFAULT_CONFIG)
        t0 = time.perf_counter()
        replay_log(log, d / "core.log", None, runner=runner)
        core = time.perf_counter() - t0
    return {
        "replay_command_x_realtime": {
            "out_only": round(seconds / plain, 1),
            "with_csv": round(seconds / with_csv, 1),
            "wall_s": round(plain, 2),
            "log_s": round(seconds, 1),
            "note": "ptw-rt replay on a 20-min candump file, wall clock from process start, cache warm, "
            "median of 3 (with_csv: one run)",
        },
        "replay_startup_s": round(startup, 2),
        "replay_core_x_realtime": round(seconds / core, 1),
    }


# A child's own peak resident memory, printed by it: VmHWM of the memory map exec gave it. Not ru_maxrss: Linux
# keeps that across fork and exec, so a child of a bench that holds 400 MB reports at least 400 MB.
PEAK_RSS_MB = "next(int(line.split()[1]) for line in open('/proc/self/status') if line.startswith('VmHWM:')) / 1024"


def measure_start(cache_dir: str) -> dict:
    code = (
        "import time, json; t0 = time.perf_counter();"
        # as `ptw-rt run` starts: the command line defers python-can's MF4 support (asammdf, pandas)
        "from ptw_rt import _deferred_imports; _deferred_imports.install();"
        "from ptw_rt.edge.cycle import build_runner;"
        f"r = build_runner({str(DEFAULT_CONFIG)!r}); r.cycle(0.01);"
        "print(json.dumps({'start_s': time.perf_counter() - t0,"
        " 'rss_mb': " + PEAK_RSS_MB + "}))"
    )
    env = dict(os.environ, NUMBA_CACHE_DIR=cache_dir)
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-c", code], env=env, cwd=ROOT, capture_output=True, text=True, check=True)
    wall = time.perf_counter() - t0
    inner = json.loads(p.stdout.strip().splitlines()[-1])
    return {
        "start_s": round(wall, 3),
        "after_import_s": round(inner["start_s"], 3),
        "rss_mb": round(inner["rss_mb"], 1),
    }


def measure_loop(seconds: float, hogs: int = 0) -> dict:
    """The real daemon loop on python-can's virtual bus, fed a ride in real time, `hogs` busy processes beside.

    jitter_us: |period - 10 ms| of the loop's wake-ups; latency_us: cycle start -> its EST_Roll frame received
    by a listener on the bus; input_to_output_us: newest IMU_Rates frame sent -> that cycle's EST_Roll received
    (includes the up-to-one-period wait of a fixed-step loop for asynchronous inputs).
    """
    import threading

    import can

    from ptw_rt.service.daemon import Daemon, load_daemon_settings
    from ptw_rt.service.realtime import apply_realtime
    from ptw_rt.settings import RealtimeSettings

    channel = f"ptw-rt-bench-{os.getpid()}-{hogs}"
    with tempfile.TemporaryDirectory() as tmp:
        # as ptw-rt.service runs it: SCHED_FIFO 40 (applied if this process may, else a warning in the result)
        realtime = RealtimeSettings(priority=40, cpus=None, lock_memory=False)
        overrides = {"interface": "virtual", "channel": channel, "state_file": str(Path(tmp) / "state.json")}
        settings = load_daemon_settings(DEFAULT_CONFIG, {**overrides, "realtime": realtime})
        daemon = Daemon(settings, DEFAULT_CONFIG)
        ride, frames = _riding_frames(seconds + 2.0)
        imu_id = daemon.codec.frame_id("IMU_Rates")
        roll_id = daemon.codec.frame_id("EST_Roll")
        cycle_times: list[float] = []
        daemon.on_cycle = lambda now, est: cycle_times.append(now)
        sent_imu: list[float] = []
        received: list[float] = []
        stop = threading.Event()

        def play() -> None:
            apply_realtime(MEASUREMENT_PRIORITY, None, False)  # not permitted: a warning, figures include its delay
            bus = can.Bus(interface="virtual", channel=channel)
            t0 = time.monotonic() + 0.05
            base = frames[0][0]
            for ts, fid, data in frames:
                if stop.is_set():
                    break
                delay = t0 + (ts - base) - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                bus.send(can.Message(arbitration_id=fid, data=data, is_extended_id=False))
                if fid == imu_id:
                    sent_imu.append(time.monotonic())
            bus.shutdown()

        def listen() -> None:
            apply_realtime(MEASUREMENT_PRIORITY, None, False)  # not permitted: a warning, figures include its delay
            bus = can.Bus(interface="virtual", channel=channel)
            while not stop.is_set():
                msg = bus.recv(timeout=0.1)
                if msg is not None and msg.arbitration_id == roll_id:
                    received.append(time.monotonic())
            bus.shutdown()

        # the hogs are ordinary processes whatever this one runs at (started under chrt, they would inherit SCHED_FIFO
        # and starve everything)
        procs = [subprocess.Popen([sys.executable, "-c", HOG], start_new_session=True) for _ in range(hogs)]
        try:
            threads = [threading.Thread(target=f, daemon=True) for f in (listen, play)]
            for th in threads:
                th.start()
            daemon.run(seconds)
        finally:
            stop.set()
            for p in procs:
                p.kill()
                p.wait()
        for th in threads:
            th.join(timeout=2.0)
    now = np.asarray(cycle_times)
    periods = np.diff(now)
    jitter = np.abs(periods - daemon.dt) * 1e6
    n = min(len(now), len(received))
    latency = (np.asarray(received[:n]) - now[:n]) * 1e6
    imu = np.asarray(sent_imu)
    idx = np.searchsorted(imu, now[:n], side="right") - 1
    ok = idx >= 0
    in_out = (np.asarray(received[:n])[ok] - imu[idx[ok]]) * 1e6

    def pct(a: np.ndarray, with_max: bool = False) -> dict:
        out = {"p50": round(float(np.percentile(a, 50)), 1), "p99": round(float(np.percentile(a, 99)), 1)}
        if with_max:
            out["max"] = round(float(np.max(a)), 1)
        return out

    return {
        "jitter_us": pct(jitter, with_max=True),
        "latency_us": pct(latency[10:]),
        "input_to_output_us": pct(in_out[10:]),
        "overruns": daemon.overruns,
        "sched_fifo": not daemon.realtime_warnings,  # only SCHED_FIFO was asked for
    }


HOG = "import os\nos.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))\nwhile True: pass"
MEASUREMENT_PRIORITY = 41  # the sensor player and the listener stand for other CAN nodes: not starved by the hogs


def run_bench(args) -> int:
    quick = bool(getattr(args, "quick", False))
    n_step = 5000 if quick else 50000
    jit = measure_step(n_step)
    nojit = _step_in_subprocess(200 if quick else 1000, disable_jit=True)
    with tempfile.TemporaryDirectory() as cache:
        cold = measure_start(cache)
        warm = measure_start(cache)
    seconds = 20.0 if quick else 60.0
    ride_s, wall = _replay_one(seconds)
    n_logs = max(2, os.cpu_count() or 1)
    with ProcessPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
        parts = list(pool.map(_replay_one, [seconds] * n_logs))
    # workers replay concurrently: the slowest one's replay time is the wall time of the batch
    wall_many = max(p[1] for p in parts) * math.ceil(n_logs / (os.cpu_count() or 1))
    result = {
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "machine": {
            "cpu": platform.processor() or platform.machine(),
            "cores": os.cpu_count(),
            "python": sys.version.split()[0],
        },
        "step_us": {"jit": jit, "no_jit": nojit, "ratio_p50": round(nojit["p50"] / jit["p50"], 1)},
        "cycle_cpu_us": measure_cycle(1000 if quick else 5000),
        "replay_x_realtime": {
            "one_log": round(ride_s / wall, 1),
            "many_logs": round(sum(p[0] for p in parts) / wall_many, 1),
            "logs": n_logs,
            "note": "frames pre-encoded in memory: decode, step and encode, no file I/O",
        },
        **measure_replay_command(),
        "start_s": {"cold": cold["start_s"], "warm": warm["start_s"]},
        "rss_mb": warm["rss_mb"],
    }
    loop_s = 10.0 if quick else 30.0
    idle = measure_loop(loop_s, hogs=0)
    loaded = measure_loop(loop_s, hogs=os.cpu_count() or 1)
    result["jitter_us"] = {"idle": idle["jitter_us"], "cpu_hog": loaded["jitter_us"], "seconds": loop_s}
    result["latency_us"] = {"idle": idle["latency_us"], "cpu_hog": loaded["latency_us"]}
    result["input_to_output_us"] = {"idle": idle["input_to_output_us"], "cpu_hog": loaded["input_to_output_us"]}
    result["loop_overruns"] = {"idle": idle["overruns"], "cpu_hog": loaded["overruns"]}
    result["loop_sched_fifo"] = loaded["sched_fifo"]
    print(json.dumps(result, indent=None if args.json else 2))
    return 0
