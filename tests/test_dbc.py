"""The DBC against the CAN interface contract (v1), and the FrameCodec built on it."""

from __future__ import annotations

import math
import re
from pathlib import Path

import cantools
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ptw_rt.io.dbc import DbcError, FrameCodec, FrameDecodeError, FrameEncodeError
from ptw_rt.io.e2e import check_p11
from ptw_rt.paths import DEFAULT_DBC

ESTIMATOR = "PTW_RT"

# The contract, transcribed independently of the DBC:
# signal -> (unit, minimum resolution, contract min, contract max). unit None = dimensionless/enum.
CONTRACT_INPUTS: dict[str, dict] = {
    "IMU_Rates": {
        "hz": 100,
        "counter": "IMU_Counter",
        "signals": {
            "RollRate": ("rad/s", 1e-4, -3.0, 3.0),
            "PitchRate": ("rad/s", 1e-4, -3.0, 3.0),
            "YawRate": ("rad/s", 1e-4, -3.0, 3.0),
        },
    },
    "IMU_Accel": {
        "hz": 100,
        "counter": "Accel_Counter",
        "signals": {
            "AccelX": ("m/s^2", 1e-3, -30.0, 30.0),
            "AccelY": ("m/s^2", 1e-3, -30.0, 30.0),
            "AccelZ": ("m/s^2", 1e-3, -30.0, 30.0),
        },
    },
    "Steer_Encoder": {
        "hz": 100,
        "counter": "Steer_Counter",
        "signals": {"SteerCount": ("count", 1, 0, 1023)},
    },
    "GPS_Velocity": {
        "hz": 10,
        "counter": "GPS_Counter",
        "signals": {
            "SpeedOverGround": ("m/s", 0.01, 0.0, 100.0),
            "CourseOverGround": ("deg", 0.01, 0.0, 360.0),
            "FixType": (None, 1, 0, 3),
            "NumSatellites": (None, 1, 0, 255),
        },
    },
}
CONTRACT_OUTPUTS: dict[str, dict] = {
    "EST_Roll": {
        "hz": 100,
        "signals": {
            "RollAngle": ("rad", 1e-4, -1.5, 1.5),
            "RollRateEst": ("rad/s", 1e-4, -3.0, 3.0),
            "RollUIHOSMO": ("rad", 1e-4, -1.5, 1.5),  # added in v1.5 (issue #16: the UIHOSMO channel's own roll)
        },
    },
    "EST_RiderTorque": {
        "hz": 100,
        "signals": {
            "RiderTorque": ("N m", 0.01, -300.0, 300.0),
            "SteerAngleEst": ("rad", 1e-4, -1.5, 1.5),
            "SteerRateEst": ("rad/s", 1e-4, -3.0, 3.0),
        },
    },
    "EST_Lateral": {
        "hz": 100,
        "signals": {
            "LateralVelocity": ("m/s", 1e-3, -30.0, 30.0),
            "FrontLateralForce": ("N", 1, -20000, 20000),
            "RearLateralForce": ("N", 1, -20000, 20000),
        },
    },
    "EST_TireStiffness": {
        "hz": 10,
        "signals": {
            "FrontCorneringStiffness": ("N/rad", 2, 0, 120000),
            "RearCorneringStiffness": ("N/rad", 2, 0, 120000),
            "FrontCamberStiffness": ("N/rad", 1, 0, 4000),
            "RearCamberStiffness": ("N/rad", 1, 0, 4000),
        },
    },
    # added in v1.1 (issue #12: the confidence of the learned tyres); every v1 name unchanged
    "EST_TireConfidence": {
        "hz": 10,
        "signals": {
            "TireScale": (None, 1e-4, 0.0, 6.5),
            "TireScaleLogSd": (None, 1e-4, 0.0, 6.5),
            "TireModelConsistency": (None, 0.01, 0.0, 600.0),
            "TireLearning": (None, 1, 0, 1),
            "TireChange": (None, 0.5, 0.0, 63.5),  # added in v1.4 (a road that changed: the bank's change statistic)
            "PitchDoubted": (None, 1, 0, 1),  # added in v1.6 (the tyres wait while the pitch is doubted)
            "TireBalanceDoubted": (None, 1, 0, 1),  # added in v1.7 (the front/rear balance not known for VALID)
            "SteerZeroDoubted": (None, 1, 0, 1),  # added in v1.8 (the steer zero the balance rests on not confirmed)
        },
    },
    # added in v1.2 (issue #16: the plausibility monitor); every earlier name unchanged
    "EST_Plausibility": {
        "hz": 10,
        "signals": {
            "TorqueResidual": ("N m", 0.01, 0.0, 655.0),
            "PlausibilityRatio": (None, 0.001, 0.0, 65.0),
            "RiderTorqueUIHOSMO": ("N m", 0.01, -300.0, 300.0),
            # added in v1.3: the steer-kinematics check's residual (0.5 deg = 0.0087 rad alarms), 3x its range
            "SteerKinematicResidual": ("rad", 0.0002, -0.025, 0.025),
        },
    },
    "EST_Status": {
        "hz": 10,
        "signals": {
            "Mode": (None, 1, 0, 4),
            "SensorTimeouts": (None, 1, 0, 15),
            "OverrunCount": (None, 1, 0, 1000),
            "CycleTimeUs": ("us", 1, 0, 10000),
            "ReasonBits": (None, 1, 0, 0x1FF),
        },
    },
}
E2E_OUTPUTS = ("EST_Roll", "EST_RiderTorque", "EST_Lateral")
ALL_CONTRACT = {**CONTRACT_INPUTS, **CONTRACT_OUTPUTS}


