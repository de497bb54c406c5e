"""Stereo on cam0's equirect vs on cubemap faces: SGBM on each, back to range, scored on the fisheye GT."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from calibration.camera import CameraModel
from calibration.pinhole import Pinhole
from calibration.rectify import rectify_rig
from calibration.rig import Rig
from calibration.spherical import CUBE_FACES, Cubemap
from calibration.stereo import (
    depth_to_disparity,
    disparity_stability_mask,
    disparity_to_depth,
    rotate_for_stereo,
    unrotate_from_stereo,
)
from calibration.types import F64, Bool
from calibration.warp import covering_crop, warp
from ingest.eval.metrics import DepthAccumulator, DepthMetrics, StereoAccumulator, StereoMetrics
from ingest.train.gt.groundtruth import GtParams
from sensorbox.analysis.stability import cubemap_seam_mask, cubemap_stereo_faces

RangeAlong = Callable[[F64], F64]
"""Unit rays (N, 3) in cam0 -> exact range (m), NaN where nothing is hit."""


@dataclass(frozen=True)
class Sgbm:
    """OpenCV semi-global matching on the rotated (horizontal) images; disparity in px."""

    num_disparities: int
    block_size: int = 5

    def compute(self, upper_bgr: np.ndarray[Any, Any], lower_bgr: np.ndarray[Any, Any]) -> F64:
        """Disparity (px) per upper pixel, vertical epipolar lines (lower row = upper row - d); NaN: none."""
        grey = [cv2.cvtColor(im, cv2.COLOR_BGR2GRAY) if im.ndim == 3 else im for im in (upper_bgr, lower_bgr)]
        bs = self.block_size
        matcher = cv2.StereoSGBM.create(
            minDisparity=0, numDisparities=self.num_disparities, blockSize=bs, P1=8 * bs * bs,
            P2=32 * bs * bs, disp12MaxDiff=1, uniquenessRatio=10, speckleWindowSize=100, speckleRange=2,
        )  # fmt: skip
        raw = unrotate_from_stereo(matcher.compute(rotate_for_stereo(grey[0]), rotate_for_stereo(grey[1])))
        disp: F64 = raw.astype(np.float64) / 16.0
        disp[raw < 0] = np.nan
        return disp


@dataclass(frozen=True)
class ProjectionResult:
    """One projection's stereo: own-pixel disparity metrics, range metrics on cam0's fisheye pixels."""

    name: str
    pixels: int  # pixels SGBM ran on (both images of a pair count once)
    warp_s: float
    sgbm_s: float
    stereo: StereoMetrics  # every upper pixel with GT
    stereo_stable: StereoMetrics  # inside the projection's stability mask (poles / seams)
    depth: DepthMetrics  # on cam0's fisheye pixels (range, m)
    depth_common: DepthMetrics  # on the fisheye pixels every projection predicts
    maps: dict[str, np.ndarray[Any, Any]] = field(default_factory=dict, repr=False)

    def row(self) -> dict[str, Any]:
        return {
            "projection": self.name, "pixels": self.pixels, "warp_s": self.warp_s, "sgbm_s": self.sgbm_s,
            "epe_px": self.stereo.epe_px, "bad1_pct": 100 * self.stereo.bad1,
            "bad3_pct": 100 * self.stereo.bad3, "stereo_coverage_pct": 100 * self.stereo.coverage,
            "stable_share_pct": 100 * self.stereo_stable.n_gt / max(self.stereo.n_gt, 1),
            "stable_epe_px": self.stereo_stable.epe_px, "stable_bad1_pct": 100 * self.stereo_stable.bad1,
            "fisheye_abs_rel": self.depth.abs_rel, "fisheye_mae_m": self.depth.mae_m,
            "fisheye_delta1_pct": 100 * self.depth.delta1, "fisheye_coverage_pct": 100 * self.depth.coverage,
            "common_abs_rel": self.depth_common.abs_rel, "common_mae_m": self.depth_common.mae_m,
            "common_pixels": self.depth_common.n,
        }  # fmt: skip


def num_disparities_for(px_per_rad: float, baseline_m: float, min_range_m: float = 0.5) -> int:
    """SGBM search range (a multiple of 16) covering points down to `min_range_m` at the equator."""
    return int(16 * math.ceil(px_per_rad * math.atan(baseline_m / min_range_m) / 16))


def _nearest_lookup(image: F64, uv: F64, ok: Bool) -> F64:
    """image[nearest pixel of uv] where ok and inside, else NaN."""
    h, w = image.shape
    out = np.full(len(uv), np.nan)
    with np.errstate(invalid="ignore"):
        col = np.floor(uv[:, 0] + 0.5)
        row = np.floor(uv[:, 1] + 0.5)
    inside = ok & (col >= 0) & (col < w) & (row >= 0) & (row < h)
    out[inside] = image[row[inside].astype(np.intp), col[inside].astype(np.intp)]
    return out


def _exact_range(
    model: CameraModel, R_cam0_model: F64, range_along: RangeAlong, where: Bool | None = None
) -> tuple[F64, F64, Bool]:
    """Unit rays of every pixel (model frame), exact range (NaN: none or outside `where`), validity."""
    rays, ok = model.unproject(model.pixel_grid())
    if where is not None:
        ok &= where
    r = np.full(ok.shape, np.nan)
    r[ok] = range_along(np.einsum("ij,nj->ni", R_cam0_model, rays[ok]))
    return rays, r, ok


@dataclass(frozen=True)
class _Run:
    """One projection's raw outputs before scoring."""

    name: str
    pixels: int
    warp_s: float
    sgbm_s: float
    disp: F64
    gt: F64
    stable: Bool
    fisheye_pred: F64
    image: np.ndarray[Any, Any]


