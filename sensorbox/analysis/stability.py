"""Stability maps: where each geometric method of the pipeline stops being trustworthy.

Each region is an error model (how large the error gets) and a mask (where it
stays below a tolerance); all are pure functions of the geometry, never of the
truth, so the pipeline can apply them to real recordings:

1. Double Sphere near its validity limit: the radial resolution dr/dtheta
   (px/rad) falls steeply towards the limit theta_max = acos(-w2) (5 % of
   the centre's there for the reference lens, 0 at the fold 1 degree later),
   so a pixel spans an ever larger angle and a half-pixel error turns into
   degrees.
   `ds_stability_mask` keeps pixels whose radial resolution is at least
   `min_ratio` of the centre's.
2. Disparity -> depth near the poles (theta -> 0, pi) and at small
   disparities (far points): `disparity_range_error` is the relative range
   error from a disparity error of +-e px; the mask is
   `calibration.stereo.disparity_stability_mask` (the pipeline's own).
3. Cubemap seams: vertical stereo on cube faces is a plain pinhole pair only
   on the faces whose image y axis lies along the baseline (front, right,
   back, left for a baseline along +y); up/down have the epipole in the
   middle. Near a face's edge the lower camera's match (u, v - d), or the
   matcher's block around it, leaves the face: `cubemap_seam_mask`.
4. Time offsets between LiDAR and camera, and 5. extrinsic rotation errors:
   every point lands displaced in the image by at most `*_displacement_px`
   and moves along its ray by at most `*_range_error_m`. A GT pixel is
   trustworthy when every GT value within that displacement (plus the sparse
   GT's own gaps) lies within the depth tolerance of its own, i.e. a
   displaced point cannot have come from another surface: `displacement_mask`.
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np

from calibration.fisheye import DoubleSphere
from calibration.spherical import CUBE_FACES
from calibration.stereo import depth_to_disparity, disparity_to_depth
from calibration.types import F64, ArrayLike, Bool

TAU_ABS_M = 0.05  # the simulator's outlier definition: |e| > max(5 cm, 3 %)
TAU_REL = 0.03


# -- 1. Double Sphere near its validity limit ---------------------------------------------


def ds_radial_resolution(model: DoubleSphere, theta_rad: ArrayLike) -> F64:
    """Radial resolution d(radius px)/d(theta) in px/rad at angle `theta_rad` off the optical axis.

    Closed form of the derivative of m(theta) = sin(theta) / n(theta), the DS
    projection of a unit ray in normalised units (n = alpha d2 + (1 - alpha) k,
    k = xi + cos(theta), d2 = sqrt(sin^2 + k^2)), times the mean focal length.
    It is small at the validity limit, 0 at the fold just beyond, then negative.
    """
    t = np.asarray(theta_rad, dtype=np.float64)
    a, xi = model.alpha, model.xi
    s, c = np.sin(t), np.cos(t)
    k = xi + c
    d2 = np.sqrt(s * s + k * k)
    n = a * d2 + (1.0 - a) * k
    dm = (c * n + s * s * (a * xi / d2 + 1.0 - a)) / (n * n)
    out: F64 = 0.5 * (model.fx + model.fy) * dm
    return out


def ds_validity_limit_rad(model: DoubleSphere) -> float:
    """Largest angle off the optical axis the DS model projects: acos(-w2) (z > -w2 |p|)."""
    return math.acos(max(-1.0, min(1.0, -model.w2)))


def ds_stable_angle_rad(model: DoubleSphere, min_ratio: float = 0.5) -> float:
    """Angle off the axis where the radial resolution falls to `min_ratio` of the centre's (bisection)."""
    centre = float(ds_radial_resolution(model, 0.0))
    lo, hi = 0.0, ds_validity_limit_rad(model)
    if float(ds_radial_resolution(model, hi)) >= min_ratio * centre:
        return hi
    for _ in range(60):  # the resolution decreases monotonically towards the fold
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if float(ds_radial_resolution(model, mid)) >= min_ratio * centre else (lo, mid)
    return lo


