"""Stereo and depth error metrics over valid ground truth, per sample and pooled.

Stereo (disparity in px): EPE = mean |pred - gt|, its median and 95th
percentile, and bad-k = share of pixels with |pred - gt| > k px (k = 1, 2, 3).
Depth (metres): AbsRel = mean |pred - gt| / gt, MAE, RMSE and delta_k = share
of pixels with max(pred/gt, gt/pred) < 1.25**k (k = 1, 2, 3).

Which pixels count:
- ground truth: finite and > 0 (0 = invalid in files, NaN in memory), inside
  the optional boolean `mask` (an edge band, a stability map, ...);
- prediction: finite, and >= 0 for disparity (SGBM's -1 means "no match") or
  > 0 for depth. A pixel with valid GT but no valid prediction is not scored;
  it lowers `coverage` = scored / valid-GT pixels, which is always reported
  beside the errors so a method cannot look good by abstaining unseen.
With nothing to score every error metric is NaN (never 0, never a warning).

Accumulators keep float64 sums, so pooling is exact for means and shares:
`add` returns one sample's metrics and folds the sample into the pool;
`result` gives the pooled metrics (every scored pixel weighs the same, as in
KITTI). Pooled quantiles come from a log-spaced histogram of errors
(`HIST_BINS_PER_OCTAVE` bins per octave) that also sums the errors in each
bin: the reported value is the mean error of the bin holding the nearest rank,
within 0.3 % of the exact quantile and exact when that bin holds one value
(errors below 2**-14 px share bin 0). Per-sample quantiles are exact (numpy's
linear interpolation).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, ClassVar, Self

import numpy as np

from calibration.types import F64, Bool
from ingest.raster.edges import edge_band, valid_gt

BAD_THRESHOLDS_PX = (1.0, 2.0, 3.0)
BAD_TOLERANCE_PX = 1e-4
"""An error counts as over a bad-k threshold only beyond it by this much (px): a prediction exactly k px off,
stored as float32 (1 part in 1e7 at a disparity of 100 px) or read against the disparity PNG's 1/256 px
steps, is not bad-k for the rounding of its last bits. Far below any disparity a method resolves."""
DELTA_BASE = 1.25
HIST_BINS_PER_OCTAVE = 128
HIST_MIN_EXP = -14  # errors below 2**-14 px (6e-5 px) go into the zero bin
HIST_MAX_EXP = 14  # errors at or above 2**14 px go into the last bin
_N_LOG_BINS = (HIST_MAX_EXP - HIST_MIN_EXP) * HIST_BINS_PER_OCTAVE

LOWER_IS_BETTER = frozenset(
    {"epe_px", "median_px", "p95_px", "bad1", "bad2", "bad3", "abs_rel", "mae_m", "rmse_m"}
)
HIGHER_IS_BETTER = frozenset({"delta1", "delta2", "delta3", "coverage"})


def _nan_if_empty(n: int, value: float) -> float:
    return value if n > 0 else math.nan


@dataclass(frozen=True)
class _Scored:
    """`n` scored pixels of `n_gt` valid-GT pixels."""

    n_gt: int
    n: int

    @property
    def coverage(self) -> float:
        """Scored / valid-GT pixels (NaN without valid GT)."""
        return self.n / self.n_gt if self.n_gt else math.nan

    def as_dict(self) -> dict[str, float | int]:
        return {**asdict(self), "coverage": self.coverage}


@dataclass(frozen=True)
class StereoMetrics(_Scored):
    """Disparity errors (px) over `n` scored pixels of `n_gt` valid-GT pixels; bad-k are shares 0..1."""

    epe_px: float
    median_px: float
    p95_px: float
    bad1: float
    bad2: float
    bad3: float


@dataclass(frozen=True)
class DepthMetrics(_Scored):
    """Depth errors (m) over `n` scored pixels of `n_gt` valid-GT pixels; delta_k are shares 0..1."""

    abs_rel: float
    mae_m: float
    rmse_m: float
    delta1: float
    delta2: float
    delta3: float


Metrics = StereoMetrics | DepthMetrics


def _check_shapes(pred: np.ndarray[Any, Any], gt: np.ndarray[Any, Any], mask: Bool | None) -> None:
    if pred.shape != gt.shape or (mask is not None and mask.shape != gt.shape):
        shapes = f"pred {pred.shape}, gt {gt.shape}" + ("" if mask is None else f", mask {mask.shape}")
        raise ValueError(f"metric inputs differ in shape: {shapes}")


def _scored(
    pred: np.ndarray[Any, Any], gt: np.ndarray[Any, Any], mask: Bool | None, pred_min_exclusive: bool
) -> tuple[int, F64, F64]:
    """(valid-GT count, pred, gt) as float64 at the pixels with valid GT and a valid prediction."""
    _check_shapes(pred, gt, mask)
    ok = valid_gt(gt, mask)
    n_gt = int(np.count_nonzero(ok))
    p = np.asarray(pred)[ok].astype(np.float64)
    g = np.asarray(gt)[ok].astype(np.float64)
    with np.errstate(invalid="ignore"):
        good = np.isfinite(p) & ((p > 0) if pred_min_exclusive else (p >= 0))
    return n_gt, p[good], g[good]


def _hist_index(err: F64) -> np.ndarray[Any, np.dtype[np.intp]]:
    """Histogram bin of each error: 0 = below 2**HIST_MIN_EXP, then log-spaced bins."""
    with np.errstate(divide="ignore"):
        k = np.floor((np.log2(err) - HIST_MIN_EXP) * HIST_BINS_PER_OCTAVE)
    k = np.where(err < 2.0**HIST_MIN_EXP, -1, np.minimum(k, _N_LOG_BINS - 1))
    return (k + 1).astype(np.intp)


def _hist_quantile(hist: np.ndarray[Any, np.dtype[np.int64]], sums: F64, q: float) -> float:
    """Nearest-rank quantile (rank ceil(q n), at least 1): the mean error of the bin holding that rank."""
    n = int(hist.sum())
    if n == 0:
        return math.nan
    rank = max(1, math.ceil(q * n))
    k = int(np.searchsorted(np.cumsum(hist), rank))
    return float(sums[k] / hist[k])


class _Pooling:
    """An accumulator of counts and sums: pooling two is adding every counter."""

    def merge(self, other: Self) -> None:
        """Pool another accumulator's pixels into this one."""
        for name, value in vars(other).items():
            setattr(self, name, getattr(self, name) + value)


