"""Depth <-> disparity for equirectangular vertical stereo and pinhole horizontal stereo.

Equirect vertical stereo, upper camera (cam0) = reference, theta = latitude
from "up" in cam0's rectified image, B = baseline, H_full = rows of the full
sphere (never of a crop). Disparity is angular, in pixels of pitch pi/H_full:

    disp_px = (H_full/pi) * atan( sin(theta) / (range/B + cos(theta)) )
    range   = B * sin(theta - rho) / sin(rho),   rho = disp_px * pi / H_full

A point at row r0 in the upper image appears at row r0 - disp_px in the lower
one. Invalid inputs (range <= 0, disparity <= 0, NaN, geometry that cannot be)
give 0, never inf or NaN.
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np

from calibration.types import F64, ArrayLike, Bool


def depth_to_disparity(
    range_m: ArrayLike, theta_rad: ArrayLike, baseline_m: float, height_full_px: int
) -> F64:
    """Disparity (px) of points at ``range_m`` seen at latitude ``theta_rad`` by the upper camera."""
    r = np.asarray(range_m, dtype=np.float64)
    t = np.asarray(theta_rad, dtype=np.float64)
    with np.errstate(all="ignore"):
        d = (height_full_px / math.pi) * np.arctan2(np.sin(t), r / baseline_m + np.cos(t))
        ok = np.isfinite(d) & (r > 0.0) & np.isfinite(r) & (d > 0.0)
    out: F64 = np.where(ok, d, 0.0)
    return out


def disparity_to_depth(
    disp_px: ArrayLike, theta_rad: ArrayLike, baseline_m: float, height_full_px: int
) -> F64:
    """Range (m) from the upper camera of a pixel at latitude ``theta_rad`` with ``disp_px``."""
    d = np.asarray(disp_px, dtype=np.float64)
    t = np.asarray(theta_rad, dtype=np.float64)
    with np.errstate(all="ignore"):
        rho = d * (math.pi / height_full_px)
        r = baseline_m * np.sin(t - rho) / np.sin(rho)
        ok = (d > 0.0) & np.isfinite(r) & (r > 0.0) & (t - rho > 0.0)
    out: F64 = np.where(ok, r, 0.0)
    return out


def disparity_stability_mask(
    theta_rad: ArrayLike,
    range_m: ArrayLike,
    baseline_m: float,
    height_full_px: int,
    max_rel_error: float,
    disp_error_px: float = 0.5,
    disp_px: ArrayLike | None = None,
) -> Bool:
    """True where disparity is a stable depth cue.

    A pixel is stable when a disparity error of ``disp_error_px`` changes the
    recovered range by at most ``max_rel_error`` (relative). Pixels near the
    poles (theta -> 0 or pi) and far points fail, as do invalid ranges.
    ``disp_px``: `depth_to_disparity` of the same arguments, when the caller
    has it already (it is not computed again).
    """
    r = np.asarray(range_m, dtype=np.float64)
    if disp_px is None:
        d = depth_to_disparity(r, theta_rad, baseline_m, height_full_px)
    else:
        d = np.asarray(disp_px, dtype=np.float64)
    r_lo = disparity_to_depth(d + disp_error_px, theta_rad, baseline_m, height_full_px)
    r_hi = disparity_to_depth(d - disp_error_px, theta_rad, baseline_m, height_full_px)
    with np.errstate(all="ignore"):
        rel = np.maximum(np.abs(r - r_lo), np.abs(r_hi - r)) / r
        # r_hi == 0 means d - err <= 0: the range is unbounded within the error.
        stable = (d > 0.0) & (r_lo > 0.0) & (r_hi > 0.0) & (rel <= max_rel_error)
    out: Bool = stable
    return out


def disparity_and_stability(
    range_m: ArrayLike,
    theta_rad: ArrayLike,
    baseline_m: float,
    height_full_px: int,
    max_rel_error: float,
    disp_error_px: float = 0.5,
) -> tuple[F64, Bool]:
    """`depth_to_disparity` and `disparity_stability_mask` of the same points in one compiled pass.

    The same values (disparity to rounding, the mask but for ranges whose
    relative error lies within rounding of ``max_rel_error``) at about a third
    of the two numpy functions' cost: the ranges at disparity +- error come
    from the tangent addition formula, so a point costs one sine, one cosine
    and one arctangent instead of seven such calls.
    """
    from calibration.kernels import disparity_stability  # numba: loaded on first use

    r, t = np.broadcast_arrays(np.asarray(range_m, np.float64), np.asarray(theta_rad, np.float64))
    shape = r.shape
    disp, stable = disparity_stability(
        np.ascontiguousarray(r.reshape(-1)), np.ascontiguousarray(t.reshape(-1)),
        baseline_m, height_full_px, max_rel_error, disp_error_px,
    )  # fmt: skip
    return disp.reshape(shape), stable.reshape(shape)


def pinhole_depth_to_disparity(z_m: ArrayLike, focal_px: float, baseline_m: float) -> F64:
    """Horizontal pinhole stereo: disp = f B / z; z <= 0 or NaN gives 0."""
    z = np.asarray(z_m, dtype=np.float64)
    with np.errstate(all="ignore"):
        d = focal_px * baseline_m / z
        out: F64 = np.where((z > 0.0) & np.isfinite(d), d, 0.0)
    return out


def pinhole_disparity_to_depth(disp_px: ArrayLike, focal_px: float, baseline_m: float) -> F64:
    """Horizontal pinhole stereo: z = f B / disp; disp <= 0 or NaN gives 0."""
    d = np.asarray(disp_px, dtype=np.float64)
    with np.errstate(all="ignore"):
        z = focal_px * baseline_m / d
        out: F64 = np.where((d > 0.0) & np.isfinite(z), z, 0.0)
    return out


def rotate_for_stereo(image: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """Rotate a vertical-stereo equirect (image or disparity) 90 degrees counter-clockwise.

    After rotating both images, the upper one is the left image and a point's
    columns satisfy x_right = x_left - disparity (horizontal stereo convention).
    """
    return cv2.rotate(image, cv2.ROTATE_90_COUNTERCLOCKWISE)


def unrotate_from_stereo(image: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """Undo `rotate_for_stereo` (90 degrees clockwise)."""
    return cv2.rotate(image, cv2.ROTATE_90_CLOCKWISE)