@pytest.fixture(scope="module")
def db() -> cantools.database.can.Database:
    return cantools.database.load_file(str(DEFAULT_DBC), strict=True)


@pytest.fixture(scope="module")
def codec() -> FrameCodec:
    return FrameCodec()


def _contract_signals():
    for msg, spec in ALL_CONTRACT.items():
        for sig, (unit, res, lo, hi) in spec["signals"].items():
            yield pytest.param(msg, sig, unit, res, lo, hi, id=f"{msg}.{sig}")


# ================================================================ the DBC file


def test_dbc_is_where_paths_says() -> None:
    assert DEFAULT_DBC.is_file()
    assert DEFAULT_DBC.parent.name == "dbc"


def test_messages_are_classic_11bit_unique_and_fit(db) -> None:
    ids = [m.frame_id for m in db.messages]
    assert len(ids) == len(set(ids))
    for m in db.messages:
        assert not m.is_extended_frame and 0 <= m.frame_id <= 0x7FF, m.name
        assert 1 <= m.length <= 8, m.name
        used = max(s.start + s.length for s in m.signals)
        assert used <= 8 * m.length, m.name
        assert m.comment, f"{m.name} has no CM_"


def test_contract_messages_exist_with_direction(db) -> None:
    names = {m.name for m in db.messages}
    assert set(ALL_CONTRACT) <= names
    for name in CONTRACT_INPUTS:
        m = db.get_message_by_name(name)
        assert ESTIMATOR not in m.senders and m.senders, name
        assert all(ESTIMATOR in s.receivers for s in m.signals), name
    for name in CONTRACT_OUTPUTS:
        assert db.get_message_by_name(name).senders == [ESTIMATOR]
    assert {n.name for n in db.nodes} >= {"IMU", "STEER", "GNSS", ESTIMATOR}


def test_input_priority_imu_first_and_inputs_before_outputs(db) -> None:
    fid = {m.name: m.frame_id for m in db.messages}
    assert fid["IMU_Rates"] < fid["IMU_Accel"] < fid["Steer_Encoder"] < fid["GPS_Velocity"]
    assert max(fid[n] for n in CONTRACT_INPUTS) < min(fid[n] for n in CONTRACT_OUTPUTS)


@pytest.mark.parametrize("name", list(ALL_CONTRACT))
def test_cycle_time_attribute(db, name: str) -> None:
    m = db.get_message_by_name(name)
    expected_ms = round(1000 / ALL_CONTRACT[name]["hz"])
    assert m.cycle_time == expected_ms
    assert m.dbc.attributes["GenMsgCycleTime"].value == expected_ms
    assert "GenMsgCycleTime" in db.dbc.attribute_definitions