class StereoAccumulator(_Pooling):
    """Pools disparity errors over samples; `add` also returns the sample's own metrics."""

    kind: ClassVar[str] = "stereo"

    def __init__(self) -> None:
        self.n_gt = 0
        self.n = 0
        self.sum_abs = 0.0
        self.bad = np.zeros(len(BAD_THRESHOLDS_PX), np.int64)
        self.hist = np.zeros(_N_LOG_BINS + 1, np.int64)
        self.hist_sum = np.zeros(_N_LOG_BINS + 1, np.float64)

    def add(
        self, pred_px: np.ndarray[Any, Any], gt_px: np.ndarray[Any, Any], mask: Bool | None = None
    ) -> StereoMetrics:
        """Score one sample (same-shape disparity maps, px) and fold it into the pool."""
        n_gt, p, g = _scored(pred_px, gt_px, mask, pred_min_exclusive=False)
        err = np.abs(p - g)
        n = len(err)
        bad = np.array([np.count_nonzero(err > t + BAD_TOLERANCE_PX) for t in BAD_THRESHOLDS_PX], np.int64)
        total = float(err.sum())
        self.n_gt += n_gt
        self.n += n
        self.sum_abs += total
        self.bad += bad
        idx = _hist_index(err)
        self.hist += np.bincount(idx, minlength=len(self.hist))
        self.hist_sum += np.bincount(idx, weights=err, minlength=len(self.hist))
        if n == 0:
            return StereoMetrics(n_gt, 0, *[math.nan] * 6)
        median, p95 = np.percentile(err, [50.0, 95.0])
        return StereoMetrics(n_gt, n, total / n, float(median), float(p95), *(bad / n).tolist())

    def result(self) -> StereoMetrics:
        """Metrics of every pixel added so far (quantiles from the histogram, see the module doc)."""
        n = self.n
        return StereoMetrics(
            self.n_gt,
            n,
            _nan_if_empty(n, self.sum_abs / max(n, 1)),
            _hist_quantile(self.hist, self.hist_sum, 0.5),
            _hist_quantile(self.hist, self.hist_sum, 0.95),
            *(_nan_if_empty(n, float(b) / max(n, 1)) for b in self.bad),
        )


