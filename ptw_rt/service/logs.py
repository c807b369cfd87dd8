"""The daemon's logging: one structured line per record, repeats rate-limited, a periodic health line.

* ``setup_logging(level, json_lines=False)`` installs one stderr handler on the root logger.
  Text lines look like ``2024-05-01T12:00:00.123Z WARNING ptw_rt.daemon: input stale msg=IMU_Rates age_ms=40``;
  with ``json_lines`` every record is one JSON object (``ts``, ``level``, ``logger``, ``msg`` and the fields).
  Structured fields are passed with ``extra=fields(key=value, ...)``.
* ``RateLimitedLog`` keeps a dying sensor (100 warnings a second) from flooding the journal: the first
  occurrence of a key is logged at once, repeats within ``repeat_interval_s`` are counted, and the next
  occurrence after the interval (or ``flush``) logs one line ending in ``(N repeats suppressed)``.
* ``HealthSummary`` formats the periodic one-line health report.
"""

from __future__ import annotations

import json
import logging
import math
import sys
from collections.abc import Mapping
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import IO, Any

from ptw_rt.core.layout import MODE_NAMES as _MODE_NAMES
from ptw_rt.core.layout import REASON_NAMES as _REASON_NAMES
from ptw_rt.errors import UserFacingError
from ptw_rt.untrusted import log_line, one_line

__all__ = [
    "FIELDS_ATTR",
    "HealthSummary",
    "JsonLineFormatter",
    "KeyValueFormatter",
    "RateLimitedLog",
    "fields",
    "format_fields",
    "setup_logging",
]

FIELDS_ATTR = "ptw_fields"
LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")
_HANDLER_MARK = "_ptw_rt_handler"


def fields(**kw: Any) -> dict[str, Any]:
    """Structured fields for one record: ``log.warning("input stale", extra=fields(msg="IMU_Rates", age_ms=40))``."""
    return {FIELDS_ATTR: kw}


def _fmt_value(v: Any) -> str:
    if isinstance(v, float):
        if not math.isfinite(v):
            return str(v)
        return f"{v:.6g}"
    if isinstance(v, Mapping):
        s = ",".join(f"{k}:{_fmt_value(x)}" for k, x in v.items())
    elif isinstance(v, (list, tuple, set, frozenset)):
        s = ",".join(_fmt_value(x) for x in v) if v else "-"
    else:
        s = str(v)
    if s == "" or any(c in s for c in ' "=\n\r\t'):
        return json.dumps(s)  # quoted, newlines escaped: always one line
    return s


def format_fields(kw: Mapping[str, Any]) -> str:
    """``key=value key=value`` (values with spaces, quotes or ``=`` are JSON-quoted)."""
    return " ".join(f"{k}={_fmt_value(v)}" for k, v in kw.items())


def _iso_utc(created: float) -> str:
    return datetime.fromtimestamp(created, tz=timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z")


class KeyValueFormatter(logging.Formatter):
    """``<ISO time> <LEVEL> <logger>: <message> key=value ...``, always exactly one line."""

    def format(self, record: logging.LogRecord) -> str:
        parts = [_iso_utc(record.created), record.levelname, f"{record.name}:", record.getMessage()]
        kw = getattr(record, FIELDS_ATTR, None)
        if kw:
            parts.append(format_fields(kw))
        if record.exc_info:
            parts.append("exc=" + json.dumps(self.formatException(record.exc_info)))
        elif record.exc_text:
            parts.append("exc=" + json.dumps(record.exc_text))
        return log_line(" ".join(parts))


def _jsonable(v: Any) -> Any:
    if isinstance(v, (str, int, bool)) or v is None:
        return v
    if isinstance(v, float):
        return v if math.isfinite(v) else str(v)
    if isinstance(v, Mapping):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple, set, frozenset)):
        return [_jsonable(x) for x in v]
    try:  # numpy scalars
        return _jsonable(v.item())
    except AttributeError:
        return str(v)


class JsonLineFormatter(logging.Formatter):
    """One JSON object per record: ``ts``, ``level``, ``logger``, ``msg``, the fields, ``exc`` if any."""

    def format(self, record: logging.LogRecord) -> str:
        doc: dict[str, Any] = {
            "ts": _iso_utc(record.created),
            "level": record.levelname,
            "logger": record.name,
            "msg": record.getMessage(),
        }
        kw = getattr(record, FIELDS_ATTR, None)
        if kw:
            for k, v in kw.items():
                doc[k if k not in doc else f"field_{k}"] = _jsonable(v)
        if record.exc_info:
            doc["exc"] = self.formatException(record.exc_info)
        return json.dumps(doc)


