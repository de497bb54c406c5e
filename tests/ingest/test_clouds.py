"""`filter_points`: which LiDAR returns are real, and the count of each reason a point was dropped;
`compensate`: the predicted image motion that decides whether points are moved."""

from __future__ import annotations

import numpy as np
import pytest

from ingest.train.plausible import NOISE_TAG_BITS
from ingest.train.trajectory.clouds import FilterCounts, filter_points, motion_decision
from ingest.train.trajectory.rig_trajectory import RigTrajectory


def test_each_point_is_kept_or_counted_under_its_first_reason() -> None:
    xyz = np.array([
        [1.0, 2.0, 3.0],  # kept
        [0.0, 0.0, 0.0],  # zero
        [np.nan, 1.0, 1.0],  # non-finite
        [1.0, np.inf, 1.0],  # non-finite
        [0.1, 0.1, 0.1],  # too close (0.17 m < 0.3 m)
        [0.0, 0.0, 0.3],  # exactly the minimum range: kept
        [5.0, 0.0, 0.0],  # noise tag
        [0.0, 0.0, 0.0],  # zero and tagged: counted as zero
        [1e200, 0.0, 0.0],  # finite and far (its square overflows): kept
    ])  # fmt: skip
    tag = np.zeros(len(xyz), np.uint8)
    tag[[6, 7]] = NOISE_TAG_BITS
    keep, counts = filter_points(xyz, tag, 0.3)
    assert keep.tolist() == [True, False, False, False, False, True, False, False, True]
    assert counts == FilterCounts(total=9, zero=2, non_finite=2, too_close=1, noise_tag=1, kept=3)
    keep_untagged, counts_untagged = filter_points(xyz, None, 0.3)
    assert keep_untagged.sum() == 4 and counts_untagged.noise_tag == 0


def test_a_point_dropped_earlier_is_not_counted_again_as_noise_tagged() -> None:
    """The filters count each point under its first reason only, so the counts add up to the total.

    A tagged point that is also too close, non-finite or zero counts under that reason, not
    under `noise_tag` as well.
    """
    xyz = np.array([
        [0.1, 0.1, 0.1],  # too close and tagged
        [np.nan, 0.0, 1.0],  # non-finite and tagged
        [0.0, 0.0, 0.0],  # zero and tagged
        [4.0, 0.0, 0.0],  # tagged only
        [0.0, 3.0, 0.0],  # kept
    ])  # fmt: skip
    tag = np.array([NOISE_TAG_BITS, 0b0000_0100, 0b0010_0000, 0b0001_0000, 0b0000_0011], np.uint8)
    keep, counts = filter_points(xyz, tag, 0.3)
    assert keep.tolist() == [False, False, False, False, True]  # bits 0-1 (return number) are no noise
    assert counts == FilterCounts(total=5, zero=1, non_finite=1, too_close=1, noise_tag=1, kept=1)
    assert sum(counts.astuple()[1:]) == counts.total
    keep1, counts1 = filter_points(xyz[:1], tag[:1], 0.3)
    assert (keep1.tolist(), counts1) == ([False], FilterCounts(total=1, too_close=1))


def test_compensation_predicts_translation_as_the_angle_seen_from_the_reference_range() -> None:
    """Predicted image motion of a translation: speed x span / reference range (rad) x px per rad.

    1 m/s over 50 ms moves the rig 5 cm; seen from 2 m that is 0.025 rad, 12.5 px at 500 px/rad,
    so the points are moved by dt x v. At 0.1 m/s over 5 ms the motion is 0.5 mm / 2 m x 500 =
    0.125 px, below the 0.25 px threshold: the points stay as they are.
    """
    pts = np.array([[0.0, 0.0, 3.0], [1.0, 0.0, 0.0]])
    d = motion_decision(np.array([0.05, -0.02]), 0.0, np.array([1.0, 0.0, 0.0]), 500.0)
    assert d.motion_px == pytest.approx(12.5, rel=1e-12)
    assert d.applied and d.speed_mps == 1.0 and d.max_rotation_deg == 0.0
    t_ns = np.array([50_000_000, -20_000_000], np.int64) + 10**9
    moved = RigTrajectory.over_window(None, np.array([1.0, 0.0, 0.0]), 10**9, (t_ns.min(), t_ns.max()))
    np.testing.assert_allclose(
        moved.to_frame(pts, t_ns, 10**9), [[0.05, 0.0, 3.0], [0.98, 0.0, 0.0]], atol=1e-15
    )

    d_slow = motion_decision(np.array([0.005, 0.001]), 0.0, np.array([0.0, 0.1, 0.0]), 500.0)
    assert d_slow.motion_px == pytest.approx(0.125, rel=1e-12)
    assert not d_slow.applied
