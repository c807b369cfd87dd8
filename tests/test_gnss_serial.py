"""Serial GNSS end to end: the real daemon loop, IMU and encoder on a python-can virtual bus, the speed from an NMEA
receiver on a pseudo-terminal (``runtime.gps.source: serial``), against the same ride with GPS_Velocity on CAN.

Tolerance: both runs are live (the daemon's cycle grid falls differently between the frames of a sample in each
run, as in the daemon-vs-replay comparison of tests/test_vcan_integration.py) and the NMEA speed is sent in knots
with 3 decimals while GPS_Velocity carries 0.01 m/s: the published roll may differ by at most 0.5 deg RMS over
the settled part of the ride (measured here: a few hundredths of a degree), and both runs are VALID there.
Unplugging the receiver sets the GPS bit of EST_Status.SensorTimeouts and DEGRADED within 3 cycles; replugged, the
daemon recovers.
"""

from __future__ import annotations

import dataclasses
import math
import os
import threading
import time
import uuid

import can
import numpy as np
import pytest
from conftest import BUS_INPUTS, on_a_quiet_host, timeouts_not_injected

from ptw_rt.core.layout import E_MODE, MODE_DEGRADED, MODE_VALID, MSG_GPS
from ptw_rt.io.dbc import FrameCodec
from ptw_rt.io.nmea import KNOT_MPS
from ptw_rt.paths import DEFAULT_CONFIG
from ptw_rt.service.daemon import Daemon, load_daemon_settings

pytest.importorskip("pynmea2")

RIDE_S = 6.0
SETTLE_S = 3.0  # GPS fix + the (shortened) convergence
ROLL_RMS_TOLERANCE_DEG = 0.5
DT = 0.01


def _nmea(body: str) -> bytes:
    checksum = 0
    for ch in body:
        checksum ^= ord(ch)
    return f"${body}*{checksum:02X}\r\n".encode()


def rmc(speed_mps: float, course_deg: float, fix: int) -> bytes:
    status = "A" if fix >= 2 else "V"
    mode = "A" if fix >= 2 else "N"
    return _nmea(
        f"GPRMC,120000.00,{status},4717.11437,N,00833.91522,E,{speed_mps / KNOT_MPS:.3f},{course_deg:.2f},"
        f"230126,,,{mode}"
    )


@pytest.fixture(scope="module")
def codec():
    return FrameCodec()


@pytest.fixture(scope="module")
def ride_frames(codec):
    from ptw_rt.sim.recording import encode_frames
    from ptw_rt.sim.ride import simulate

    ride = simulate("dlc_100", duration=RIDE_S + 1.0)
    return [(t - ride.epoch, fid, data) for t, fid, data in encode_frames(ride, codec)]


class Pty:
    """A receiver on a pseudo-terminal: the test writes on the master; the daemon opens ``link`` (like a
    /dev/serial/by-id/ name, which comes and goes with the device)."""

    def __init__(self, link) -> None:
        self.link = link
        self.master, self.slave = os.openpty()
        link.unlink(missing_ok=True)
        link.symlink_to(os.ttyname(self.slave))

    def write(self, data: bytes) -> None:
        os.write(self.master, data)

    def unplug(self) -> None:
        self.link.unlink(missing_ok=True)
        for fd in (self.master, self.slave):
            os.close(fd)


def _settings(channel: str, tmp_path, serial_port: str | None):
    s = load_daemon_settings(
        DEFAULT_CONFIG, {"interface": "virtual", "channel": channel, "state_file": tmp_path / "state.json"}
    )
    runtime = s.runtime
    if serial_port is not None:
        gps = dataclasses.replace(runtime.gps, source="serial", serial_port=serial_port, serial_baudrate=115200)
        runtime = dataclasses.replace(runtime, gps=gps)
    est = dataclasses.replace(s.estimator, converge_time=1.0, reason_hold_time=0.3)
    return dataclasses.replace(s, runtime=runtime, estimator=est)


