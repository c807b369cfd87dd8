"""The CAN frame codec: the only place that knows the wire format, all of it read from the DBC.

``FrameCodec`` wraps a cantools database with what the estimator needs on top of it:

* inputs/outputs derived from the DBC senders (outputs = sent by the estimator node),
* encoding with clipping to each signal's [min, max], strict checking of the signal names,
  defaults only for counters, CRCs and validity bits, and AUTOSAR E2E Profile 11 protection
  (Data ID = CAN id) for every message that has a ``<Message>_CRC`` signal,
* decoding that raises only ``FrameDecodeError`` (with a machine-readable ``reason``) and returns
  plain floats (no choice strings).
"""

from __future__ import annotations

import math
import operator
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import cantools
import numpy as np
from cantools.database.can import Database, Message

from ptw_rt.io.e2e import check_p11, profile11_crc_seeded, profile11_seed
from ptw_rt.paths import DEFAULT_DBC

__all__ = [
    "DEFAULT_ESTIMATOR_NODE",
    "DbcError",
    "FrameCodec",
    "FrameDecodeError",
    "FrameEncodeError",
    "MessageLayout",
    "SignalLayout",
]

DEFAULT_ESTIMATOR_NODE = "PTW_RT"
_STD_ID_MASK = 0x7FF
_EXT_ID_MASK = 0x1FFFFFFF
_MISSING = object()


class DbcError(ValueError):
    """The DBC file is missing, unreadable, or violates the interface rules the codec relies on."""


class FrameDecodeError(ValueError):
    """A received frame cannot be decoded. ``reason`` is one of ``REASONS``."""

    UNKNOWN_ID = "unknown_id"
    WRONG_DLC = "wrong_dlc"
    GARBAGE = "garbage"
    CRC = "crc"
    REASONS = (UNKNOWN_ID, WRONG_DLC, GARBAGE, CRC)

    def __init__(self, reason: str, frame_id: int | None, detail: str = "") -> None:
        self.reason = reason
        self.frame_id = frame_id
        self.detail = detail
        fid = "None" if frame_id is None else f"0x{frame_id:03X}"
        super().__init__(f"cannot decode frame {fid}: {reason}" + (f" ({detail})" if detail else ""))


class FrameEncodeError(ValueError):
    """Signals given to ``encode`` are missing, unknown, NaN, or a counter is out of range."""


@dataclass(frozen=True)
class SignalLayout:
    """One signal as the codec packs it: bit position, scaling and its physical [lo, hi]."""

    name: str
    start: int  # cantools' start bit
    length: int
    signed: bool
    scale: float
    offset: float
    lo: float  # DBC min/max narrowed to what the raw field can hold
    hi: float
    can_exceed: bool  # some raw value of the field decodes outside [lo, hi] (or to a non-finite value)

    @property
    def neutral(self) -> float:
        """What a NaN is packed as: 0 if the range holds it, else the range's lower end."""
        return 0.0 if self.lo <= 0.0 <= self.hi else self.lo


def _raw_physical_range(sig) -> tuple[float, float]:
    if sig.is_signed:
        lo_raw, hi_raw = -(1 << (sig.length - 1)), (1 << (sig.length - 1)) - 1
    else:
        lo_raw, hi_raw = 0, (1 << sig.length) - 1
    a = lo_raw * sig.scale + sig.offset
    b = hi_raw * sig.scale + sig.offset
    return (a, b) if a <= b else (b, a)


