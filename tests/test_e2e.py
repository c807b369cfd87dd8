"""AUTOSAR E2E Profile 11 helpers: contract known answers and agreement with the autosar-e2e package."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ptw_rt.io.e2e import (
    COUNTER_MAX,
    P11Checker,
    P11Status,
    check_p11,
    counter_delta,
    crc8_sae_j1850,
    next_counter,
    profile11_crc,
    protect_p11,
)

p11 = pytest.importorskip("e2e.p11", reason="autosar-e2e (pip install autosar-e2e) is the test oracle")
e2e_crc = pytest.importorskip("e2e.crc")

frames = st.binary(min_size=8, max_size=8)
data_ids = st.integers(0, 0xFFFF)
counters = st.integers(0, COUNTER_MAX)


# ---------------------------------------------------------------- known answers (contract)


def test_crc8_sae_j1850_check_value() -> None:
    assert crc8_sae_j1850(b"123456789") == 0x4B  # init 0xFF, xor-out 0xFF
    assert crc8_sae_j1850(b"123456789", 0xFF, True) == e2e_crc.calculate_crc8(b"123456789")


def test_crc8_profile_variant_check_value() -> None:
    # poly 0x1D, init 0x00, no xor-out: CRC-8/GSM-A, check value 0x37
    assert crc8_sae_j1850(b"123456789", start=0x00, xor_out=False) == 0x37


def test_crc8_empty_input() -> None:
    assert crc8_sae_j1850(b"") == 0x00  # 0xFF ^ 0xFF
    assert crc8_sae_j1850(b"", start=0x00, xor_out=False) == 0x00


def test_profile11_known_answer_zero_payload() -> None:
    frame = bytearray(8)
    protect_p11(0x123, frame, 0)
    assert frame[0] == 0xCC
    assert bytes(frame) == bytes([0xCC]) + bytes(7)
    assert profile11_crc(0x123, bytes(8)) == 0xCC
    assert check_p11(0x123, bytes(frame))


def test_profile11_crc_equals_plain_crc_over_id_and_payload() -> None:
    frame = bytes(range(8))
    expected = crc8_sae_j1850(bytes([0x23, 0x01]) + frame[1:], start=0x00, xor_out=False)
    assert profile11_crc(0x123, frame) == expected


# ---------------------------------------------------------------- oracle: autosar-e2e


@settings(max_examples=400, deadline=None)
@given(payload=frames, data_id=data_ids, counter=counters)
def test_protect_matches_autosar_e2e(payload: bytes, data_id: int, counter: int) -> None:
    ours = bytearray(payload)
    protect_p11(data_id, ours, counter)
    ref = bytearray(payload)
    ref[1] = (ref[1] & 0xF0) | counter
    p11.e2e_p11_protect(ref, data_id, data_id_mode=p11.E2E_P11_DATAID_BOTH, increment_counter=False)
    assert ours == ref
    assert ours[1] & 0x0F == counter
    assert ours[1] >> 4 == payload[1] >> 4  # high nibble of byte 1 untouched
    assert ours[2:] == payload[2:]


@settings(max_examples=200, deadline=None)
@given(payload=st.binary(min_size=2, max_size=8), data_id=data_ids, counter=counters)
def test_protect_matches_autosar_e2e_short_frames(payload: bytes, data_id: int, counter: int) -> None:
    ours = bytearray(payload)
    protect_p11(data_id, ours, counter)
    ref = bytearray(payload)
    ref[1] = (ref[1] & 0xF0) | counter
    p11.e2e_p11_protect(ref, data_id, increment_counter=False)
    assert ours == ref


@settings(max_examples=400, deadline=None)
@given(payload=frames, data_id=data_ids)
def test_check_matches_autosar_e2e(payload: bytes, data_id: int) -> None:
    """On arbitrary (mostly unprotected) frames both checks agree (including the counter-15 rejection)."""
    assert check_p11(data_id, payload) == p11.e2e_p11_check(bytearray(payload), data_id)


@settings(max_examples=200, deadline=None)
@given(payload=frames, data_id=data_ids)
def test_reference_protected_frames_pass_our_check(payload: bytes, data_id: int) -> None:
    ref = bytearray(payload)
    p11.e2e_p11_protect(ref, data_id)
    assert check_p11(data_id, bytes(ref))


@pytest.mark.parametrize("counter", range(COUNTER_MAX + 1))
def test_counter_increment_matches_autosar_e2e(counter: int) -> None:
    ref = bytearray(8)
    ref[1] = counter
    p11.e2e_p11_protect(ref, 0x300, increment_counter=True)
    assert ref[1] & 0x0F == next_counter(counter)


# ---------------------------------------------------------------- detection


@settings(max_examples=100, deadline=None)
@given(payload=frames, counter=counters)
def test_every_single_bit_flip_is_detected(payload: bytes, counter: int) -> None:
    frame = bytearray(payload)
    protect_p11(0x300, frame, counter)
    assert check_p11(0x300, bytes(frame))
    for bit in range(64):
        bad = bytearray(frame)
        bad[bit // 8] ^= 1 << (bit % 8)
        assert not check_p11(0x300, bytes(bad)), f"bit {bit} flip not detected"


def test_wrong_data_id_detected() -> None:
    frame = bytearray(b"\x00\x00\x12\x34\x56\x78\x9a\xbc")
    protect_p11(0x300, frame, 7)
    # any other id with the same high byte differs in one CRC input byte: always detected
    for other in range(0x300, 0x400):
        if other != 0x300:
            assert not check_p11(other, bytes(frame)), hex(other)
    # the other estimator outputs (misrouted frame) are detected
    for other in (0x301, 0x302, 0x003, 0x100):
        assert not check_p11(other, bytes(frame))


def test_checker_detects_repeated_counter() -> None:
    chk = P11Checker(0x300)
    frame = bytearray(8)
    protect_p11(0x300, frame, 3)
    assert chk.check(bytes(frame)) == P11Status.INITIAL
    assert chk.check(bytes(frame)) == P11Status.REPEATED  # frozen sender
    protect_p11(0x300, frame, 4)
    assert chk.check(bytes(frame)) == P11Status.OK


def test_checker_sequence_over_wrap_and_losses() -> None:
    chk = P11Checker(0x301, max_delta_counter=3)
    c = 12
    frame = bytearray(8)
    protect_p11(0x301, frame, c)
    assert chk.check(bytes(frame)) == P11Status.INITIAL
    for _ in range(40):  # crosses 14 -> 0 several times
        c = next_counter(c)
        protect_p11(0x301, frame, c)
        assert chk.check(bytes(frame)) == P11Status.OK
    protect_p11(0x301, frame, (c + 3) % 15)  # two frames lost
    assert chk.check(bytes(frame)) == P11Status.OKSOMELOST
    c = (c + 3) % 15
    protect_p11(0x301, frame, (c + 5) % 15)
    assert chk.check(bytes(frame)) == P11Status.WRONGSEQUENCE


def test_checker_rejects_corruption_wrong_id_and_counter_15() -> None:
    chk = P11Checker(0x302)
    frame = bytearray(8)
    protect_p11(0x302, frame, 0)
    assert chk.check(bytes(frame)) == P11Status.INITIAL
    bad = bytearray(frame)
    bad[5] ^= 0x10
    assert chk.check(bytes(bad)) == P11Status.ERROR
    other = bytearray(8)
    protect_p11(0x300, other, 1)
    assert chk.check(bytes(other)) == P11Status.ERROR  # misrouted
    f15 = bytearray(8)
    f15[1] = 0x0F
    f15[0] = profile11_crc(0x302, f15)  # correct CRC but a counter that is never sent
    assert chk.check(bytes(f15)) == P11Status.ERROR
    protect_p11(0x302, frame, 1)
    assert chk.check(bytes(frame)) == P11Status.OK  # errors did not disturb the sequence state


# ---------------------------------------------------------------- counter


def test_next_counter_wraps_14_to_0_and_never_yields_15() -> None:
    assert next_counter(13) == 14
    assert next_counter(14) == 0
    assert next_counter(15) == 0
    c, seen = 0, []
    for _ in range(100):
        seen.append(c)
        c = next_counter(c)
    assert 15 not in seen
    assert seen[:16] == [*range(15), 0]
    assert set(seen) == set(range(15))


def test_counter_delta() -> None:
    assert counter_delta(14, 0) == 1
    assert counter_delta(3, 3) == 0
    assert counter_delta(13, 1) == 3
    assert counter_delta(15, 0, modulus=16) == 1


@pytest.mark.parametrize("bad", [-1, 15, 16])
def test_protect_rejects_counter_out_of_range(bad: int) -> None:
    with pytest.raises(ValueError):
        protect_p11(0x300, bytearray(8), bad)


def test_check_rejects_counter_15_even_with_correct_crc() -> None:
    for high in (0x00, 0x50, 0xF0):
        frame = bytearray(8)
        frame[1] = high | 0x0F
        frame[0] = profile11_crc(0x300, frame)
        assert not check_p11(0x300, bytes(frame))
        assert not p11.e2e_p11_check(bytearray(frame), 0x300)


@settings(max_examples=300, deadline=None)
@given(payload=frames, data_id=data_ids)
def test_check_agrees_with_autosar_e2e_when_crc_is_right(payload: bytes, data_id: int) -> None:
    """Random frames almost never carry a valid CRC: force it, so the counter handling is compared too."""
    frame = bytearray(payload)
    frame[0] = profile11_crc(data_id, frame)
    assert check_p11(data_id, bytes(frame)) == p11.e2e_p11_check(bytearray(frame), data_id)


def test_check_rejects_too_short() -> None:
    assert not check_p11(0x300, b"")
    assert not check_p11(0x300, b"\x00")