def _score(runs: list[_Run], fisheye_gt: F64) -> list[ProjectionResult]:
    common = np.logical_and.reduce([np.isfinite(r.fisheye_pred) for r in runs])
    out = []
    for r in runs:
        stereo = StereoAccumulator().add(r.disp, r.gt)
        stereo_stable = StereoAccumulator().add(r.disp, r.gt, r.stable)
        depth = DepthAccumulator().add(r.fisheye_pred, fisheye_gt)
        depth_common = DepthAccumulator().add(r.fisheye_pred, fisheye_gt, common)
        maps = {"disp": r.disp, "gt": r.gt, "stable": r.stable, "image": r.image}
        out.append(
            ProjectionResult(
                r.name, r.pixels, r.warp_s, r.sgbm_s, stereo, stereo_stable, depth, depth_common, maps
            )
        )
    return out


@dataclass(frozen=True)
class _Pair:
    """One stereo pair and what every projection of it shares."""

    upper_bgr: np.ndarray[Any, Any]
    lower_bgr: np.ndarray[Any, Any]
    upper: CameraModel
    lower: CameraModel
    R_cam0_rect: F64
    R_cam1_rect: F64
    baseline_m: float
    height_full: int
    sgbm: Sgbm
    range_along: RangeAlong
    flat_rays: F64  # cam0's fisheye pixel rays in the rectified frame, (N, 3)
    flat_ok: Bool
    fish_shape: tuple[int, ...]


def _equirect_run(p: _Pair, gt: GtParams) -> _Run:
    """SGBM on the crop of the full sphere that covers cam0's fisheye."""
    B, H = p.baseline_m, p.height_full
    eq = covering_crop(p.upper, p.R_cam0_rect, H)
    t0 = time.perf_counter()
    up, up_ok = warp(p.upper_bgr, p.upper, eq, p.R_cam0_rect)
    down, _ = warp(p.lower_bgr, p.lower, eq, p.R_cam1_rect)
    t1 = time.perf_counter()
    disp = p.sgbm.compute(up, down)
    t2 = time.perf_counter()
    rays, r, ok = _exact_range(eq, p.R_cam0_rect, p.range_along, up_ok)
    ok &= np.isfinite(r)
    theta = np.arccos(np.clip(-np.nan_to_num(rays[..., 1]), -1.0, 1.0))
    gt_disp = np.where(ok, depth_to_disparity(np.nan_to_num(r), theta, B, H), np.nan)
    stable = ok & disparity_stability_mask(
        theta, np.nan_to_num(r), B, H, gt.stability_max_rel_error, gt.stability_disp_error_px
    )
    disp[~up_ok] = np.nan
    pred_r = np.where(np.isfinite(disp), disparity_to_depth(np.nan_to_num(disp), theta, B, H), np.nan)
    pred_r[pred_r <= 0] = np.nan
    uv, uv_ok = eq.project(np.nan_to_num(p.flat_rays))
    fish_pred = _nearest_lookup(pred_r, uv, uv_ok & p.flat_ok).reshape(p.fish_shape)
    return _Run("equirect", eq.width * eq.height, t1 - t0, t2 - t1, disp, gt_disp, stable, fish_pred, up)


