"""Daemon logging: one structured line per record, rate-limited repeats, the health line."""

from __future__ import annotations

import io
import json
import logging
import re

import pytest

from ptw_rt.errors import UserFacingError
from ptw_rt.service.logs import HealthSummary, RateLimitedLog, fields, format_fields, setup_logging

ISO = r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z"


@pytest.fixture
def restore_root():
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    yield root
    for h in list(root.handlers):
        if h not in handlers:
            root.removeHandler(h)
    root.setLevel(level)
    logging.captureWarnings(False)


class _ListHandler(logging.Handler):
    def __init__(self):
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []

    def emit(self, record):
        self.records.append(record)

    @property
    def messages(self):
        return [r.getMessage() for r in self.records]


@pytest.fixture
def captured():
    logger = logging.getLogger("ptw_rt.test_logs")
    logger.propagate = False
    logger.setLevel(logging.DEBUG)
    handler = _ListHandler()
    logger.addHandler(handler)
    yield logger, handler
    logger.removeHandler(handler)


# ---------------------------------------------------------------- setup_logging / formatters


def test_text_lines_are_structured_and_single(restore_root):
    buf = io.StringIO()
    setup_logging("info", stream=buf)
    log = logging.getLogger("ptw_rt.daemon")
    log.info("input stale", extra=fields(msg="IMU_Rates", age_ms=40, note="two words"))
    log.debug("not shown")
    try:
        raise RuntimeError("boom\nsecond line")
    except RuntimeError:
        log.exception("cycle failed\nwith newline")
    lines = buf.getvalue().splitlines()
    assert len(lines) == 2
    assert re.fullmatch(ISO + r' INFO ptw_rt\.daemon: input stale msg=IMU_Rates age_ms=40 note="two words"', lines[0])
    assert re.match(ISO + r" ERROR ptw_rt\.daemon: cycle failed\\nwith newline exc=\"Traceback", lines[1])
    assert "RuntimeError: boom" in lines[1]


def test_control_characters_are_escaped_and_text_kept(restore_root):
    """A message carrying an untrusted name (a device, a state file's path) with ESC, NUL or a C1 control went to
    the journal raw: journalctl shows such a line as a blob, and a terminal takes ESC as a command. Escaped now,
    in the message and in the fields; the daemon's own UTF-8 (deg, us) kept."""
    buf = io.StringIO()
    setup_logging("info", stream=buf)
    logging.getLogger("ptw_rt.daemon").warning(
        "state file /tmp/a\x1b[2Jb\x00c\x85d\te refused (4.2 \u00b0, 12 \u00b5s)", extra=fields(path="x\x1by\x07")
    )
    (line,) = buf.getvalue().splitlines()
    assert not re.search("[\x00-\x1f\x7f-\x9f]", line), repr(line)
    assert "/tmp/a\\x1b[2Jb\\x00c\\x85d\\x09e refused (4.2 \u00b0, 12 \u00b5s)" in line
    assert "path=x\\x1by\\x07" in line


def test_json_lines(restore_root):
    buf = io.StringIO()
    setup_logging("DEBUG", json_lines=True, stream=buf)
    log = logging.getLogger("ptw_rt.daemon")
    log.debug("saved state", extra=fields(path="/var/lib/ptw-rt/state.json", stiffness=(1.0, float("nan"))))
    log.warning("plain")
    docs = [json.loads(line) for line in buf.getvalue().splitlines()]
    assert len(docs) == 2
    assert docs[0]["level"] == "DEBUG" and docs[0]["msg"] == "saved state"
    assert docs[0]["path"] == "/var/lib/ptw-rt/state.json"
    assert docs[0]["stiffness"] == [1.0, "nan"]
    assert re.fullmatch(ISO, docs[0]["ts"])
    assert docs[1] == {"ts": docs[1]["ts"], "level": "WARNING", "logger": "ptw_rt.daemon", "msg": "plain"}


def test_setup_twice_replaces_handler(restore_root):
    a, b = io.StringIO(), io.StringIO()
    setup_logging("INFO", stream=a)
    setup_logging("WARNING", stream=b)
    logging.getLogger("ptw_rt.x").warning("once")
    logging.getLogger("ptw_rt.x").info("filtered")
    assert a.getvalue() == ""
    assert b.getvalue().count("\n") == 1


def test_bad_level_is_user_facing(restore_root):
    with pytest.raises(UserFacingError):
        setup_logging("LOUD")


def test_format_fields_quotes():
    assert format_fields({"a": 1, "b": 0.1234567, "c": "x y", "d": "", "e": [], "f": {"rx": 3}}) == (
        'a=1 b=0.123457 c="x y" d="" e=- f=rx:3'
    )