class DepthAccumulator(_Pooling):
    """Pools depth errors over samples; `add` also returns the sample's own metrics."""

    kind: ClassVar[str] = "depth"

    def __init__(self) -> None:
        self.n_gt = 0
        self.n = 0
        self.sum_rel = 0.0
        self.sum_abs = 0.0
        self.sum_sq = 0.0
        self.delta = np.zeros(3, np.int64)

    def add(
        self, pred_m: np.ndarray[Any, Any], gt_m: np.ndarray[Any, Any], mask: Bool | None = None
    ) -> DepthMetrics:
        """Score one sample (same-shape depth maps, metres) and fold it into the pool."""
        n_gt, p, g = _scored(pred_m, gt_m, mask, pred_min_exclusive=True)
        e = np.abs(p - g)
        ratio = np.maximum(p / g, g / p)
        delta = np.array([np.count_nonzero(ratio < DELTA_BASE**k) for k in (1, 2, 3)], np.int64)
        sums = (float((e / g).sum()), float(e.sum()), float((e * e).sum()))
        n = len(e)
        self.n_gt += n_gt
        self.n += n
        self.sum_rel += sums[0]
        self.sum_abs += sums[1]
        self.sum_sq += sums[2]
        self.delta += delta
        return _depth_metrics(n_gt, n, *sums, delta)

    def result(self) -> DepthMetrics:
        """Metrics of every pixel added so far."""
        return _depth_metrics(self.n_gt, self.n, self.sum_rel, self.sum_abs, self.sum_sq, self.delta)


def _depth_metrics(
    n_gt: int, n: int, sum_rel: float, sum_abs: float, sum_sq: float, delta: np.ndarray[Any, Any]
) -> DepthMetrics:
    if n == 0:
        return DepthMetrics(n_gt, 0, *[math.nan] * 6)
    return DepthMetrics(n_gt, n, sum_rel / n, sum_abs / n, math.sqrt(sum_sq / n), *(delta / n).tolist())


Accumulator = StereoAccumulator | DepthAccumulator


def stereo_metrics(
    pred_px: np.ndarray[Any, Any], gt_px: np.ndarray[Any, Any], mask: Bool | None = None
) -> StereoMetrics:
    """Disparity metrics of one sample (see the module doc for which pixels count)."""
    return StereoAccumulator().add(pred_px, gt_px, mask)


def depth_metrics(
    pred_m: np.ndarray[Any, Any], gt_m: np.ndarray[Any, Any], mask: Bool | None = None
) -> DepthMetrics:
    """Depth metrics of one sample (see the module doc for which pixels count)."""
    return DepthAccumulator().add(pred_m, gt_m, mask)


def median_scale(pred: np.ndarray[Any, Any], gt: np.ndarray[Any, Any], mask: Bool | None = None) -> float:
    """median(gt) / median(pred) over the scored depth pixels: aligns scale-free (relative) predictions.

    Returns 1.0 when nothing can be scored (the prediction is then left as it is).
    """
    _, p, g = _scored(pred, gt, mask, pred_min_exclusive=True)
    if len(p) == 0:
        return 1.0
    return float(np.median(g) / np.median(p))


@dataclass(frozen=True)
class RangeScore:
    """A range map scored against exact range (both in metres, 0/NaN = none).

    `median_mm`, `p90_mm` and `bias_mm` are over pixels beyond `band_px` of a
    depth edge of the truth; `leak` is the share of valid pixels farther than
    truth by more than max(5 cm, 3 %) (background seen through foreground), and
    `leak_off_silhouette` the same beyond 1 px of an edge.
    """

    median_mm: float
    p90_mm: float
    bias_mm: float
    leak: float
    leak_off_silhouette: float
    valid: int


def score_range(range_m: np.ndarray[Any, Any], exact_m: np.ndarray[Any, Any], band_px: int = 3) -> RangeScore:
    """Score `range_m` against `exact_m` (same shape), see `RangeScore`."""
    ok = (range_m > 0) & np.isfinite(exact_m)
    err_m = range_m.astype(np.float64) - exact_m
    exact0 = np.nan_to_num(exact_m, nan=0.0).astype(np.float32)
    inner = ok & ~edge_band(exact0, band_px)
    leak = ok & (err_m > np.maximum(0.05, 0.03 * exact_m))
    n_ok = max(int(ok.sum()), 1)
    with np.errstate(all="ignore"):
        abs_inner = np.abs(err_m[inner]) if inner.any() else np.array([np.nan])
        return RangeScore(
            median_mm=float(np.median(abs_inner)) * 1e3,
            p90_mm=float(np.percentile(abs_inner, 90)) * 1e3,
            bias_mm=float(np.median(err_m[inner])) * 1e3 if inner.any() else math.nan,
            leak=float(leak.sum()) / n_ok,
            leak_off_silhouette=float((leak & ~edge_band(exact0, 1)).sum()) / n_ok,
            valid=int(ok.sum()),
        )
