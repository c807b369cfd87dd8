"""The persisted learned tyre stiffness: a small JSON file written atomically, read back defensively.

The daemon saves the adapted stiffnesses every ``state_save_interval_s`` and at shutdown, and starts
from them at the next boot. A power cut at any moment must leave either the old or the new file,
never a half-written one: ``save_state`` writes a temporary file in the same directory, flushes and
fsyncs it, ``os.replace``-s it over the target and fsyncs the directory.

``load_state`` never raises for bad content: a missing, unreadable, corrupt or foreign file, a file
written for another configuration (config hash mismatch; but see ``learned_state_hash`` below) or one holding a
value outside its bounds gives
``(None, reason)`` and the daemon starts from the configured nominal stiffnesses. The file is untrusted
(``ptw_rt.untrusted``): only a regular file is read (a FIFO at the path never blocks start-up), at most
``MAX_STATE_BYTES``, nesting at most ``MAX_STATE_DEPTH`` levels, checked before ``json.loads`` recurses.

Validation is driven by ``STATE_FIELDS``, one row per learned value (its JSON object and key, unit, shape,
whether it must be positive). Every value must be a finite number (positive where the row says so) and lie
within the bounds the caller passes (``stiffness_bounds``: the projection bounds of the design, i.e. what the
adaptive observer can reach); one value out of bounds rejects the whole file, because clipping it would save
the clipped value back at shutdown as if it had been learned. ``restore_state`` is the start-up entry point:
it also removes orphan temporary files of saves that were killed, and says how loudly to log the outcome.

File content (format ``ptw-rt-state``, version 1)::

    {"format": "ptw-rt-state", "version": 1, "config_hash": "...", "saved_at": "2024-05-01T12:00:00.000+00:00",
     "stiffness": {"front_cornering": ..., "front_camber": ..., "rear_cornering": ..., "rear_camber": ...},
     "sensor_biases": {"roll_gyro": ..., "pitch_gyro": ..., "yaw_gyro": ..., "lateral_accel": ...},
     "accel_biases": {"longitudinal_accel": ..., "vertical_accel": ...},
     "extra": {...}}

``sensor_biases`` (the attitude filter's gyro biases in rad/s and lateral accelerometer bias in m/s^2, bounded by
``sensor_bias_bounds``) is optional: files written before it existed still load; when present it is checked like
every other group and a bad value refuses the whole file. So is ``accel_biases`` (the longitudinal and vertical
accelerometers' biases in m/s^2, new 2026-12-06: a group of its own, so files with the four sensor biases and
without these still load; bounded like the lateral one). So is ``steer_zero``: the steering encoder's zero error
learned riding straight (``shift``, rad, bounded by ``steer_zero_bounds``) and the configured zero count it was
learned against (``zero_count``: the caller restores the shift only while the configuration still has that zero,
since a re-fitted encoder is re-zeroed in the file, not by what the last ride learned)::

     "steer_zero": {"zero_count": 512.0, "shift": 0.0061}

``learned_state_hash`` (new 2026-12-06, optional) is the configuration's hash but for the vehicle's payload
(``ptw_rt.settings.learned_state_hash``): a file saved with it is restored by a configuration whose config hash
differs from the saved one only by ``vehicle.added_mass`` (a pillion's file, or the rider's again after it), since
a payload changes no tyre and no sensor. A file without it is restored by the same config hash alone, as before.
"""

from __future__ import annotations

import json
import logging
import math
import os
import stat
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from ptw_rt.untrusted import check_nesting, check_replaceable, decode_utf8, excerpt, read_bounded

__all__ = [
    "STATE_FORMAT",
    "STATE_VERSION",
    "STIFFNESS_KEYS",
    "SENSOR_BIAS_KEYS",
    "STATE_FIELDS",
    "LoadedState",
    "StateField",
    "StateLoad",
    "group_within_bounds",
    "load_state",
    "remove_orphan_temp_files",
    "restore_state",
    "save_state",
    "sensor_bias_bounds",
    "steer_zero_bounds",
    "stiffness_bounds",
]