@pytest.mark.parametrize(("msg", "sig", "unit", "res", "lo", "hi"), list(_contract_signals()))
def test_contract_signal(db, msg: str, sig: str, unit: str | None, res: float, lo: float, hi: float) -> None:
    s = db.get_message_by_name(msg).get_signal_by_name(sig)
    assert (s.unit or None) == unit
    assert s.byte_order == "little_endian"
    assert s.scale <= res * (1 + 1e-9), f"resolution {s.scale} coarser than {res}"
    assert s.minimum is not None and s.maximum is not None
    assert s.minimum <= lo and s.maximum >= hi, f"[{s.minimum}, {s.maximum}] does not cover [{lo}, {hi}]"
    # the raw field can hold the whole [min, max]
    raw_lo = -(1 << (s.length - 1)) if s.is_signed else 0
    raw_hi = (1 << (s.length - 1)) - 1 if s.is_signed else (1 << s.length) - 1
    assert raw_lo * s.scale + s.offset <= s.minimum + 1e-9
    assert raw_hi * s.scale + s.offset >= s.maximum - 1e-9
    assert s.is_signed == (lo < 0)
    assert s.comment, f"{msg}.{sig} has no CM_"


def test_the_attitude_filter_knows_the_gyros_full_scale(db) -> None:
    """A reading at IMU_Rates' range is a saturated gyro to the attitude filter (core.attitude.GYRO_FULL_SCALE:
    the core does not read the DBC, so this test holds the two together)."""
    from ptw_rt.core.attitude import GYRO_FULL_SCALE

    rates = db.get_message_by_name("IMU_Rates")
    for name in ("RollRate", "PitchRate", "YawRate"):
        signal = rates.get_signal_by_name(name)
        assert (signal.minimum, signal.maximum) == (-GYRO_FULL_SCALE, GYRO_FULL_SCALE)


def test_steer_count_is_raw_10_bit(db) -> None:
    s = db.get_message_by_name("Steer_Encoder").get_signal_by_name("SteerCount")
    assert (s.length, s.scale, s.offset, s.is_signed) == (10, 1, 0, False)


def test_every_signal_is_intel_and_commented(db) -> None:
    for m in db.messages:
        for s in m.signals:
            assert s.byte_order == "little_endian", f"{m.name}.{s.name}"
            assert s.comment, f"{m.name}.{s.name} has no CM_"


def test_enum_value_tables(db) -> None:
    fix = db.get_message_by_name("GPS_Velocity").get_signal_by_name("FixType")
    assert set(fix.choices) == {0, 1, 2, 3}
    mode = db.get_message_by_name("EST_Status").get_signal_by_name("Mode")
    assert {int(k): str(v) for k, v in mode.choices.items()} == {
        0: "INIT",
        1: "CONVERGING",
        2: "VALID",
        3: "DEGRADED",
        4: "FAULT",
    }


@pytest.mark.parametrize(("msg", "counter"), [(m, s["counter"]) for m, s in CONTRACT_INPUTS.items()])
def test_input_counters(db, msg: str, counter: str) -> None:
    s = db.get_message_by_name(msg).get_signal_by_name(counter)
    assert (s.length, s.is_signed, s.scale, s.offset) == (4, False, 1, 0)


@pytest.mark.parametrize("msg", list(CONTRACT_OUTPUTS))
def test_outputs_have_counter_and_valid(db, msg: str) -> None:
    m = db.get_message_by_name(msg)
    c = m.get_signal_by_name(f"{msg}_Counter")
    v = m.get_signal_by_name(f"{msg}_Valid")
    assert (c.length, c.is_signed, c.scale, c.offset) == (4, False, 1, 0)
    assert c.maximum == 14  # 15 is never sent
    assert (v.length, v.is_signed) == (1, False)