def ds_stability_mask(model: DoubleSphere, pixels: ArrayLike, min_ratio: float = 0.5) -> Bool:
    """True at pixels (..., 2) that unproject and whose radial resolution is >= `min_ratio` x the centre's.

    Where the mask is False a half-pixel error (calibration, corner detection,
    interpolation) costs more than 1/min_ratio times the angle it costs at the
    image centre.
    """
    rays, ok = model.unproject(pixels)
    theta = np.arccos(np.clip(np.nan_to_num(rays[..., 2], nan=1.0), -1.0, 1.0))
    ratio = ds_radial_resolution(model, theta) / float(ds_radial_resolution(model, 0.0))
    out: Bool = ok & (ratio >= min_ratio)
    return out


# -- 2. Disparity -> depth near the poles and at small disparities ------------------------


def disparity_range_error(
    theta_rad: ArrayLike, range_m: ArrayLike, baseline_m: float, height_full_px: int, disp_error_px: float
) -> F64:
    """Worst relative range error |r' - r| / r from a disparity error of +-`disp_error_px` (inf: unbounded).

    The range is unbounded when d - e <= 0 (the far side of the error reaches
    infinity), which happens at small disparities: far points and the poles.
    """
    r = np.asarray(range_m, dtype=np.float64)
    d = depth_to_disparity(r, theta_rad, baseline_m, height_full_px)
    near = disparity_to_depth(d + disp_error_px, theta_rad, baseline_m, height_full_px)
    far = disparity_to_depth(d - disp_error_px, theta_rad, baseline_m, height_full_px)
    with np.errstate(all="ignore"):
        rel = np.maximum(np.abs(r - near), np.abs(far - r)) / r
    out: F64 = np.where((d > 0) & (near > 0) & (far > 0), rel, np.inf)
    return out


# -- 3. Cubemap seams ---------------------------------------------------------------------


def cubemap_stereo_faces(baseline_dir: ArrayLike, tol: float = 1e-9) -> tuple[str, ...]:
    """Faces of `calibration.spherical.Cubemap` on which the baseline is a pure image-y translation.

    There a pair of faces is a rectified pinhole pair with vertical epipolar
    lines (v_lower = v_upper - f B / z). On the faces whose optical axis holds
    the baseline (up/down for a vertical rig) the epipole is inside the face
    and the epipolar lines are radial: no row/column matcher works there.
    """
    b = np.asarray(baseline_dir, dtype=np.float64)
    b = b / np.linalg.norm(b)
    return tuple(
        name for name, R in CUBE_FACES if abs(float(R[:, 2] @ b)) <= tol and float(R[:, 1] @ b) >= 1.0 - tol
    )


def cubemap_seam_mask(
    u_px: ArrayLike,
    v_px: ArrayLike,
    disp_px: ArrayLike,
    face_size: int,
    block_radius_px: int,
    search_px: int = 0,
    pad_px: int = 0,
) -> Bool:
    """True where a face pixel's stereo match and both matching blocks lie inside the same face.

    `u_px`, `v_px` are pixel coordinates within one rectifiable face (0 ..
    face_size - 1), `disp_px` the disparity along v (the lower camera sees the
    point at v - d). Near the top edge the match falls onto the neighbouring
    face (a seam): the block needs `block_radius_px` of context on every side
    of both the pixel and its match. A matcher that needs its whole search
    range on the image (OpenCV's SGBM leaves the first minDisparity +
    numDisparities columns empty) passes that range as `search_px`. A face
    rendered `pad_px` rows taller above (same focal length) gives the match
    that much more room.
    """
    u = np.asarray(u_px, dtype=np.float64)
    v = np.asarray(v_px, dtype=np.float64)
    d = np.asarray(disp_px, dtype=np.float64)
    m = float(block_radius_px)
    hi = face_size - 1 - m
    with np.errstate(invalid="ignore"):
        reach = np.maximum(d, float(search_px))
        out: Bool = (u >= m) & (u <= hi) & (v <= hi) & (v + pad_px - reach >= m) & np.isfinite(d) & (d >= 0)
    return out


