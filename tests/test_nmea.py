"""NMEA 0183 GNSS: RMC/VTG -> GPS_Velocity meaning, counted errors, and the serial reader over a real pty."""

from __future__ import annotations

import math
import os
import threading
import time
from functools import reduce

import pytest

from ptw_rt.errors import UserFacingError
from ptw_rt.io import nmea

KN = 1852.0 / 3600.0


def sentence(body: str, checksum: str | None = None) -> str:
    """``$body*hh`` with a correct checksum (XOR of the characters between ``$`` and ``*``) unless given."""
    cs = checksum if checksum is not None else f"{reduce(lambda a, c: a ^ ord(c), body, 0):02X}"
    return f"${body}*{cs}"


def test_checksum_helper_matches_a_published_sentence():
    published = "$GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,*47"
    assert sentence("GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,") == published


@pytest.fixture
def parser():
    pytest.importorskip("pynmea2")
    return nmea.NmeaParser()


@pytest.mark.parametrize(
    ("body", "speed", "course", "fix"),
    [
        # NMEA 0183 v2.1 RMC (no mode indicator): status A -> 2D
        ("GPRMC,123519,A,4807.038,N,01131.000,E,022.4,084.4,230394,003.1,W", 22.4 * KN, 84.4, 2),
        # u-blox NMEA 4.x with mode indicator and navigational status
        ("GNRMC,083559.00,A,4717.11437,N,00833.91522,E,0.004,77.52,091202,,,A,V", 0.004 * KN, 77.52, 2),
        ("GNRMC,083559.00,A,4717.11437,N,00833.91522,E,1.000,10.0,091202,,,D", KN, 10.0, 2),
        ("GNRMC,083559.00,A,4717.11437,N,00833.91522,E,1.000,10.0,091202,,,E", KN, 10.0, 1),  # dead reckoning
        ("GNRMC,083559.00,V,,,,,,,091202,,,N", math.nan, math.nan, 0),
        ("GPRMC,123519,V,4807.038,N,01131.000,E,022.4,084.4,230394,003.1,W", 22.4 * KN, 84.4, 0),
        ("GLRMC,123519,A,4807.038,N,01131.000,E,10.0,360.0,230394,,", 10.0 * KN, 0.0, 2),  # 360 -> 0
        ("GLRMC,123519,A,4807.038,N,01131.000,E,10.0,-1e-300,230394,,", 10.0 * KN, 0.0, 2),  # not 360 (rounding)
        ("GPRMC,123519,A,4807.038,N,01131.000,E,0.0,,230394,,", 0.0, math.nan, 2),  # standing: no course
        ("GPVTG,054.7,T,034.4,M,005.5,N,010.2,K,A", 10.2 / 3.6, 54.7, 2),
        ("GPVTG,054.7,T,034.4,M,005.5,N,010.2,K,D", 10.2 / 3.6, 54.7, 2),
        ("GPVTG,054.7,T,034.4,M,005.5,N,010.2,K,E", 10.2 / 3.6, 54.7, 1),
        ("GPVTG,,T,,M,,N,,K,N", math.nan, math.nan, 0),
        ("GPVTG,054.7,T,034.4,M,005.5,N,010.2,K,N", 10.2 / 3.6, 54.7, 0),
        ("GPVTG,054.7,T,034.4,M,005.5,N,010.2,K", 10.2 / 3.6, 54.7, 2),  # NMEA < 2.3: no mode field
        ("GNVTG,12.5,T,,M,005.5,N,,K,A", 5.5 * KN, 12.5, 2),  # knots only
    ],
)
def test_rmc_and_vtg(parser, body, speed, course, fix):
    got = parser.feed(sentence(body) + "\r\n")
    assert got is not None
    assert got.sentence == body[2:5]
    assert got.fix_type == fix
    if math.isnan(speed):
        assert math.isnan(got.speed_mps)
    else:
        assert got.speed_mps == pytest.approx(speed, abs=1e-9)
    if math.isnan(course):
        assert math.isnan(got.course_deg)
    else:
        assert got.course_deg == pytest.approx(course)
    assert parser.counters() == {"parsed": 1, "used": 1, "checksum_errors": 0, "garbage": 0}


