"""sd_notify against a real AF_UNIX datagram socket, and the watchdog gate that pings only from a healthy loop."""

from __future__ import annotations

import os
import socket
import threading
import time
import uuid

import pytest

from ptw_rt.service.sdnotify import SystemdNotifier, WatchdogGate


class Receiver:
    """What systemd does: a bound SOCK_DGRAM socket collecting one message per datagram."""

    def __init__(self, address: str) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(address)

    def get(self, timeout: float = 1.0) -> str:
        self.sock.settimeout(timeout)
        return self.sock.recv(4096).decode()

    def drain(self) -> list[str]:
        out = []
        self.sock.setblocking(False)
        try:
            while True:
                out.append(self.sock.recv(4096).decode())
        except BlockingIOError:
            return out

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def path_socket(tmp_path):
    path = str(tmp_path / "notify.sock")
    rx = Receiver(path)
    yield path, rx
    rx.close()


def _notifier(address: str, **env: str) -> SystemdNotifier:
    return SystemdNotifier(environ={"NOTIFY_SOCKET": address, **env})


def _check_protocol(notifier: SystemdNotifier, rx: Receiver) -> None:
    assert notifier.enabled
    assert notifier.ready("running, 100 Hz")
    assert rx.get() == "READY=1\nSTATUS=running, 100 Hz"
    assert notifier.status("line one\nline two")
    assert rx.get() == "STATUS=line one line two"
    assert notifier.watchdog()
    assert rx.get() == "WATCHDOG=1"
    assert notifier.extend_timeout(1.5)
    assert rx.get() == "EXTEND_TIMEOUT_USEC=1500000"
    before = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
    assert notifier.reloading("re-reading config")
    lines = rx.get().split("\n")
    assert lines[0] == "RELOADING=1" and lines[2] == "STATUS=re-reading config"
    key, usec = lines[1].split("=")
    assert key == "MONOTONIC_USEC" and before <= int(usec) <= before + 5_000_000
    assert notifier.stopping("saving state")
    assert rx.get() == "STOPPING=1\nSTATUS=saving state"
    assert notifier.sent == 6 and notifier.send_failures == 0
    assert rx.drain() == []


def test_path_socket_receives_every_message(path_socket):
    path, rx = path_socket
    notifier = _notifier(path)
    _check_protocol(notifier, rx)
    notifier.close()
    assert not notifier.enabled and notifier.ready() is False


def test_abstract_socket_receives_every_message():
    name = f"ptw-rt-test-{os.getpid()}-{uuid.uuid4().hex}"
    rx = Receiver("\0" + name)
    try:
        _check_protocol(_notifier("@" + name), rx)
    finally:
        rx.close()


def test_reads_notify_socket_from_process_environment(path_socket, monkeypatch):
    path, rx = path_socket
    monkeypatch.setenv("NOTIFY_SOCKET", path)
    assert SystemdNotifier().ready()
    assert rx.get() == "READY=1"


def test_unset_environment_removes_the_variables_but_keeps_notifying(path_socket, monkeypatch):
    path, rx = path_socket
    monkeypatch.setenv("NOTIFY_SOCKET", path)
    monkeypatch.setenv("WATCHDOG_USEC", "2000000")
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    notifier = SystemdNotifier(unset_environment=True)
    for name in ("NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID"):
        assert name not in os.environ
    assert notifier.watchdog_interval_s() == 2.0
    assert notifier.watchdog()
    assert rx.get() == "WATCHDOG=1"


@pytest.mark.parametrize("environ", [{}, {"NOTIFY_SOCKET": ""}, {"NOTIFY_SOCKET": "vsock:2:1234"}])
def test_without_systemd_everything_is_a_silent_noop(environ, monkeypatch):
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    for notifier in (SystemdNotifier(environ=environ), SystemdNotifier()):
        assert not notifier.enabled
        assert notifier.ready("x") is False
        assert notifier.status("x") is False
        assert notifier.watchdog() is False
        assert notifier.reloading() is False
        assert notifier.stopping() is False
        assert notifier.extend_timeout(3) is False
        assert notifier.sent == 0 and notifier.send_failures == 0
        notifier.close()
        gate = WatchdogGate(notifier, 2.0)
        assert not gate.active
        assert not any(gate.cycle_done(True, t * 0.01) for t in range(500))
        assert gate.pings == 0


