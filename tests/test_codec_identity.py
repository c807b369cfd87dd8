"""The one codec against cantools, byte for byte: every message of the shipped DBC, inputs and outputs, both ways;
and a DBC written here with what the shipped one lacks (Motorola byte order, signed and offset signals, an
extended identifier, an E2E message with a Motorola signal), so that the codec's generic branch runs too."""

from __future__ import annotations

from pathlib import Path

import cantools
import numpy as np
import pytest

from ptw_rt.io.dbc import FrameCodec, FrameDecodeError
from ptw_rt.io.e2e import P11Checker, P11Status, protect_p11
from ptw_rt.paths import DEFAULT_DBC

SHIPPED = FrameCodec()
DB = cantools.database.load_file(str(DEFAULT_DBC))

# big-endian unsigned scaled, big-endian signed with offset, little-endian signed with offset, an extended id;
# an E2E output with a Motorola signal
TEST_DBC = """VERSION ""

NS_ :

BS_:

BU_: PTW_RT SENSOR

BO_ 2364540158 Wheel_Ext: 8 SENSOR
 SG_ WheelSpeed : 7|16@0+ (0.01,0) [0|300] "m/s" PTW_RT
 SG_ Torque : 23|12@0- (0.5,-10) [-1000|1000] "N m" PTW_RT
 SG_ Temp : 32|8@1- (1,-40) [-100|100] "degC" PTW_RT
 SG_ Wheel_Counter : 40|4@1+ (1,0) [0|15] "" PTW_RT

BO_ 1280 EST_Test: 8 PTW_RT
 SG_ EST_Test_CRC : 0|8@1+ (1,0) [0|255] "" SENSOR
 SG_ EST_Test_Counter : 8|4@1+ (1,0) [0|14] "" SENSOR
 SG_ EST_Test_Valid : 12|1@1+ (1,0) [0|1] "" SENSOR
 SG_ Angle : 23|16@0- (0.001,0) [-30|30] "rad" SENSOR
 SG_ Gain : 39|8@0+ (0.25,-5) [-5|58.75] "" SENSOR

BA_DEF_ BO_  "GenMsgCycleTime" INT 0 10000;
BA_DEF_DEF_  "GenMsgCycleTime" 0;
BA_ "GenMsgCycleTime" BO_ 2364540158 10;
BA_ "GenMsgCycleTime" BO_ 1280 10;
"""


def _random_values(message, rng, codec: FrameCodec) -> dict[str, float]:
    """Physical values of every signal: in range, at the ends, beyond them, and exact half raw steps."""
    values = {}
    layout = codec.layout(message.name)
    for s in layout.signals:
        r = rng.random()
        if r < 0.1:
            v = (round((rng.uniform(s.lo, s.hi) - s.offset) / s.scale) + 0.5) * s.scale + s.offset
        elif r < 0.2:
            span = s.hi - s.lo
            v = rng.choice([s.lo - span, s.hi + span, s.lo, s.hi])
        else:
            v = rng.uniform(s.lo, s.hi)
        values[s.name] = float(v)
    if layout.counter_signal is not None:
        values[layout.counter_signal] = int(rng.integers(0, layout.counter_max + 1))
    if layout.crc_signal is not None:
        values[layout.crc_signal] = 0
    return values


def _cantools_frame(message, values: dict[str, float], codec: FrameCodec) -> bytes:
    """The reference: values clipped to their range, cantools' encoder, autosar CRC for E2E messages."""
    layout = codec.layout(message.name)
    clipped = {s.name: min(max(values[s.name], s.lo), s.hi) for s in layout.signals}
    data = bytearray(message.encode(clipped, scaling=True, padding=False, strict=False))
    if layout.crc_signal is not None:
        protect_p11(message.frame_id, data, int(clipped[layout.counter_signal]))
    return bytes(data)


def _cantools_values(message, data: bytes) -> dict[str, float]:
    return {k: float(v) for k, v in message.decode(data, decode_choices=False, scaling=True).items()}


@pytest.fixture(scope="module")
def test_codec(tmp_path_factory) -> tuple[FrameCodec, cantools.database.Database]:
    path = Path(tmp_path_factory.mktemp("dbc")) / "test.dbc"
    path.write_text(TEST_DBC)
    return FrameCodec(path), cantools.database.load_file(str(path))


