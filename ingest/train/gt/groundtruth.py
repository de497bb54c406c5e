"""Sparse ground truth from LiDAR points in cam0: fisheye range and rectified-equirect disparity.

Steps, each a pure function:
1. `surface_normals`: a local plane per point (PCA of its k nearest neighbours,
   `ingest.train.trajectory.planes`).
2. `occlusion_filter`: LiDAR-camera parallax lets a LiDAR see surfaces the camera
   cannot; such points land a few pixels beside a nearer foreground point. A
   point is dropped when a k x k window around its pixel (square splats of
   nearer points, ETH3D-style) holds a point nearer by more than
   max(`tau_m`, `tau_rel` * range). The window spans `window_rad` of view
   (default 0.018 rad: 9 px at the reference rig's 500 px/rad) or two mean
   point spacing in the image, whichever is wider, so a foreground surface
   covers its own gaps even when the window holds few points.
3. `splat_to_pixels`: nearest pixel centre per point and a z-buffer on range.
   The value stored is the range along the pixel-centre ray, not the point's
   own range: the ray is intersected with the point's local plane (when the
   neighbourhood is planar and the ray not grazing), which removes the error
   of up to half a pixel of depth gradient on oblique surfaces.
4. Disparity uses the same surviving points, splatted into the rectified
   full-sphere equirect of cam0, converted with DESIGN.md's formula, and
   masked by the stability test (both in `disparity_and_stability`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import cv2
import numpy as np

from calibration.camera import CameraModel
from calibration.spherical import Equirectangular
from calibration.stereo import disparity_and_stability
from calibration.types import F64, Bool
from ingest.dataset.sparse import SparseImage
from ingest.train.trajectory.planes import Normals, plane_normals

VALID_FRACTION_DS = 0.9  # share of a fisheye image with valid rays (point spacing estimate only)


@dataclass(frozen=True)
class GtParams:
    """Ground-truth parameters (written to dataset.yaml)."""

    window_rad: float = 0.018
    window_spacings: float = 2.0  # ... or this many mean point spacings, whichever is wider
    tau_m: float = 0.10
    tau_rel: float = 0.03
    plane_neighbours: int = 8
    plane_max_flatness: float = 0.05  # smallest / summed PCA eigenvalue
    plane_min_cos: float = 0.2  # |n . ray| below this: grazing, keep the raw range
    stability_max_rel_error: float = 0.5
    stability_disp_error_px: float = 0.5
    occlusion: bool = True  # False: no parallax filter (an ablation for `sensorbox bench`)
    zbuffer: Literal["nearest", "farthest"] = "nearest"  # "farthest" keeps the wrong point (an ablation)


def surface_normals(pts: F64, k: int, max_flatness: float, query: Bool | None = None) -> Normals:
    """PCA normal of each point's k-neighbourhood (the point included).

    With `query` (a mask over `pts`) only those points get normals, fitted to
    neighbours among the queried points: the ground truth needs normals of the
    points the camera sees, not of the whole 360 degree cloud. (A point at the
    image border fits its plane to neighbours on the inner side only; on a
    plane that is the same plane.)
    """
    return plane_normals(pts if query is None else pts[query], k, max_flatness)


def px_per_rad(model: CameraModel) -> float:
    """Angular resolution at the principal ray (pixels per radian)."""
    eps = 1e-5
    uv, _ = model.project(np.array([[0.0, 0.0, 1.0], [np.sin(eps), 0.0, np.cos(eps)]]))
    return float(abs(uv[1, 0] - uv[0, 0]) / eps)


@dataclass(frozen=True)
class Splat:
    """One value per pixel: flat pixel index, the point it came from, and the range along the pixel ray."""

    pixel: np.ndarray[Any, np.dtype[np.int64]]
    point: np.ndarray[Any, np.dtype[np.int64]]
    range_m: F64
    ray: F64  # unit pixel-centre ray in the model frame


View = tuple[Bool, F64, F64]
"""`in_view`'s result: (in view, nearest pixel-centre columns, rows)."""


def splat_to_pixels(
    model: CameraModel, pts_model: F64, normals_model: Normals, params: GtParams, view: View | None = None
) -> Splat:
    """Nearest-pixel z-buffer of points given in the model's frame, ranges moved onto pixel-centre rays.

    `view` is `in_view(model, pts_model)` when the caller has it already.
    """
    ok, cols, rows = in_view(model, pts_model) if view is None else view
    idx = np.nonzero(ok)[0]
    centres = np.stack([cols[idx], rows[idx]], axis=1)
    ray, ray_ok = model.unproject(centres)
    idx, ray, centres = idx[ray_ok], ray[ray_ok], centres[ray_ok]
    p = pts_model[idx]
    r_point = np.linalg.norm(p, axis=1)
    n = normals_model.normal[idx]
    cos = np.einsum("ij,ij->i", n, ray)
    use_plane = normals_model.planar[idx] & (np.abs(cos) >= params.plane_min_cos)
    with np.errstate(divide="ignore", invalid="ignore"):
        r_plane = np.einsum("ij,ij->i", n, p) / cos
    # a plane correction moves the range by at most one pixel's worth of gradient on that plane: a pixel
    # at the principal ray, or twice the point's own angle off its pixel-centre ray where pixels span
    # more angle than there (a fisheye's corners; the point is within half of its own pixel)
    off_rad = np.arctan2(np.linalg.norm(np.cross(p, ray), axis=1), np.einsum("ij,ij->i", p, ray))
    pixel_rad = np.maximum(1.0 / px_per_rad(model), 2.0 * off_rad)
    limit = r_point * np.sqrt(np.maximum(1.0 / np.maximum(cos**2, 1e-12) - 1.0, 0.0)) * pixel_rad
    use_plane &= np.isfinite(r_plane) & (np.abs(r_plane - r_point) <= limit + 1e-9)
    r = np.where(use_plane, r_plane, r_point)
    flat = centres[:, 1].astype(np.int64) * model.width + centres[:, 0].astype(np.int64)
    order = np.argsort(_pixel_range_key(flat, r, params.zbuffer == "nearest"), kind="stable")
    first = np.ones(len(order), bool)
    first[1:] = flat[order][1:] != flat[order][:-1]
    win = order[first]
    return Splat(flat[win], idx[win], r[win], ray[win])


