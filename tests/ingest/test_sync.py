"""The one stereo pairing rule: `pair_stereo` on a recording, `StereoPairer` as frames arrive."""

from __future__ import annotations

import numpy as np
import pytest

from ingest.train.sync import lidar_covered, median_period_ns, pair_stereo, pair_tolerance_ns, select_samples
from sensorbox.live.cameras import StereoPairer


def test_pair_stereo_is_one_to_one():
    up = np.array([0, 100, 200, 300])
    low = np.array([2, 98, 105, 299, 460])  # 98 and 105 both near 100: only the nearer pairs
    pairs = pair_stereo(up, low, 40)
    assert pairs.upper.tolist() == [0, 1, 3] and pairs.lower.tolist() == [0, 1, 3]
    assert pairs.dt_ns.tolist() == [2, -2, -1] and (pairs.dropped_upper, pairs.dropped_lower) == (1, 2)
    assert len(pair_stereo(up, np.array([], np.int64), 40).upper) == 0
    assert pair_stereo(np.array([5]), np.array([7]), 1).upper.tolist() == []


def test_of_two_upper_frames_near_one_lower_frame_the_nearer_pairs():
    """Greedy by |dt| over both cameras: a duplicated or jittered upper frame that comes first does not
    take the lower frame from the later, nearer one."""
    pairs = pair_stereo(np.array([0, 10]), np.array([9]), 20)
    assert pairs.upper.tolist() == [1] and pairs.lower.tolist() == [0] and pairs.dt_ns.tolist() == [-1]
    assert (pairs.dropped_upper, pairs.dropped_lower) == (1, 0)
    pairs = pair_stereo(np.array([0, 100, 112]), np.array([3, 110, 96]), 20)  # lower out of order too
    assert pairs.upper.tolist() == [0, 1, 2] and pairs.lower.tolist() == [0, 2, 1]
    assert pairs.dt_ns.tolist() == [3, -4, -2]


def test_the_tolerance_is_half_a_period():
    stamps = np.arange(10, dtype=np.int64) * 33_333_333
    assert (
        median_period_ns(stamps) == 33_333_333 and pair_tolerance_ns(median_period_ns(stamps)) == 16_666_666
    )
    assert median_period_ns(stamps[:1]) == 0.0


@pytest.mark.parametrize("seed", range(5))
def test_the_live_pairer_pairs_as_the_recording_rule_does(seed):
    """Jittered 30 Hz cameras with missing frames: pairing as frames arrive = pairing the whole recording."""
    rng = np.random.default_rng(seed)
    period = 33_333_333
    tol = pair_tolerance_ns(period)
    base = np.arange(300, dtype=np.int64) * period
    up = base + rng.integers(-3_000_000, 3_000_000, len(base))
    low = base + 100_000 + rng.integers(-3_000_000, 3_000_000, len(base))
    up = np.sort(up[rng.random(len(up)) > 0.05])  # ~5 % of frames missing on each camera
    low = np.sort(low[rng.random(len(low)) > 0.05])
    want = pair_stereo(up, low, tol)
    live = StereoPairer(tol)
    got: list[tuple[int, int]] = []
    events = sorted([(int(t), 0) for t in up] + [(int(t), 1) for t in low])  # arrival in stamp order
    for stamp, cam in events:
        got += live.push(cam, stamp, stamp)
    live.flush()
    assert got == list(zip(up[want.upper].tolist(), low[want.lower].tolist(), strict=True))
    assert live.pairs == len(want.upper)
    assert live.unpaired[0] + live.at_stop[0] == want.dropped_upper
    assert live.unpaired[1] + live.at_stop[1] == want.dropped_lower


def test_frames_without_lidar_in_their_window_are_left_out_and_can_be_counted():
    """A sweep covers a frame when it overlaps [t - w, t + w]; the others are not samples (and the
    pipeline counts them as 'stereo pairs without LiDAR points in their window')."""
    frames = np.array([0, 100, 200, 300, 400], np.int64)
    spans = [(60, 140), (240, 250)]  # PointCloud2 without point times: a sweep can be one instant
    covered = lidar_covered(frames, spans, 50)
    assert covered.tolist() == [False, True, True, True, False]  # 200: 250 - 50; 300: 250 + 50
    assert select_samples(frames, spans, 50).tolist() == [1, 2, 3]
    assert select_samples(frames, spans, 50, every=2).tolist() == [1, 3]
    assert lidar_covered(frames, [], 50).tolist() == [False] * 5


def test_lidar_covered_is_the_overlap_test_of_every_sweep_on_random_spans():
    """The one-sort, one-search version against the definition (some sweep overlaps [t - w, t + w])
    on random overlapping, nested and touching spans, frames on the window's edges included."""
    rng = np.random.default_rng(3)
    for _ in range(200):
        n = int(rng.integers(1, 12))
        first = rng.integers(0, 1000, n)
        spans = [(int(a), int(a + b)) for a, b in zip(first, rng.integers(0, 200, n), strict=True)]
        w = int(rng.integers(0, 60))
        edges = [t for a, b in spans for t in (a - w - 1, a - w, b + w, b + w + 1)]
        frames = np.sort(np.r_[rng.integers(-100, 1300, 30), edges]).astype(np.int64)
        expected = [any(a <= t + w and b >= t - w for a, b in spans) for t in frames]
        assert lidar_covered(frames, spans, w).tolist() == expected