def setup_logging(level: str = "INFO", json_lines: bool = False, *, stream: IO[str] | None = None) -> logging.Handler:
    """Install the daemon's log handler on the root logger (replacing one installed earlier); returns it.

    ``level`` is one of DEBUG, INFO, WARNING, ERROR (case-insensitive); anything else is a ``UserFacingError``.
    Output goes to ``stream`` (default stderr, which systemd sends to the journal).
    """
    name = str(level).upper()
    if name not in LEVELS:
        raise UserFacingError(f"log level must be one of {', '.join(LEVELS)}, got {level!r}")
    handler = logging.StreamHandler(stream if stream is not None else sys.stderr)
    handler.setFormatter(JsonLineFormatter() if json_lines else KeyValueFormatter())
    _install(handler)
    logging.getLogger().setLevel(getattr(logging, name))
    logging.captureWarnings(True)
    return handler


class _StderrNow(logging.StreamHandler):
    """Writes to ``sys.stderr`` as it is at each record (a stream redirected after the start, a test's capture), as
    Python's last-resort handler does."""

    @property
    def stream(self) -> IO[str]:  # type: ignore[override]
        return sys.stderr

    @stream.setter
    def stream(self, value: IO[str]) -> None:
        pass


class MessageLineFormatter(logging.Formatter):
    """A command's warning as its bare message (what Python's last resort printed), always one line: a log file
    named ``x\nerror: y.log: ...`` in a replayed directory forged an error line of its own."""

    def format(self, record: logging.LogRecord) -> str:
        return one_line(record.getMessage())


def setup_command_logging() -> None:
    """For the commands other than the daemon (which calls `setup_logging`, replacing this): warnings and errors on
    stderr, one line each (`MessageLineFormatter`)."""
    handler = _StderrNow()
    handler.setLevel(logging.WARNING)
    handler.setFormatter(MessageLineFormatter())
    _install(handler)


def _install(handler: logging.Handler) -> None:
    """``handler`` on the root logger, in place of the one ours installed before (marked ``_HANDLER_MARK``)."""
    root = logging.getLogger()
    for h in list(root.handlers):
        if getattr(h, _HANDLER_MARK, False):
            root.removeHandler(h)
            h.close()
    setattr(handler, _HANDLER_MARK, True)
    root.addHandler(handler)


@dataclass
class _KeyState:
    window_start: float
    suppressed: int = 0
    last_message: str = ""
    last_level: int = logging.WARNING
    last_fields: dict[str, Any] = field(default_factory=dict)