@pytest.mark.parametrize("msg", list(CONTRACT_OUTPUTS))
def test_only_100hz_outputs_have_e2e_layout(db, msg: str) -> None:
    m = db.get_message_by_name(msg)
    names = {s.name for s in m.signals}
    if msg in E2E_OUTPUTS:
        assert m.length == 8  # CRC over bytes 1..7
        crc = m.get_signal_by_name(f"{msg}_CRC")
        assert (crc.start, crc.length, crc.byte_order, crc.is_signed) == (0, 8, "little_endian", False)
        ctr = m.get_signal_by_name(f"{msg}_Counter")
        assert (ctr.start, ctr.length, ctr.byte_order) == (8, 4, "little_endian")  # low nibble of byte 1
        # nothing else overlaps bytes 0 and the low nibble of byte 1
        for s in m.signals:
            if s.name not in (crc.name, ctr.name):
                assert s.start >= 12, s.name
    else:
        assert f"{msg}_CRC" not in names


def test_tire_stiffness_fits_without_crc(db) -> None:
    m = db.get_message_by_name("EST_TireStiffness")
    assert m.length == 8
    bits = sum(s.length for s in m.signals)
    assert bits <= 64
    # the four stiffnesses + counter + valid alone leave fewer than 8 bits: no room for a CRC
    mandatory = sum(
        m.get_signal_by_name(n).length
        for n in (*CONTRACT_OUTPUTS["EST_TireStiffness"]["signals"], "EST_TireStiffness_Counter")
    )
    assert 64 - mandatory - 1 < 8


def test_status_fields(db) -> None:
    m = db.get_message_by_name("EST_Status")
    st_ = m.get_signal_by_name("SensorTimeouts")
    assert st_.length == 4
    for i, name in enumerate(CONTRACT_INPUTS):
        assert f"bit{i} {name}" in st_.comment
    rb = m.get_signal_by_name("ReasonBits")
    assert (rb.length, rb.is_signed) == (16, False)
    for phrase in (
        "bit0 speed below model validity",
        "bit1 GPS lost",
        "bit2 sensor stale",
        "bit3 observer diverging/reset",
        "bit4 input out of range",
        "bit5 decode errors",
        "bit6 counter jumps",
        "bit7 overrun",
        "bit8 send failure",
        "reserved",
    ):
        assert phrase in rb.comment
    assert m.get_signal_by_name("EST_Status_Valid").length == 1


def test_no_signals_overlap(db) -> None:
    for m in db.messages:
        used = 0
        for s in m.signals:
            mask = ((1 << s.length) - 1) << s.start
            assert not used & mask, f"{m.name}.{s.name} overlaps"
            used |= mask


def test_cantools_cli_dump_accepts_dbc() -> None:
    import subprocess
    import sys

    out = subprocess.run(
        [sys.executable, "-m", "cantools", "dump", str(DEFAULT_DBC)], capture_output=True, text=True, check=True
    ).stdout
    for name in ALL_CONTRACT:
        assert name in out


# ================================================================ FrameCodec: queries


def test_codec_directions_from_senders(codec: FrameCodec) -> None:
    assert set(codec.input_messages) == set(CONTRACT_INPUTS)
    assert set(codec.output_messages) == set(CONTRACT_OUTPUTS)
    assert sorted(codec.input_ids) == sorted(codec.frame_id(n) for n in CONTRACT_INPUTS)
    for n in CONTRACT_INPUTS:
        assert not codec.is_output(n)
    filters = codec.can_filters()
    assert {f["can_id"] for f in filters} == set(codec.input_ids)
    assert all(f["can_mask"] == 0x7FF and f["extended"] is False for f in filters)


def test_codec_queries(codec: FrameCodec, db) -> None:
    for m in db.messages:
        assert codec.frame_id(m.name) == m.frame_id
        assert codec.message_name(m.frame_id) == m.name
        assert codec.expected_length(m.name) == m.length
        assert codec.signal_names(m.name) == tuple(s.name for s in m.signals)
    assert codec.message_name(0x7FF) is None
    assert codec.cycle_time_s("EST_Roll") == pytest.approx(0.01)
    assert codec.cycle_time_s("GPS_Velocity") == pytest.approx(0.1)
    assert codec.cycle_time_s("EST_Status") == pytest.approx(0.1)
    assert codec.counter_signal("IMU_Accel") == "Accel_Counter"
    assert codec.counter_signal("EST_Roll") == "EST_Roll_Counter"
    assert codec.counter_modulus("EST_Status") == 15
    assert codec.counter_modulus("IMU_Rates") == 16
    assert codec.valid_signal("EST_Lateral") == "EST_Lateral_Valid"
    assert codec.crc_signal("EST_Roll") == "EST_Roll_CRC"
    assert codec.crc_signal("EST_TireStiffness") is None
    assert codec.is_e2e("EST_Lateral") and not codec.is_e2e("EST_Status")
    assert codec.choices("EST_Status", "Mode")[4] == "FAULT"
    assert codec.signal_limits("EST_Roll")["RollAngle"] == (-1.5, 1.5)
    with pytest.raises(KeyError):
        codec.frame_id("NoSuchMessage")