def test_bytes_and_lowercase_checksum(parser):
    line = sentence("GPVTG,054.7,T,034.4,M,005.5,N,010.2,K,A")
    assert parser.feed(line.encode() + b"\r\n").speed_mps == pytest.approx(10.2 / 3.6)
    assert parser.feed(line[:-2] + line[-2:].lower()) is not None


def test_gsa_3d_fix_upgrades_2d(parser):
    rmc = sentence("GNRMC,083559.00,A,4717.11437,N,00833.91522,E,10.0,77.52,091202,,,A")
    assert parser.feed(rmc).fix_type == 2
    assert parser.feed(sentence("GNGSA,A,3,23,29,07,08,09,18,26,,,,,,1.94,1.18,1.54,1")) is None
    assert parser.feed(sentence("GNGSA,A,2,,,,,,,,,,,,,1.94,1.18,1.54,2")) is None  # second system, same epoch
    assert parser.feed(rmc).fix_type == 3
    assert parser.feed(sentence("GNVTG,77.52,T,,M,10.0,N,18.52,K,A")).fix_type == 3
    # a dead-reckoning or invalid solution is never upgraded
    assert parser.feed(sentence("GNVTG,77.52,T,,M,10.0,N,18.52,K,E")).fix_type == 1
    assert parser.feed(sentence("GNRMC,083559.00,V,,,,,,,091202,,,N")).fix_type == 0
    # the next epoch's GSA says 2D
    assert parser.feed(sentence("GNGSA,A,2,23,29,07,,,,,,,,,,1.94,1.18,1.54,1")) is None
    assert parser.feed(rmc).fix_type == 2
    # a receiver that stops sending GSA: the last 3D is not trusted for long
    parser.feed(sentence("GNGSA,A,3,23,29,07,08,09,18,26,,,,,,1.94,1.18,1.54,1"))
    fixes = [parser.feed(rmc).fix_type for _ in range(8)]
    assert fixes[0] == 3 and fixes[-1] == 2


def test_checksum_errors_are_counted_and_skipped(parser):
    good = sentence("GPRMC,123519,A,4807.038,N,01131.000,E,022.4,084.4,230394,003.1,W")
    bad = [
        good[:-2] + ("00" if good[-2:] != "00" else "01"),  # wrong checksum
        good.replace("022.4", "023.4"),  # a corrupted digit
        good.split("*")[0],  # no checksum at all
    ]
    for line in bad:
        assert parser.feed(line) is None
    assert parser.counters() == {"parsed": 0, "used": 0, "checksum_errors": 3, "garbage": 0}
    assert parser.feed(good) is not None
    assert parser.counters()["parsed"] == 1


def test_garbage_is_counted_and_skipped(parser):
    lines = [
        "hello world",
        b"\xff\xfe\x00\x13\x88",  # noise at a wrong baud rate
        b"$GPRMC,12\xff\xfe",
        "123519,A,4807.038,N*5C",  # tail of a sentence cut off at connect
        sentence("GPXYZ,1,2,3"),  # valid checksum, unknown sentence type
        sentence("GPRMC,123519,A,4807.038,N,01131.000,E,fast,084.4,230394,,"),  # malformed speed
        sentence("GPVTG,054.7,T,034.4,M,005.5,N,-10.2,K,A"),  # negative speed
        sentence("GPVTG,nan,T,034.4,M,005.5,N,10.2,K,A"),  # course not finite
        "$" + "A" * 300,
    ]
    for line in lines:
        assert parser.feed(line) is None, line
    assert parser.feed("") is None and parser.feed("\r\n") is None  # blank lines are not counted
    assert parser.counters() == {"parsed": 0, "used": 0, "checksum_errors": 0, "garbage": len(lines)}


