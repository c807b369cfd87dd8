"""python-can's SQLite CAN log (``can.SqliteWriter``/``SqliteReader``, ``.db``), read and written within bounds.

The file is one table ``messages(ts REAL, arbitration_id INTEGER, extended INTEGER, remote INTEGER, error INTEGER,
dlc INTEGER, data BLOB)``, a row per frame in the order logged. python-can's reader opens the file read-write (it
creates a missing one) and runs ``SELECT * FROM messages`` on whatever the file declares. An SQLite file is a
program as much as data: ``messages`` may be a view whose recursive query never ends, a row may hold a blob of
gigabytes, a column may hold text where a number belongs. So ``rows``:

* opens the file read-only and immutable (no journal, no lock, nothing written or created), with the schema
  untrusted (``PRAGMA trusted_schema = OFF``: no function of the schema runs);
* reads ``messages`` only when it is a table (a view or a virtual table is refused), its seven columns by name;
* bounds a value at ``MAX_VALUE_BYTES`` (SQLite's length limit: a larger one ends the log there, counted) and the
  time at ``TIME_BUDGET_S`` plus ``TIME_PER_MB_S`` per MB of file (a progress handler interrupts the query);
* gives each row as it is read (no ``fetchall``), and a row whose values are not the schema's types as a problem.

``SqliteLogWriter`` writes the same table (what python-can reads back), in the caller's thread: python-can's writer
runs a thread of its own whose errors a caller cannot see (a full disk would lose the log silently), so errors here
are ``OSError`` like every other output's (replay's exit code 74).
"""

from __future__ import annotations

import errno
import math
import sqlite3
import time
import urllib.parse
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

from ptw_rt.untrusted import error_text

MAGIC = b"SQLite format 3\x00"
TABLE = "messages"
COLUMNS = ("ts", "arbitration_id", "extended", "remote", "error", "dlc", "data")
MAX_VALUE_BYTES = 1 << 16  # a frame's data is at most 64 bytes (CAN FD): any value beyond is no frame's
TIME_BUDGET_S = 10.0
TIME_PER_MB_S = 2.0
WRITE_BATCH = 4096  # rows per INSERT batch


class SqliteLogError(ValueError):
    """The file cannot be read as python-can's SQLite log at all (one line)."""


Row = tuple[float, int, bool, bool, bool, bytes]  # time stamp, id, extended, remote, error, data


def rows(path: str | Path, size: int, declared: Callable[[int], None] | None = None) -> Iterator[tuple[int, Row | str]]:
    """(row number, frame fields) for each row, or (row number, why it is no frame); ``SqliteLogError`` when the
    file is no python-can SQLite log. Stops, with a last (row, why) item, when SQLite cannot go on (a corrupt
    page, a value beyond the bound, the time budget spent). ``declared``: called once with the largest row id
    (the rows to come, for a progress bar)."""
    uri = "file:" + urllib.parse.quote(str(Path(path).resolve())) + "?mode=ro&immutable=1"
    try:
        conn = sqlite3.connect(uri, uri=True, isolation_level=None, check_same_thread=True)
    except sqlite3.Error as exc:
        raise SqliteLogError(f"unreadable SQLite file ({error_text(exc)})") from None
    deadline = time.monotonic() + TIME_BUDGET_S + TIME_PER_MB_S * size / 1e6
    interrupted = []

    def watchdog() -> int:
        if time.monotonic() > deadline:
            interrupted.append(True)
            return 1  # SQLite stops the statement: "interrupted"
        return 0

    n = 0
    try:
        conn.setlimit(sqlite3.SQLITE_LIMIT_LENGTH, MAX_VALUE_BYTES)
        conn.set_progress_handler(watchdog, 10_000)
        conn.execute("PRAGMA trusted_schema = OFF")
        try:
            kind = conn.execute("SELECT type FROM sqlite_master WHERE name = ?", (TABLE,)).fetchone()
        except sqlite3.Error as exc:
            raise SqliteLogError(f"unreadable SQLite file ({error_text(exc)})") from None
        if kind is None:
            raise SqliteLogError(f"an SQLite file without python-can's table {TABLE!r}: not a CAN log")
        if kind[0] != "table":
            raise SqliteLogError(f"{TABLE!r} is a {error_text(kind[0])}, not a table: not read")
        try:
            names = {row[1] for row in conn.execute(f"PRAGMA table_info({TABLE})")}
        except sqlite3.Error as exc:
            raise SqliteLogError(f"unreadable SQLite file ({error_text(exc)})") from None
        missing = [c for c in COLUMNS if c not in names]
        if missing:
            raise SqliteLogError(f"table {TABLE!r} is not python-can's (no column {', '.join(missing)})")
        try:
            cursor = conn.execute(f"SELECT {', '.join(COLUMNS)} FROM {TABLE}")  # noqa: S608 - constant names
        except sqlite3.Error as exc:  # a corrupt first page, the budget spent
            yield 1, f"the file is not read: {'the time budget is spent' if interrupted else error_text(exc)}"
            return
        if declared is not None:
            try:
                last = conn.execute(f"SELECT max(rowid) FROM {TABLE}").fetchone()[0]  # noqa: S608
            except sqlite3.Error:
                last = 0  # a corrupt page: the rows before it are read below, and the rest said lost
            declared(last if isinstance(last, int) else 0)
        while True:
            try:
                record = cursor.fetchone()
            except sqlite3.Error as exc:
                why = "the time budget is spent" if interrupted else error_text(exc)
                yield n + 1, f"the rest of the file is not read: {why}"
                return
            if record is None:
                return
            n += 1
            yield n, _fields(record)
    finally:
        conn.close()