def test_vanished_socket_is_counted_not_raised(path_socket):
    path, rx = path_socket
    notifier = _notifier(path)
    assert notifier.ready()
    rx.close()
    os.unlink(path)
    assert notifier.watchdog() is False
    assert notifier.stopping() is False
    assert notifier.send_failures == 2 and notifier.sent == 1
    assert "FileNotFoundError" in notifier.last_error or "ConnectionRefused" in notifier.last_error


def test_socket_never_existed_and_closed_receiver(tmp_path):
    notifier = _notifier(str(tmp_path / "nobody-here"))
    assert notifier.enabled
    assert notifier.ready() is False and notifier.send_failures == 1
    # bound then closed but the file left behind: ECONNREFUSED
    path = str(tmp_path / "stale.sock")
    Receiver(path).close()
    notifier = _notifier(path)
    assert notifier.watchdog() is False and notifier.send_failures == 1
    # an AF_UNIX path longer than sun_path
    notifier = _notifier("/" + "x" * 200)
    assert notifier.ready() is False and notifier.send_failures == 1


def test_full_receiver_never_blocks_the_sender(path_socket):
    path, rx = path_socket
    notifier = _notifier(path)
    start = time.monotonic()
    results = [notifier.status("x" * 1000) for _ in range(5000)]
    assert time.monotonic() - start < 2.0
    assert not all(results), "receiver never read: the queue must fill up and sends must fail, not block"
    assert notifier.send_failures == results.count(False) > 0


@pytest.mark.parametrize(
    ("env", "expected"),
    [
        ({"WATCHDOG_USEC": "2000000"}, 2.0),
        ({"WATCHDOG_USEC": "500000", "WATCHDOG_PID": "<self>"}, 0.5),
        ({"WATCHDOG_USEC": "2000000", "WATCHDOG_PID": "<other>"}, None),
        ({"WATCHDOG_USEC": "2000000", "WATCHDOG_PID": "abc"}, None),
        ({"WATCHDOG_USEC": "0"}, None),
        ({"WATCHDOG_USEC": "-5"}, None),
        ({"WATCHDOG_USEC": "2s"}, None),
        ({"WATCHDOG_USEC": ""}, None),
        ({}, None),
    ],
)
def test_watchdog_usec_and_pid(env, expected):
    env = dict(env)
    if env.get("WATCHDOG_PID") == "<self>":
        env["WATCHDOG_PID"] = str(os.getpid())
    elif env.get("WATCHDOG_PID") == "<other>":
        env["WATCHDOG_PID"] = str(os.getpid() + 1)
    assert SystemdNotifier("", environ=env).watchdog_interval_s() == expected


def _run(gate: WatchdogGate, t0: float, t1: float, healthy: bool, dt: float = 0.01) -> list[float]:
    """Simulated 100 Hz loop from t0 to t1; returns the cycle times at which a ping went out."""
    pings = []
    for k in range(round((t1 - t0) / dt)):
        now = t0 + k * dt
        if gate.cycle_done(healthy, now):
            pings.append(now)
    return pings


def test_gate_pings_at_half_the_interval_while_healthy(path_socket):
    path, rx = path_socket
    gate = WatchdogGate(_notifier(path, WATCHDOG_USEC="2000000"))
    assert gate.active and gate.interval_s == 2.0 and gate.period_s == 1.0
    pings = _run(gate, 0.0, 10.0, healthy=True)
    assert pings[0] == 0.0  # first healthy cycle pings right away
    gaps = [b - a for a, b in zip(pings[:-1], pings[1:], strict=True)]
    assert all(1.0 - 1e-9 <= g <= 1.0 + 0.011 for g in gaps), gaps
    assert 9 <= len(pings) <= 11
    assert rx.drain() == ["WATCHDOG=1"] * len(pings)
    assert gate.pings == len(pings) and gate.withheld == 0 and gate.stalls == 0