def test_out_of_range(codec: FrameCodec) -> None:
    assert codec.out_of_range("IMU_Rates", {"RollRate": 0.1, "YawRate": 3.5, "PitchRate": math.nan}) == (
        "YawRate",
        "PitchRate",
    )


# ================================================================ FrameCodec: loading errors


def test_missing_dbc(tmp_path: Path) -> None:
    with pytest.raises(DbcError):
        FrameCodec(tmp_path / "nope.dbc")
    assert issubclass(DbcError, ValueError)


def test_invalid_dbc(tmp_path: Path) -> None:
    p = tmp_path / "bad.dbc"
    p.write_text("this is not a DBC\nBO_ 1 X: 8 Y\n SG_ broken\n")
    with pytest.raises(DbcError):
        FrameCodec(p)


def test_dbc_output_without_counter_rejected(tmp_path: Path) -> None:
    text = DEFAULT_DBC.read_text().replace("EST_Status_Counter", "EST_Status_Cnt")
    p = tmp_path / "nocounter.dbc"
    p.write_text(text)
    with pytest.raises(DbcError, match="EST_Status_Counter"):
        FrameCodec(p)


def test_dbc_e2e_crc_not_in_byte0_rejected(tmp_path: Path) -> None:
    text = DEFAULT_DBC.read_text().replace(" SG_ EST_Roll_CRC : 0|8@1+", " SG_ EST_Roll_CRC : 48|8@1+")
    text = text.replace(" SG_ RollUIHOSMO : 48|16@1-", " SG_ RollUIHOSMO : 56|8@1-")  # the bits the CRC moves to
    p = tmp_path / "badcrc.dbc"
    p.write_text(text)
    with pytest.raises(DbcError, match="byte 0"):
        FrameCodec(p)


def test_directions_follow_dbc_senders(tmp_path: Path) -> None:
    """Add a message sent by a sensor node and another by the estimator: the codec classifies them by sender."""
    extra = (
        'BO_ 300 Wheel_Speed: 3 IMU\n SG_ WheelSpeed : 0|16@1+ (0.01,0) [0|100] "m/s" PTW_RT\n'
        ' SG_ Wheel_Counter : 16|4@1+ (1,0) [0|15] "" PTW_RT\n\n'
        'BO_ 900 EST_Extra: 2 PTW_RT\n SG_ EST_Extra_Counter : 0|4@1+ (1,0) [0|14] "" Vector__XXX\n'
        ' SG_ EST_Extra_Valid : 4|1@1+ (1,0) [0|1] "" Vector__XXX\n\n'
    )
    text = DEFAULT_DBC.read_text()
    text = text.replace("BO_ 256 IMU_Rates", extra + "BO_ 256 IMU_Rates", 1)
    text += 'BA_ "GenMsgCycleTime" BO_ 300 10;\nBA_ "GenMsgCycleTime" BO_ 900 100;\n'
    p = tmp_path / "extra.dbc"
    p.write_text(text)
    c = FrameCodec(p)
    assert "Wheel_Speed" in c.input_messages and 300 in c.input_ids
    assert "EST_Extra" in c.output_messages
    assert c.counter_signal("Wheel_Speed") == "Wheel_Counter"


# ================================================================ FrameCodec: encode / decode


def _step(codec: FrameCodec, msg: str, sig: str) -> float:
    return codec.database.get_message_by_name(msg).get_signal_by_name(sig).scale