# ---------------------------------------------------------------- RateLimitedLog


def test_dying_sensor_produces_a_handful_of_lines(captured):
    logger, handler = captured
    rl = RateLimitedLog(logger, repeat_interval_s=5.0)
    written = 0
    for k in range(1000):  # 1000 warnings over 10 s (100 Hz)
        now = 100.0 + k * 0.01
        written += rl.warn("stale:IMU_Rates", "IMU_Rates stale", now, age_ms=40 + k)
    assert written == len(handler.records)
    assert 1 <= len(handler.records) <= 3
    assert handler.messages[0] == "IMU_Rates stale"
    assert handler.messages[1] == "IMU_Rates stale (499 repeats suppressed)"
    assert handler.records[1].ptw_fields["suppressed"] == 499
    assert all(r.levelno == logging.WARNING for r in handler.records)
    pending = rl.suppressed("stale:IMU_Rates")
    assert len(handler.records) - 1 + sum(r.ptw_fields.get("suppressed", 0) for r in handler.records) + pending == 999


def test_flush_reports_pending_count_after_condition_stops(captured):
    logger, handler = captured
    rl = RateLimitedLog(logger, repeat_interval_s=5.0)
    for k in range(10):
        rl.warn("crc", "CRC error", 0.0 + k * 0.1)
    assert handler.messages == ["CRC error"]
    assert rl.flush(3.0) == 0  # interval not yet over
    assert rl.flush(5.5) == 1
    assert handler.messages[-1] == "CRC error (9 repeats suppressed)"
    assert rl.flush(20.0) == 0  # nothing pending any more
    assert rl.warn("crc", "CRC error", 21.0)  # forgotten key: logged at once again
    assert handler.messages[-1] == "CRC error"


def test_keys_are_independent(captured):
    logger, handler = captured
    rl = RateLimitedLog(logger, repeat_interval_s=5.0)
    assert rl.warn("a", "sensor a", 0.0)
    assert rl.warn("b", "sensor b", 0.1)
    assert not rl.warn("a", "sensor a", 0.2)
    assert not rl.warn("a", "sensor a", 0.3)
    assert not rl.warn("b", "sensor b", 0.4)
    assert rl.suppressed("a") == 2 and rl.suppressed("b") == 1
    assert rl.warn("a", "sensor a", 5.0)
    assert rl.suppressed("a") == 0 and rl.suppressed("b") == 1
    assert handler.messages == ["sensor a", "sensor b", "sensor a (2 repeats suppressed)"]


def test_clear_and_zero_interval(captured):
    logger, handler = captured
    rl = RateLimitedLog(logger, repeat_interval_s=5.0)
    rl.error("x", "bad", 0.0)
    rl.error("x", "bad", 1.0)
    rl.clear("x")
    assert handler.messages == ["bad", "bad (1 repeats suppressed)"]
    assert handler.records[0].levelno == logging.ERROR
    every = RateLimitedLog(logger, repeat_interval_s=0.0)
    assert all(every.warn("y", "each", t * 0.01) for t in range(5))


def test_max_keys_bounded(captured):
    logger, _ = captured
    rl = RateLimitedLog(logger, repeat_interval_s=5.0, max_keys=8)
    for k in range(100):
        rl.warn(f"k{k}", "x", 0.0)
    assert len(rl._keys) <= 8


def test_negative_interval_rejected():
    with pytest.raises(ValueError):
        RateLimitedLog("x", repeat_interval_s=-1)


# ---------------------------------------------------------------- HealthSummary


def test_health_summary_line(captured):
    s = HealthSummary(
        mode=3,
        reasons=(1 << 2) | (1 << 7),
        cycles=6000,
        overruns=2,
        worst_cycle_us=1834.26,
        inputs={"IMU_Rates": {"rx": 5990, "decode_err": 0, "jumps": 1}, "GPS_Velocity": {"rx": 600}},
    )
    line = s.format()
    assert "\n" not in line
    assert line == (
        "health mode=DEGRADED reasons=sensor_stale,overrun cycles=6000 overruns=2 worst_cycle_us=1834.3 "
        "IMU_Rates=rx:5990,decode_err:0,jumps:1 GPS_Velocity=rx:600"
    )
    assert str(s) == line
    ok = HealthSummary(mode="VALID", reasons=0, cycles=1)
    assert ok.format() == "health mode=VALID reasons=- cycles=1 overruns=0 worst_cycle_us=0"
    logger, handler = captured
    s.log(logger)
    assert handler.messages == ["health"]
    assert handler.records[0].ptw_fields["reasons"] == ["sensor_stale", "overrun"]
    assert json.dumps(s.as_fields())  # serialisable for --json / JSON logs
