"""The compiled scan of plain candump blocks (`ptw_rt.io.candump_scan`) against the definition, `parse_line`.

The scan may refuse a block that `parse_line` would take (the block then goes line by line, to the same
frames), but a block it accepts must give exactly `parse_line`'s frames: the same doubles for the stamps,
ids, widths, payloads and channels. Mutated lines probe every field's edges.
"""

from __future__ import annotations

import numpy as np
import pytest

from ptw_rt.io.candump import MAX_LINE_CHARS, _plain_columns, parse_line

PLAIN = [
    "(1700000000.123456) vcan0 123#DEADBEEF",
    "(0000000001.000000) can0 7FF#",
    "(1.) can0 000#00",
    "(99999.999999999) can0 1FFFFFFF#0011223344556677",
    "(1700000000.1) x 00000123#aBcD",
]


def _by_definition(lines):
    frames = [parse_line(line, k + 1) for k, line in enumerate(lines)]
    return frames


def _assert_same(lines):
    got = _plain_columns(lines)
    try:
        frames = _by_definition(lines)
    except ValueError:
        frames = None
    if got is None:
        return False
    assert frames is not None, f"scan accepted a block parse_line refuses: {lines!r}"
    columns, channels = got
    assert all(not f.is_remote for f in frames)
    np.testing.assert_array_equal(columns.times, [f.timestamp for f in frames])
    assert columns.times.tobytes() == np.array([f.timestamp for f in frames]).tobytes()  # the same doubles
    assert columns.ids.tolist() == [f.frame_id for f in frames]
    assert columns.extended.tolist() == [f.is_extended for f in frames]
    assert [columns.data[k, : columns.lengths[k]].tobytes() for k in range(len(frames))] == [f.data for f in frames]
    assert not columns.data[np.arange(8)[None, :] >= columns.lengths[:, None]].any()  # zero-padded
    assert list(channels) == [f.channel for f in frames]
    assert columns.channel == frames[0].channel
    return True


def test_plain_lines_are_taken():
    assert _assert_same(PLAIN)
    assert _assert_same(PLAIN[:1])


@pytest.mark.parametrize(
    "line",
    [
        "",
        "(1700000000.123456) vcan0 123#DEADBEEF\r",  # a CRLF log: line by line
        "(1700000000.123456) vcan0 123#DEADBEE",  # odd digits
        "(1700000000.123456) vcan0 123#001122334455667788",  # 9 bytes
        "(1700000000.123456) vcan0 800#00",  # 11-bit id out of range
        "(1700000000.123456) vcan0 20000000#00",  # 29-bit id out of range
        "(1700000000.123456) vcan0 1234#00",  # 4 id digits
        "(1700000000.123456) vc#an0 123#00",  # '#' in the channel
        "(1700000000.123456)  vcan0 123#00",  # two spaces
        "(1700000000.123456) vcan0 123#R",  # remote frame
        "(1700000000.123456) vcan0 123##100",  # CAN FD
        "(1700000000.123456) vcan0 123#00 R",  # direction field
        "(17000000000.12345) vcan0 123#00",  # 11 integer digits
        "(1700000000.1234567890) vcan0 123#00",  # 10 fraction digits
        "(9999999999.999999) vcan0 123#00",  # after 2200
        "(1700000000.123456789) vcan0 123#00",  # beyond 2^53 as an integer: line by line
        "(-1.0) vcan0 123#00",
        "(1e9) vcan0 123#00",
        "(1700000000) vcan0 123#00",  # no dot
        "(1700000000.123456) vcän0 123#00",  # not ASCII
        "(1700000000.123456) vcan0 123#00" + "0" * 300,  # too long
        "(1700000000.123456) vcan0",
        "(1700000000.123456",
    ],
)
def test_a_line_that_is_not_plain_sends_the_block_line_by_line(line):
    block = [PLAIN[0], line, PLAIN[1]]
    assert _plain_columns(block) is None
    assert _plain_columns([line]) is None


def test_several_channels_keep_each_line_its_own():
    block = ["(1.000000) can0 123#00", "(1.010000) can1 123#01", "(1.020000) can0 123#02"]
    columns, channels = _plain_columns(block)
    assert list(channels) == ["can0", "can1", "can0"]
    assert _assert_same(block)


def test_random_stamps_are_the_doubles_float_gives():
    rng = np.random.default_rng(7)
    lines = []
    for _ in range(3000):
        whole = int(rng.integers(0, 7_258_118_400))
        digits = int(rng.integers(0, 7))  # candump writes 6: within 2^53 as an integer
        frac = "".join(str(d) for d in rng.integers(0, 10, digits))
        lines.append(f"({whole:010d}.{frac}) can0 {int(rng.integers(0, 0x800)):03X}#{'AB' * int(rng.integers(0, 9))}")
    assert _assert_same(lines)


def test_mutated_lines_are_taken_only_as_parse_line_takes_them():
    """Random single-character edits of plain lines: whatever the scan accepts, parse_line gives the same."""
    rng = np.random.default_rng(3)
    alphabet = "0123456789abcdefABCDEF#.() R\t-xX" + "\r"
    accepted = 0
    for _ in range(3000):
        line = list(PLAIN[int(rng.integers(0, len(PLAIN)))])
        for _ in range(int(rng.integers(1, 3))):
            k = int(rng.integers(0, len(line) + 1))
            op = int(rng.integers(0, 3))
            c = alphabet[int(rng.integers(0, len(alphabet)))]
            if op == 0 and k < len(line):
                line[k] = c
            elif op == 1:
                line.insert(k, c)
            elif k < len(line):
                del line[k]
        text = "".join(line)
        if "\n" in text or len(text) > MAX_LINE_CHARS:
            continue
        accepted += _assert_same([text])
    assert accepted > 300  # the edits leave many lines plain: the comparison is not vacuous