def _full_values(codec: FrameCodec, msg: str, pick) -> dict[str, float]:
    """A value for every signal of ``msg`` (except the CRC), chosen by ``pick(signal, lo, hi)``."""
    out = {}
    for name, (lo, hi) in codec.signal_limits(msg).items():
        if name == codec.crc_signal(msg):
            continue
        if name == codec.counter_signal(msg):
            out[name] = int(pick(name, 0, codec.counter_modulus(msg) - 1))
        else:
            out[name] = pick(name, lo, hi)
    return out


def _assert_round_trip(codec: FrameCodec, msg: str, values: dict[str, float]) -> None:
    fid, data = codec.encode(msg, values)
    assert fid == codec.frame_id(msg)
    assert len(data) == codec.expected_length(msg)
    name, decoded = codec.decode(fid, data)
    assert name == msg
    assert all(isinstance(v, float) for v in decoded.values())
    for sig, v in values.items():
        half = _step(codec, msg, sig) / 2
        assert abs(decoded[sig] - v) <= half + 1e-9, f"{msg}.{sig}: sent {v}, got {decoded[sig]}"
    if codec.is_e2e(msg):
        assert check_p11(fid, data)
        codec.decode_checked(fid, data)


@pytest.mark.parametrize("msg", list(ALL_CONTRACT))
@pytest.mark.parametrize("where", ["min", "max", "mid", "zero"])
def test_round_trip_extremes(codec: FrameCodec, msg: str, where: str) -> None:
    def pick(_name, lo, hi):
        return {"min": lo, "max": hi, "mid": (lo + hi) / 2, "zero": min(max(0.0, lo), hi)}[where]

    _assert_round_trip(codec, msg, _full_values(codec, msg, pick))


def test_negative_extremes_exact(codec: FrameCodec) -> None:
    vals = {"RiderTorque": -300.0, "SteerAngleEst": -1.5, "SteerRateEst": -3.0}
    _, data = codec.encode("EST_RiderTorque", vals, counter=0)
    _, dec = codec.decode(codec.frame_id("EST_RiderTorque"), data)
    assert dec["RiderTorque"] == pytest.approx(-300.0, abs=0.005)
    assert dec["SteerAngleEst"] == pytest.approx(-1.5, abs=5e-5)
    assert dec["SteerRateEst"] == pytest.approx(-3.0, abs=5e-5)


@pytest.mark.parametrize("msg", list(ALL_CONTRACT))
@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_round_trip_property(codec: FrameCodec, msg: str, data) -> None:
    def pick(name, lo, hi):
        if name == codec.counter_signal(msg):
            return data.draw(st.integers(int(lo), int(hi)), label=name)
        return data.draw(st.floats(lo, hi, allow_nan=False), label=name)

    _assert_round_trip(codec, msg, _full_values(codec, msg, pick))


def test_encode_clips_to_range(codec: FrameCodec) -> None:
    _, data = codec.encode("EST_Roll", {"RollAngle": 7.0, "RollRateEst": -1e9, "RollUIHOSMO": 0.0}, counter=1)
    _, dec = codec.decode(codec.frame_id("EST_Roll"), data)
    assert dec["RollAngle"] == pytest.approx(1.5)
    assert dec["RollRateEst"] == pytest.approx(-3.0)
    _, data = codec.encode("EST_Roll", {"RollAngle": math.inf, "RollRateEst": -math.inf, "RollUIHOSMO": 0.0}, counter=1)
    _, dec = codec.decode(codec.frame_id("EST_Roll"), data)
    assert (dec["RollAngle"], dec["RollRateEst"]) == (pytest.approx(1.5), pytest.approx(-3.0))


def test_encode_missing_mandatory_signal_raises(codec: FrameCodec) -> None:
    with pytest.raises(FrameEncodeError, match="RollRateEst"):
        codec.encode("EST_Roll", {"RollAngle": 0.1}, counter=0)
    with pytest.raises(FrameEncodeError):
        codec.encode("IMU_Rates", {"RollRate": 0.1, "PitchRate": 0.0})


def test_encode_unknown_signal_raises(codec: FrameCodec) -> None:
    with pytest.raises(FrameEncodeError, match="RollAngle_valid"):
        codec.encode(
            "EST_Roll", {"RollAngle": 0.1, "RollRateEst": 0.0, "RollUIHOSMO": 0.0, "RollAngle_valid": 1}, counter=0
        )


