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
from ptw_rt.untrusted import decode_utf8, excerpt, read_bounded, short_text

# A configuration file is a few kB; these bound the time and memory of reading a hostile one.
MAX_CONFIG_BYTES = 256 * 1024
MAX_CONFIG_DEPTH = 32  # mapping/sequence nesting (the schema itself is 4 deep)
MAX_CONFIG_NODES = 10_000  # keys, values and list items (config/scooter.yaml has about 220); bounds parse time
MAX_INT_DIGITS = 32  # a longer integer is no configuration value (and int() of a huge one is slow)


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
            raise ConfigError(
                f"{key}: expected a number{self._unit()}, got {type(value).__name__} {excerpt(value)}{hint}"
            )
        if self.integer and not float(value).is_integer():
            raise ConfigError(f"{key}: expected a whole number, got {excerpt(value)}")
        if not math.isfinite(value):
            raise ConfigError(f"{key}: must be finite, got {excerpt(value)}")
        for bound, ok, word in (
            (self.gt, lambda b: value > b, ">"),
            (self.ge, lambda b: value >= b, ">="),
            (self.lt, lambda b: value < b, "<"),
            (self.le, lambda b: value <= b, "<="),
        ):
            if bound is not None and not ok(bound):
                raise ConfigError(f"{key}: must be {word} {bound}{self._unit()}, got {excerpt(value)}")
        return int(value) if self.integer else float(value)

    def _unit(self) -> str:
        return f" [{self.unit}]" if self.unit else ""


MAX_PATH_CHARS = 4096  # Linux's PATH_MAX


def check_path_text(key: str, value: str) -> str:
    """A file name from a configuration or the command line: non-empty, no NUL (no system call takes one: it was a
    ValueError traceback when the daemon first opened the file), at most ``MAX_PATH_CHARS``."""
    if not value:
        raise ConfigError(f"{key}: an empty file name")
    if "\0" in value:
        raise ConfigError(f"{key}: a file name with a NUL character: {excerpt(value)}")
    if len(value) > MAX_PATH_CHARS:
        raise ConfigError(f"{key}: a file name of {len(value)} characters (at most {MAX_PATH_CHARS})")
    return value


@dataclass(frozen=True)
class Text:
    choices: tuple[str, ...] | None = None
    doc: str = ""
    path: bool = False  # a file name: checked by check_path_text

    def check(self, key: str, value: Any) -> str:
        if not isinstance(value, str):
            raise ConfigError(f"{key}: expected text, got {type(value).__name__} {excerpt(value)}")
        if self.choices is not None and value not in self.choices:
            raise ConfigError(f"{key}: must be one of {', '.join(self.choices)}; got {excerpt(value)}")
        if self.path:
            return check_path_text(key, value)
        if "\0" in value:
            raise ConfigError(f"{key}: text with a NUL character: {excerpt(value)}")
        return value


@dataclass(frozen=True)
class Flag:
    doc: str = ""

    def check(self, key: str, value: Any) -> bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: expected true or false, got {excerpt(value)}")
        return value


@dataclass(frozen=True)
class NumberList:
    item: Number
    min_len: int = 1
    max_len: int | None = None
    doc: str = ""

    def check(self, key: str, value: Any) -> tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{key}: expected a list of numbers, got {type(value).__name__} {excerpt(value)}")
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
            raise ConfigError(f"{where}: expected a mapping of keys, got {type(value).__name__} {excerpt(value)}")
        known = set(self.fields) | set(self.optional)
        for name in value:
            if name not in known:
                shown = _key_name(name)
                hint = _closest(shown, known)
                raise ConfigError(f"{_join(key, shown)}: unknown key{hint}")
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


def _key_name(name: Any) -> str:
    """A key as it may appear in a message: plain if short printable text, else a short escaped excerpt."""
    if isinstance(name, str) and len(name) <= 40 and name.isprintable():
        return name
    return excerpt(name, 40)


def _closest(name: str, known: set[str]) -> str:
    import difflib

    match = difflib.get_close_matches(name, sorted(known), n=1)
    return f" (did you mean '{match[0]}'?)" if match else f" (known keys: {', '.join(sorted(known))})"


