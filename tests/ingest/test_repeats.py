"""`ingest.train.repeats.FirstCopies`: the first copy of each message passes, repeats are counted."""

from __future__ import annotations

from ingest.train.repeats import FirstCopies, fingerprint


def test_first_copies_pass_and_repeats_are_counted_per_topic():
    copies = FirstCopies()
    assert [copies.first("/a", k, k) for k in (1, 2, 1, 3, 2)] == [True, True, False, True, False]
    assert copies.first("/b", 1, 1)  # the same key on another topic is another message
    assert copies.repeats == {"/a": 2}


def test_keys_are_forgotten_only_far_behind_their_own_topic():
    copies = FirstCopies(horizon_ns=100)
    assert copies.first("/imu", 0, 0)  # a sensor on another clock: stamps of zero
    for t in range(0, 20_000, 2):  # many readings on a clock far ahead: pruning happens on the way
        assert copies.first("/cam", t, 1_000_000 + t)
    assert not copies.first("/imu", 0, 0)  # still known: /cam's clock does not prune /imu
    assert not copies.first("/cam", 19_998, 1_019_998)  # recent: known
    assert copies.first("/cam", 0, 1_000_000)  # 19_998 behind /cam's newest: forgotten, taken as new
    assert copies.repeats == {"/imu": 1, "/cam": 1}


def test_a_repeat_with_other_bytes_is_left_out_and_listed_by_its_stamp():
    copies = FirstCopies()
    frame = bytes(range(256)) * 40
    other = frame[:-1] + b"\x00"  # another exposure under the same header stamp
    assert copies.stamped("/cam", 5, fingerprint(frame))
    assert not copies.stamped("/cam", 5, fingerprint(frame))  # a copy: counted only
    assert not copies.stamped("/cam", 5, fingerprint(other))
    assert not copies.stamped("/cam", 5)  # the passes that compare no bytes
    assert copies.repeats == {"/cam": 3}
    assert copies.restamped == {"/cam": [5]}


def test_a_fingerprint_tells_apart_what_differs_in_length_or_in_the_last_bytes():
    a = bytes(10_000)
    assert fingerprint(a) == fingerprint(memoryview(a))
    assert fingerprint(a) != fingerprint(a + b"\x00")
    assert fingerprint(a) != fingerprint(a[:-1] + b"\x01")