def test_encode_nan_raises(codec: FrameCodec) -> None:
    with pytest.raises(FrameEncodeError, match="NaN"):
        codec.encode("EST_Roll", {"RollAngle": math.nan, "RollRateEst": 0.0, "RollUIHOSMO": 0.0}, counter=0)


@pytest.mark.parametrize("bad", [None, "fast", [1.0]])
def test_encode_non_number_raises(codec: FrameCodec, bad) -> None:
    with pytest.raises(FrameEncodeError, match="RollAngle"):
        codec.encode("EST_Roll", {"RollAngle": bad, "RollRateEst": 0.0, "RollUIHOSMO": 0.0}, counter=0)


def test_encode_defaults_counter_crc_valid(codec: FrameCodec) -> None:
    fid, data = codec.encode("EST_Roll", {"RollAngle": 0.2, "RollRateEst": 0.0, "RollUIHOSMO": 0.0})
    _, dec = codec.decode_checked(fid, data)
    assert dec["EST_Roll_Counter"] == 0
    assert dec["EST_Roll_Valid"] == 0  # a missing validity bit means invalid
    assert dec["RollAngle_Valid"] == 0
    _, data = codec.encode("IMU_Rates", {"RollRate": 0, "PitchRate": 0, "YawRate": 0, "IMU_Counter": 9})
    assert codec.decode(codec.frame_id("IMU_Rates"), data)[1]["IMU_Counter"] == 9


def test_encode_counter_argument_and_range(codec: FrameCodec) -> None:
    vals = {"RollAngle": 0.0, "RollRateEst": 0.0, "RollUIHOSMO": 0.0, "EST_Roll_Valid": 1}
    for c in range(15):
        fid, data = codec.encode("EST_Roll", vals, counter=c)
        assert data[1] & 0x0F == c
        assert check_p11(fid, data)
    with pytest.raises(FrameEncodeError):
        codec.encode("EST_Roll", vals, counter=15)
    with pytest.raises(FrameEncodeError):
        codec.encode(
            "EST_Status",
            {"Mode": 2, "SensorTimeouts": 0, "OverrunCount": 0, "CycleTimeUs": 1, "ReasonBits": 0},
            counter=15,
        )
    with pytest.raises(FrameEncodeError):
        codec.encode("EST_Roll", vals, counter=2.5)
    # plain 4-bit input counters use all 16 values
    _, data = codec.encode("Steer_Encoder", {"SteerCount": 512}, counter=15)
    assert codec.decode(codec.frame_id("Steer_Encoder"), data)[1] == {"SteerCount": 512.0, "Steer_Counter": 15.0}


def test_e2e_frames_verified_by_autosar_e2e(codec: FrameCodec) -> None:
    p11 = pytest.importorskip("e2e.p11")
    for msg in E2E_OUTPUTS:
        vals = _full_values(codec, msg, lambda _n, lo, hi: lo + 0.3 * (hi - lo))
        vals.pop(codec.counter_signal(msg))
        for c in (0, 7, 14):
            fid, data = codec.encode(msg, vals, counter=c)
            assert p11.e2e_p11_check(bytearray(data), fid)
            ref = bytearray(data)
            ref[1] = (ref[1] & 0xF0) | ((c - 1) % 15)
            p11.e2e_p11_protect(ref, fid, increment_counter=True)  # reference sender one step later
            assert bytes(ref) == data


def test_decode_checked_detects_corruption_and_misrouting(codec: FrameCodec) -> None:
    vals = {"LateralVelocity": -1.25, "FrontLateralForce": 800, "RearLateralForce": -650, "EST_Lateral_Valid": 1}
    fid, data = codec.encode("EST_Lateral", vals, counter=5)
    codec.decode_checked(fid, data)
    bad = bytearray(data)
    bad[4] ^= 0x01
    codec.decode(fid, bytes(bad))  # unchecked decode does not look at the CRC
    with pytest.raises(FrameDecodeError) as ei:
        codec.decode_checked(fid, bytes(bad))
    assert ei.value.reason == "crc"
    with pytest.raises(FrameDecodeError) as ei:  # same payload arriving under another E2E id
        codec.decode_checked(codec.frame_id("EST_Roll"), data)
    assert ei.value.reason == "crc"