STATE_FORMAT = "ptw-rt-state"
STATE_VERSION = 1
# order of the ``stiffness`` sequence: C_af, C_gf, C_ar, C_gr (N/rad)
STIFFNESS_KEYS = ("front_cornering", "front_camber", "rear_cornering", "rear_camber")
MAX_STATE_BYTES = 64 * 1024  # a state file is a few hundred bytes; anything this large is not ours
MAX_STATE_DEPTH = 8  # JSON nesting (today 2: the document and its "stiffness" object)
_TMP_SUFFIX = ".tmp"
_BOUND_TOLERANCE = 1e-9  # relative: nominal + deviation - nominal may exceed the bound by a rounding error


@dataclass(frozen=True)
class StateField:
    """One learned value of the state file: ``doc[group][key]``, a number or a nested list of ``shape``."""

    group: str
    key: str
    unit: str
    shape: tuple[int, ...] = ()
    positive: bool = True  # a stiffness is > 0; a covariance's off-diagonal terms are not
    optional: bool = False  # its group may be absent (older files); if present, every key of it is checked

    @property
    def name(self) -> str:
        return f"{self.group}.{self.key}"


# The learned values: what load_state checks (bounds come from the caller, keyed by StateField.name).
# order of the ``sensor_biases`` sequence: the attitude filter's b_p, b_q, b_r [rad/s] and b_ay [m/s^2]
SENSOR_BIAS_KEYS = ("roll_gyro", "pitch_gyro", "yaw_gyro", "lateral_accel")
_SENSOR_BIAS_UNITS = ("rad/s", "rad/s", "rad/s", "m/s^2")
# order of the ``accel_biases`` sequence: the attitude filter's b_ax and b_az [m/s^2]
ACCEL_BIAS_KEYS = ("longitudinal_accel", "vertical_accel")
# order of the ``steer_zero`` pair: the configured zero count it was learned against, the zero error [rad]
STEER_ZERO_KEYS = ("zero_count", "shift")
STATE_FIELDS: tuple[StateField, ...] = (
    tuple(StateField("stiffness", key, "N/rad") for key in STIFFNESS_KEYS)
    + tuple(
        StateField("sensor_biases", key, unit, positive=False, optional=True)
        for key, unit in zip(SENSOR_BIAS_KEYS, _SENSOR_BIAS_UNITS, strict=True)
    )
    + tuple(StateField("accel_biases", key, "m/s^2", positive=False, optional=True) for key in ACCEL_BIAS_KEYS)
    + tuple(
        StateField("steer_zero", key, unit, positive=False, optional=True)
        for key, unit in zip(STEER_ZERO_KEYS, ("count", "rad"), strict=True)
    )
)

Bounds = Mapping[str, tuple[float, float]]


def stiffness_bounds(nominal: Sequence[float], deviation_bound: Sequence[float]) -> dict[str, tuple[float, float]]:
    """Bounds of the four stiffnesses: nominal +- the adaptive observer's projection bound (design file's
    ``ad_theta_nominal`` and ``ad_theta_bound``), the only values the observer can ever have learned."""
    return {
        f"stiffness.{key}": (float(n) - abs(float(b)), float(n) + abs(float(b)))
        for key, n, b in zip(STIFFNESS_KEYS, nominal, deviation_bound, strict=True)
    }


def sensor_bias_bounds(max_gyro_bias: float, max_accel_bias: float) -> dict[str, tuple[float, float]]:
    """Bounds of the persisted sensor and accelerometer biases: +- what the attitude filter may plausibly have
    learned."""
    limits = (max_gyro_bias, max_gyro_bias, max_gyro_bias, max_accel_bias)
    bounds = {f"sensor_biases.{key}": (-abs(b), abs(b)) for key, b in zip(SENSOR_BIAS_KEYS, limits, strict=True)}
    bounds.update({f"accel_biases.{key}": (-abs(max_accel_bias), abs(max_accel_bias)) for key in ACCEL_BIAS_KEYS})
    return bounds


