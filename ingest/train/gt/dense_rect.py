"""Dense GT on the rectified equirect: the ranges of its rays from cam0's GT range image.

The rectified equirect shares cam0's centre, so it is not rendered a second
time: each of its rays takes the plane of the GT pixel of cam0 nearest to
where it projects (`rect_ranges`), over the crop of the full sphere that
cam0 sees (`cam0_window`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from calibration.camera import CameraModel
from calibration.spherical import Equirectangular
from calibration.types import F32, F64, I64
from ingest.dataset.sparse import SparseImage
from ingest.raster.kernels import I32, nearest_pixel_groups, planar_resample
from ingest.raster.view import pixel_rays


@dataclass(frozen=True)
class ResampleParams:
    """`rect_ranges`' tolerances: a pixel's 3x3 points within `flat_m` + `flat_rel` x range (m) of their
    plane, a ray meeting it at |cos| >= `min_cos`, its range within `max_change` of the pixel's."""

    flat_m: float
    flat_rel: float
    max_change: float
    min_cos: float


def rect_ranges(
    model: CameraModel, win: Equirectangular, R_cam0_rect: F64, range_img: SparseImage, params: ResampleParams
) -> F32:
    """Range (m) along every ray of `win` (rectified frame; 0: none), from cam0's GT range image.

    The rectified equirect and cam0 share their centre (`R_cam0_rect` is a
    rotation), so what cam0 sees along a direction is what the equirect sees
    along it: a ray's surface is the one of the GT pixel nearest to where it
    projects in cam0, and its range is where it meets that pixel's plane (the
    least-squares plane of the pixel's point and its GT neighbours, which
    must lie on it within `params.flat_m` + `params.flat_rel` x range:
    the renderer's same-surface tolerance, so a noisy surface keeps its GT
    and a crease or step does not), exact on planes as the snapped values
    are. Rays whose nearest cam0 pixel holds no GT (a hole, a silhouette, a
    mover) get none: disparity is GT only where depth is.
    """
    rays, _ = pixel_rays(model)
    start, order, rays_win = rect_lookup(model, win, R_cam0_rect)
    tolerances = (params.flat_m, params.flat_rel, params.max_change)
    return planar_resample(
        range_img.dense(), rays, range_img.pixel, start, order, rays_win, params.min_cos, *tolerances,
    )  # fmt: skip


@lru_cache(maxsize=2)
def _rect_lookup_cached(model: CameraModel, win: Equirectangular, R_bytes: bytes) -> tuple[I64, I32, F32]:
    R_cam0_rect = np.frombuffer(R_bytes).reshape(3, 3)
    rays_rect, ok = win.unproject(win.pixel_grid())
    rays_cam0 = rays_rect.reshape(-1, 3) @ R_cam0_rect.T  # p_cam0 = R_cam0_rect p_rect
    uv, good = model.project(rays_cam0)
    good &= ok.reshape(-1)
    start, order = nearest_pixel_groups(np.where(good[:, None], uv, np.nan), model.width, model.height)
    return start, order, np.ascontiguousarray(np.nan_to_num(rays_cam0), np.float32)


def rect_lookup(model: CameraModel, win: Equirectangular, R_cam0_rect: F64) -> tuple[I64, I32, F32]:
    """Cached: the rays of `win` grouped by their nearest pixel of `model` (`nearest_pixel_groups`'
    start and order) and the rays in cam0 ((N, 3) unit).
    """
    return _rect_lookup_cached(model, win, np.ascontiguousarray(R_cam0_rect, np.float64).tobytes())


@lru_cache(maxsize=4)
def _cam0_window_cached(model: CameraModel, eq: Equirectangular, R_bytes: bytes) -> Equirectangular:
    R_cam0_rect = np.frombuffer(R_bytes).reshape(3, 3)
    rays, ok = pixel_rays(model)
    full = eq.full()
    uv, good = full.project(rays[ok].astype(np.float64) @ R_cam0_rect)
    uv = uv[good]
    m = 1  # an equirect ray outside cam0's image has no GT pixel near it
    c0 = max(0, int(np.floor(uv[:, 0].min())) - m)
    c1 = min(full.width, int(np.ceil(uv[:, 0].max())) + m + 1)
    r0 = max(0, int(np.floor(uv[:, 1].min())) - m)
    r1 = min(full.height, int(np.ceil(uv[:, 1].max())) + m + 1)
    return full.crop(r0, c0, r1 - r0, c1 - c0)


def cam0_window(model: CameraModel, eq: Equirectangular, R_cam0_rect: F64) -> Equirectangular:
    """The crop of `eq`'s full sphere holding every ray of `model` (plus a pixel), cached."""
    return _cam0_window_cached(model, eq, np.ascontiguousarray(R_cam0_rect, np.float64).tobytes())
