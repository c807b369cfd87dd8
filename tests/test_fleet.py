"""Many logs at once (issue #15, part 3): directory trees and list files, local cores or a Dask cluster, and the
fleet summary. Every output must be byte-identical to the single-process replay of that log, wherever it ran."""

from __future__ import annotations

import contextlib
import csv
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ptw_rt.apps.fleet import FLEET_COLUMNS, ListFileError, read_list_file
from ptw_rt.apps.replay import replay_log
from ptw_rt.errors import UserFacingError
from ptw_rt.paths import DEFAULT_CONFIG

RIDES = (("dlc_50", 6.0, "a"), ("slalom_30", 8.0, "b/c"), ("dlc_100", 5.0, "b"))


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    """A tree of three short rides (one two levels down), a junk file, and each log's single-process replay."""
    from ptw_rt.sim.recording import write_ride
    from ptw_rt.sim.ride import simulate

    base = tmp_path_factory.mktemp("fleet")
    top = base / "rides"
    expected = {}
    for scenario, seconds, sub in RIDES:
        d = top / sub
        d.mkdir(parents=True, exist_ok=True)
        log = write_ride(simulate(scenario, duration=seconds), d)["log"]
        rel = log.relative_to(top)
        ref = base / "reference" / rel
        ref.parent.mkdir(parents=True, exist_ok=True)
        replay_log(log, ref, None, DEFAULT_CONFIG)
        expected[rel] = ref.read_bytes()
    (top / "b" / "junk.log").write_bytes(b"\x00\x01 not a log\n" * 20)
    return base, top, expected


def _cli(args, cwd, extra_env=None):
    return subprocess.run(
        [sys.executable, "-m", "ptw_rt", *map(str, args)],
        cwd=cwd,
        capture_output=True,
        text=True,
        errors="replace",
        timeout=600,
        env={**os.environ, "NUMBA_NUM_THREADS": "1", **(extra_env or {})},
    )