def test_other_sentences_are_parsed_but_not_used(parser):
    assert parser.feed("$GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,*47") is None
    assert parser.feed(sentence("GPGSV,3,1,11,03,03,111,00,04,15,270,00,06,01,010,00,13,06,292,00")) is None
    assert parser.counters() == {"parsed": 2, "used": 0, "checksum_errors": 0, "garbage": 0}


@pytest.mark.parametrize("knots", ["999999999999", "1e308", "25000"])
def test_an_absurd_speed_a_receiver_sends_is_refused_at_the_edge_and_counted(parser, knots):
    """The parser keeps a sentence's speed as sent (the checksum is right); the edge range-checks it against
    GPS_Velocity's range in the DBC as it does a frame's, so the estimator never sees it and the input is counted
    out of range (the daemon feeds the serial solutions through `CycleRunner.on_values`)."""
    from ptw_rt.core.layout import S_GPS_SPEED
    from ptw_rt.edge.cycle import build_runner
    from ptw_rt.paths import DEFAULT_CONFIG
    from ptw_rt.service.daemon import SERIAL_GPS_MESSAGE

    fix = parser.feed(sentence(f"GPRMC,123519,A,4807.038,N,01131.000,E,{knots},084.4,230394,003.1,W,A"))
    assert fix is not None and fix.speed_mps > 100.0
    runner = build_runner(DEFAULT_CONFIG)
    good = {"SpeedOverGround": 10.0, "CourseOverGround": 84.4, "FixType": 2.0}
    runner.on_values(SERIAL_GPS_MESSAGE, 1.0, good)
    runner.on_values(
        SERIAL_GPS_MESSAGE,
        1.1,
        {"SpeedOverGround": fix.speed_mps, "CourseOverGround": fix.course_deg, "FixType": float(fix.fix_type)},
    )
    runner.tracker.fill(runner.sample, 1.105)
    assert runner.sample[S_GPS_SPEED] == 10.0  # the last sound value, held
    assert runner.tracker.summary()[SERIAL_GPS_MESSAGE]["out_of_range"] == 1


def test_missing_pynmea2_is_a_user_facing_error(monkeypatch):
    monkeypatch.setattr(nmea, "pynmea2", None)
    for make in (nmea.NmeaParser, lambda: nmea.SerialGnssReader("/dev/ttyACM0", 9600)):
        with pytest.raises(UserFacingError, match=r"pip install 'ptw-rt\[gnss\]'"):
            make()


# --- the reader over a pseudo-terminal --------------------------------------------------------------------------


def wait_for(condition, timeout: float = 3.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.01)
    return condition()


@pytest.fixture
def thread_errors(monkeypatch):
    errors = []
    monkeypatch.setattr(threading, "excepthook", lambda args: errors.append(args.exc_value))
    return errors


