"""AUTOSAR E2E Profile 11 (Data ID mode BOTH) for classic 8-byte CAN frames.

Pure functions, no cantools. Frame layout (CAN interface contract v1):

* byte 0: CRC-8 SAE J1850 (polynomial 0x1D) as Profile 11 computes it: start value 0x00, no final XOR,
  over the Data ID's low byte, then its high byte, then bytes 1..n-1 of the frame. (AUTOSAR's
  ``Crc_CalculateCRC8`` is called with start value 0xFF and ``IsFirstCall = FALSE``, which un-does its
  own 0xFF pre/post XOR: the net effect is the plain polynomial with init 0x00 and no output XOR.)
* byte 1, low nibble: counter 0..14, incremented once per sent frame, wrapping 14 -> 0; 15 is never sent.

The Data ID is the message's 11-bit CAN identifier. Verified against the ``autosar-e2e`` package
(``e2e.p11``) in ``tests/test_e2e.py``.
"""

from __future__ import annotations

from enum import IntEnum

__all__ = [
    "COUNTER_MAX",
    "CRC8_TABLE",
    "CounterChecker",
    "CRC8_POLY",
    "P11Checker",
    "P11Status",
    "check_p11",
    "counter_delta",
    "crc8_sae_j1850",
    "next_counter",
    "profile11_crc",
    "profile11_crc_seeded",
    "profile11_seed",
    "protect_p11",
]

CRC8_POLY = 0x1D
COUNTER_MAX = 14  # Profile 11 counter range 0..14; 15 is never sent
_COUNTER_MODULUS = COUNTER_MAX + 1


def _make_table(poly: int) -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ poly) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table.append(crc)
    return tuple(table)


_TABLE = _make_table(CRC8_POLY)
CRC8_TABLE = _TABLE  # for compiled code (``ptw_rt.edge.encoding``): the same table


def _crc8_raw(data: bytes | bytearray | memoryview, crc: int) -> int:
    """Table-driven CRC-8/0x1D update without any pre/post XOR."""
    table = _TABLE
    for b in data:
        crc = table[crc ^ b]
    return crc


def crc8_sae_j1850(data: bytes, start: int = 0xFF, xor_out: bool = True) -> int:
    """CRC-8 SAE J1850 (polynomial 0x1D, not reflected).

    ``start`` is the initial register value; ``xor_out`` applies the final XOR with 0xFF.
    Defaults give the standard CRC-8/SAE-J1850 (check value of ``b"123456789"`` is 0x4B).
    ``start=0x00, xor_out=False`` is the variant AUTOSAR E2E Profiles 1 and 11 use.
    """
    crc = _crc8_raw(data, start & 0xFF)
    return crc ^ 0xFF if xor_out else crc


def profile11_seed(data_id: int) -> int:
    """The Profile 11 CRC register after the Data ID (low byte, then high byte), before any frame byte.

    A sender of a fixed message computes it once and passes it to ``profile11_crc_seeded`` per frame.
    """
    crc = _TABLE[data_id & 0xFF]  # start value 0x00: first step is table[0 ^ b]
    return _TABLE[crc ^ ((data_id >> 8) & 0xFF)]


def profile11_crc_seeded(seed: int, frame: bytes) -> int:
    """Profile 11 CRC of ``frame[1:]`` continuing from ``seed = profile11_seed(data_id)``."""
    table = _TABLE
    crc = seed
    for b in frame[1:]:
        crc = table[crc ^ b]
    return crc


def profile11_crc(data_id: int, frame: bytes) -> int:
    """Profile 11 CRC (Data ID mode BOTH) of ``frame``: over Data ID low byte, high byte, then ``frame[1:]``.

    Byte 0 of ``frame`` (the CRC itself) is not included.
    """
    return profile11_crc_seeded(profile11_seed(data_id), frame)


def protect_p11(data_id: int, data: bytearray, counter: int) -> None:
    """Write ``counter`` into the low nibble of byte 1 (high nibble kept) and the Profile 11 CRC into byte 0.

    Raises ValueError if the counter is outside 0..14 or the frame is shorter than 2 bytes.
    """
    if not 0 <= counter <= COUNTER_MAX:
        raise ValueError(f"E2E P11 counter must be 0..{COUNTER_MAX}, got {counter}")
    if len(data) < 2:
        raise ValueError("E2E P11 frame needs at least 2 bytes")
    data[1] = (data[1] & 0xF0) | counter
    data[0] = profile11_crc(data_id, data)


