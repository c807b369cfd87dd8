"""The input tracker's rolling-counter rule: which frames are suspect (their payload may be garbage, and the
estimator holds it). A frame is in sequence when its counter follows the previous frame's, or the last
in-sequence frame's by the frames received since: a garbage payload between two sound frames takes a slot of the
sequence, and the sound frame after it must not be thrown away with it (`sensor_faults`: in a burst where every
other frame was garbage every sound frame was held, 0.3 s of held rates and steer)."""

from __future__ import annotations

import pytest

from ptw_rt.core import layout as L  # noqa: N812
from ptw_rt.edge.cycle import build_runner
from ptw_rt.edge.inputs import InputTracker
from ptw_rt.paths import DEFAULT_CONFIG


@pytest.fixture(scope="module")
def codec():
    return build_runner(DEFAULT_CONFIG).codec


class Steer:
    """A steer encoder's frames, one per call, into a fresh tracker; returns whether that frame was suspect."""

    def __init__(self, codec):
        self.codec = codec
        self.tracker = InputTracker(codec)
        self.sample = L.new_sample()
        self.t = 0.0

    def frame(self, counter: int, count: int = 512) -> bool:
        frame_id, data = self.codec.encode("Steer_Encoder", {"SteerCount": count}, counter=counter)
        return self.raw(frame_id, data)

    def raw(self, frame_id: int, data: bytes) -> bool:
        self.t += 0.01
        self.tracker.on_frame(self.t, frame_id, data)
        self.tracker.fill(self.sample, self.t)
        return bool(int(self.sample[L.S_SUSPECT]) & L.MSG_STEER)

    def jumps(self) -> int:
        return self.tracker.summary()["Steer_Encoder"]["counter_jumps"]


def test_a_sound_frame_after_a_garbage_one_is_in_sequence(codec):
    s = Steer(codec)
    assert not any(s.frame(c) for c in range(5))
    assert s.frame(11)  # garbage in slot 5: a random counter
    assert not s.frame(6)  # the sound frame of slot 6 continues 4 by the two frames since
    assert not s.frame(7)
    assert s.jumps() == 1


def test_every_other_frame_garbage_leaves_the_sound_ones_in_sequence(codec):
    s = Steer(codec)
    s.frame(0)
    for slot in range(1, 40):
        garbage = slot % 2 == 1
        counter = (slot + 7) % 16 if garbage else slot % 16
        assert s.frame(counter) == garbage, slot


def test_an_undecodable_frame_takes_a_slot(codec):
    s = Steer(codec)
    for c in range(3):
        s.frame(c)
    frame_id, data = codec.encode("Steer_Encoder", {"SteerCount": 512}, counter=3)
    s.raw(frame_id, data[:1])  # the wrong length: a decode error in slot 3
    assert not s.frame(4)
    assert s.jumps() == 0


def test_a_lost_frame_a_repeated_one_and_a_restarted_counter_are_suspect_once(codec):
    s = Steer(codec)
    for c in range(4):
        s.frame(c)
    assert s.frame(5)  # slot 4 lost on the bus: the sequence broke
    assert not s.frame(6)  # ... and goes on from the frame before
    assert s.frame(6)  # repeated
    assert not s.frame(7)
    assert s.frame(0)  # the sensor restarted its counter
    assert not s.frame(1)  # follows the previous frame: a new sequence
    assert not s.frame(2)
    assert s.jumps() == 3


def test_a_frozen_counter_is_suspect_for_as_long_as_it_repeats(codec):
    s = Steer(codec)
    for c in range(3):
        s.frame(c)
    assert all(s.frame(2) for _ in range(5))
    assert not s.frame(8)  # the sender resumed where it would have been: 2 + the 6 frames since
    assert all(s.frame(8) for _ in range(20))  # a turn of the counter and more: the 16th repeat is no sequence
    assert s.frame((8 + 21) % 16)  # nor is the resumed one (16 lost frames look like none)
    assert not s.frame((8 + 22) % 16)
