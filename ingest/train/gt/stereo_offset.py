"""How far a sample's lower rectified image sits off its upper one, measured at the disparity GT's pixels.

The two rectified equirects share their columns (epipolar lines, DESIGN.md): the scene at upper pixel
(col, row) with disparity d lies at lower pixel (col, row - d). Where the GT gives d, the lower image
sampled there is the upper image up to the cameras' gain and offset, so one shift of the lower image
(`dx_px` across the epipolar lines, `dy_px` along them) that best explains it says how well the pair and
its GT agree: about 0 for every sample of a right rig; a frame moved by a readout glitch, a frame of another
moment or a camera turned by a knock shows as a shift that the run's other samples do not share. The
LiDAR alignments measure the same thing a hundred times more coarsely (a pixel of a 480-px fisheye is
0.75 deg): the pair's own texture resolves a tenth of a pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from calibration.types import F32, F64, I64
from ingest.dataset.sparse import SparseImage
from ingest.train.gt.align import grey_levels
from ingest.train.gt.lidar_agreement import MAD_TO_SIGMA
from ingest.train.gt.window_fit import evenly_spread

MIN_PIXELS = 300
"""Disparity pixels a sample needs for its shift to be measured."""
MAX_PIXELS = 5_000
"""Pixels used at most (evenly spread over the GT's): the simulated pairs' shifts come out within 0.01 px
of those from 15,000, and a dense GT's quarter million would cost fifty times more for nothing."""
ITERATIONS = 6
"""Gauss-Newton steps from no shift: made pairs shifted by 1 px converge to 0.001 px in three; the walk's
pair with its lower frame moved 1 px reaches 1.20 of the 1.21 px that twelve give (robust weights settle
slowly)."""
QUADRANT_ITERATIONS = 3
"""Steps of each quadrant's fit, from the whole pair's shift, gain and offset."""
CAUCHY_SCALE = 2.0
"""Residuals weighted down beyond this many robust sigmas (occlusion edges, speculars, the pair's two
views of a surface)."""


@dataclass(frozen=True)
class PairOffset:
    """The lower image's shift against the upper (px of the rectified equirect), the pixels used, and the
    same shift fitted in each quadrant of them (split at their median column and row: upper left, upper
    right, lower left, lower right; None for one under `MIN_PIXELS` / 4): a frame turned, torn or half of
    another moment shifts its quadrants apart while their mean may stay near 0."""

    dx_px: float  # across the epipolar lines (columns)
    dy_px: float  # along them (rows): a disparity bias
    pixels: int
    quadrants: tuple[tuple[float, float] | None, ...] = ()

    def to_meta(self) -> list[float]:
        return [round(self.dx_px, 3), round(self.dy_px, 3), self.pixels]

    def quadrants_meta(self) -> list[list[float] | None]:
        return [None if q is None else [round(q[0], 3), round(q[1], 3)] for q in self.quadrants]


def _at(image: F32, cols: F64, rows: F64) -> F64:
    """`image` at sub-pixel positions (bilinear); NaN off the image."""
    x, y = cols.astype(np.float32).reshape(-1, 1), rows.astype(np.float32).reshape(-1, 1)
    out = cv2.remap(image, x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=float("nan"))
    return out.ravel().astype(np.float64)


@dataclass(frozen=True)
class _Pair:
    """The lower image and its gradients (per pixel), and the GT pixels: their upper grey levels, columns
    and the lower rows their disparity puts them at."""

    lower: F32
    grad_x: F32
    grad_y: F32
    ref: F64
    cols: F64
    lower_rows: F64


def _fit(
    pair: _Pair, idx: I64, least: int, start: F64 | None = None, iterations: int = ITERATIONS
) -> tuple[F64, int] | None:
    """The shift (dx, dy px) and the gain and offset (lower = gain * upper + offset) that best lay the
    lower image onto the upper at the GT pixels `idx`, from `start` (those four; default: no shift, gain
    1), and the pixels used; None with under `least` of them inside the image or no texture."""
    state = np.array([0.0, 0.0, 1.0, 0.0]) if start is None else start.copy()
    shift, affine = state[:2], state[2:]  # views: updated in place
    ref, used = pair.ref[idx], 0
    for _ in range(iterations):
        x, y = pair.cols[idx] + shift[0], pair.lower_rows[idx] + shift[1]
        sampled = np.stack([_at(pair.lower, x, y), _at(pair.grad_x, x, y), _at(pair.grad_y, x, y)], axis=1)
        ok = np.isfinite(sampled).all(axis=1)
        used = int(ok.sum())
        if used < least:
            return None
        value, gx, gy = sampled[ok].T
        residual = value - (affine[0] * ref[ok] + affine[1])
        spread = MAD_TO_SIGMA * float(np.median(np.abs(residual - np.median(residual))))
        if not spread > 0:
            return None
        weight = 1.0 / (1.0 + (residual / (CAUCHY_SCALE * spread)) ** 2)
        rows_j = np.stack([gx, gy, -ref[ok], -np.ones(used)], axis=1)
        weighted = rows_j * weight[:, None]
        try:
            delta = -np.linalg.solve(weighted.T @ rows_j, weighted.T @ residual)
        except np.linalg.LinAlgError:
            return None
        shift += delta[:2]
        affine += delta[2:]
    if not np.isfinite(state).all():
        return None
    return state, used


def pair_offset(upper: np.ndarray, lower: np.ndarray, disparity: SparseImage) -> PairOffset | None:
    """The shift of the `lower` rectified image against the `upper` one (both 8-bit, same shape) that best
    lays it onto the upper image at `disparity`'s pixels (px of the full sphere, the equirects' pitch), with
    a gain and offset between the cameras, over them all and per quadrant; None with under `MIN_PIXELS` of
    them inside both images or no texture there."""
    if len(disparity.pixel) < MIN_PIXELS or upper.shape[:2] != lower.shape[:2]:
        return None
    keep = evenly_spread(len(disparity.pixel), MAX_PIXELS)
    rows, cols = np.divmod(disparity.pixel[keep], disparity.shape[1])
    down = grey_levels(lower)
    pair = _Pair(
        down, cv2.Sobel(down, cv2.CV_32F, 1, 0, ksize=3) * np.float32(0.125),
        cv2.Sobel(down, cv2.CV_32F, 0, 1, ksize=3) * np.float32(0.125),
        grey_levels(upper)[rows, cols].astype(np.float64), cols.astype(np.float64),
        rows - disparity.value[keep].astype(np.float64),
    )  # fmt: skip
    whole = _fit(pair, np.arange(len(keep)), MIN_PIXELS)
    if whole is None:
        return None
    state, used = whole
    right, low = cols >= np.median(cols), rows >= np.median(rows)
    quadrants = []
    for part in ((~low) & (~right), (~low) & right, low & (~right), low & right):
        found = _fit(pair, np.flatnonzero(part), MIN_PIXELS // 4, state, QUADRANT_ITERATIONS)
        quadrants.append(None if found is None else (float(found[0][0]), float(found[0][1])))
    return PairOffset(float(state[0]), float(state[1]), used, tuple(quadrants))