class RateLimitedLog:
    """Log a recurring condition once per ``repeat_interval_s`` per key, counting the repeats in between.

    ``warn(key, message, now)``: the first occurrence of ``key`` is logged at once; later ones within
    ``repeat_interval_s`` of the last logged line are only counted; the first one after the interval is
    logged with `` (N repeats suppressed)`` appended. ``flush(now)`` reports pending counts of keys whose
    interval has passed even if the condition stopped recurring (call it from the periodic health log).
    ``now`` is any monotonic clock in seconds. Keys are independent. ``repeat_interval_s = 0`` logs everything.
    """

    def __init__(self, logger: logging.Logger | str, repeat_interval_s: float = 5.0, max_keys: int = 1024) -> None:
        if not repeat_interval_s >= 0:
            raise ValueError(f"repeat_interval_s must be >= 0, got {repeat_interval_s}")
        self.logger = logging.getLogger(logger) if isinstance(logger, str) else logger
        self.repeat_interval_s = float(repeat_interval_s)
        self.max_keys = int(max_keys)
        self._keys: dict[str, _KeyState] = {}

    def suppressed(self, key: str) -> int:
        """Repeats of ``key`` counted but not yet reported."""
        st = self._keys.get(key)
        return 0 if st is None else st.suppressed

    def _emit(self, level: int, message: str, suppressed: int, kw: Mapping[str, Any]) -> None:
        text = f"{message} ({suppressed} repeats suppressed)" if suppressed else message
        kw = {**kw, "suppressed": suppressed} if suppressed else kw
        extra = fields(**kw) if kw else None
        self.logger.log(level, text, extra=extra)

    def log(self, level: int, key: str, message: str, now: float, **kw: Any) -> bool:
        """Log ``message`` at ``level`` unless ``key`` was logged less than ``repeat_interval_s`` ago.

        Returns True if a line was written. ``kw`` are structured fields (see ``fields``).
        """
        st = self._keys.get(key)
        if st is None:
            if len(self._keys) >= self.max_keys:
                self._evict(now)
            self._keys[key] = _KeyState(window_start=now)
            self._emit(level, message, 0, kw)
            return True
        if now - st.window_start >= self.repeat_interval_s or now < st.window_start:
            n = st.suppressed
            st.window_start, st.suppressed, st.last_fields = now, 0, {}
            self._emit(level, message, n, kw)
            return True
        st.suppressed += 1
        st.last_message, st.last_level, st.last_fields = message, level, kw
        return False

    def warn(self, key: str, message: str, now: float, **kw: Any) -> bool:
        return self.log(logging.WARNING, key, message, now, **kw)

    warning = warn

    def error(self, key: str, message: str, now: float, **kw: Any) -> bool:
        return self.log(logging.ERROR, key, message, now, **kw)

    def info(self, key: str, message: str, now: float, **kw: Any) -> bool:
        return self.log(logging.INFO, key, message, now, **kw)

    def flush(self, now: float) -> int:
        """Report the pending repeat counts of keys whose interval has passed, and forget those keys.

        A key forgotten here is logged at once when it recurs. Returns the number of lines written.
        """
        written = 0
        for key in list(self._keys):
            st = self._keys[key]
            if now - st.window_start < self.repeat_interval_s and now >= st.window_start:
                continue
            if st.suppressed:
                self._emit(st.last_level, st.last_message, st.suppressed, st.last_fields)
                written += 1
            del self._keys[key]
        return written

    def clear(self, key: str) -> None:
        """The condition behind ``key`` is over: report its pending repeats (if any) and forget it."""
        st = self._keys.pop(key, None)
        if st is not None and st.suppressed:
            self._emit(st.last_level, st.last_message, st.suppressed, st.last_fields)

    def _evict(self, now: float) -> None:
        self.flush(now)
        while len(self._keys) >= self.max_keys:
            oldest = min(self._keys, key=lambda k: self._keys[k].window_start)
            self.clear(oldest)


def _mode_name(mode: int | str) -> str:
    if isinstance(mode, str):
        return mode
    m = int(mode)
    return _MODE_NAMES[m] if 0 <= m < len(_MODE_NAMES) else f"MODE{m}"


def _reason_list(reasons: int | str | list[str] | tuple[str, ...]) -> list[str]:
    if isinstance(reasons, str):
        return [reasons] if reasons else []
    if isinstance(reasons, (list, tuple)):
        return [str(r) for r in reasons]
    bits = int(reasons)
    out = [name for k, name in enumerate(_REASON_NAMES) if bits >> k & 1]
    out += [f"bit{k}" for k in range(len(_REASON_NAMES), 16) if bits >> k & 1]
    return out


@dataclass
class HealthSummary:
    """One periodic health line: ``health mode=VALID reasons=- cycles=6000 overruns=0 worst_cycle_us=812 ...``.

    ``mode`` is an EST_Status Mode number or name, ``reasons`` the ReasonBits (or a list of names),
    ``inputs`` per-input counters, e.g. ``{"IMU_Rates": {"rx": 6000, "decode_err": 0, "jumps": 1}}``.
    """

    mode: int | str
    reasons: int | str | list[str] | tuple[str, ...] = 0
    cycles: int = 0
    overruns: int = 0
    worst_cycle_us: float = 0.0
    inputs: dict[str, Any] = field(default_factory=dict)

    def as_fields(self) -> dict[str, Any]:
        """The summary as structured fields (for ``extra=fields(**summary.as_fields())`` or JSON)."""
        out: dict[str, Any] = {
            "mode": _mode_name(self.mode),
            "reasons": _reason_list(self.reasons),
            "cycles": int(self.cycles),
            "overruns": int(self.overruns),
            "worst_cycle_us": round(float(self.worst_cycle_us), 1),
        }
        for name, counters in self.inputs.items():
            out[str(name)] = dict(counters) if isinstance(counters, Mapping) else counters
        return out

    def format(self) -> str:
        f = self.as_fields()
        f["reasons"] = f["reasons"] or "-"
        return "health " + format_fields(f)

    __str__ = format

    def log(self, logger: logging.Logger, level: int = logging.INFO) -> None:
        """Write the summary as one record: message ``health``, the summary as fields."""
        logger.log(level, "health", extra=fields(**self.as_fields()))