def _ride(
    codec,
    ride_frames,
    tmp_path,
    *,
    serial: bool,
    unplug_at: float | None = None,
    replug_at: float | None = None,
    can_gps_too: bool = False,
):
    """One live run: returns ([(cycle time, ride time, roll, roll valid, mode, SensorTimeouts)], events, daemon).
    `can_gps_too`: with the serial receiver, GPS_Velocity frames on the bus as well (another node's, or a forged
    one's), which the daemon must not take."""
    channel = f"ptw-gnss-{uuid.uuid4().hex[:10]}"
    gps_id = codec.frame_id("GPS_Velocity")
    link = tmp_path / f"gnss-{uuid.uuid4().hex[:6]}"
    pty = Pty(link) if serial else None
    daemon = Daemon(_settings(channel, tmp_path, str(link) if serial else None), DEFAULT_CONFIG)
    rows: list[tuple[float, float]] = []
    events: dict[str, float] = {}
    daemon.on_cycle = lambda now, e: rows.append((now, float(e[E_MODE])))
    status_id = codec.frame_id("EST_Status")
    roll_id = codec.frame_id("EST_Roll")
    listener = can.Bus(interface="virtual", channel=channel)
    received: list[tuple[float, int, bytes]] = []
    stop = threading.Event()

    def listen() -> None:
        while not stop.is_set():
            msg = listener.recv(timeout=0.02)
            if msg is not None and msg.arbitration_id in (status_id, roll_id):
                received.append((time.monotonic(), msg.arbitration_id, bytes(msg.data)))

    def play(t0: float) -> None:
        nonlocal pty
        bus = can.Bus(interface="virtual", channel=channel)
        for t, fid, data in ride_frames:
            if t >= RIDE_S or stop.is_set():
                break
            delay = t0 + t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            if unplug_at is not None and t >= unplug_at and "unplug" not in events:
                pty.unplug()
                events["unplug"] = time.monotonic()
            if replug_at is not None and t >= replug_at and "replug" not in events:
                pty = Pty(link)
                events["replug"] = time.monotonic()
            if fid == gps_id and serial:
                v = codec.decode(fid, data)[1]
                if "unplug" not in events or "replug" in events:
                    pty.write(rmc(v["SpeedOverGround"], v["CourseOverGround"], int(v["FixType"])))
                if can_gps_too:
                    bus.send(can.Message(arbitration_id=fid, data=data, is_extended_id=False))
            else:
                bus.send(can.Message(arbitration_id=fid, data=data, is_extended_id=False))
        bus.shutdown()

    listen_thread = threading.Thread(target=listen, daemon=True)
    listen_thread.start()
    th = threading.Thread(target=daemon.run, args=(RIDE_S + 0.2,), daemon=True)
    th.start()
    assert daemon.ready.wait(10.0)
    t0 = time.monotonic() + 0.05
    events["t0"] = t0
    player = threading.Thread(target=play, args=(t0,), daemon=True)
    player.start()
    player.join(timeout=RIDE_S + 5)
    th.join(timeout=RIDE_S + 5)
    stop.set()
    listen_thread.join()
    listener.shutdown()
    if pty is not None and ("unplug" not in events or "replug" in events):
        pty.unplug()
    assert not th.is_alive()
    return rows, received, events, daemon


def _roll_series(codec, received, t0):
    out = []
    for t, fid, data in received:
        if fid == codec.frame_id("EST_Roll"):
            v = codec.decode_checked(fid, data)[1]
            out.append((t - t0, v["RollAngle"], v["EST_Roll_Valid"] * v["RollAngle_Valid"]))
    return np.array(out)


def _late_bus_inputs(result) -> int:
    """Timeouts of the inputs on the bus beyond the one each gets when the player stops."""
    return timeouts_not_injected(result[3], dict.fromkeys(BUS_INPUTS, 1))