# -- 4. LiDAR-camera time offsets and 5. extrinsic rotation errors ------------------------


def time_offset_displacement_px(
    dt_s: float, omega_rad_s: float, speed_mps: float, range_m: ArrayLike, px_per_rad: float
) -> F64:
    """Largest image displacement (px) of a point at `range_m` when the clocks differ by `dt_s`.

    The rig turns by omega |dt| and moves by v |dt| in the meantime: the ray
    to the point turns by at most omega |dt| + v |dt| / range.
    """
    r = np.asarray(range_m, dtype=np.float64)
    with np.errstate(divide="ignore"):
        out: F64 = px_per_rad * abs(dt_s) * (abs(omega_rad_s) + abs(speed_mps) / r)
    return out


def time_offset_range_error_m(dt_s: float, speed_mps: float) -> float:
    """Largest change of a point's range (m) along its ray from a clock offset: v |dt|."""
    return abs(dt_s) * abs(speed_mps)


def extrinsic_displacement_px(angle_rad: float, range_m: ArrayLike, lever_m: float, px_per_rad: float) -> F64:
    """Largest image displacement (px) of a point at `range_m` when T_cam0_lidar is off by `angle_rad`.

    A rotation error turns the LiDAR-frame point p_L (|p_L| <= range + lever,
    lever = |LiDAR centre - camera centre|) by the angle, moving it by at most
    angle * (range + lever), which the camera sees as an angle of at most
    angle * (1 + lever / range).
    """
    r = np.asarray(range_m, dtype=np.float64)
    with np.errstate(divide="ignore"):
        out: F64 = px_per_rad * abs(angle_rad) * (1.0 + lever_m / r)
    return out


def extrinsic_range_error_m(angle_rad: float, lever_m: float) -> float:
    """Largest change of a point's range (m) from a rotation error: angle * lever.

    The displacement angle x (p - t_L) has no component along p for the p x
    part, so only the lever arm t_L moves the point along its ray.
    """
    return abs(angle_rad) * lever_m


GAP_WINDOW_PX = 31  # the window in which `gt_gap_px` counts GT pixels
RADIUS_STEP = 1.1  # radii are rounded up to a ladder of ratio 1.1: a few passes, never a smaller reach
DIRECT_RADIUS_PX = 12  # discs up to this radius in one pass; larger ones grown from the previous rung


def gt_gap_px(range_img: np.ndarray[Any, Any], window_px: int = GAP_WINDOW_PX) -> np.ndarray[Any, Any]:
    """Local mean spacing (px) between sparse GT pixels: sqrt(window area / GT pixels in the window).

    Far and peripheral regions are sparser than the image on average, so the
    spacing is measured around each pixel (a `window_px` box, clipped at the
    border; a window without GT gives the window size).
    """
    ok = (np.isfinite(range_img) & (range_img > 0)).astype(np.float32)
    ones = np.ones_like(ok)
    count = cv2.boxFilter(ok, -1, (window_px, window_px), normalize=False, borderType=cv2.BORDER_CONSTANT)
    area = cv2.boxFilter(ones, -1, (window_px, window_px), normalize=False, borderType=cv2.BORDER_CONSTANT)
    out: np.ndarray[Any, Any] = np.minimum(np.sqrt(area / np.maximum(count, 1.0)), float(window_px))
    return out