def steer_zero_bounds(max_shift: float, counts_per_rev: float) -> dict[str, tuple[float, float]]:
    """Bounds of the persisted steer zero: the shift within +-``max_shift`` rad (what the conditioning may learn),
    the zero count on the encoder."""
    return {"steer_zero.shift": (-abs(max_shift), abs(max_shift)), "steer_zero.zero_count": (0.0, counts_per_rev)}


@dataclass(frozen=True)
class LoadedState:
    """A state file that passed every check. ``stiffness`` is (C_af, C_gf, C_ar, C_gr) in N/rad."""

    stiffness: tuple[float, float, float, float]
    config_hash: str
    saved_at: str
    same_config: bool = True  # False: restored through ``learned_state_hash`` (saved with another payload)
    extra: dict[str, Any] = field(default_factory=dict)
    values: dict[str, Any] = field(default_factory=dict)  # every STATE_FIELDS value by StateField.name
    sensor_biases: tuple[float, float, float, float] | None = None  # SENSOR_BIAS_KEYS order, if the file has them
    accel_biases: tuple[float, float] | None = None  # ACCEL_BIAS_KEYS order, if the file has them
    steer_zero: tuple[float, float] | None = None  # (zero_count, shift [rad]), if the file has them


@dataclass(frozen=True)
class StateLoad:
    """What ``restore_state`` found: the state (or None), why, how loudly to log it, orphans removed."""

    state: LoadedState | None
    reason: str
    level: int  # logging.INFO (restored, or no file yet) or logging.WARNING (a file was there and refused)
    removed_temp_files: tuple[str, ...] = ()


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


def _finite_group(values: Sequence[float], keys: tuple[str, ...], expected: str) -> dict[str, float]:
    """``values`` as the state file's object of ``keys``; ValueError ("expected ...", nothing written) unless they
    are exactly that many finite numbers."""
    numbers = [float(v) for v in values]
    if len(numbers) != len(keys) or not all(math.isfinite(v) for v in numbers):
        raise ValueError(f"expected {expected}, got {values!r}")
    return dict(zip(keys, numbers, strict=True))