def check_p11(data_id: int, data: bytes) -> bool:
    """Stateless Profile 11 check: byte 0 is the correct CRC of ``data`` for ``data_id`` and the counter is 0..14.

    A counter of 15 is never sent, so such a frame fails even with a correct CRC (as in ``e2e.p11.e2e_p11_check``).
    Counter sequence (repetition, loss) needs state: see ``P11Checker``.
    """
    if len(data) < 2 or data[1] & 0x0F > COUNTER_MAX:
        return False
    return data[0] == profile11_crc(data_id, data)


def next_counter(c: int) -> int:
    """The counter after ``c``: 0, 1, ..., 14, 0, ... (15 is never produced; a stray 15 maps to 0)."""
    return c + 1 if 0 <= c < COUNTER_MAX else 0


def counter_delta(previous: int, current: int, modulus: int = _COUNTER_MODULUS) -> int:
    """How far a rolling counter advanced from ``previous`` to ``current`` (0 = repeated, 1 = in sequence).

    ``modulus`` is 15 for Profile 11 / estimator outputs (0..14) and 16 for plain 4-bit input counters (0..15).
    """
    return (current - previous) % modulus


class P11Status(IntEnum):
    """Receiver-side result of a Profile 11 check (names after AUTOSAR E2E_P11CheckStatusType)."""

    OK = 0
    OKSOMELOST = 1
    REPEATED = 2
    WRONGSEQUENCE = 3
    ERROR = 4
    INITIAL = 5  # first valid frame after construction / reset: sequence not yet known


class CounterChecker:
    """Receiver-side check of one message's rolling counter: in sequence, repeated, some lost, out of sequence.

    The one counter check of the project: the input tracker (plain 4-bit input counters, ``modulus=16``), the
    monitor and the demo (estimator outputs, ``modulus=15``) and ``P11Checker`` all use it.
    ``step(counter)`` returns ``INITIAL`` for the first counter after construction / ``reset``, ``REPEATED`` if
    it did not advance (frozen sender, duplicated frame), ``OK`` for an advance of 1, ``OKSOMELOST`` for
    2..``max_delta_counter`` and ``WRONGSEQUENCE`` beyond. ``frame_lost()`` tells it that a frame of the message
    arrived but failed its other checks (CRC, decoding): the next counter may then be one further ahead.
    """

    __slots__ = ("modulus", "max_delta_counter", "_last", "_lost")

    def __init__(self, modulus: int = _COUNTER_MODULUS, max_delta_counter: int = 1) -> None:
        if not 1 <= max_delta_counter < modulus:
            raise ValueError(f"max_delta_counter must be 1..{modulus - 1}")
        self.modulus = modulus
        self.max_delta_counter = max_delta_counter
        self._last: int | None = None
        self._lost = 0

    def reset(self) -> None:
        self._last = None
        self._lost = 0

    @property
    def last(self) -> int | None:
        """The last counter stepped, None before the first."""
        return self._last

    def frame_lost(self) -> None:
        self._lost += 1

    def step(self, counter: int) -> P11Status:
        last, self._last = self._last, counter
        lost, self._lost = self._lost, 0
        if last is None:
            return P11Status.INITIAL
        delta = (counter - last) % self.modulus
        if delta == 1:
            return P11Status.OK
        if delta == 0:
            return P11Status.REPEATED
        if delta <= self.max_delta_counter + lost:
            return P11Status.OKSOMELOST
        return P11Status.WRONGSEQUENCE


class P11Checker(CounterChecker):
    """Stateful Profile 11 receiver check for one Data ID: CRC, counter range, repetition and jumps.

    ``check(data)`` returns ``ERROR`` for a wrong CRC (corrupted or misrouted frame) or counter 15, else the
    counter's ``CounterChecker.step`` status. Only frames that pass the CRC update the state.
    """

    __slots__ = ("data_id",)

    def __init__(self, data_id: int, max_delta_counter: int = 1) -> None:
        if not 1 <= max_delta_counter <= COUNTER_MAX:
            raise ValueError(f"max_delta_counter must be 1..{COUNTER_MAX}")
        super().__init__(_COUNTER_MODULUS, max_delta_counter)
        self.data_id = data_id

    def check(self, data: bytes) -> P11Status:
        if not check_p11(self.data_id, data):  # wrong CRC or counter 15
            return P11Status.ERROR
        return self.step(data[1] & 0x0F)