class _ConfigLoader(yaml.SafeLoader):
    """PyYAML's safe loader for configuration: no anchors or aliases, bounded nesting, node count and integers.

    Aliases are what makes a few-kB "billion laughs" document expand to gigabytes; a configuration file has no
    use for them, so they are refused outright rather than capped. Nesting is bounded before the composer's
    recursion (three Python frames per level) can hit the interpreter's limit.
    """

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._depth = 0
        self._nodes = 0

    def compose_node(self, parent: Any, index: Any) -> Any:
        event = self.peek_event()
        if isinstance(event, yaml.AliasEvent):
            raise _Refused("aliases (*name) are not allowed in configuration files", event.start_mark)
        if getattr(event, "anchor", None) is not None:
            raise _Refused("anchors (&name) are not allowed in configuration files", event.start_mark)
        self._nodes += 1
        if self._nodes > MAX_CONFIG_NODES:
            raise _Refused(f"more than {MAX_CONFIG_NODES} keys, values and items", event.start_mark)
        if isinstance(event, (yaml.MappingStartEvent, yaml.SequenceStartEvent)):
            if self._depth >= MAX_CONFIG_DEPTH:
                raise _Refused(f"nested deeper than {MAX_CONFIG_DEPTH} levels", event.start_mark)
            self._depth += 1
            try:
                return super().compose_node(parent, index)
            finally:
                self._depth -= 1
        return super().compose_node(parent, index)

    def construct_yaml_int(self, node: Any) -> int:
        digits = sum(ch.isdigit() for ch in str(node.value))
        if digits > MAX_INT_DIGITS:
            raise _Refused(f"integer with {digits} digits (at most {MAX_INT_DIGITS})", node.start_mark)
        return super().construct_yaml_int(node)

    def construct_mapping(self, node: Any, deep: bool = False) -> Any:
        # YAML takes the last of two equal keys silently: a tuning value written twice (or a section pasted twice)
        # would be half ignored with nothing said
        seen = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            try:
                if key in seen:
                    raise _Refused(f"key {short_text(repr(key))} appears twice in one section", key_node.start_mark)
                seen.add(key)
            except TypeError:  # an unhashable key: the base class says so
                pass
        return super().construct_mapping(node, deep)


_ConfigLoader.add_constructor("tag:yaml.org,2002:int", _ConfigLoader.construct_yaml_int)


class _Refused(yaml.YAMLError):
    def __init__(self, problem: str, mark: Any) -> None:
        super().__init__(problem)
        self.problem = problem
        self.problem_mark = mark


def read_yaml(path: str | Path) -> Any:
    """Parse a configuration file: a regular file of at most ``MAX_CONFIG_BYTES``, UTF-8, no aliases/anchors,
    nesting at most ``MAX_CONFIG_DEPTH``, at most ``MAX_CONFIG_NODES`` nodes. Any problem: a one-line ``ConfigError``.
    Worst case about half a second of parsing on a 2020s x86 core."""
    path = Path(path)
    raw = read_bounded(path, max_bytes=MAX_CONFIG_BYTES, what="configuration file", error=ConfigError)
    text = decode_utf8(raw, path, what="configuration file", error=ConfigError)
    try:
        loader = _ConfigLoader(text)
        try:
            return loader.get_single_data()
        finally:
            loader.dispose()
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError(f"{path}: not valid YAML{where}: {short_text(problem)}") from None
    except (ValueError, TypeError, OverflowError) as exc:  # e.g. a date like 2024-13-45 (constructors raise these)
        raise ConfigError(f"{path}: not valid YAML: {short_text(str(exc))}") from None
    except (KeyError, IndexError, AttributeError) as exc:
        # PyYAML's constructors on an explicit tag they cannot read: !!bool "maybe", !!int "", !!timestamp "abc"
        raise ConfigError(
            f"{path}: not valid YAML: a value its explicit tag (!!bool, !!int, !!float, !!timestamp ...) cannot read"
            f" ({type(exc).__name__} {short_text(str(exc))})"
        ) from None
    except RecursionError:  # defence in depth: the depth bound above should make this unreachable
        raise ConfigError(f"{path}: not valid YAML: nested too deeply") from None


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