@pytest.mark.parametrize("name", SHIPPED.input_messages + SHIPPED.output_messages)
def test_shipped_messages_encode_like_cantools(name):
    rng = np.random.default_rng(abs(hash(name)) % 2**32)
    message = DB.get_message_by_name(name)
    assert SHIPPED.layout(name).plain  # the shipped DBC takes the integer branch
    for _ in range(300):
        values = _random_values(message, rng, SHIPPED)
        fid, data = SHIPPED.encode(name, values)
        assert fid == message.frame_id
        assert data == _cantools_frame(message, values, SHIPPED), values


@pytest.mark.parametrize("name", SHIPPED.input_messages + SHIPPED.output_messages)
def test_shipped_messages_decode_like_cantools(name):
    rng = np.random.default_rng(7 + len(name))
    message = DB.get_message_by_name(name)
    for _ in range(300):
        data = rng.integers(0, 256, message.length, dtype=np.uint8).tobytes()
        got_name, values = SHIPPED.decode(message.frame_id, data)
        assert got_name == name
        assert values == _cantools_values(message, data)


def test_generic_branch_runs_for_motorola_signed_scaled_and_extended(test_codec):
    codec, db = test_codec
    assert codec.input_messages == ("Wheel_Ext",) and codec.output_messages == ("EST_Test",)
    assert not codec.layout("Wheel_Ext").plain and not codec.layout("EST_Test").plain
    assert codec.can_filters() == [{"can_id": 0x0CF004FE, "can_mask": 0x1FFFFFFF, "extended": True}]
    rng = np.random.default_rng(3)
    for name in ("Wheel_Ext", "EST_Test"):
        message = db.get_message_by_name(name)
        extended = message.is_extended_frame
        for _ in range(300):
            values = _random_values(message, rng, codec)
            fid, data = codec.encode(name, values)
            assert data == _cantools_frame(message, values, codec), (name, values)
            got, decoded = codec.decode_checked(fid, data, extended=extended)
            assert got == name and decoded == _cantools_values(message, data)
            raw = rng.integers(0, 256, message.length, dtype=np.uint8).tobytes()
            assert codec.decode(fid, raw, extended=extended)[1] == _cantools_values(message, raw)
    # the extended id is not the standard one of the same number, and the other way round
    with pytest.raises(FrameDecodeError, match="unknown_id"):
        codec.decode(0x0CF004FE, bytes(8), extended=False)
    with pytest.raises(FrameDecodeError, match="unknown_id"):
        codec.decode(1280, bytes(8), extended=True)


def test_generic_e2e_frames_pass_the_profile_11_check(test_codec):
    codec, _ = test_codec
    checker = P11Checker(codec.frame_id("EST_Test"))
    statuses = []
    for c in range(20):
        _, data = codec.encode("EST_Test", {"Angle": -1.234, "Gain": 3.25, "EST_Test_Valid": 1}, counter=c % 15)
        statuses.append(checker.check(data))
    assert statuses[0] == P11Status.INITIAL and set(statuses[1:]) == {P11Status.OK}
    bad = bytearray(data)
    bad[3] ^= 0x10
    with pytest.raises(FrameDecodeError, match="crc"):
        codec.decode_checked(1280, bytes(bad))


@pytest.mark.parametrize("name", SHIPPED.input_messages + SHIPPED.output_messages)
def test_generated_plain_codec_equals_the_reference_loop(name):
    """A plain message's generated pack/unpack (``_plain_codec``) against the loop it unrolls: clipping, NaN
    and infinities, the counter as an int, the CRC; every raw bit pattern class on the way back."""
    layout = SHIPPED.layout(name)
    assert layout.plain
    rng = np.random.default_rng(15)
    specials = (np.nan, np.inf, -np.inf)
    for _ in range(500):
        values = [
            specials[rng.integers(3)] if rng.random() < 0.1 else float(rng.uniform(2 * s.lo - 1, 2 * s.hi + 1))
            for s in layout.signals
        ]
        if layout.counter_signal is not None:
            values[layout.index[layout.counter_signal]] = int(rng.integers(0, layout.counter_modulus))
        assert layout.pack(values) == layout._pack_reference(values)
        data = rng.bytes(layout.length)
        assert layout.unpack(data) == layout._unpack_reference(data)
