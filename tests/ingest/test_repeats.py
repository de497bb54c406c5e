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


def test_a_sweep_repeating_its_previous_one_or_another_lidars_at_once_is_left_out_a_replay_is_kept():
    """A stale buffer (the LiDAR's previous sweep again) and one unit's points on the other's topic are left
    out; an older sweep of the same LiDAR sent again, as the emulator replays its scan every
    `loop_s` (sweep 8: 15 sweeps per LiDAR of a plain emulated recording were left out), is kept."""
    import numpy as np

    from ingest.bags.decode import Sweep

    def sweep(points: int, t0_ms: int) -> Sweep:
        xyz = np.random.default_rng(points).normal(size=(200, 3)).astype(np.float32)
        stamps = t0_ms * 1_000_000 + np.arange(200, dtype=np.int64) * 500_000
        return Sweep(t0_ms * 1_000_000, "livox", xyz, stamps, None, None, None)

    copies = FirstCopies()
    assert copies.sweep("/top", sweep(1, 0)) and copies.sweep("/top", sweep(2, 100))
    assert not copies.sweep("/top", sweep(2, 200))  # the previous sweep's points again
    assert copies.sweep("/top", sweep(3, 300)) and copies.sweep("/top", sweep(1, 400))  # a replay of 0 ms
    assert copies.sweep("/bottom", sweep(4, 300)) and not copies.sweep("/top", sweep(4, 350))  # at once
    assert copies.sweep("/bottom", sweep(5, 400)) and not copies.sweep("/top", sweep(5, 700))  # any time
    assert copies.repeated_points == {
        "/top": [(200_000_000, "/top"), (350_000_000, "/bottom"), (700_000_000, "/bottom")]
    }
    assert copies.crossed == {
        "/bottom": [(300_000_000, 399_500_000), (400_000_000, 499_500_000)],
        "/top": [(350_000_000, 449_500_000), (700_000_000, 799_500_000)],
    }