def test_serial_gnss_matches_can_gps(codec, ride_frames, tmp_path):
    def run_once():
        return _ride(codec, ride_frames, tmp_path, serial=False), _ride(codec, ride_frames, tmp_path, serial=True)

    # a host that starves the players makes the IMU or the encoder time out in either run: run both again
    runs = on_a_quiet_host(run_once, lambda r: _late_bus_inputs(r[0]) + _late_bus_inputs(r[1]))
    (_, rx_can, ev_can, d_can), (_, rx_ser, ev_ser, d_ser) = runs
    can_roll = _roll_series(codec, rx_can, ev_can["t0"])
    ser_roll = _roll_series(codec, rx_ser, ev_ser["t0"])
    settled = (ser_roll[:, 0] >= SETTLE_S) & (ser_roll[:, 0] <= min(RIDE_S, can_roll[-1, 0]))
    assert settled.sum() >= 0.9 * 100 * (RIDE_S - SETTLE_S)
    # valid over the settled part, as with CAN GPS (a starved test machine may delay a frame by a cycle: 1 % slack)
    can_valid = np.interp(ser_roll[settled, 0], can_roll[:, 0], can_roll[:, 2]) == 1.0
    both = can_valid & (ser_roll[settled, 2] == 1.0)
    assert both.mean() >= 0.99, (ser_roll[settled, 2].mean(), can_valid.mean())
    t = ser_roll[settled, 0][both]
    diff = np.degrees(ser_roll[settled, 1][both] - np.interp(t, can_roll[:, 0], can_roll[:, 1]))
    rms = math.sqrt(float(np.mean(diff**2)))
    print(f"roll RMS difference serial vs CAN GPS: {rms:.4f} deg (max {np.abs(diff).max():.4f})")
    assert rms < ROLL_RMS_TOLERANCE_DEG, rms
    assert np.degrees(np.abs(can_roll[:, 1]).max()) > 2.0  # the ride leans: the comparison means something
    g = d_ser.health()["gnss"]
    assert g["used"] >= 10 * (RIDE_S - 0.5) and g["checksum_errors"] == 0 and g["disconnects"] == 0
    assert d_ser.health()["inputs"]["GPS_Velocity"]["frames"] == g["used"]


def test_unplugged_receiver_degrades_within_3_cycles_and_recovers(codec, ride_frames, tmp_path):
    """GPS_Velocity frames on the bus all along: with the GPS on the serial port they are not taken (they kept an
    unplugged receiver from ever being flagged; found by fuzzing, 2026-11-26)."""
    slack = 0.012  # the reader thread notices the hang-up, the loop's next cycle

    def run_once():
        return _ride(codec, ride_frames, tmp_path, serial=True, unplug_at=3.0, replug_at=3.5, can_gps_too=True)

    def first_bad(result) -> float:
        rows, _, events, _ = result
        return next((t for t, m in rows if t >= events["unplug"] and m == MODE_DEGRADED), math.inf)

    def modes_before(result) -> list[float]:
        rows, _, events, _ = result
        return [m for t, m in rows if events["unplug"] - 0.3 <= t < events["unplug"]]

    def not_valid_before(result) -> float:
        modes = modes_before(result)
        return 0.0 if modes and all(m == MODE_VALID for m in modes) else 1.0

    # the player shares the interpreter with the daemon: a CI host that starves it makes the IMU or the encoder time
    # out as well (once in a full run: the encoder, 0.3 s before the unplug), which is the host, not the receiver.
    # Such a run, or one whose flag came late, or one not VALID in the 0.3 s before the unplug (once in a fresh
    # clone's CI run, 2026-12-07, with no bus input late; its cause not captured), is repeated; an unplug that
    # is never or late flagged, or a ride never VALID before it, still fails.
    result = on_a_quiet_host(
        run_once,
        _late_bus_inputs,
        excess=lambda r: first_bad(r) - r[2]["unplug"] - (3 * DT + slack) + not_valid_before(r),
    )
    rows, received, events, daemon = result
    unplug, replug = events["unplug"], events["replug"]
    assert not_valid_before(result) == 0.0, modes_before(result)
    assert first_bad(result) - unplug <= 3 * DT + slack
    # SensorTimeouts carries the GPS bit in the next status frames
    status_id = codec.frame_id("EST_Status")
    timeouts = [(t, int(codec.decode(fid, d)[1]["SensorTimeouts"])) for t, fid, d in received if fid == status_id]
    assert any(bits & MSG_GPS for t, bits in timeouts if unplug < t < replug)
    assert all(not bits & MSG_GPS for t, bits in timeouts if unplug - 1.0 < t < unplug)
    # replugged: reopened (retry every second), the speed flows again, VALID again before the end of the ride
    g = daemon.health()["gnss"]
    assert g["disconnects"] == 1 and g["opens"] == 2
    end = events["t0"] + RIDE_S  # the player stops there (then the IMU times out too)
    assert any(m == MODE_VALID for t, m in rows if replug < t < end), [(round(t - replug, 2), m) for t, m in rows]
    assert any(not bits & MSG_GPS for t, bits in timeouts if t > replug)