def _pixel_range_key(flat: np.ndarray[Any, np.dtype[np.int64]], range_m: F64, nearest: bool) -> Any:
    """One int64 per point that sorts by pixel, then by range (nearest or farthest first).

    The range takes the low 32 bits, quantised over [0, max range] (steps of
    ~1e-8 m at 40 m); one stable argsort of it is ~2x faster than
    `np.lexsort((range, pixel))` and orders the same up to that step.
    """
    r = np.maximum(range_m, 0.0)
    top = float(r.max()) if len(r) else 1.0
    q = np.floor(r * ((2.0**32 - 1.0) / max(top, 1e-30))).astype(np.int64)
    return (flat << 32) | (q if nearest else (2**32 - 1) - q)


def in_view(model: CameraModel, pts_model: F64) -> View:
    """Points whose nearest pixel centre lies in the image, and those centres' (cols, rows)."""
    uv, ok = model.project(pts_model)
    cols = np.floor(uv[:, 0] + 0.5)
    rows = np.floor(uv[:, 1] + 0.5)
    ok &= (cols >= 0) & (cols < model.width) & (rows >= 0) & (rows < model.height)
    return ok, cols, rows


def occlusion_filter(model: CameraModel, pts_model: F64, params: GtParams, view: View | None = None) -> Bool:
    """Keep mask: in view and not hidden behind nearer points (parallax bleed).

    `view` is `in_view(model, pts_model)` when the caller has it already.
    """
    ok, cols, rows = in_view(model, pts_model) if view is None else view
    if not params.occlusion:
        return ok
    r = np.linalg.norm(pts_model, axis=1)
    img = np.full((model.height, model.width), np.inf, np.float32)
    ci, ri = cols[ok].astype(np.int64), rows[ok].astype(np.int64)
    np.minimum.at(img, (ri, ci), r[ok].astype(np.float32))
    # the window must also bridge the gaps between points: their mean spacing in pixels
    spacing_px = np.sqrt(model.width * model.height * VALID_FRACTION_DS / max(int(ok.sum()), 1))
    k = max(3, round(max(params.window_rad * px_per_rad(model), params.window_spacings * spacing_px)) | 1)
    nearest = cv2.erode(img, np.ones((k, k), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=np.inf)
    keep = ok.copy()
    tau = np.maximum(params.tau_m, params.tau_rel * r[ok])
    keep[ok] = r[ok] - nearest[ri, ci] <= tau
    return keep


def fisheye_range(model: CameraModel, splat: Splat) -> SparseImage:
    """Range image (H, W) in metres along each pixel's ray."""
    return SparseImage((model.height, model.width), splat.pixel, splat.range_m.astype(np.float32))


def equirect_disparity(
    eq: Equirectangular,
    R_rect_cam0: F64,
    pts_cam0: F64,
    normals_cam0: Normals,
    baseline_m: float,
    params: GtParams,
) -> tuple[SparseImage, SparseImage, int]:
    """Disparity (px of the full sphere) and range images in cam0's rectified equirect.

    Returns (disparity, range, unstable): pixels failing the stability mask
    have no disparity (their range is kept) and are counted in `unstable`.
    """
    pts_rect = np.einsum("ij,nj->ni", R_rect_cam0, pts_cam0)
    normals_rect = Normals(np.einsum("ij,nj->ni", R_rect_cam0, normals_cam0.normal), normals_cam0.planar)
    splat = splat_to_pixels(eq, pts_rect, normals_rect, params)
    theta = np.arccos(np.clip(-splat.ray[:, 1], -1.0, 1.0))
    disp, stable = disparity_and_stability(
        splat.range_m, theta, baseline_m, eq.height_full, params.stability_max_rel_error,
        params.stability_disp_error_px,
    )  # fmt: skip
    shape = (eq.height, eq.width)
    disp_img = SparseImage(shape, splat.pixel[stable], disp[stable].astype(np.float32))
    range_img = SparseImage(shape, splat.pixel, splat.range_m.astype(np.float32))
    return disp_img, range_img, int((~stable).sum())