class Pty:
    """A pseudo-terminal pair: the test writes on the master, the reader opens the slave's path."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        self.path = os.ttyname(self.slave)

    def write(self, text: str | bytes) -> None:
        os.write(self.master, text.encode() if isinstance(text, str) else text)

    def close(self) -> None:
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass


@pytest.fixture
def reader_factory():
    pytest.importorskip("pynmea2")
    readers, ptys = [], []

    def make(port: str, **kw) -> nmea.SerialGnssReader:
        reader = nmea.SerialGnssReader(port, 9600, retry_s=0.1, **kw)
        readers.append(reader)
        return reader.start()

    make.ptys = ptys
    yield make
    for reader in readers:
        reader.stop()
    for pty in ptys:
        pty.close()


RMC = sentence("GNRMC,083559.00,A,4717.11437,N,00833.91522,E,19.438,77.52,091202,,,A") + "\r\n"
VTG = sentence("GNVTG,77.52,T,,M,10.0,N,18.52,K,D") + "\r\n"


def test_reader_receives_sentences(reader_factory, thread_errors):
    pty = Pty()
    reader_factory.ptys.append(pty)
    reader = reader_factory(pty.path)
    assert reader.latest() is None
    assert wait_for(lambda: reader.stats()["connected"])
    t0 = time.monotonic()
    pty.write(RMC)
    assert wait_for(lambda: reader.latest() is not None)
    received, speed, course, fix = reader.latest()
    assert t0 <= received <= time.monotonic()
    assert speed == pytest.approx(19.438 * KN) and course == pytest.approx(77.52) and fix == 2
    # a sentence split over two writes, then garbage and a checksum error around a VTG
    pty.write(VTG[:20])
    time.sleep(0.05)
    pty.write(VTG[20:] + "noise\r\n" + RMC[:-5] + "00\r\n")
    assert wait_for(lambda: reader.stats()["checksum_errors"] == 1)
    # one solution per epoch: the VTG after an RMC repeats its velocity and is not taken
    assert reader.latest()[1:] == (pytest.approx(19.438 * KN), pytest.approx(77.52), 2)
    stats = reader.stats()
    assert stats["parsed"] == 2 and stats["used"] == 2 and stats["garbage"] == 1
    assert stats["opens"] == 1 and stats["disconnects"] == 0 and stats["bytes"] > 0
    assert reader.bad_lines == 2  # what the daemon counts as GPS decode errors: the checksum error and the garbage
    # noise without a newline (megabytes of it were counted as no decode error at all)
    pty.write(b"x" * 20_000)
    assert wait_for(lambda: reader.bad_lines > 2)
    assert thread_errors == []


def test_reader_takes_vtg_without_rmc(reader_factory, thread_errors, monkeypatch):
    monkeypatch.setattr(nmea, "_RMC_PREFERRED_S", 0.0)  # as if the last RMC were long ago
    pty = Pty()
    reader_factory.ptys.append(pty)
    reader = reader_factory(pty.path)
    assert wait_for(lambda: reader.stats()["connected"])
    pty.write(RMC + VTG)
    assert wait_for(lambda: reader.stats()["used"] == 2)
    assert reader.latest()[1:] == (pytest.approx(18.52 / 3.6), pytest.approx(77.52), 2)
    assert thread_errors == []


def test_reader_survives_unplug_and_replug(reader_factory, thread_errors, tmp_path):
    link = tmp_path / "gnss"  # like /dev/serial/by-id/usb-u-blox...: comes and goes with the device
    first = Pty()
    reader_factory.ptys.append(first)
    link.symlink_to(first.path)
    reader = reader_factory(str(link))
    assert wait_for(lambda: reader.stats()["connected"])
    first.write(RMC)
    assert wait_for(lambda: reader.latest() is not None)

    # unplug: the device and its name vanish
    first.close()
    link.unlink()
    assert wait_for(lambda: reader.stats()["disconnects"] == 1 and not reader.stats()["connected"])
    assert wait_for(lambda: reader.stats()["open_failures"] >= 2)
    assert reader.running
    assert reader.latest() is not None  # the last solution is kept; its receive time tells its age

    # replug
    second = Pty()
    reader_factory.ptys.append(second)
    link.symlink_to(second.path)
    assert wait_for(lambda: reader.stats()["connected"] and reader.stats()["opens"] == 2)
    second.write(VTG)
    assert wait_for(lambda: reader.latest()[1] == pytest.approx(18.52 / 3.6))
    assert reader.running and thread_errors == []
    stats = reader.stats()
    assert stats["disconnects"] == 1 and stats["last_error"]
    reader.stop()
    assert not reader.running


def test_reader_waits_for_a_port_that_does_not_exist_yet(reader_factory, thread_errors, tmp_path):
    link = tmp_path / "ttyACM9"
    reader = reader_factory(str(link))
    assert wait_for(lambda: reader.stats()["open_failures"] >= 2)
    assert reader.running and not reader.stats()["connected"] and reader.latest() is None
    pty = Pty()
    reader_factory.ptys.append(pty)
    link.symlink_to(pty.path)
    assert wait_for(lambda: reader.stats()["connected"])
    pty.write(RMC)
    assert wait_for(lambda: reader.latest() is not None)
    assert thread_errors == []