def _check(out: Path, top: Path, expected: dict, proc) -> list[dict]:
    assert proc.returncode == 1, proc.stderr  # one junk log: a partial failure
    for rel, data in expected.items():
        assert (out / rel).read_bytes() == data, rel  # the same bytes as the single-process replay
    junk = top / "b" / "junk.log"
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error: ")]
    names = "candump/ASC/BLF/TRC/CSV/MF4/SQLite/candump -t/python-can text"
    assert errors == [f"error: {junk}: not a CAN log (no {names} frame in the first 64 KiB)"]
    assert "fleet: 3 of 4 logs replayed" in proc.stderr
    with open(out / "fleet.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert tuple(rows[0]) == FLEET_COLUMNS
    by_log = {Path(r["log"]).relative_to(top): r for r in rows}
    assert by_log[Path("b/junk.log")]["status"] == "failed" and "not a CAN log" in by_log[Path("b/junk.log")]["error"]
    for scenario, seconds, sub in RIDES:
        row = by_log[Path(sub) / f"{scenario}.log"]
        assert row["status"] == "ok" and int(row["cycles"]) > 0
        shares = sum(float(row[c]) for c in FLEET_COLUMNS if c.startswith("share_"))
        assert shares == pytest.approx(1.0, abs=1e-3)
        assert float(row["duration_s"]) == pytest.approx(seconds, abs=0.2)
        assert float(row["c_alpha_front"]) > 0 and row["stiffness_valid"] in ("0", "1")
    return rows


def test_a_tree_through_a_two_worker_local_dask_cluster(tree):
    pytest.importorskip("dask.distributed")
    base, top, expected = tree
    out = base / "out_dask"
    proc = _cli(["replay", top, "--out", out, "--dask", "local", "--jobs", "2", "--no-progress"], base)
    _check(out, top, expected, proc)
    summaries = [json.loads(line) for line in proc.stdout.splitlines()]
    assert len(summaries) == 4
    if importlib_available("pyarrow"):
        import pyarrow.parquet as pq

        table = pq.read_table(out / "fleet.parquet")
        assert table.num_rows == 4 and table.column_names == list(FLEET_COLUMNS)


def test_a_list_file_on_local_cores_by_default(tree):
    base, top, expected = tree
    listing = base / "rides.txt"
    rels = sorted(expected, key=str)
    listing.write_text("# this month's rides\n\n" + "\n".join(f"rides/{r}" for r in rels) + "\nrides/b/junk.log\n")
    out = base / "out_list"
    proc = _cli(["replay", "--list", listing, "--out", out, "--no-progress"], base)
    assert proc.returncode == 1, proc.stderr
    for rel, data in expected.items():  # a listed file keeps its name under --out
        assert (out / rel.name).read_bytes() == data
    assert "fleet: 3 of 4 logs replayed" in proc.stderr


def test_the_output_directory_inside_the_tree_is_not_read_back(tree, tmp_path):
    base, top, expected = tree
    copy = tmp_path / "rides"
    shutil.copytree(top, copy)
    (copy / "b" / "junk.log").unlink()
    for _ in range(2):  # the second run must not take the first run's outputs as inputs
        proc = _cli(["replay", copy, "--out", copy / "est", "--no-progress"], tmp_path)
        assert proc.returncode == 0, proc.stderr
        assert "fleet: 3 of 3 logs replayed" in proc.stderr


@pytest.mark.parametrize(
    "content, message",
    [
        ("\n# only comments\n", "names no log"),
        ("a\0b\n", "NUL"),
        (b"\xff\xfe\x00", "UTF-8"),
        # a log given to --list: each frame line was a missing log (3100 error lines, 94 s; fuzzing, 2026-11-26)
        ("(1700000000.000000) can0 100#0A00D3FFEEFF08\n" * 50, "a CAN log \\(candump\\), not a list of logs"),
    ],
)
def test_a_bad_list_file_is_one_line(tmp_path, content, message):
    path = tmp_path / "list.txt"
    path.write_bytes(content.encode() if isinstance(content, str) else content)
    with pytest.raises(ListFileError, match=message):
        read_list_file(path)
    proc = _cli(["replay", "--list", path, "--out", tmp_path / "out"], tmp_path)
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr


def test_dask_without_the_extra_says_so(tree, tmp_path):
    """Without dask installed, --dask is one line naming the extra (exit 2): simulated by hiding the module."""
    base, top, _ = tree
    hide = tmp_path / "hide"
    hide.mkdir()
    (hide / "dask").mkdir()
    (hide / "dask" / "__init__.py").write_text("raise ModuleNotFoundError('No module named dask', name='dask')\n")
    proc = _cli(["replay", top, "--out", tmp_path / "o", "--dask", "local"], tmp_path, {"PYTHONPATH": str(hide)})
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().endswith("needs the 'fleet' extra (dask is not installed): pip install 'ptw-rt[fleet]'")


def importlib_available(name: str) -> bool:
    import importlib.util

    return importlib.util.find_spec(name) is not None


@pytest.mark.parametrize("address", ["not a url", "tcp://", "tcp://127.0.0.1:1"])
def test_a_bad_or_unreachable_scheduler_is_one_line(tree, tmp_path, address):
    pytest.importorskip("dask.distributed")
    base, top, _ = tree
    proc = _cli(["replay", top, "--out", tmp_path / "o", "--dask", address, "--no-progress"], tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and "Dask scheduler" in proc.stderr, proc.stderr


def test_dask_with_one_log_says_it_replays_here(tree, tmp_path):
    """One log needs no cluster: it is replayed in this process, and the option is answered, not ignored."""
    base, top, expected = tree
    rel = next(iter(expected))
    out = tmp_path / "one.log"
    proc = _cli(["replay", top / rel, "--out", out, "--dask", "tcp://127.0.0.1:1", "--no-progress"], tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "replay: one log is replayed in this process" in proc.stderr
    assert out.read_bytes() == expected[rel]


@pytest.mark.parametrize(
    ("reply", "message"),
    [
        (b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n" * 10, "what answered is not a Dask scheduler"),
        (b"", "no Dask scheduler answered within"),
    ],
)
def test_a_server_that_is_not_a_dask_scheduler_is_one_line(monkeypatch, reply, message):
    """An HTTP server sent dask allocating 3 EiB (a traceback); one that accepts and says nothing held the command
    past a minute (dask's timeout is the connection's, not the handshake's)."""
    pytest.importorskip("dask.distributed")
    import socket
    import threading

    from ptw_rt.apps import fleet

    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(4)
    held = []

    def serve():
        while True:
            try:
                conn, _ = server.accept()
            except OSError:
                return
            held.append(conn)
            if reply:
                conn.sendall(reply)

    threading.Thread(target=serve, daemon=True).start()
    monkeypatch.setattr(fleet, "DASK_CONNECT_TIMEOUT_S", 1.0)
    try:
        with pytest.raises(UserFacingError, match=message) as info:
            fleet._dask_client(f"tcp://127.0.0.1:{server.getsockname()[1]}", 1)
        assert "\n" not in str(info.value)
    finally:
        server.close()
        for conn in held:
            conn.close()


def test_the_local_pool_holds_a_bounded_number_of_logs_in_flight(monkeypatch):
    """A list of 200 000 logs submitted at once held every future and its arguments (915 MB at the peak): the
    local pool keeps at most IN_FLIGHT_PER_WORKER per worker submitted and not yet handed back, and every log's
    result still comes back under its own index."""
    from concurrent.futures import Future

    from ptw_rt import parallel
    from ptw_rt.apps import fleet

    count = {"submitted": 0, "handed_back": 0, "peak": 0}

    class RecordingPool:  # runs each job at once, in this process; counts what is in flight
        def __init__(self, max_workers):
            self.max_workers = max_workers

        def shutdown(self, wait=True, cancel_futures=False):
            pass

        def submit(self, fn, *args):
            count["submitted"] += 1
            count["peak"] = max(count["peak"], count["submitted"] - count["handed_back"])
            fut = Future()
            fut.set_result(fn(*args))
            return fut

    monkeypatch.setattr(parallel, "ProcessPoolExecutor", RecordingPool)
    results = {}
    for index, result in fleet._completed(lambda k: 10 * k, [(k,) for k in range(100)], workers=2, dask=None):
        count["handed_back"] += 1
        results[index] = result()
    assert results == {k: 10 * k for k in range(100)}
    assert count["peak"] <= parallel.IN_FLIGHT_PER_WORKER * 2


def test_a_dask_cluster_gets_a_bounded_number_of_logs_in_flight(monkeypatch):
    """The Dask path submitted every log of the list at once as well (a `--list` of 20 000: 561 MB at the peak): it
    now keeps a bounded number per worker of the cluster submitted and not yet handed back, and every result comes
    back under its own index."""
    pytest.importorskip("dask.distributed")
    from dask.distributed import Client, LocalCluster

    from ptw_rt.apps import fleet

    cluster = LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None)
    client = Client(cluster)
    count = {"submitted": 0, "handed_back": 0, "peak": 0}
    submit_batch = client.map

    def counting_map(*args, **kwargs):
        futures = submit_batch(*args, **kwargs)
        count["submitted"] += len(futures)
        count["peak"] = max(count["peak"], count["submitted"] - count["handed_back"])
        return futures

    monkeypatch.setattr(client, "map", counting_map)
    monkeypatch.setattr(fleet, "_dask_client", lambda address, workers: (client, cluster))
    results = {}
    for index, result in fleet._completed(_times_ten, [(k,) for k in range(300)], workers=1, dask="local"):
        count["handed_back"] += 1
        results[index] = result()
    assert results == {k: 10 * k for k in range(300)}
    assert count["submitted"] == 300
    # a finished batch's successors are submitted before it is handed back (the cluster keeps working): at most
    # twice the bound
    assert count["peak"] <= 2 * fleet.DASK_IN_FLIGHT_PER_WORKER


def _times_ten(k):
    return 10 * k


def test_a_fleet_row_has_every_column_and_nothing_else():
    """Rows are tuples in FLEET_COLUMNS order (kept per log instead of the whole summary): a key that is not a
    column would shift every column after it, which the csv module's DictWriter used to refuse."""
    from ptw_rt.apps import fleet

    ok = {
        "log": "a.log",
        "cycles": 200,
        "log_duration_s": 2.0,
        "segments": 1,
        "sensor_fault_cycles": 3,
        "overruns": 0,
        "wall_s": 0.1,
        "modes": {"VALID": 150, "CONVERGING": 50},
        "final": {"tyre_scale": 0.91234, "c_alpha_front": float("nan"), "stiffness_valid": True},
    }
    row = dict(zip(FLEET_COLUMNS, fleet.fleet_row(ok), strict=True))
    assert row["status"] == "ok" and row["share_valid"] == 0.75 and row["share_converging"] == 0.25
    assert row["tyre_scale"] == 0.9123 and row["c_alpha_front"] == "" and row["stiffness_valid"] == 1
    failed = dict(
        zip(FLEET_COLUMNS, fleet.fleet_row({"log": "b.log", "error": "b.log: CAN log not found"}), strict=True)
    )
    assert failed["status"] == "failed" and failed["error"] == "b.log: CAN log not found" and failed["cycles"] == ""


def test_a_dask_scheduler_lost_mid_run_fails_the_logs_it_had_not_run(monkeypatch):
    """A scheduler that died mid-run: the client cancels what the scheduler had (those logs fail) and reconnects in
    vain; a batch given to it meanwhile never ran, and the command waited for ever. Now every log comes back, the
    ones never given to the cluster with one reason, within DASK_LOST_AFTER_S of the loss."""
    pytest.importorskip("dask.distributed")
    from dask.distributed import Client, LocalCluster

    from ptw_rt.apps import fleet

    cluster = LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None)
    client = Client(cluster, timeout="2s")
    # the cluster is closed here, not by the fleet (closing a LocalCluster whose scheduler died waits for it)
    monkeypatch.setattr(fleet, "_dask_client", lambda address, workers: (client, None))
    monkeypatch.setattr(fleet, "DASK_LOST_AFTER_S", 2.0)
    outcomes = {}
    start = time.monotonic()
    try:
        for index, result in fleet._completed(_slowly_times_ten, [(k,) for k in range(300)], workers=1, dask="x"):
            try:
                outcomes[index] = result()
            except Exception as exc:  # noqa: BLE001 - what each log's failure is, below
                outcomes[index] = exc
            if len(outcomes) == 20:
                cluster.sync(cluster.scheduler.close)
        took = time.monotonic() - start
    finally:
        with contextlib.suppress(Exception):
            cluster.close(timeout=2)
    assert sorted(outcomes) == list(range(300))
    finished = [k for k, v in outcomes.items() if isinstance(v, int)]
    assert len(finished) >= 20 and all(outcomes[k] == 10 * k for k in finished)
    lost = [v for v in outcomes.values() if isinstance(v, UserFacingError)]
    assert lost and all("was lost during the run" in str(v) for v in lost)
    assert took < 20.0


def _slowly_times_ten(k):
    time.sleep(0.02)
    return 10 * k


def test_a_worker_that_dies_fails_the_logs_in_flight_and_a_fresh_pool_replays_the_rest():
    """A worker killed mid-run (the OOM killer, a log that crashes the interpreter) broke the local pool: the next
    submission raised BrokenProcessPool out of the command, a traceback. Now the logs in flight fail with that reason
    and a fresh pool takes the rest."""
    from concurrent.futures.process import BrokenProcessPool

    from ptw_rt.apps import fleet

    outcomes = {}
    for index, result in fleet._completed(_dies_at_30, [(k,) for k in range(300)], workers=2, dask=None):
        try:
            outcomes[index] = result()
        except BrokenProcessPool as exc:
            outcomes[index] = exc
    assert sorted(outcomes) == list(range(300))
    assert isinstance(outcomes[30], BrokenProcessPool)
    failed = [k for k, v in outcomes.items() if not isinstance(v, int)]
    assert all(outcomes[k] == 10 * k for k in outcomes if k not in failed)
    # the logs in flight when the pool broke fail with it (how many the pool took before it noticed depends on the
    # host's load); the last ones run on a fresh pool
    assert all(outcomes[k] == 10 * k for k in range(250, 300)), failed


def test_an_evaluation_whose_worker_dies_is_one_line():
    """The evaluation's map (the matrix, random rides) needs every ride: a worker that dies there is one line naming
    the ride (it was a BrokenProcessPool traceback out of `ptw-rt evaluate`)."""
    from ptw_rt.parallel import map_in_processes

    with pytest.raises(UserFacingError, match=r"^a worker process died with ride \d+ in flight \(killed") as info:
        map_in_processes(_dies_at_30, list(range(300)), 2, None, lambda k: f"ride {k}")
    assert "\n" not in str(info.value)
    assert map_in_processes(_times_ten, list(range(40)), 2, None, str) == [10 * k for k in range(40)]


def _dies_at_30(k):
    if k == 30:
        os._exit(9)
    time.sleep(0.01)
    return 10 * k


def _marks_its_start(directory, k):
    (Path(directory) / str(k)).touch()
    time.sleep(0.3)
    return k


def test_a_caller_that_stops_early_cancels_the_jobs_not_yet_started(tmp_path):
    """The evaluation stops at a dead worker's first result, Ctrl-C stops a fleet: the pool then waits only for the
    jobs already running, not for the rest of what it had been given (IN_FLIGHT_PER_WORKER per worker)."""
    from ptw_rt import parallel

    jobs = [(str(tmp_path), k) for k in range(100)]
    results = parallel.completed_in_processes(_marks_its_start, jobs, 2)
    next(results)
    results.close()  # the pool is shut down here
    started = len(list(tmp_path.iterdir()))
    # running or already handed to a worker's queue (2 workers, one call queued beyond them) when the first
    # finished; all of the 16 in flight would start without the cancel
    assert started <= 8 < parallel.IN_FLIGHT_PER_WORKER * 2, started