class MessageLayout:
    """One message compiled once from the DBC: the only code that turns signal values into bytes and back.

    ``pack(values)`` / ``unpack(data)`` take and give the values of ALL signals in DBC order (``signals``).
    When every signal is a plain Intel integer (the shipped DBC) they work with integer shifts on one
    little-endian word (5-10x faster than cantools, byte-identical to it: tested); otherwise (Motorola byte
    order, float signals) they go through cantools. ``pack`` clips each value to its [lo, hi], packs a NaN as the
    signal's neutral value, rounds as cantools does, and writes the Profile 11 CRC into byte 0 of E2E messages.
    """

    __slots__ = (
        "name",
        "frame_id",
        "length",
        "message",
        "is_output",
        "cycle_time_s",
        "signals",
        "names",
        "index",
        "counter_signal",
        "counter_max",
        "crc_signal",
        "valid_signal",
        "plain",
        "_fields",
        "_crc_seed",
        "pack",
        "unpack",
    )

    def __init__(
        self,
        message: Message,
        *,
        is_output: bool,
        signals: tuple[SignalLayout, ...],
        counter_signal: str | None,
        counter_max: int,
        crc_signal: str | None,
        valid_signal: str | None,
    ) -> None:
        self.name = message.name
        self.frame_id = message.frame_id
        self.length = message.length
        self.message = message
        self.is_output = is_output
        self.cycle_time_s = message.cycle_time / 1000.0
        self.signals = signals
        self.names = tuple(s.name for s in signals)
        self.index = {n: k for k, n in enumerate(self.names)}  # signal -> position in the values list
        self.counter_signal = counter_signal
        self.counter_max = counter_max
        self.crc_signal = crc_signal
        self.valid_signal = valid_signal
        self.plain = all(s.byte_order == "little_endian" and not s.is_float for s in message.signals)
        # per signal: (start, mask, sign bit, 2**length, scale, offset, lo, hi, neutral)
        self._fields = tuple(
            (s.start, (1 << s.length) - 1, 1 << (s.length - 1) if s.signed else 0, 1 << s.length)
            + (s.scale, s.offset, s.lo, s.hi, s.neutral)
            for s in signals
        )
        # the CRC register after the Data ID: the same for every frame of this message
        self._crc_seed = None if crc_signal is None else profile11_seed(self.frame_id)
        if self.plain:  # this message's own straight-line pack and unpack (see _plain_codec)
            self.pack, self.unpack = _plain_codec(self.name, self._fields, self.length, self._crc_seed)
        else:
            self.pack, self.unpack = self._pack_reference, self._unpack_reference

    @property
    def counter_modulus(self) -> int:
        return self.counter_max + 1

    def _pack_reference(self, values: Sequence[float]) -> bytes:
        """The frame's bytes from the physical values of all signals in DBC order (counter included, CRC ignored).

        ``pack`` is this, or for a plain message the same steps unrolled by ``_plain_codec`` (tested equal)."""
        if not self.plain:
            return self._pack_generic(values)
        word = 0
        for v, (start, mask, _sign, _full, scale, offset, lo, hi, neutral) in zip(values, self._fields, strict=True):
            if v < lo:
                v = lo
            elif v > hi:
                v = hi
            elif v != v:  # NaN
                v = neutral
            # cantools' rounding (numeric_scaled_to_raw: where that takes the divmod quotient, the remainder is 0,
            # so the quotient is an integer and equals the division exactly)
            word |= (round((v - offset) / scale) & mask) << start
        data = word.to_bytes(self.length, "little")
        if self._crc_seed is None:
            return data
        # byte 0 replaced by the CRC, as protect_p11 does on the frame
        return ((word & ~0xFF) | profile11_crc_seeded(self._crc_seed, data)).to_bytes(self.length, "little")

    def _pack_generic(self, values: Sequence[float]) -> bytes:
        clipped = {}
        for v, s in zip(values, self.signals, strict=True):
            clipped[s.name] = s.neutral if v != v else min(max(v, s.lo), s.hi)
        try:
            data = self.message.encode(clipped, scaling=True, padding=False, strict=False)
        except Exception as exc:  # should not happen after clipping; never leak cantools types
            raise FrameEncodeError(f"{self.name}: {exc}") from exc
        if self._crc_seed is None:
            return data
        buf = bytearray(data)
        buf[0] = profile11_crc_seeded(self._crc_seed, data)
        return bytes(buf)

    def unpack_many(self, data: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Physical values of many frames of this message at once: ``data`` is ``uint8[n, 8]`` (each frame's bytes,
        zero-padded to 8; its DLC must already be this message's ``length``). Returns ``(values[n, len(signals)],
        ok[n])``: for a plain message the arithmetic of ``unpack`` on whole columns (numpy; the same float
        operations, so the same values: tested), else ``unpack`` frame by frame (``ok`` False where it fails)."""
        n = data.shape[0]
        values = np.zeros((n, len(self.signals)))
        ok = np.ones(n, dtype=bool)
        if not self.plain:
            for i in range(n):
                try:
                    values[i] = self.unpack(data[i, : self.length].tobytes())
                except Exception:  # undecodable for cantools: counted by the caller as a decode error
                    ok[i] = False
            return values, ok
        words = np.ascontiguousarray(data).view("<u8")[:, 0]
        for j, (start, mask, sign, full, scale, offset, _lo, _hi, _neutral) in enumerate(self._fields):
            raw = ((words >> np.uint64(start)) & np.uint64(mask)).astype(np.int64)
            if sign:
                raw = np.where(raw & sign, raw - full, raw)
            values[:, j] = raw * scale + offset
        return values, ok

    def _unpack_reference(self, data: bytes) -> list[float]:
        """Physical values of all signals in DBC order (``raw * scale + offset``). ``data`` must be ``length``
        bytes (``FrameCodec.decode`` checks it); cantools errors of the generic path propagate.

        ``unpack`` is this, or for a plain message the same steps unrolled by ``_plain_codec`` (tested equal)."""
        if not self.plain:
            raw = self.message.decode(bytes(data), decode_choices=False, scaling=True)
            return [float(raw[n]) for n in self.names]
        word = int.from_bytes(data, "little")
        out = []
        for start, mask, sign, full, scale, offset, _lo, _hi, _neutral in self._fields:
            raw = (word >> start) & mask
            if raw & sign:
                raw -= full
            out.append(raw * scale + offset)
        return out


def _plain_codec(name: str, fields: tuple, length: int, crc_seed: int | None) -> tuple:
    """``(pack, unpack)`` of one plain message (Intel integers only) as straight-line Python generated from its
    fields: the same operations in the same order as ``MessageLayout._pack_reference`` / ``_unpack_reference``
    (byte-identical, tested), without the per-signal loop, tuple unpacking and zip that cost more than the
    arithmetic itself. Replay packs ~3 and unpacks ~3 frames per 10 ms cycle; the daemon gains the same.
    The field constants are default arguments: local-variable reads in the generated functions."""
    n = len(fields)
    constants: dict[str, object] = {"crc_seed": crc_seed, "crc": profile11_crc_seeded}
    pack = ["word = 0"]
    unpack = ["word = int.from_bytes(data, 'little')"]
    for k, (start, mask, sign, full, scale, offset, lo, hi, neutral) in enumerate(fields):
        constants.update({f"lo{k}": lo, f"hi{k}": hi, f"neutral{k}": neutral, f"scale{k}": scale})
        constants[f"offset{k}"] = offset
        pack += [
            f"v = v{k}",
            f"if v < lo{k}: v = lo{k}",
            f"elif v > hi{k}: v = hi{k}",
            f"elif v != v: v = neutral{k}",  # NaN
            f"word |= (round((v - offset{k}) / scale{k}) & {mask}) << {start}",
        ]
        unpack.append(f"raw = (word >> {start}) & {mask}")
        if sign:
            unpack.append(f"if raw & {sign}: raw -= {full}")
        unpack.append(f"r{k} = raw * scale{k} + offset{k}")
    if crc_seed is None:
        pack.append(f"return word.to_bytes({length}, 'little')")
    else:  # byte 0 replaced by the CRC, as protect_p11 does on the frame
        pack.append(
            f"return ((word & ~0xFF) | crc(crc_seed, word.to_bytes({length}, 'little'))).to_bytes({length}, 'little')"
        )
    unpack.append("return [" + ", ".join(f"r{k}" for k in range(n)) + "]")
    defaults = ", ".join(f"{c}={c}" for c in constants)
    unpacked = ", ".join(f"v{k}" for k in range(n)) + ("," if n == 1 else "")
    source = (
        f"def pack(values, *, {defaults}):\n"
        f"    if len(values) != {n}: raise ValueError('{name}: {n} values expected, got %d' % len(values))\n"
        f"    {unpacked} = values\n"
        + "".join(f"    {line}\n" for line in pack)
        + f"def unpack(data, *, {defaults}):\n"
        + "".join(f"    {line}\n" for line in unpack)
    )
    namespace = dict(constants)
    exec(compile(source, f"<dbc codec {name}>", "exec"), namespace)  # noqa: S102 - source built from the DBC's numbers
    return namespace["pack"], namespace["unpack"]


def _as_counter(value: object) -> int | None:
    """Integer value of a counter given as int, numpy integer or integral float; None otherwise."""
    if isinstance(value, bool):
        return None
    try:
        return operator.index(value)
    except TypeError:
        pass
    if isinstance(value, float) and value.is_integer():
        return int(value)
    return None


class FrameCodec:
    """Encode/decode the project's CAN frames as defined by one DBC file.

    ``estimator_node`` is the DBC node of this estimator: messages it sends are outputs,
    all others (sent by sensor nodes) are inputs. Every message is compiled once into a ``MessageLayout``
    (``layout(name)``), which the hot paths (``InputTracker``, ``OutputEncoder``) use directly.
    """

    def __init__(self, dbc_path: Path | str = DEFAULT_DBC, *, estimator_node: str = DEFAULT_ESTIMATOR_NODE) -> None:
        self.dbc_path = Path(dbc_path)
        self.estimator_node = estimator_node
        if not self.dbc_path.is_file():
            raise DbcError(f"DBC file not found: {self.dbc_path}")
        try:
            db = cantools.database.load_file(str(self.dbc_path), database_format="dbc", strict=True)
        except Exception as exc:  # cantools raises many types (ParseError, UnsupportedDatabaseFormat, ...)
            raise DbcError(f"cannot load DBC {self.dbc_path}: {exc}") from exc
        if not isinstance(db, Database):
            raise DbcError(f"{self.dbc_path} is not a CAN database")
        self.database: Database = db

        by_name: dict[str, MessageLayout] = {}
        by_id: dict[tuple[int, bool], MessageLayout] = {}
        self._encode_rules: dict[str, tuple[frozenset[str], dict[str, float]]] = {}
        for msg in db.messages:
            layout = self._compile(msg)
            key = (msg.frame_id, bool(msg.is_extended_frame))
            if key in by_id:
                raise DbcError(f"duplicate frame id 0x{msg.frame_id:03X}")
            by_name[layout.name] = layout
            by_id[key] = layout
        if not any(m.is_output for m in by_name.values()):
            raise DbcError(f"no message in {self.dbc_path} is sent by estimator node {estimator_node!r}")
        self._by_name = by_name
        self._by_id = by_id
        self._outputs = tuple(n for n, m in by_name.items() if m.is_output)
        self._inputs = tuple(n for n, m in by_name.items() if not m.is_output)
        self._input_ids = tuple(by_name[n].frame_id for n in self._inputs)

    # ------------------------------------------------------------------ loading

    def _compile(self, msg: Message) -> MessageLayout:
        name = msg.name
        where = f"{self.dbc_path}: message {name}"
        if msg.frame_id > (_EXT_ID_MASK if msg.is_extended_frame else _STD_ID_MASK):
            raise DbcError(f"{where}: frame id 0x{msg.frame_id:X} does not fit its identifier format")
        if msg.is_container or any(s.multiplexer_ids for s in msg.signals):
            raise DbcError(f"{where}: multiplexed/container messages are not supported")
        if not msg.senders:
            raise DbcError(f"{where}: no sender node")
        if not msg.cycle_time or msg.cycle_time <= 0:
            raise DbcError(f"{where}: missing GenMsgCycleTime")
        is_output = self.estimator_node in msg.senders
        sigs = {s.name: s for s in msg.signals}

        if is_output:
            counter = f"{name}_Counter"
            valid = f"{name}_Valid"
            for required in (counter, valid):
                if required not in sigs:
                    raise DbcError(f"{where}: output message lacks {required}")
        else:
            counters = [s for s in sigs if s.endswith("_Counter")]
            if len(counters) > 1:
                raise DbcError(f"{where}: more than one *_Counter signal: {counters}")
            counter = counters[0] if counters else None
            valid = f"{name}_Valid" if f"{name}_Valid" in sigs else None

        crc = f"{name}_CRC" if f"{name}_CRC" in sigs else None
        if crc is not None:
            c, k = sigs[crc], sigs.get(counter) if counter else None
            if msg.is_extended_frame:
                raise DbcError(f"{where}: E2E Profile 11 (Data ID = CAN id) needs an 11-bit identifier")
            if not (c.start == 0 and c.length == 8 and c.byte_order == "little_endian"):
                raise DbcError(f"{where}: {crc} must occupy byte 0 (start 0, length 8, Intel)")
            if k is None or not (k.start == 8 and k.length == 4 and k.byte_order == "little_endian"):
                raise DbcError(f"{where}: E2E counter must be the low nibble of byte 1 (start 8, length 4, Intel)")
            if msg.length < 2:
                raise DbcError(f"{where}: E2E message needs at least 2 bytes")

        counter_max = 15
        if counter is not None:
            cs = sigs[counter]
            if cs.length != 4 or cs.is_signed or cs.scale != 1 or cs.offset != 0:
                raise DbcError(f"{where}: {counter} must be a 4-bit unsigned raw counter")
            counter_max = int(cs.maximum) if cs.maximum is not None else 15
            if crc is not None:
                counter_max = min(counter_max, 14)

        signals = []
        for s in msg.signals:
            lo_raw, hi_raw = _raw_physical_range(s)
            lo = lo_raw if s.minimum is None else max(float(s.minimum), lo_raw)
            hi = hi_raw if s.maximum is None else min(float(s.maximum), hi_raw)
            if lo > hi:
                raise DbcError(f"{where}: signal {s.name} has an empty range [{s.minimum}, {s.maximum}]")
            # raw * scale + offset is monotonic in raw: the ends of the raw range bound every decoded value
            can_exceed = s.is_float or not (
                math.isfinite(lo_raw) and math.isfinite(hi_raw) and lo <= lo_raw and hi_raw <= hi
            )
            signals.append(
                SignalLayout(
                    s.name, s.start, s.length, s.is_signed, float(s.scale), float(s.offset), lo, hi, can_exceed
                )
            )

        defaults: dict[str, float] = {}
        for sname in sigs:
            if sname == counter or sname == crc or sname.endswith("_Valid"):
                defaults[sname] = 0.0  # validity defaults to 0 = invalid (fail-safe)
        self._encode_rules[name] = (frozenset(n for n in sigs if n not in defaults), defaults)
        return MessageLayout(
            msg,
            is_output=is_output,
            signals=tuple(signals),
            counter_signal=counter,
            counter_max=counter_max,
            crc_signal=crc,
            valid_signal=valid,
        )

    def layout(self, message_name: str) -> MessageLayout:
        """The compiled message (bit layout, limits, counter, CRC): what the hot paths pack and unpack with."""
        try:
            return self._by_name[message_name]
        except KeyError:
            raise KeyError(f"unknown message {message_name!r} in {self.dbc_path}") from None

    # ------------------------------------------------------------------ queries

    @property
    def input_messages(self) -> tuple[str, ...]:
        """Messages sent by sensor nodes (any sender other than the estimator), in DBC order."""
        return self._inputs

    @property
    def output_messages(self) -> tuple[str, ...]:
        """Messages sent by the estimator node, in DBC order."""
        return self._outputs

    @property
    def input_ids(self) -> tuple[int, ...]:
        """Frame ids of the input messages."""
        return self._input_ids

    def can_filters(self, message_names: Iterable[str] | None = None) -> list[dict]:
        """python-can receive filters (exact identifier match) for the given messages (default: all inputs)."""
        names = self._inputs if message_names is None else tuple(message_names)
        filters = []
        for n in names:
            m = self.layout(n)
            ext = bool(m.message.is_extended_frame)
            filters.append({"can_id": m.frame_id, "can_mask": _EXT_ID_MASK if ext else _STD_ID_MASK, "extended": ext})
        return filters

    def frame_id(self, message_name: str) -> int:
        return self.layout(message_name).frame_id

    def message_name(self, frame_id: int, extended: bool = False) -> str | None:
        m = self._by_id.get((frame_id, extended))
        return None if m is None else m.name

    def is_output(self, message_name: str) -> bool:
        return self.layout(message_name).is_output

    def cycle_time_s(self, message_name: str) -> float:
        """Nominal period from the ``GenMsgCycleTime`` attribute, in seconds."""
        return self.layout(message_name).cycle_time_s

    def signal_names(self, message_name: str) -> tuple[str, ...]:
        return self.layout(message_name).names

    def expected_length(self, message_name: str) -> int:
        """DLC in bytes."""
        return self.layout(message_name).length

    def counter_signal(self, message_name: str) -> str | None:
        """Name of the message's rolling-counter signal (e.g. ``Accel_Counter``), None if it has none."""
        return self.layout(message_name).counter_signal

    def counter_modulus(self, message_name: str) -> int:
        """Number of counter values: 15 for outputs / E2E (0..14), 16 for plain 4-bit input counters."""
        return self.layout(message_name).counter_modulus

    def valid_signal(self, message_name: str) -> str | None:
        return self.layout(message_name).valid_signal

    def crc_signal(self, message_name: str) -> str | None:
        """``<Message>_CRC`` if the message is E2E Profile 11 protected, else None."""
        return self.layout(message_name).crc_signal

    def is_e2e(self, message_name: str) -> bool:
        return self.layout(message_name).crc_signal is not None

    def signal_limits(self, message_name: str) -> Mapping[str, tuple[float, float]]:
        """Physical [min, max] per signal (DBC min/max, narrowed to what the raw field can hold)."""
        return {s.name: (s.lo, s.hi) for s in self.layout(message_name).signals}

    def choices(self, message_name: str, signal_name: str) -> dict[int, str]:
        """Value table of an enum signal (e.g. ``Mode``), empty if it has none."""
        sig = self.layout(message_name).message.get_signal_by_name(signal_name)
        return {int(k): str(v) for k, v in (sig.choices or {}).items()}

    def out_of_range(self, message_name: str, values: Mapping[str, float]) -> tuple[str, ...]:
        """Names of signals in ``values`` outside their DBC [min, max] (or not finite)."""
        m = self.layout(message_name)
        bad = []
        for k, v in values.items():
            i = m.index.get(k)
            if i is not None and not (m.signals[i].lo <= v <= m.signals[i].hi):
                bad.append(k)
        return tuple(bad)

    # ------------------------------------------------------------------ encode

    def encode(
        self, message_name: str, signals: Mapping[str, float], *, counter: int | None = None
    ) -> tuple[int, bytes]:
        """Encode one frame; returns ``(frame_id, data)``.

        Every signal must be given except the counter, the CRC and ``*_Valid`` bits (these default to 0;
        a missing validity bit therefore means *invalid*). Values are clipped to the signal's [min, max];
        NaN raises. ``counter`` (if given) overrides a counter value in ``signals``. Messages with a
        ``<Message>_CRC`` signal get E2E Profile 11 protection with the frame id as Data ID; their counter
        must be 0..14. Raises ``FrameEncodeError`` (a ValueError) or ``KeyError`` for an unknown message.
        """
        m = self.layout(message_name)
        required, defaults = self._encode_rules[message_name]
        missing = required.difference(signals)
        if missing:
            raise FrameEncodeError(f"{message_name}: missing signals {sorted(missing)}")
        if not signals.keys() <= m.index.keys():
            unknown = sorted(set(signals) - set(m.names))
            raise FrameEncodeError(f"{message_name}: unknown signals {unknown}")

        values: list[float] = []
        get = signals.get
        for name in m.names:
            v = get(name, _MISSING)
            if v is _MISSING:
                v = defaults[name]
            else:
                try:
                    v = float(v)
                except (TypeError, ValueError):
                    raise FrameEncodeError(f"{message_name}.{name}: not a number: {v!r}") from None
                if v != v:
                    raise FrameEncodeError(f"{message_name}.{name}: NaN")
            values.append(v)

        cname = m.counter_signal
        if cname is not None:
            raw_c = counter if counter is not None else get(cname, 0)
            c = _as_counter(raw_c)
            if c is None or not 0 <= c <= m.counter_max:
                raise FrameEncodeError(f"{message_name}: counter must be an integer 0..{m.counter_max}: {raw_c!r}")
            values[m.index[cname]] = c
        elif counter is not None:
            raise FrameEncodeError(f"{message_name} has no counter signal")
        return m.frame_id, m.pack(values)

    # ------------------------------------------------------------------ decode

    def _lookup(self, frame_id: int, data: bytes, extended: bool) -> MessageLayout:
        m = self._by_id.get((frame_id, bool(extended)))
        if m is None:
            raise FrameDecodeError(FrameDecodeError.UNKNOWN_ID, frame_id)
        try:
            n = len(data)
        except TypeError:
            raise FrameDecodeError(FrameDecodeError.GARBAGE, frame_id, f"data is {type(data).__name__}") from None
        if n != m.length:
            raise FrameDecodeError(FrameDecodeError.WRONG_DLC, frame_id, f"{n} bytes, expected {m.length}")
        return m

    def decode(self, frame_id: int, data: bytes, *, extended: bool = False) -> tuple[str, dict[str, float]]:
        """Decode a received frame to ``(message_name, {signal: float})`` (enums as numbers).

        Raises ``FrameDecodeError`` with reason ``unknown_id`` (id not in the DBC, in its identifier format),
        ``wrong_dlc`` (length differs from the DBC) or ``garbage`` (undecodable data) - never another type.
        """
        try:
            frame_id = operator.index(frame_id)
        except TypeError:
            raise FrameDecodeError(FrameDecodeError.UNKNOWN_ID, None, f"frame id {frame_id!r}") from None
        m = self._lookup(frame_id, data, extended)
        try:
            values = m.unpack(bytes(data))
        except Exception as exc:
            raise FrameDecodeError(FrameDecodeError.GARBAGE, frame_id, str(exc)) from exc
        return m.name, dict(zip(m.names, values, strict=True))

    def decode_checked(self, frame_id: int, data: bytes, *, extended: bool = False) -> tuple[str, dict[str, float]]:
        """Like ``decode`` and, for E2E-protected messages, also verify the Profile 11 CRC (reason ``crc``)
        and that the counter is 0..14 (reason ``garbage``). Other messages are decoded as by ``decode``.
        Counter sequence (repetition, loss) is stateful: see ``ptw_rt.io.e2e.CounterChecker``.
        """
        name, values = self.decode(frame_id, data, extended=extended)
        m = self._by_name[name]
        if m.crc_signal is not None:
            if values[m.counter_signal] > m.counter_max:
                raise FrameDecodeError(FrameDecodeError.GARBAGE, frame_id, "E2E counter 15")
            if not check_p11(frame_id, data):
                raise FrameDecodeError(FrameDecodeError.CRC, frame_id)
        return name, values
