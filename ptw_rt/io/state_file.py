"""The persisted learned tyre stiffness: a small JSON file written atomically, read back defensively.

The daemon saves the adapted stiffnesses every ``state_save_interval_s`` and at shutdown, and starts
from them at the next boot. A power cut at any moment must leave either the old or the new file,
never a half-written one: ``save_state`` writes a temporary file in the same directory, flushes and
fsyncs it, ``os.replace``-s it over the target and fsyncs the directory.

``load_state`` never raises for bad content: a missing, unreadable, corrupt or foreign file, a file
written for another configuration (config hash mismatch) or one holding non-finite or non-positive
values gives ``(None, reason)`` and the daemon starts from the configured nominal stiffnesses.

File content (format ``ptw-rt-state``, version 1)::

    {"format": "ptw-rt-state", "version": 1, "config_hash": "...", "saved_at": "2024-05-01T12:00:00.000+00:00",
     "stiffness": {"front_cornering": ..., "front_camber": ..., "rear_cornering": ..., "rear_camber": ...},
     "extra": {...}}
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

__all__ = [
    "STATE_FORMAT",
    "STATE_VERSION",
    "STIFFNESS_KEYS",
    "LoadedState",
    "load_state",
    "save_state",
]

STATE_FORMAT = "ptw-rt-state"
STATE_VERSION = 1
# order of the ``stiffness`` sequence: C_af, C_gf, C_ar, C_gr (N/rad)
STIFFNESS_KEYS = ("front_cornering", "front_camber", "rear_cornering", "rear_camber")
_MAX_BYTES = 1 << 20  # a state file is a few hundred bytes; anything this large is not ours
_TMP_SUFFIX = ".tmp"


@dataclass(frozen=True)
class LoadedState:
    """A state file that passed every check. ``stiffness`` is (C_af, C_gf, C_ar, C_gr) in N/rad."""

    stiffness: tuple[float, float, float, float]
    config_hash: str
    saved_at: str
    extra: dict[str, Any] = field(default_factory=dict)


def _is_positive_finite(v: object) -> bool:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return False
    try:
        f = float(v)
    except OverflowError:  # an int beyond float range
        return False
    return math.isfinite(f) and f > 0


def _check_stiffness(stiffness: Sequence[float]) -> tuple[float, float, float, float]:
    try:
        values = tuple(float(v) for v in stiffness)
    except (TypeError, ValueError):
        raise ValueError(f"stiffness must be 4 numbers, got {stiffness!r}") from None
    if len(values) != len(STIFFNESS_KEYS):
        raise ValueError(f"stiffness must be 4 numbers (C_af, C_gf, C_ar, C_gr), got {len(values)}")
    bad = [k for k, v in zip(STIFFNESS_KEYS, values, strict=True) if not (math.isfinite(v) and v > 0)]
    if bad:
        raise ValueError(f"stiffness must be finite and positive: {', '.join(bad)}")
    return values  # type: ignore[return-value]


def _fsync_dir(directory: Path) -> None:
    """Make a rename in ``directory`` durable. Not possible on every platform/file system: best effort."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def save_state(
    path: Path | str,
    stiffness: Sequence[float],
    config_hash: str,
    extra: Mapping[str, Any] | None = None,
) -> Path:
    """Atomically write the learned stiffness (C_af, C_gf, C_ar, C_gr in N/rad) to ``path``; returns the path.

    Creates the parent directory if missing. Raises ``ValueError`` for non-finite or non-positive values
    (nothing is written), ``TypeError`` if ``extra`` is not JSON-serialisable and ``OSError`` if the file
    cannot be written; the previous file, if any, is then left untouched and no temporary file remains.
    """
    path = Path(path)
    values = _check_stiffness(stiffness)
    doc: dict[str, Any] = {
        "format": STATE_FORMAT,
        "version": STATE_VERSION,
        "config_hash": str(config_hash),
        "saved_at": datetime.now(timezone.utc).isoformat(timespec="milliseconds"),
        "stiffness": dict(zip(STIFFNESS_KEYS, values, strict=True)),
    }
    if extra:
        doc["extra"] = dict(extra)
    text = json.dumps(doc, indent=2, allow_nan=False) + "\n"

    directory = path.parent
    directory.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(dir=directory, prefix=f".{path.name}.", suffix=_TMP_SUFFIX)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp_name, 0o644)
        os.replace(tmp_name, path)
    except BaseException:
        try:
            os.unlink(tmp_name)
        except OSError:
            pass
        raise
    _fsync_dir(directory)
    return path


def load_state(path: Path | str, config_hash: str) -> tuple[LoadedState | None, str]:
    """Read a state file written by ``save_state`` for the configuration ``config_hash``.

    Returns ``(LoadedState, "ok")``, or ``(None, reason)`` with a one-line human-readable reason if the
    file is missing, unreadable, not JSON, of another format/version, written for another configuration
    or holds non-finite or non-positive stiffness values. Never raises for bad file content.
    """
    path = Path(path)
    try:
        with open(path, "rb") as f:
            raw = f.read(_MAX_BYTES + 1)
    except FileNotFoundError:
        return None, f"no state file at {path}"
    except OSError as exc:
        return None, f"state file {path} unreadable: {exc.strerror or exc}"
    if len(raw) > _MAX_BYTES:
        return None, f"state file {path} too large (> {_MAX_BYTES} bytes)"
    try:
        doc = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as exc:  # JSONDecodeError is a ValueError
        return None, f"state file {path} is not valid JSON: {exc}"
    if not isinstance(doc, dict):
        return None, f"state file {path} is not a JSON object"
    if doc.get("format") != STATE_FORMAT:
        return None, f"state file {path} has wrong format {doc.get('format')!r} (expected {STATE_FORMAT!r})"
    version = doc.get("version")
    if version != STATE_VERSION or isinstance(version, bool):
        return None, f"state file {path} has unsupported version {version!r} (expected {STATE_VERSION})"
    saved_hash = doc.get("config_hash")
    if not isinstance(saved_hash, str):
        return None, f"state file {path} has no config_hash"
    if saved_hash != config_hash:
        return None, (
            f"state file {path} was saved for another configuration (config hash {saved_hash[:12]}, "
            f"current {str(config_hash)[:12]})"
        )
    stiff = doc.get("stiffness")
    if not isinstance(stiff, dict):
        return None, f"state file {path} has no stiffness object"
    missing = [k for k in STIFFNESS_KEYS if k not in stiff]
    if missing:
        return None, f"state file {path} lacks stiffness values: {', '.join(missing)}"
    bad = [k for k in STIFFNESS_KEYS if not _is_positive_finite(stiff[k])]
    if bad:
        shown = ", ".join(f"{k}={stiff[k]!r}" for k in bad)
        return None, f"state file {path} has non-finite or non-positive stiffness: {shown}"
    saved_at = doc.get("saved_at")
    extra = doc.get("extra")
    state = LoadedState(
        stiffness=tuple(float(stiff[k]) for k in STIFFNESS_KEYS),  # type: ignore[arg-type]
        config_hash=saved_hash,
        saved_at=saved_at if isinstance(saved_at, str) else "",
        extra=extra if isinstance(extra, dict) else {},
    )
    return state, "ok"
