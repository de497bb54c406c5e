"""`filter_points`: which LiDAR returns are real, and the count of each reason a point was dropped."""

from __future__ import annotations

import numpy as np

from ingest.train.clouds import NOISE_TAG_BITS, FilterCounts, filter_points


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