def _cubemap_run(p: _Pair, block_size: int, padded: bool) -> _Run:
    """SGBM on the stereo cubemap faces of the same pitch at their centres (padded above, or not)."""
    B, F = p.baseline_m, 2 * round(p.height_full / math.pi)
    f = F / 2.0
    pad = p.sgbm.num_disparities + block_size if padded else 0
    model = Pinhole(f, f, (F - 1) / 2.0, (F - 1) / 2.0 + pad, F, F + pad)
    strip_disp, strip_gt, strip_range = (np.full((F, 6 * F), np.nan) for _ in range(3))
    strip_stable = np.zeros((F, 6 * F), bool)
    strip_image = np.zeros((F, 6 * F, 3), np.uint8)
    warp_s = sgbm_s = 0.0
    pixels = 0
    names = [n for n, _ in CUBE_FACES]
    for name in cubemap_stereo_faces([0.0, 1.0, 0.0]):
        k = names.index(name)
        R_rect_face = CUBE_FACES[k][1]
        t0 = time.perf_counter()
        fu, fu_ok = warp(p.upper_bgr, p.upper, model, p.R_cam0_rect @ R_rect_face)
        if fu_ok[pad:].mean() < 0.01:  # the fisheye does not see this face (back)
            continue
        fd, _ = warp(p.lower_bgr, p.lower, model, p.R_cam1_rect @ R_rect_face)
        t1 = time.perf_counter()
        d = p.sgbm.compute(fu, fd)[pad:]
        t2 = time.perf_counter()
        warp_s, sgbm_s, pixels = warp_s + t1 - t0, sgbm_s + t2 - t1, pixels + model.width * model.height
        face_rays, fr, f_ok = _exact_range(model, p.R_cam0_rect @ R_rect_face, p.range_along, fu_ok)
        face_rays, fr, f_ok = face_rays[pad:], fr[pad:], f_ok[pad:] & np.isfinite(fr[pad:])
        z = fr * face_rays[..., 2]
        g = np.where(f_ok & (z > 0), f * B / np.where(z > 0, z, 1.0), np.nan)
        v, u = np.mgrid[0:F, 0:F].astype(np.float64)
        seam = cubemap_seam_mask(u, v, np.nan_to_num(g), F, block_size // 2, p.sgbm.num_disparities, pad)
        d[~fu_ok[pad:]] = np.nan
        with np.errstate(divide="ignore", invalid="ignore"):
            pr = np.where(d > 0, f * B / d / face_rays[..., 2], np.nan)
        cols = slice(k * F, (k + 1) * F)
        strip_disp[:, cols], strip_gt[:, cols], strip_stable[:, cols] = d, g, seam & f_ok
        strip_range[:, cols], strip_image[:, cols] = pr, fu[pad:]
    uv, uv_ok = Cubemap(F).project(np.nan_to_num(p.flat_rays))
    fish_pred = _nearest_lookup(strip_range, uv, uv_ok & p.flat_ok).reshape(p.fish_shape)
    name = "cubemap, padded faces" if padded else "cubemap"
    return _Run(name, pixels, warp_s, sgbm_s, strip_disp, strip_gt, strip_stable, fish_pred, strip_image)


def compare_projections(
    upper_bgr: np.ndarray[Any, Any],
    lower_bgr: np.ndarray[Any, Any],
    rig: Rig,
    height_full: int,
    range_along: RangeAlong,
    block_size: int = 5,
    min_range_m: float = 0.5,
    gt: GtParams | None = None,
) -> list[ProjectionResult]:
    """SGBM on cam0's rectified equirect crop, on the stereo cubemap faces, and on padded faces.

    `range_along` gives the exact range of cam0 rays at the pair's time (the
    simulator's truth). The equirect's stability mask is the pipeline's
    disparity mask (`gt` thresholds); the faces' is `cubemap_seam_mask`.
    """
    rect = rectify_rig(rig)
    sgbm = Sgbm(num_disparities_for(height_full / math.pi, rect.baseline_m, min_range_m), block_size)
    # the common ground: cam0's fisheye pixels and their exact ranges
    fish_rays, fish_gt, fish_ok = _exact_range(rig.upper.model, np.eye(3), range_along)
    rays_rect = np.full(fish_rays.shape, np.nan)
    rays_rect[fish_ok] = np.einsum("ji,nj->ni", rect.R_cam0_rect, fish_rays[fish_ok])
    pair = _Pair(
        upper_bgr, lower_bgr, rig.upper.model, rig.lower.model, rect.R_cam0_rect, rect.R_cam1_rect,
        rect.baseline_m, height_full, sgbm, range_along, rays_rect.reshape(-1, 3), fish_ok.reshape(-1),
        fish_ok.shape,
    )  # fmt: skip
    runs = [_equirect_run(pair, gt or GtParams())]
    runs += [_cubemap_run(pair, block_size, padded) for padded in (False, True)]
    return _score(runs, fish_gt)
