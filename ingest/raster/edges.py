"""Depth discontinuities of a range or disparity map: the band where point-based values mix surfaces."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
from numba import njit

from calibration.types import Bool

STEP_ABS_M = 0.05  # a range step of depth: more than this ...
STEP_REL = 0.03  # ... and more than this fraction of the nearer range


def valid_gt(gt: np.ndarray[Any, Any], mask: Bool | None = None) -> Bool:
    """GT pixels that count: finite, > 0 and inside `mask`."""
    with np.errstate(invalid="ignore"):
        ok: Bool = np.isfinite(gt) & (gt > 0)
    return ok & mask if mask is not None else ok


def edge_band(
    gt: np.ndarray[Any, Any], band_px: int = 3, step_abs: float = STEP_ABS_M, step_rel: float = STEP_REL
) -> Bool:
    """Valid-GT pixels within `band_px` of a discontinuity of the GT map itself.

    A discontinuity is a 3x3 neighbourhood whose valid values differ by more
    than max(`step_abs`, `step_rel` * their minimum) (in the map's unit: 5 cm /
    3 % suit depth in metres; for disparity use e.g. 0.25 px / 3 %). Only
    steps between valid GT pixels are seen, so sparse GT finds fewer edges
    than dense GT does. Values are compared in float32.
    """
    ok = valid_gt(gt)
    step = np.empty(gt.shape, np.uint8)
    g = np.ascontiguousarray(gt, np.float32)
    _steps(g, ok, np.float32(step_abs), np.float32(step_rel), np.empty((2, *gt.shape), np.float32), step)
    size = 2 * band_px + 1
    band = cv2.dilate(step, np.ones((size, size), np.uint8)) > 0
    out: Bool = band & ok
    return out


@njit(cache=True, nogil=True)
def _steps(g, ok, step_abs, step_rel, rows_hi_lo, step):  # type: ignore[no-untyped-def]  # pragma: no cover
    """step[r, c] = 1 where the valid values of the 3x3 around (r, c) span more than max(abs, rel * min).

    Separable: the largest and smallest valid value of each row's three
    pixels first (0 and inf: none), then of three rows of those.
    """
    H, W = g.shape
    zero, inf = np.float32(0.0), np.float32(np.inf)
    row_hi, row_lo = rows_hi_lo[0], rows_hi_lo[1]
    hi_c, lo_c = np.empty(W + 2, np.float32), np.empty(W + 2, np.float32)
    hi_c[0] = hi_c[W + 1] = zero
    lo_c[0] = lo_c[W + 1] = inf
    for r in range(H):
        for c in range(W):
            v, valid = g[r, c], ok[r, c]
            hi_c[c + 1] = v if valid else zero
            lo_c[c + 1] = v if valid else inf
        for c in range(W):
            row_hi[r, c] = max(max(hi_c[c], hi_c[c + 1]), hi_c[c + 2])
            row_lo[r, c] = min(min(lo_c[c], lo_c[c + 1]), lo_c[c + 2])
    for r in range(H):
        above, below = max(r - 1, 0), min(r + 1, H - 1)
        for c in range(W):
            hi = max(max(row_hi[above, c], row_hi[r, c]), row_hi[below, c])
            lo = min(min(row_lo[above, c], row_lo[r, c]), row_lo[below, c])
            step[r, c] = 1 if hi - lo > max(lo * step_rel, step_abs) else 0