def _fields(record: Sequence[Any]) -> Row | str:
    ts, frame_id, extended, remote, error, dlc, data = record
    if not isinstance(ts, (int, float)) or isinstance(ts, bool):
        return f"time stamp of type {type(ts).__name__}"
    for name, value in (("arbitration_id", frame_id), ("extended", extended), ("remote", remote), ("error", error)):
        if not isinstance(value, int):
            return f"{name} of type {type(value).__name__}"
    if data is None:
        data = b""
    if not isinstance(data, bytes):
        return f"data of type {type(data).__name__}"
    return float(ts), frame_id, bool(extended), bool(remote), bool(error), data


class SqliteLogWriter:
    """Frames into a new python-can SQLite log (an existing file at ``path`` is replaced, like every output)."""

    def __init__(self, path: str | Path) -> None:
        self.name = str(path)
        self.lines_written = 0
        self._rows: list[tuple] = []
        path = Path(path)
        try:
            if path.is_file():
                path.unlink()  # python-can's writer appends to a table already there: an output is replaced
            self._conn: sqlite3.Connection | None = sqlite3.connect(str(path), isolation_level=None)
            # a new file written once: no rollback journal beside it (a failed replay removes the output, and a
            # `-journal` file would be left behind), and no fsync per batch (the replay's other outputs have none)
            self._conn.execute("PRAGMA journal_mode = OFF")
            self._conn.execute("PRAGMA synchronous = OFF")
            self._conn.execute(
                f"CREATE TABLE {TABLE} (ts REAL, arbitration_id INTEGER, extended INTEGER, remote INTEGER, "
                "error INTEGER, dlc INTEGER, data BLOB)"
            )
        except sqlite3.Error as exc:
            raise _os_error(exc) from None

    def write(self, timestamp: float, frame_id: int, data: bytes, *, extended: bool | None = None, **_: Any) -> None:
        ext = frame_id > 0x7FF if extended is None else extended
        self._rows.append((timestamp if math.isfinite(timestamp) else 0.0, frame_id, ext, 0, 0, len(data), data))
        self.lines_written += 1
        if len(self._rows) >= WRITE_BATCH:
            self.flush()

    def write_cycle(self, timestamp: float, frames: Sequence[tuple[int, bytes]]) -> None:
        for frame_id, data in frames:
            self.write(timestamp, frame_id, data)

    def flush(self) -> None:
        if not self._rows or self._conn is None:
            return
        rows_, self._rows = self._rows, []
        try:
            self._conn.execute("BEGIN")
            self._conn.executemany(f"INSERT INTO {TABLE} VALUES (?, ?, ?, ?, ?, ?, ?)", rows_)  # noqa: S608
            self._conn.execute("COMMIT")
        except sqlite3.Error as exc:
            raise _os_error(exc) from None

    def close(self) -> None:
        if self._conn is None:
            return
        try:
            self.flush()
        finally:
            conn, self._conn = self._conn, None
            conn.close()

    def __enter__(self) -> SqliteLogWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _os_error(exc: sqlite3.Error) -> OSError:
    full = "full" in str(exc)
    return OSError(errno.ENOSPC if full else errno.EIO, f"SQLite: {error_text(exc)}")
