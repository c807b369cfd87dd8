"""Real-time settings: never fatal without privileges, validated config, CPU affinity that really applies."""

from __future__ import annotations

import json
import os
import resource

import pytest

from ptw_rt.schema import ConfigError
from ptw_rt.service import realtime
from ptw_rt.service.realtime import apply_realtime, realtime_state
from ptw_rt.settings import REALTIME_SCHEMA

NOBODY = 65534


def _in_unprivileged_child(func) -> dict:
    """Run ``func()`` in a forked child without privileges (root drops to nobody and loses every capability)
    and with RLIMIT_RTPRIO 0 and a finite RLIMIT_MEMLOCK, as a normal login shell has; returns its JSON result."""
    read_fd, write_fd = os.pipe()
    pid = os.fork()
    if pid == 0:  # child: never return into pytest
        code = 1
        try:
            os.close(read_fd)
            resource.setrlimit(resource.RLIMIT_RTPRIO, (0, 0))
            resource.setrlimit(resource.RLIMIT_MEMLOCK, (64 * 1024, 64 * 1024))
            if os.getuid() == 0:
                os.setgroups([])
                os.setgid(NOBODY)
                os.setuid(NOBODY)
            result = {"ok": True, "value": func(), "caps": realtime._has_capability(realtime._CAP_IPC_LOCK)}
        except BaseException as exc:  # noqa: BLE001 - report everything to the parent
            result = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
        try:
            with os.fdopen(write_fd, "w") as fh:
                json.dump(result, fh)
            code = 0
        finally:
            os._exit(code)
    os.close(write_fd)
    with os.fdopen(read_fd) as fh:
        data = fh.read()
    _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0, data
    return json.loads(data)


def test_unprivileged_apply_realtime_warns_and_keeps_running():
    def child():
        warnings = apply_realtime(40, None, True)
        return {"warnings": warnings, "state": realtime_state()}

    result = _in_unprivileged_child(child)
    assert result["ok"], result
    if result["caps"]:
        pytest.skip("the child still holds capabilities (ambient caps?): cannot test the unprivileged case")
    warnings = result["value"]["warnings"]
    assert len(warnings) == 2, warnings
    fifo, mlock = warnings
    assert fifo.startswith("SCHED_FIFO priority 40") and "LimitRTPRIO" in fifo
    assert mlock.startswith("mlockall") and "LimitMEMLOCK=infinity" in mlock
    state = result["value"]["state"]
    assert state["policy"] == "other" and state["priority"] == 0
    assert not state["locked_kib"]


def test_refused_settings_are_warnings_never_exceptions(monkeypatch, caplog):
    def eperm(*args):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(realtime.os, "sched_setscheduler", eperm)
    monkeypatch.setattr(realtime.os, "sched_setaffinity", eperm)
    monkeypatch.setattr(realtime.resource, "getrlimit", lambda which: (65536, 65536))
    monkeypatch.setattr(realtime, "_has_capability", lambda bit: False)
    with caplog.at_level("WARNING", logger="ptw_rt.service.realtime"):
        warnings = apply_realtime(10, [0], True)
    assert [w.split(":")[0] for w in warnings] == [
        "SCHED_FIFO priority 10",
        "CPU affinity [0]",
        "mlockall(MCL_CURRENT|MCL_FUTURE)",
    ]
    assert all("EPERM" in w for w in warnings[:2])
    assert len([r for r in caplog.records if r.levelname == "WARNING"]) == 3


def test_unexpected_errors_are_warnings_too(monkeypatch):
    def boom(*args):
        raise RuntimeError("kernel says no")

    monkeypatch.setattr(realtime.os, "sched_setscheduler", boom)
    monkeypatch.setattr(realtime.resource, "getrlimit", boom)
    warnings = apply_realtime(10, None, True)
    assert len(warnings) == 2
    assert all("RuntimeError: kernel says no" in w for w in warnings)


def test_nothing_asked_nothing_done():
    before = realtime_state()
    assert apply_realtime(None, None, False) == []
    assert realtime_state()["policy"] == before["policy"]


def test_nonexistent_cpu_is_a_warning():
    before = os.sched_getaffinity(0)
    try:
        warnings = apply_realtime(None, [4095], False)
    finally:
        os.sched_setaffinity(0, before)
    assert len(warnings) == 1 and warnings[0].startswith("CPU affinity [4095]")
    assert "EINVAL" in warnings[0] and "current affinity" in warnings[0]
    assert os.sched_getaffinity(0) == before


def test_affinity_to_an_allowed_cpu_applies():
    before = os.sched_getaffinity(0)
    cpu = max(before)
    try:
        assert apply_realtime(None, [cpu], False) == []
        assert os.sched_getaffinity(0) == {cpu}
        assert realtime_state()["cpus"] == [cpu]
    finally:
        os.sched_setaffinity(0, before)
    assert os.sched_getaffinity(0) == before


def test_schema_defaults_and_valid_values():
    assert REALTIME_SCHEMA.check("runtime.realtime", {}) == {"priority": None, "cpus": None, "lock_memory": False}
    got = REALTIME_SCHEMA.check("runtime.realtime", {"priority": 40, "cpus": [1, 3], "lock_memory": True})
    assert got == {"priority": 40, "cpus": (1, 3), "lock_memory": True}
    assert REALTIME_SCHEMA.check("r", {"priority": 1})["priority"] == 1
    assert REALTIME_SCHEMA.check("r", {"priority": 99, "cpus": None})["priority"] == 99


@pytest.mark.parametrize(
    ("doc", "message"),
    [
        ({"priority": 0}, "runtime.realtime.priority: must be >= 1"),
        ({"priority": 100}, "runtime.realtime.priority: must be <= 99"),
        ({"priority": 40.5}, "runtime.realtime.priority: expected a whole number"),
        ({"priority": "high"}, "runtime.realtime.priority: expected a number"),
        ({"cpus": [1, 1]}, "runtime.realtime.cpus: CPU numbers must be distinct"),
        ({"cpus": [0, 2, 0]}, "runtime.realtime.cpus: CPU numbers must be distinct"),
        ({"cpus": []}, "runtime.realtime.cpus: expected >= 1 items"),
        ({"cpus": [-1]}, "runtime.realtime.cpus[0]: must be >= 0"),
        ({"cpus": 1}, "runtime.realtime.cpus: expected a list"),
        ({"lock_memory": "yes"}, "runtime.realtime.lock_memory: expected true or false"),
        ({"priorty": 40}, "runtime.realtime.priorty: unknown key (did you mean 'priority'?)"),
    ],
)
def test_schema_rejects_bad_values(doc, message):
    with pytest.raises(ConfigError) as info:
        REALTIME_SCHEMA.check("runtime.realtime", doc)
    assert str(info.value).startswith(message), str(info.value)


def test_a_thread_that_ran_the_loop_at_sched_fifo_gets_its_policy_back():
    """Processes started afterwards (the bench's CPU hogs) must not inherit the loop's SCHED_FIFO."""
    import threading

    result = {}

    def worker():
        saved = realtime.thread_scheduling()
        result["warnings"] = apply_realtime(10, None, False)
        result["during"] = os.sched_getscheduler(0)
        realtime.restore_scheduling(saved)
        result["after"] = os.sched_getscheduler(0)

    t = threading.Thread(target=worker)
    t.start()
    t.join()
    if result["warnings"]:
        pytest.skip(f"SCHED_FIFO not permitted here: {result['warnings'][0]}")
    assert result["during"] == os.SCHED_FIFO
    assert result["after"] == os.SCHED_OTHER