def test_documented_daemon_yaml_with_serial_gnss(tmp_path, capsys):
    """config/daemon-runtime.example.yaml spliced into config/scooter.yaml as its header says: a valid daemon
    configuration reading the speed from the serial receiver."""
    from ptw_rt.cli import main
    from ptw_rt.paths import CONFIG_DIR
    from ptw_rt.settings import load_settings

    base = DEFAULT_CONFIG.read_text()
    daemon_yaml = tmp_path / "daemon.yaml"
    daemon_yaml.write_text(
        base[: base.index("\nruntime:") + 1] + (CONFIG_DIR / "daemon-runtime.example.yaml").read_text()
    )
    settings = load_settings(daemon_yaml)
    assert settings.runtime.gps.source == "serial" and settings.runtime.gps.serial_port.startswith("/dev/serial/by-id/")
    assert settings.config_hash == load_settings(DEFAULT_CONFIG).config_hash  # the committed design still fits
    assert main(["run", "--config", str(daemon_yaml), "--check-config"]) == 0
    assert "gps serial" in capsys.readouterr().out


def test_a_flood_of_junk_lines_costs_the_cycle_one_call(monkeypatch):
    """A receiver (or a USB CDC port, which ignores the baud rate) writing junk lines: the cycle took each bad line
    as one call into the input tracker, 750 000 a second, and one cycle took 209 ms (found by fuzzing, 2026-12-07).
    However many lines went bad since the last cycle, they are counted in one call."""
    from types import SimpleNamespace

    from ptw_rt.edge.cycle import build_runner

    runner = build_runner(DEFAULT_CONFIG)
    calls = []
    decode_error = runner.tracker.decode_error
    monkeypatch.setattr(runner.tracker, "decode_error", lambda *a: calls.append(a) or decode_error(*a))
    warned = []
    owner = SimpleNamespace(
        _gnss_connected=True,
        _gnss_bad=0,
        _gnss_taken=None,
        rate_log=SimpleNamespace(warn=lambda *a: warned.append(a), error=lambda *a: None),
    )
    gnss = SimpleNamespace(
        connected=True,
        port="/dev/ttyFAKE",
        bad_lines=750_000,
        parser=SimpleNamespace(checksum_errors=0),
        latest=lambda: None,
    )
    Daemon._poll_gnss(owner, runner, gnss, 0.0)
    assert len(calls) == 1 and owner._gnss_bad == 750_000 and len(warned) == 1
    assert runner.tracker.summary()["GPS_Velocity"]["decode_errors"] == 750_000
    gnss.bad_lines += 3
    Daemon._poll_gnss(owner, runner, gnss, 0.01)
    assert len(calls) == 2 and runner.tracker.summary()["GPS_Velocity"]["decode_errors"] == 750_003
