"""Typed, bounded YAML configuration: one declarative schema, clear errors.

Every configuration file of the project (vehicle, estimator tuning, daemon)
is validated through here, so a user always gets the same kind of message:
the dotted key, what was expected and what was found, never a traceback.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from ptw_rt.errors import UserFacingError


class ConfigError(UserFacingError, ValueError):
    """A configuration file is missing, unreadable or has an invalid value."""


@dataclass(frozen=True)
class Number:
    """A real number with optional strict/loose bounds and a unit for messages."""

    unit: str = ""
    gt: float | None = None
    ge: float | None = None
    lt: float | None = None
    le: float | None = None
    integer: bool = False
    doc: str = ""

    def check(self, key: str, value: Any) -> float | int:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            hint = ""
            if isinstance(value, str):
                try:
                    float(value)
                    hint = " (YAML reads exponents without a sign as text: write 2.0e+5, not 2.0e5)"
                except ValueError:
                    pass
            raise ConfigError(f"{key}: expected a number{self._unit()}, got {type(value).__name__} {value!r}{hint}")
        if self.integer and not float(value).is_integer():
            raise ConfigError(f"{key}: expected a whole number, got {value!r}")
        if not math.isfinite(value):
            raise ConfigError(f"{key}: must be finite, got {value!r}")
        for bound, ok, word in (
            (self.gt, lambda b: value > b, ">"),
            (self.ge, lambda b: value >= b, ">="),
            (self.lt, lambda b: value < b, "<"),
            (self.le, lambda b: value <= b, "<="),
        ):
            if bound is not None and not ok(bound):
                raise ConfigError(f"{key}: must be {word} {bound}{self._unit()}, got {value!r}")
        return int(value) if self.integer else float(value)

    def _unit(self) -> str:
        return f" [{self.unit}]" if self.unit else ""


@dataclass(frozen=True)
class Text:
    choices: tuple[str, ...] | None = None
    doc: str = ""

    def check(self, key: str, value: Any) -> str:
        if not isinstance(value, str):
            raise ConfigError(f"{key}: expected text, got {type(value).__name__} {value!r}")
        if self.choices is not None and value not in self.choices:
            raise ConfigError(f"{key}: must be one of {', '.join(self.choices)}; got {value!r}")
        return value


@dataclass(frozen=True)
class Flag:
    doc: str = ""

    def check(self, key: str, value: Any) -> bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: expected true or false, got {value!r}")
        return value


@dataclass(frozen=True)
class NumberList:
    item: Number
    min_len: int = 1
    max_len: int | None = None
    doc: str = ""

    def check(self, key: str, value: Any) -> tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{key}: expected a list of numbers, got {type(value).__name__} {value!r}")
        if len(value) < self.min_len or (self.max_len is not None and len(value) > self.max_len):
            span = f"{self.min_len}..{self.max_len}" if self.max_len is not None else f">= {self.min_len}"
            raise ConfigError(f"{key}: expected {span} items, got {len(value)}")
        return tuple(self.item.check(f"{key}[{i}]", v) for i, v in enumerate(value))


@dataclass(frozen=True)
class Section:
    """A mapping with a fixed set of keys; unknown keys are errors (typos must not pass)."""

    fields: Mapping[str, Any]
    optional: Mapping[str, Any] = field(default_factory=dict)
    doc: str = ""

    def check(self, key: str, value: Any) -> dict:
        where = key or "top level"
        if not isinstance(value, Mapping):
            raise ConfigError(f"{where}: expected a mapping of keys, got {type(value).__name__} {value!r}")
        known = set(self.fields) | set(self.optional)
        for name in value:
            if name not in known:
                hint = _closest(str(name), known)
                raise ConfigError(f"{_join(key, str(name))}: unknown key{hint}")
        out = {}
        for name, spec in self.fields.items():
            if name not in value:
                raise ConfigError(f"{_join(key, name)}: missing required key")
            out[name] = spec.check(_join(key, name), value[name])
        for name, (spec, default) in self.optional.items():
            out[name] = spec.check(_join(key, name), value[name]) if name in value else default
        return out


def _join(prefix: str, name: str) -> str:
    return f"{prefix}.{name}" if prefix else name


def _closest(name: str, known: set[str]) -> str:
    import difflib

    match = difflib.get_close_matches(name, sorted(known), n=1)
    return f" (did you mean '{match[0]}'?)" if match else f" (known keys: {', '.join(sorted(known))})"


def read_yaml(path: str | Path) -> Any:
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{path}: configuration file not found") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read configuration file ({exc.strerror})") from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise ConfigError(f"{path}: not valid YAML{where}: {getattr(exc, 'problem', exc)}") from None


def validate(document: Any, schema: Section, source: str, prefix: str = "") -> dict:
    """Check `document` against `schema`; errors read "<source>: <prefix.key>: <problem>"."""
    try:
        return schema.check(prefix, document)
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None


def canonical_hash(data: Any) -> str:
    """Stable SHA-256 of validated configuration data (key order and float repr independent)."""

    def normalise(obj: Any) -> Any:
        if isinstance(obj, Mapping):
            return {str(k): normalise(v) for k, v in sorted(obj.items())}
        if isinstance(obj, (list, tuple)):
            return [normalise(v) for v in obj]
        if isinstance(obj, float):
            return float(f"{obj:.12g}")
        return obj

    blob = json.dumps(normalise(data), sort_keys=True, separators=(",", ":")).encode()
    return hashlib.sha256(blob).hexdigest()
