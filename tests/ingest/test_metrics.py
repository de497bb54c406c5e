"""Stereo and depth metrics on hand-computed examples, pooling, quantile histogram, edge band."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from ingest.eval.metrics import (
    DepthAccumulator,
    StereoAccumulator,
    depth_metrics,
    median_scale,
    score_range,
    stereo_metrics,
)
from ingest.raster.edges import edge_band

NAN = np.nan


def test_stereo_hand_example() -> None:
    gt = np.array([[1.0, 2.0, 3.0, 0.0], [4.0, 5.0, NAN, 6.0]], np.float32)
    pred = np.array([[1.5, 2.0, 6.0, 9.0], [6.5, NAN, 3.0, -1.0]], np.float32)
    m = stereo_metrics(pred, gt)
    # valid GT: 1, 2, 3, 4, 5, 6 (0 and NaN are invalid); predictions NaN and -1 do not count
    assert (m.n_gt, m.n) == (6, 4)
    assert m.coverage == pytest.approx(4 / 6)
    # errors 0.5, 0, 3, 2.5
    assert m.epe_px == pytest.approx(6.0 / 4)
    assert m.median_px == pytest.approx(1.5)
    assert m.p95_px == pytest.approx(2.5 + 0.85 * 0.5)  # linear interpolation at rank 0.95 * 3
    assert (m.bad1, m.bad2, m.bad3) == (0.5, 0.5, 0.0)  # bad-k is "> k": an error of exactly 3 is not bad-3


def test_a_prediction_exactly_k_px_off_in_float32_is_not_bad_k() -> None:
    """Sweep 6: GT + 1.00 px stored as float32 scored bad-1 4.81 % (errors came out as 1.0000000185)."""
    gt = np.linspace(0.3, 300.7, 4096).astype(np.float32).reshape(64, 64)
    for k in (1.0, 2.0, 3.0):
        pred = (gt.astype(np.float64) + k).astype(np.float32)
        assert (pred.astype(np.float64) - gt > k).any()  # float32 rounding lands beyond k on some
        m = stereo_metrics(pred, gt)
        assert m.epe_px == pytest.approx(k, abs=1e-4)
        assert [m.bad1, m.bad2, m.bad3] == [1.0 if t < k else 0.0 for t in (1.0, 2.0, 3.0)]
    assert stereo_metrics((gt.astype(np.float64) + 1.001).astype(np.float32), gt).bad1 == 1.0


def test_stereo_mask_restricts_the_pixels() -> None:
    gt = np.array([[1.0, 2.0, 3.0, 0.0], [4.0, 5.0, NAN, 6.0]], np.float32)
    pred = np.array([[1.5, 2.0, 6.0, 9.0], [6.5, NAN, 3.0, -1.0]], np.float32)
    mask = np.ones(gt.shape, bool)
    mask[0, 2] = False  # the pixel with error 3
    m = stereo_metrics(pred, gt, mask)
    assert (m.n_gt, m.n) == (5, 3)
    assert m.epe_px == pytest.approx(1.0) and m.median_px == pytest.approx(0.5)
    assert (m.bad1, m.bad2, m.bad3) == pytest.approx((1 / 3, 1 / 3, 0.0))


def test_zero_disparity_prediction_is_a_prediction() -> None:
    m = stereo_metrics(np.array([0.0]), np.array([2.0]))
    assert (m.n, m.epe_px, m.bad1, m.bad2, m.bad3) == (1, 2.0, 1.0, 0.0, 0.0)


def test_single_pixel() -> None:
    s = stereo_metrics(np.array([[3.5]]), np.array([[2.0]]))
    assert (s.n_gt, s.n, s.epe_px, s.median_px, s.p95_px) == (1, 1, 1.5, 1.5, 1.5)
    assert (s.bad1, s.bad2, s.bad3) == (1.0, 0.0, 0.0)
    d = depth_metrics(np.array([[2.5]]), np.array([[2.0]]))
    assert (d.n, d.abs_rel, d.mae_m, d.rmse_m) == (1, 0.25, 0.5, 0.5)
    assert (d.delta1, d.delta2, d.delta3) == (0.0, 1.0, 1.0)  # ratio 1.25 is not < 1.25


def test_depth_hand_example() -> None:
    gt = np.array([2.0, 4.0, 1.0, 0.0, 5.0], np.float32)
    pred = np.array([1.0, 5.0, 1.0, 3.0, 0.0], np.float32)  # depth 0 = no prediction
    m = depth_metrics(pred, gt)
    assert (m.n_gt, m.n) == (4, 3)
    assert m.abs_rel == pytest.approx((1 / 2 + 1 / 4 + 0) / 3)
    assert m.mae_m == pytest.approx(2 / 3)
    assert m.rmse_m == pytest.approx(math.sqrt(2 / 3))
    # ratios max(p/g, g/p): 2, 1.25, 1 against 1.25, 1.5625, 1.953125
    assert (m.delta1, m.delta2, m.delta3) == pytest.approx((1 / 3, 2 / 3, 2 / 3))


@pytest.mark.parametrize("fn", [stereo_metrics, depth_metrics])
def test_all_invalid_gives_nan_without_warnings(fn) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        none = fn(np.full((3, 4), 5.0), np.zeros((3, 4)))  # no valid GT
        abstain = fn(np.full((3, 4), NAN), np.full((3, 4), 2.0))  # valid GT, no prediction
        empty = fn(np.zeros((0, 0)), np.zeros((0, 0)))
    assert (none.n_gt, none.n) == (0, 0) and math.isnan(none.coverage)
    assert (abstain.n_gt, abstain.n, abstain.coverage) == (12, 0, 0.0)
    for m in (none, abstain, empty):
        values = [v for k, v in m.as_dict().items() if k not in ("n_gt", "n", "coverage")]
        assert len(values) == 6 and all(math.isnan(v) for v in values)


def test_shape_mismatch_is_an_error() -> None:
    with pytest.raises(ValueError, match=r"pred \(2, 3\), gt \(3, 2\)"):
        stereo_metrics(np.zeros((2, 3)), np.zeros((3, 2)))


def test_pooling_weighs_pixels_not_samples() -> None:
    acc = StereoAccumulator()
    a = acc.add(np.array([2.0, 3.0]), np.array([1.0, 2.0]))  # errors 1, 1
    b = acc.add(np.array([5.0, 9.0]), np.array([1.0, 0.0]))  # error 4 (second pixel: no GT)
    assert (a.epe_px, b.epe_px) == (1.0, 4.0)
    pooled = acc.result()
    assert (pooled.n_gt, pooled.n) == (3, 3)
    assert pooled.epe_px == pytest.approx(2.0)  # (1 + 1 + 4) / 3, not the mean of 1 and 4
    assert (pooled.bad1, pooled.bad2, pooled.bad3) == pytest.approx((1 / 3,) * 3)
    # nearest ranks 2 and ceil(2.85) = 3 of (1, 1, 4); exact: each histogram bin holds one value
    assert (pooled.median_px, pooled.p95_px) == (1.0, 4.0)

    depth = DepthAccumulator()
    depth.add(np.array([1.0, 3.0]), np.array([2.0, 3.0]))
    depth.add(np.array([8.0]), np.array([4.0]))
    d = depth.result()
    assert d.abs_rel == pytest.approx((0.5 + 0 + 1.0) / 3)
    assert d.rmse_m == pytest.approx(math.sqrt((1 + 0 + 16) / 3))
    assert (d.delta1, d.delta3) == pytest.approx((1 / 3, 1 / 3))

    merged = StereoAccumulator()
    merged.merge(acc)
    merged.merge(acc)
    assert merged.result().epe_px == pytest.approx(2.0) and merged.result().n == 6


def test_pooled_quantiles_within_the_histogram_resolution() -> None:
    rng = np.random.default_rng(3)
    gt = rng.uniform(1.0, 60.0, 20_000)
    err = np.concatenate([rng.exponential(0.4, 19_000), rng.uniform(3.0, 40.0, 1_000)])
    acc = StereoAccumulator()
    acc.add(gt[:7_000] + err[:7_000], gt[:7_000])
    acc.add(gt[7_000:] - err[7_000:], gt[7_000:])  # negative predictions drop out of both
    kept = np.abs(err[(np.r_[gt[:7_000] + err[:7_000], gt[7_000:] - err[7_000:]]) >= 0])
    pooled = acc.result()
    assert pooled.n == len(kept)
    for q, got in ((0.5, pooled.median_px), (0.95, pooled.p95_px)):
        exact = float(np.quantile(kept, q, method="inverted_cdf"))  # nearest rank
        assert got == pytest.approx(exact, rel=2.8e-3), q
    zeros = StereoAccumulator()
    zeros.add(gt, gt)
    assert (zeros.result().median_px, zeros.result().p95_px) == (0.0, 0.0)


def test_median_scale() -> None:
    gt = np.array([1.0, 2.0, 4.0, 0.0])
    assert median_scale(gt / 2.5, gt) == pytest.approx(2.5)
    assert median_scale(np.zeros(4), gt) == 1.0


def test_score_range_leak_is_farther_than_max_5cm_or_3_percent() -> None:
    """A pixel leaks when it lies farther than truth by more than max(5 cm, 3 % of the truth).

    On a flat 5 m truth the 3 % term rules (15 cm): +10 cm is not a leak, +20 cm is, and
    nearer than truth never is. On a 1 m truth the 5 cm floor rules: +4 cm (4 %) is not a
    leak, +6 cm is. A 30 % threshold would call none of them a leak.
    """
    exact = np.full((20, 20), 5.0)
    range_m = np.full((20, 20), 5.2)  # rows 10-19: +20 cm, a leak
    range_m[:5] = 4.8  # nearer: never a leak
    range_m[5:10] = 5.1  # +10 cm = 2 %: within 3 %
    range_m[0, 0] = 0.0  # no value: not counted at all
    s = score_range(range_m, exact)
    assert s.valid == 399
    assert s.leak == 200 / 399
    assert s.leak_off_silhouette == 200 / 399  # a flat truth has no silhouette
    # |errors|: 100 x 0.1 m and 299 x 0.2 m; errors: 99 x -0.2, 100 x 0.1, 200 x 0.2 (median: rank 199)
    assert (s.median_mm, s.p90_mm, s.bias_mm) == pytest.approx((200.0, 200.0, 200.0))

    near = np.full((4, 4), 1.0)
    near_range_m = np.full((4, 4), 1.04)  # 4 %, but within the 5 cm floor
    near_range_m[:, 2:] = 1.06  # beyond 5 cm: a leak
    assert score_range(near_range_m, near).leak == 0.5


def test_edge_band_around_a_depth_step() -> None:
    depth = np.full((20, 20), 1.0, np.float32)
    depth[:, 10:] = 3.0
    depth[0, 0] = 0.0  # invalid pixels are never in the band
    band = edge_band(depth, band_px=3)
    cols = np.flatnonzero(band.all(axis=0))
    assert cols.tolist() == list(range(6, 14))  # the step between columns 9 and 10, +-3 px
    assert band[:, :6].sum() == 0 and band[:, 14:].sum() == 0
    ramp = np.tile(1.0 + 0.01 * np.arange(40, dtype=np.float32), (10, 1))  # 1 % per px: no step
    assert not edge_band(ramp).any()
    sparse = np.zeros((20, 20), np.float32)  # sparse GT: a step is seen between valid neighbours only
    sparse[5, 5], sparse[5, 6], sparse[15, 15] = 1.0, 2.0, 9.0
    assert np.argwhere(edge_band(sparse, band_px=1)).tolist() == [[5, 5], [5, 6]]


@pytest.mark.parametrize("shape", [(1, 1), (1, 7), (6, 1), (97, 131)])
def test_compiled_edge_steps_are_the_numpy_min_max_filters(shape: tuple[int, int]) -> None:
    """The separable compiled pass finds the steps that cv2's 3x3 dilate and erode find: at the borders,
    between valid pixels only (zeros, negatives, NaN and inf are not GT), float64 maps compared in float32."""
    from ingest.raster.edges import _steps, valid_gt
    from tests.ingest.oracles import edge_steps_numpy

    rng = np.random.default_rng(7)
    gt = rng.uniform(0.5, 3.0, shape) * rng.choice([1.0, 1.02, 1.1], shape)
    holes = rng.random(shape)
    gt[holes < 0.2] = 0.0
    gt[(holes >= 0.2) & (holes < 0.25)] = np.nan
    gt[(holes >= 0.25) & (holes < 0.28)] = np.inf
    gt[(holes >= 0.28) & (holes < 0.3)] = -1.0
    for m in (gt, gt.astype(np.float32)):
        step = np.empty(shape, np.uint8)
        _steps(np.asarray(m, np.float32), valid_gt(m), np.float32(0.05), np.float32(0.03),
               np.empty((2, *shape), np.float32), step)  # fmt: skip
        want = edge_steps_numpy(m)
        assert np.array_equal(step > 0, want)
        assert shape == (1, 1) or want.any()