def save_state(
    path: Path | str,
    stiffness: Sequence[float],
    config_hash: str,
    extra: Mapping[str, Any] | None = None,
    sensor_biases: Sequence[float] | None = None,
    steer_zero: tuple[float, float] | None = None,
    accel_biases: Sequence[float] | None = None,
    learned_state_hash: str | None = None,
) -> Path:
    """Atomically write the learned stiffness (C_af, C_gf, C_ar, C_gr in N/rad), and if given the sensor biases
    (SENSOR_BIAS_KEYS order), the accelerometer biases (ACCEL_BIAS_KEYS order) and the steer zero ((zero_count,
    shift [rad])), to ``path``; returns the path. ``learned_state_hash`` lets a configuration that differs only by
    its payload restore the file.

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
        **({} if learned_state_hash is None else {"learned_state_hash": str(learned_state_hash)}),
        "saved_at": datetime.now(timezone.utc).isoformat(timespec="milliseconds"),
        "stiffness": dict(zip(STIFFNESS_KEYS, values, strict=True)),
    }
    if sensor_biases is not None:
        doc["sensor_biases"] = _finite_group(
            sensor_biases, SENSOR_BIAS_KEYS, f"{len(SENSOR_BIAS_KEYS)} finite sensor biases"
        )
    if accel_biases is not None:
        doc["accel_biases"] = _finite_group(
            accel_biases, ACCEL_BIAS_KEYS, f"{len(ACCEL_BIAS_KEYS)} finite accelerometer biases"
        )
    if steer_zero is not None:
        doc["steer_zero"] = _finite_group(steer_zero, STEER_ZERO_KEYS, "a finite (zero_count, shift) steer zero")
    if extra:
        doc["extra"] = dict(extra)
    text = json.dumps(doc, indent=2, allow_nan=False) + "\n"

    check_replaceable(path)  # a state file that is a device node was refused when read and replaced when saved
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


class _RefusedError(ValueError):
    pass


def _check_value(spec: StateField, value: Any, bounds: Bounds | None) -> str | None:
    """None if ``value`` is acceptable for ``spec``, else a short reason."""
    if spec.shape:
        if not isinstance(value, list) or len(value) != spec.shape[0]:
            return f"expected a list of {spec.shape[0]}, got {excerpt(value, 40)}"
        inner = StateField(spec.group, spec.key, spec.unit, spec.shape[1:], spec.positive)
        for item in value:
            problem = _check_value(inner, item, bounds)
            if problem:
                return problem
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return f"not a number: {excerpt(value, 40)}"
    try:
        v = float(value)
    except OverflowError:  # an int beyond float range
        return f"out of range: {excerpt(value, 40)}"
    if not math.isfinite(v):
        return f"non-finite: {v!r}"
    if spec.positive and v <= 0:
        return f"non-positive: {v!r}"
    if bounds is not None and spec.name in bounds:
        lo, hi = bounds[spec.name]
        slack = _BOUND_TOLERANCE * max(abs(lo), abs(hi))
        if not lo - slack <= v <= hi + slack:
            return f"{v:.6g} {spec.unit} outside the learnable range [{lo:.6g}, {hi:.6g}]"
    return None


def group_within_bounds(group: str, values: Sequence[float], bounds: Bounds) -> bool:
    """Whether load_state would take ``values`` (the keys of ``group`` in order) under ``bounds``: a save that wrote a
    value it would not take wrote a file the next start refuses whole."""
    specs = [spec for spec in STATE_FIELDS if spec.group == group]
    return len(values) == len(specs) and all(
        _check_value(spec, value, bounds) is None for spec, value in zip(specs, values, strict=True)
    )


class _DuplicateKeyError(Exception):
    """A key written twice in one JSON object (not a ValueError: json.loads would report it as bad JSON)."""


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise _DuplicateKeyError(key)
        out[key] = value
    return out


def load_state(
    path: Path | str, config_hash: str, bounds: Bounds | None = None, learned_state_hash: str | None = None
) -> tuple[LoadedState | None, str]:
    """Read a state file written by ``save_state`` for the configuration ``config_hash`` (or, given
    ``learned_state_hash``, for one that differs from it only by the payload).

    Returns ``(LoadedState, "ok")``, or ``(None, reason)`` with a one-line human-readable reason if the
    file is missing, not a regular file, too large or too deeply nested, unreadable, not JSON, of another
    format/version, written for another configuration or holds a value that is not a finite (positive)
    number within ``bounds`` (``StateField.name`` -> (low, high); see ``stiffness_bounds``). Never raises for
    bad file content.
    """
    path = Path(path)
    try:
        raw = read_bounded(path, max_bytes=MAX_STATE_BYTES, what="state file", error=_RefusedError)
    except _RefusedError as exc:
        if str(exc).endswith(" not found"):
            return None, f"no state file at {path}"
        return None, f"state file {path} {str(exc).removeprefix(f'{path}: state file ')}"
    try:
        text = decode_utf8(raw, path, what="state file", error=_RefusedError)
        check_nesting(text, MAX_STATE_DEPTH, path, what="state file", error=_RefusedError)
    except _RefusedError as exc:
        detail = str(exc).removeprefix(f"{path}: state file ")
        return None, f"state file {path} is not valid JSON: {detail}"
    try:
        doc = json.loads(text, object_pairs_hook=_unique_keys)
    except _DuplicateKeyError as exc:  # the last one would win: an out-of-range first value hidden behind it
        return None, f"state file {path}: key {excerpt(str(exc), 40)} written twice in one object"
    except (ValueError, RecursionError) as exc:  # JSONDecodeError is a ValueError; so is an int too long
        return None, f"state file {path} is not valid JSON: {excerpt(str(exc), 80)}"
    if not isinstance(doc, dict):
        return None, f"state file {path} is not a JSON object"
    if doc.get("format") != STATE_FORMAT:
        return None, f"state file {path} has wrong format {excerpt(doc.get('format'), 40)} (expected {STATE_FORMAT!r})"
    version = doc.get("version")
    if version != STATE_VERSION or isinstance(version, bool):
        return None, f"state file {path} has unsupported version {excerpt(version, 20)} (expected {STATE_VERSION})"
    saved_hash = doc.get("config_hash")
    if not isinstance(saved_hash, str):
        return None, f"state file {path} has no config_hash"
    saved_learned = doc.get("learned_state_hash")
    same_config = saved_hash == config_hash
    if not same_config and not (learned_state_hash is not None and saved_learned == learned_state_hash):
        return None, (
            f"state file {path} was saved for another configuration (config hash {excerpt(saved_hash[:12], 16)}, "
            f"current {str(config_hash)[:12]})"
        )
    values: dict[str, Any] = {}
    fields = []  # the rows this file must satisfy: every mandatory one, an optional group's if it is there
    for spec in STATE_FIELDS:
        if spec.optional and spec.group not in doc:
            continue
        if not isinstance(doc.get(spec.group), dict):
            return None, f"state file {path} has no {spec.group} object"
        fields.append(spec)
    for group in dict.fromkeys(spec.group for spec in fields):
        missing = [spec.key for spec in fields if spec.group == group and spec.key not in doc[group]]
        if missing:
            return None, f"state file {path} lacks {group} values: {', '.join(missing)}"
    problems = []
    for spec in fields:
        value = doc[spec.group][spec.key]
        problem = _check_value(spec, value, bounds)
        if problem:
            problems.append(f"{spec.key} {problem}")
        else:
            values[spec.name] = value
    if problems:
        more = f" (and {len(problems) - 2} more)" if len(problems) > 2 else ""
        return None, f"state file {path} refused whole, a learned value is invalid: {'; '.join(problems[:2])}{more}"
    saved_at = doc.get("saved_at")
    extra = doc.get("extra")
    state = LoadedState(
        stiffness=tuple(float(values[f"stiffness.{k}"]) for k in STIFFNESS_KEYS),  # type: ignore[arg-type]
        config_hash=saved_hash,
        saved_at=saved_at[:40] if isinstance(saved_at, str) else "",
        same_config=same_config,
        extra=extra if isinstance(extra, dict) else {},
        values=values,
        sensor_biases=tuple(float(values[f"sensor_biases.{k}"]) for k in SENSOR_BIAS_KEYS)  # type: ignore[arg-type]
        if "sensor_biases" in doc
        else None,
        accel_biases=tuple(float(values[f"accel_biases.{k}"]) for k in ACCEL_BIAS_KEYS)  # type: ignore[arg-type]
        if "accel_biases" in doc
        else None,
        steer_zero=(float(values["steer_zero.zero_count"]), float(values["steer_zero.shift"]))
        if "steer_zero" in doc
        else None,
    )
    return state, "ok"


def remove_orphan_temp_files(path: Path | str) -> list[Path]:
    """Delete the temporary files ``save_state`` leaves behind when killed between create and rename.

    Only names ``save_state`` creates (``.<name>.*.tmp`` next to ``path``), and only regular files (never
    follows a symlink). Call at start-up, before any save can be running. Never raises.
    """
    path = Path(path)
    removed = []
    try:
        candidates = list(path.parent.glob(f".{path.name}.*{_TMP_SUFFIX}"))
    except OSError:
        return removed
    for tmp in candidates[:1000]:
        try:
            if stat.S_ISREG(os.lstat(tmp).st_mode):
                os.unlink(tmp)
                removed.append(tmp)
        except OSError:
            continue
    return removed


def restore_state(
    path: Path | str, config_hash: str, bounds: Bounds | None = None, learned_state_hash: str | None = None
) -> StateLoad:
    """Start-up read of the state file: orphan temp files removed, then ``load_state``.

    ``level`` is INFO when the state was restored or there is no file yet, WARNING when a file was there and
    was refused (the reason names why); the daemon then starts from the nominal stiffness.
    """
    removed = tuple(str(p) for p in remove_orphan_temp_files(path))
    state, reason = load_state(path, config_hash, bounds, learned_state_hash)
    quiet = state is not None or reason.startswith("no state file at ")
    return StateLoad(state, reason, logging.INFO if quiet else logging.WARNING, removed)
