"""OutputEncoder: counters, E2E CRCs, 10 Hz messages, validity bits, byte-identity with FrameCodec.encode."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ptw_rt.core.layout import (
    E_C_ALPHA_FRONT,
    E_C_ALPHA_REAR,
    E_C_GAMMA_FRONT,
    E_C_GAMMA_REAR,
    E_FY_REAR,
    E_MODE,
    E_REASONS,
    E_ROLL,
    E_ROLL_UIO_SENSORS,
    E_VALID,
    MODE_CONVERGING,
    MODE_DEGRADED,
    MODE_FAULT,
    MODE_INIT,
    MODE_VALID,
    REASON_OVERRUN,
    V_CAMBER,
    V_CORNERING,
    V_FY_FRONT,
    V_FY_REAR,
    V_LAT_VEL,
    V_ROLL,
    V_ROLL_RATE,
    new_estimates,
)
from ptw_rt.edge.outputs import SIGNAL_MAP, OutputEncoder
from ptw_rt.io.dbc import FrameCodec

ALL_VALID = (1 << 10) - 1


@pytest.fixture(scope="module")
def codec():
    return FrameCodec()


def _estimates(mode=MODE_VALID, valid=ALL_VALID, values=None):
    e = new_estimates()
    e[E_MODE] = mode
    e[E_VALID] = valid
    e[E_C_ALPHA_FRONT], e[E_C_GAMMA_FRONT], e[E_C_ALPHA_REAR], e[E_C_GAMMA_REAR] = 30000, 1500, 40000, 1200
    for k, v in (values or {}).items():
        e[k] = v
    return e


def _decode_all(codec, frames):
    return {name: values for name, values in (codec.decode_checked(fid, data) for fid, data in frames)}


def test_rates_counters_and_crcs(codec):
    enc = OutputEncoder(codec, 0.01)
    e = _estimates()
    seen: dict[str, list[int]] = {}
    per_cycle = []
    for k in range(100):
        frames = enc.frames(e, k, {"overrun_count": 0, "cycle_time_us": 100})
        per_cycle.append(len(frames))
        for name, values in _decode_all(codec, frames).items():  # decode_checked verifies the P11 CRCs
            seen.setdefault(name, []).append(int(values[f"{name}_Counter"]))
    slow = ("EST_Status", "EST_TireStiffness", "EST_TireConfidence", "EST_Plausibility")
    assert enc.periods == {n: (10 if n in slow else 1) for n in enc.periods}
    assert per_cycle[0] == 7 and per_cycle[10] == 7 and per_cycle[1] == 3 and per_cycle[9] == 3
    assert sum(per_cycle) == 3 * 100 + 4 * 10
    for name in ("EST_Roll", "EST_RiderTorque", "EST_Lateral"):
        assert seen[name] == [k % 15 for k in range(100)]  # wraps 14 -> 0, 15 never sent
    for name in ("EST_Status", "EST_TireStiffness", "EST_TireConfidence", "EST_Plausibility"):
        assert seen[name] == list(range(10))
    # a counter continuing over the wrap
    assert seen["EST_Roll"][14:16] == [14, 0]


def test_crc_detects_corruption(codec):
    from ptw_rt.io.dbc import FrameDecodeError

    enc = OutputEncoder(codec)
    fid, data = enc.frames(_estimates(values={E_ROLL: 0.2}), 1)[0]
    bad = bytearray(data)
    bad[3] ^= 0x01
    with pytest.raises(FrameDecodeError):
        codec.decode_checked(fid, bytes(bad))


def test_valid_bits(codec):
    enc = OutputEncoder(codec)
    e = _estimates(valid=V_ROLL | V_LAT_VEL | V_CORNERING)
    d = _decode_all(codec, enc.frames(e, 0, {}))
    assert d["EST_Roll"]["EST_Roll_Valid"] == 1
    assert d["EST_Roll"]["RollAngle_Valid"] == 1 and d["EST_Roll"]["RollRateEst_Valid"] == 0
    assert d["EST_RiderTorque"]["EST_RiderTorque_Valid"] == 0  # no signal of the group valid
    assert d["EST_Lateral"]["EST_Lateral_Valid"] == 1
    assert d["EST_Lateral"]["LateralVelocity_Valid"] == 1 and d["EST_Lateral"]["FrontLateralForce_Valid"] == 0
    assert d["EST_TireStiffness"]["CorneringStiffness_Valid"] == 1
    assert d["EST_TireStiffness"]["CamberStiffness_Valid"] == 0
    assert d["EST_TireStiffness"]["EST_TireStiffness_Valid"] == 1
    assert d["EST_Status"]["EST_Status_Valid"] == 1
    for mode, ok in ((MODE_INIT, 0), (MODE_FAULT, 0), (MODE_CONVERGING, 1), (MODE_DEGRADED, 1), (MODE_VALID, 1)):
        d = _decode_all(codec, enc.frames(_estimates(mode=mode), 0, {}))
        for name in ("EST_Roll", "EST_RiderTorque", "EST_Lateral", "EST_TireStiffness"):
            assert d[name][f"{name}_Valid"] == ok, (mode, name)
        assert d["EST_Status"]["Mode"] == mode
        assert d["EST_Roll"]["RollAngle_Valid"] == 1  # per-signal bits are E_VALID as is


def test_status_content_and_saturation(codec):
    enc = OutputEncoder(codec)
    e = _estimates(mode=MODE_DEGRADED, values={E_REASONS: REASON_OVERRUN | 1})
    d = _decode_all(codec, enc.frames(e, 0, {"overrun_count": 70000, "cycle_time_us": 123456}, stale_bits=0b1010))
    st = d["EST_Status"]
    assert st["Mode"] == MODE_DEGRADED
    assert st["SensorTimeouts"] == 0b1010
    assert st["ReasonBits"] == REASON_OVERRUN | 1
    assert st["OverrunCount"] == 65535 and st["CycleTimeUs"] == 65535
    _, data = enc.status_frame(e, 0, {}, valid=False)
    assert codec.decode(codec.frame_id("EST_Status"), data)[1]["EST_Status_Valid"] == 0


def test_non_finite_and_clipping(codec):
    enc = OutputEncoder(codec)
    e = _estimates(values={E_ROLL: 5.0, E_FY_REAR: math.nan})
    d = _decode_all(codec, enc.frames(e, 1))
    assert d["EST_Roll"]["RollAngle"] == pytest.approx(1.5)  # clipped to the DBC range
    assert d["EST_Lateral"]["RearLateralForce"] == 0.0
    assert d["EST_Lateral"]["RearLateralForce_Valid"] == 0
    assert d["EST_Lateral"]["FrontLateralForce_Valid"] == 1


def test_byte_identical_to_cantools(codec):
    """The codec's integer packing must produce exactly what cantools produces, rounding included: the same
    encoder on a codec whose messages all take the generic (cantools) branch is the reference."""
    rng = np.random.default_rng(1)
    enc = OutputEncoder(codec)
    generic = FrameCodec()
    for name in generic.output_messages:
        generic.layout(name).plain = False  # reference: cantools' Message.encode
    ref = OutputEncoder(generic)
    assert all(codec.layout(n).plain for n in codec.output_messages)
    for k in range(400):
        e = new_estimates()
        for name, slots in SIGNAL_MAP.items():
            for signal, index, _ in slots:
                lo, hi = codec.signal_limits(name)[signal]
                span = hi - lo
                r = rng.random()
                if r < 0.1:  # exact half steps of the raw resolution (banker's rounding in cantools)
                    e[index] = round(rng.uniform(lo, hi)) + 0.5
                elif r < 0.2:
                    e[index] = rng.choice([lo - span, hi + span, lo, hi, 0.0])
                else:
                    e[index] = rng.uniform(lo, hi)
        e[E_MODE] = rng.integers(0, 5)
        e[E_VALID] = rng.integers(0, 1024)
        e[E_REASONS] = rng.integers(0, 512)
        status = {"overrun_count": int(rng.integers(0, 70000)), "cycle_time_us": int(rng.integers(0, 70000))}
        stale = int(rng.integers(0, 16))
        assert enc.frames(e, k, status, stale) == ref.frames(e, k, status, stale)
    # sanity: plus one explicit codec.encode
    fid, data = codec.encode(
        "EST_Roll",
        {
            "RollAngle": 0.12345,
            "RollRateEst": -0.5,
            "RollUIHOSMO": 0.1,
            "RollAngle_Valid": 1,
            "RollRateEst_Valid": 1,
            "EST_Roll_Valid": 1,
        },
        counter=7,
    )
    enc2 = OutputEncoder(codec)
    enc2.counters["EST_Roll"] = 7
    e = _estimates(valid=V_ROLL | V_ROLL_RATE | V_FY_FRONT | V_FY_REAR | V_CAMBER, values={E_ROLL: 0.12345})
    e[1] = -0.5
    e[E_ROLL_UIO_SENSORS] = 0.1
    assert enc2.frames(e, 1)[0] == (fid, data)
