"""Depth discontinuities of a range or disparity map: the band where point-based values mix surfaces."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from calibration.types import Bool


def valid_gt(gt: np.ndarray[Any, Any], mask: Bool | None = None) -> Bool:
    """GT pixels that count: finite, > 0 and inside `mask`."""
    with np.errstate(invalid="ignore"):
        ok: Bool = np.isfinite(gt) & (gt > 0)
    return ok & mask if mask is not None else ok


def edge_band(
    gt: np.ndarray[Any, Any], band_px: int = 3, step_abs: float = 0.05, step_rel: float = 0.03
) -> Bool:
    """Valid-GT pixels within `band_px` of a discontinuity of the GT map itself.

    A discontinuity is a 3x3 neighbourhood whose valid values differ by more
    than max(`step_abs`, `step_rel` * their minimum) (in the map's unit: 5 cm /
    3 % suit depth in metres; for disparity use e.g. 0.25 px / 3 %). Only
    steps between valid GT pixels are seen, so sparse GT finds fewer edges
    than dense GT does.
    """
    ok = valid_gt(gt)
    kernel = np.ones((3, 3), np.uint8)
    g = np.where(ok, gt, np.float32(0.0)).astype(np.float32, copy=False)
    hi = cv2.dilate(g, kernel)  # largest valid value around (0: none)
    np.copyto(g, np.float32(np.inf), where=~ok)
    lo = cv2.erode(g, kernel)  # smallest valid value around (inf: none, so hi - lo = -inf: no step)
    threshold = lo * np.float32(step_rel)
    np.maximum(threshold, np.float32(step_abs), out=threshold)
    step = hi - lo > threshold
    size = 2 * band_px + 1
    band = cv2.dilate(step.astype(np.uint8), np.ones((size, size), np.uint8)) > 0
    out: Bool = band & ok
    return out