def test_gate_withholds_pings_while_unhealthy_and_resumes(path_socket):
    path, rx = path_socket
    gate = WatchdogGate(_notifier(path), 2.0)
    before = _run(gate, 0.0, 3.0, healthy=True)
    assert len(before) == 3
    during = _run(gate, 3.0, 10.0, healthy=False)
    # at most one more ping (within max_unhealthy_s = 1 s of the last healthy cycle), then silence
    assert all(t <= 3.0 + 1.0 for t in during), during
    assert gate.withheld > 0
    assert len(rx.drain()) == len(before) + len(during)
    # the last ping is at most max_unhealthy_s after the last healthy cycle (2.99 s), so systemd's 2 s watchdog
    # fires within 1.5 intervals of it
    last_ping = (before + during)[-1]
    assert last_ping - 2.99 <= gate.max_unhealthy_s + 1e-9
    after = _run(gate, 10.0, 12.0, healthy=True)
    assert after and after[0] <= 10.0 + gate.period_s / 8 + 0.011  # re-checked soon after a withheld ping
    assert rx.drain() == ["WATCHDOG=1"] * len(after)


def test_gate_occasional_unhealthy_cycles_do_not_stop_pings(path_socket):
    path, rx = path_socket
    gate = WatchdogGate(_notifier(path), 2.0)
    pings = []
    for k in range(1000):  # 10 s, every tenth cycle healthy
        now = k * 0.01
        if gate.cycle_done(k % 10 == 0, now):
            pings.append(now)
    assert 9 <= len(pings) <= 11
    assert len(rx.drain()) == len(pings)


def test_gate_stalled_loop_sends_nothing_in_real_time(path_socket):
    """A real 100 Hz loop thread that stops calling the gate: nothing else pings for it."""
    path, rx = path_socket
    gate = WatchdogGate(_notifier(path), 0.2)  # ping every 0.1 s
    stall_from, stall_to = 0.4, 0.9
    start = time.monotonic()

    def loop():
        stalled = False
        while (now := time.monotonic()) - start < 1.3:
            if not stalled and now - start >= stall_from:
                stalled = True
                time.sleep(stall_to - stall_from)  # hung: no cycle completes
                continue
            gate.cycle_done(True, now)
            time.sleep(0.01)

    thread = threading.Thread(target=loop)
    thread.start()
    arrivals = []
    rx.sock.settimeout(0.05)
    while thread.is_alive() or arrivals == []:
        try:
            assert rx.sock.recv(64) == b"WATCHDOG=1"
            arrivals.append(time.monotonic() - start)
        except TimeoutError:
            pass
    thread.join()
    arrivals += [time.monotonic() - start for _ in rx.drain()]
    assert any(t < stall_from for t in arrivals)
    assert any(t > stall_to for t in arrivals)
    silent = [t for t in arrivals if stall_from + 0.05 < t < stall_to - 0.01]
    assert silent == [], f"pings arrived while the loop was stalled: {arrivals}"
    assert gate.stalls >= 1


def test_gate_inactive_without_watchdog(path_socket):
    path, rx = path_socket
    gate = WatchdogGate(_notifier(path))  # no WATCHDOG_USEC: systemd expects no pings
    assert not gate.active
    assert _run(gate, 0.0, 5.0, healthy=True) == []
    gate = WatchdogGate(_notifier(path, WATCHDOG_USEC="1000000", WATCHDOG_PID=str(os.getpid() + 1)))  # not ours
    assert not gate.active
    assert _run(gate, 0.0, 5.0, healthy=True) == []
    assert rx.drain() == []