def test_decode_enums_as_numbers(codec: FrameCodec) -> None:
    vals = {"Mode": 3, "SensorTimeouts": 0b1010, "OverrunCount": 2, "CycleTimeUs": 812, "ReasonBits": 0x104}
    fid, data = codec.encode("EST_Status", vals, counter=14)
    name, dec = codec.decode_checked(fid, data)
    assert name == "EST_Status"
    assert dec["Mode"] == 3.0 and isinstance(dec["Mode"], float)
    assert dec["SensorTimeouts"] == 10 and dec["ReasonBits"] == 0x104 and dec["EST_Status_Counter"] == 14


# ---------------------------------------------------------------- decode errors


def test_decode_wrong_dlc(codec: FrameCodec) -> None:
    fid = codec.frame_id("IMU_Rates")
    for n in (0, 6, 8):
        with pytest.raises(FrameDecodeError) as ei:
            codec.decode(fid, bytes(n))
        assert ei.value.reason == "wrong_dlc"
        assert ei.value.frame_id == fid


def test_decode_unknown_id(codec: FrameCodec) -> None:
    with pytest.raises(FrameDecodeError) as ei:
        codec.decode(0x7FE, bytes(8))
    assert ei.value.reason == "unknown_id"
    with pytest.raises(FrameDecodeError) as ei:  # a 29-bit frame with the same number is another frame
        codec.decode(codec.frame_id("IMU_Rates"), bytes(7), extended=True)
    assert ei.value.reason == "unknown_id"
    with pytest.raises(FrameDecodeError) as ei:
        codec.decode("IMU_Rates", bytes(7))  # type: ignore[arg-type]
    assert ei.value.reason == "unknown_id"


@pytest.mark.parametrize("data", ["abcdefg", None, [300, 0, 0, 0, 0, 0, 0], 12345])
def test_decode_garbage(codec: FrameCodec, data) -> None:
    with pytest.raises(FrameDecodeError) as ei:
        codec.decode(codec.frame_id("IMU_Rates"), data)
    assert ei.value.reason == "garbage"


def test_decode_checked_counter_15_is_garbage(codec: FrameCodec) -> None:
    from ptw_rt.io.e2e import profile11_crc

    fid = codec.frame_id("EST_Roll")
    frame = bytearray(8)
    frame[1] = 0x0F
    frame[0] = profile11_crc(fid, frame)
    with pytest.raises(FrameDecodeError) as ei:
        codec.decode_checked(fid, bytes(frame))
    assert ei.value.reason == "garbage"


@settings(max_examples=500, deadline=None)
@given(
    frame_id=st.one_of(st.integers(0, 0x7FF), st.sampled_from([0x100, 0x101, 0x102, 0x110, 0x300, 0x301, 0x310])),
    data=st.binary(min_size=0, max_size=16),
    extended=st.booleans(),
)
def test_decode_never_raises_anything_else(codec: FrameCodec, frame_id: int, data: bytes, extended: bool) -> None:
    for fn in (codec.decode, codec.decode_checked):
        try:
            name, values = fn(frame_id, data, extended=extended)
        except FrameDecodeError as exc:
            assert exc.reason in FrameDecodeError.REASONS
            assert isinstance(exc, ValueError)
        else:
            assert name == codec.message_name(frame_id)
            assert len(data) == codec.expected_length(name)
            assert all(isinstance(v, float) and math.isfinite(v) for v in values.values())


def test_contract_names_are_exact_in_dbc_text() -> None:
    """Guard against case/underscore drift in mandated names (a rename is a breaking change)."""
    text = DEFAULT_DBC.read_text()
    mandated = set(ALL_CONTRACT)
    for spec in ALL_CONTRACT.values():
        mandated |= set(spec["signals"])
        if "counter" in spec:
            mandated.add(spec["counter"])
    for msg in CONTRACT_OUTPUTS:
        mandated |= {f"{msg}_Counter", f"{msg}_Valid"}
    for msg in E2E_OUTPUTS:
        mandated.add(f"{msg}_CRC")
    for name in mandated:
        assert re.search(rf"\b{re.escape(name)}\b", text), name