def _ladder(radius: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """Round radii (px, >= 0) up to 0, 1, 2, 3 and then steps of `RADIUS_STEP`."""
    top = float(radius.max()) if radius.size else 0.0
    steps = [0.0, 1.0, 2.0, 3.0]
    while steps[-1] < top:
        steps.append(float(math.ceil(steps[-1] * RADIUS_STEP)))
    ladder = np.array(steps)
    out: np.ndarray[Any, Any] = ladder[np.searchsorted(ladder, np.ceil(radius - 1e-9))]
    return out


def displacement_mask(
    range_img: np.ndarray[Any, Any],
    displacement_px: float | np.ndarray[Any, Any],
    range_error_m: float,
    tau_abs_m: float = TAU_ABS_M,
    tau_rel: float = TAU_REL,
    gap_px: float | np.ndarray[Any, Any] | None = None,
) -> Bool:
    """GT pixels whose value stays within max(`tau_abs_m`, `tau_rel` r) under the given displacement.

    `range_img` is a sparse range image (m; 0 or NaN = no GT), `displacement_px`
    the bound on how far any point may have moved in the image (a number or
    an image of per-pixel bounds, e.g. from `time_offset_displacement_px` of
    the GT ranges), `range_error_m` the bound on its move along the ray.

    Why this suffices: the true surface point Y on a pixel's ray was moved to
    Y' at most `displacement_px` away and at most `range_error_m` nearer or
    farther, so |GT - truth| <= |GT(p) - GT(p')| + range error for a p' within
    the displacement, as long as a GT sample represents Y'. A pixel is kept
    when every GT value within radius displacement + `gap_px` (the local GT
    spacing `gt_gap_px` by default: a surface may hide between GT samples)
    differs from its own by at most the tolerance minus the range error.
    Structures thinner than the GT spacing can still hide. Neighbourhoods are
    discs whose radius is rounded up to a short ladder (one small pass per rung).
    """
    r = np.asarray(range_img, dtype=np.float32)
    ok = np.isfinite(r) & (r > 0)
    gap = gt_gap_px(r) if gap_px is None else np.asarray(gap_px, dtype=np.float64)
    disp = np.broadcast_to(np.asarray(displacement_px, dtype=np.float64), r.shape)
    reach = np.nan_to_num(disp, nan=1e6, posinf=1e6) + gap
    radius = np.zeros(r.shape)
    radius[ok] = _ladder(np.broadcast_to(reach, r.shape)[ok])
    # up to DIRECT_RADIUS_PX one disc pass per rung; beyond, grow rung by rung: a disc of radius a
    # dilated by one of radius b covers the disc of radius a + b (checked down to the pixel)
    src_hi = np.where(ok, r, np.float32(0.0)).astype(np.float32)
    src_lo = np.where(ok, r, np.float32(np.inf)).astype(np.float32)
    hi_acc: np.ndarray[Any, Any] = src_hi
    lo_acc: np.ndarray[Any, Any] = src_lo
    hi = np.zeros_like(r)
    lo = np.full_like(r, np.inf)
    reached = 0
    for rad in np.unique(radius[ok]).astype(int):
        sel = ok & (radius == rad)
        if rad >= max(r.shape):  # the whole image is within reach
            hi[sel], lo[sel] = src_hi[ok].max(), src_lo[ok].min()
            continue
        step = rad if rad <= DIRECT_RADIUS_PX else rad - reached
        base_hi, base_lo = (src_hi, src_lo) if rad <= DIRECT_RADIUS_PX else (hi_acc, lo_acc)
        kernel: np.ndarray[Any, Any] = (
            np.ones((3, 3), np.uint8)
            if step == 1
            else cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * step + 1, 2 * step + 1))
        )
        if step > 0:
            hi_acc = cv2.dilate(base_hi, kernel)
            lo_acc = cv2.erode(base_lo, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=np.inf)
            reached = rad
        hi[sel], lo[sel] = hi_acc[sel], lo_acc[sel]
    budget = np.maximum(tau_abs_m, tau_rel * r) - range_error_m
    with np.errstate(invalid="ignore"):
        out: Bool = ok & (hi - r <= budget) & (r - lo <= budget)
    return out
