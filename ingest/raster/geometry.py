"""What every backend of the renderer shares: pixel geometry, the points in view, the result.

A camera model's pixel rays and local resolution (`pixel_geometry`, cached
per model), the numpy projection of scan points into a view
(`points_in_view`: pixel, sub-pixel position, range, footprint half-widths),
the points of a view (`ViewPoints`) and a rendered view (`Rendering`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property, lru_cache
from typing import Any

import cv2
import numpy as np

from calibration.camera import CameraModel
from calibration.types import F32, F64, I64, U8, Bool
from calibration.virtual import project_f32
from ingest.raster.params import RenderParams

I16 = np.ndarray[Any, np.dtype[np.int16]]

PPR_STRIDE = 8  # coarse pixels-per-radian map: one node every 8 pixels
# Oversampled corners of an image (a Cassini's or equirect's poles) get no more points per solid
# angle than this many times the image's median resolution: there splats close the surface, and
# a 195-degree Cassini window stays at ~2 points per pixel instead of drawing the whole scan.
LOD_PPR_CAP = 2.0


@dataclass(frozen=True, eq=False)
class PixelGeometry:
    """Per camera model: which pixels have a ray, and pixels per radian along u and v (coarse)."""

    valid: Bool  # (H, W)
    ppr_u: F32  # (ceil(H/s), ceil(W/s))
    ppr_v: F32
    stride: int
    ppr_max: float
    ppr_lod_cap: float  # level of detail stops adding points beyond this resolution (pixels per radian)

    @property
    def coarse(self) -> tuple[F32, F32, int, float, float]:
        return self.ppr_u, self.ppr_v, self.stride, self.ppr_max, self.ppr_lod_cap

    @cached_property
    def ppr(self) -> F32:
        """(H, W) geometric-mean pixels per radian, expanded from the coarse maps."""
        H, W = self.valid.shape
        m = np.sqrt(self.ppr_u * self.ppr_v)
        out: F32 = np.repeat(np.repeat(m, self.stride, axis=0), self.stride, axis=1)[:H, :W]
        return np.ascontiguousarray(out)


@lru_cache(maxsize=2)
def pixel_rays(model: CameraModel) -> tuple[F32, Bool]:
    """Cached per model (few: a ray grid is 12 bytes per pixel): unit ray of every pixel centre, valid."""
    rays, valid = model.unproject(model.pixel_grid())
    return np.ascontiguousarray(np.nan_to_num(rays), np.float32), np.ascontiguousarray(valid)


@lru_cache(maxsize=24)
def pixel_geometry(model: CameraModel) -> PixelGeometry:
    """Cached per (hashable) model: ray validity of every pixel and local angular resolution."""
    valid = pixel_rays(model)[1]  # the one unprojection of every pixel, shared with the ray grid
    s = PPR_STRIDE
    uu, vv = np.meshgrid(np.arange(0, model.width, s, dtype=np.float64),
                         np.arange(0, model.height, s, dtype=np.float64))  # fmt: skip
    maps = []
    for du, dv in ((0.5, 0.0), (0.0, 0.5)):
        a, ok_a = model.unproject(np.stack([uu - du, vv - dv], axis=-1))
        b, ok_b = model.unproject(np.stack([uu + du, vv + dv], axis=-1))
        ang = np.arccos(np.clip(np.einsum("...i,...i->...", a, b), -1.0, 1.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            maps.append(np.where(ok_a & ok_b & (ang > 0), 1.0 / ang, np.nan))
    both = np.stack(maps)
    ppr_max = float(np.nanmax(both)) if np.isfinite(both).any() else 1.0
    ppr_u, ppr_v = (np.nan_to_num(m, nan=ppr_max).astype(np.float32) for m in maps)
    mean = np.sqrt(both[0] * both[1])
    typical = float(np.nanmedian(mean)) if np.isfinite(mean).any() else ppr_max
    return PixelGeometry(valid, ppr_u, ppr_v, s, ppr_max, LOD_PPR_CAP * typical)


@dataclass(frozen=True, eq=False)
class Rendering:
    """One rendered view; ``range_m`` is 0 where there is no valid value."""

    bgr: U8  # (H, W, 3)
    range_m: F32  # (H, W), metres from the camera centre along the pixel ray; 0 = invalid
    surface: Bool  # a surface was rendered (before masks and clipping)
    masked: Bool  # invalid: a reflective/transparent (mask) surface is in front
    clipped: Bool  # invalid: farther than clip_m
    rays: Bool  # pixels with a camera ray (and inside the requested pixel mask)
    stats: dict[str, int] = field(default_factory=dict)

    @property
    def holes(self) -> Bool:
        """Pixels with a ray but no data."""
        out: Bool = self.rays & ~self.surface
        return out


@dataclass(frozen=True, eq=False)
class ViewPoints:
    """Points in the image: flat pixel, sub-pixel position, range, footprint half-widths, colour, mask."""

    pix: I64
    u: F32
    v: F32
    r: F32
    ku: I16
    kv: I16
    rgb: U8
    masked: Bool


def concat_points(parts: list[tuple[Any, ...]]) -> ViewPoints:
    if not parts:
        f, i, k = np.zeros(0, np.float32), np.zeros(0, np.int64), np.zeros(0, np.int16)
        return ViewPoints(i, f, f, f, k, k, np.zeros((0, 3), np.uint8), np.zeros(0, bool))
    if len(parts) == 1:
        return ViewPoints(*parts[0])
    return ViewPoints(*(np.concatenate([p[k] for p in parts]) for k in range(8)))


def points_in_view(
    model: CameraModel, geo: PixelGeometry, T_cam_scan: F64, xyz: F32, spacing_rad: F32, params: RenderParams
) -> tuple[Any, ...]:
    """Project scan-frame points; (pix, u, v, r, ku, kv, kept index) of those landing in the image."""
    R = T_cam_scan[:3, :3].astype(np.float32)
    t = T_cam_scan[:3, 3].astype(np.float32)
    px, py, pz = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    # explicit components, not (N,3)@(3,3): no BLAS threads on the hot path
    x = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t[0]
    y = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t[1]
    z = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t[2]
    r = np.sqrt(x * x + y * y + z * z)
    u, v, ok = project_f32(model, x, y, z)
    ok &= r > params.near_m
    if params.clip_m is not None and params.clip_mode == "drop":
        ok &= r <= params.clip_m
    col = np.floor(u + 0.5)
    row = np.floor(v + 0.5)
    ok &= (col >= 0) & (col < model.width) & (row >= 0) & (row < model.height)
    keep = np.flatnonzero(ok)
    col_i, row_i = col[keep].astype(np.int64), row[keep].astype(np.int64)
    r_k = r[keep]
    pk = xyz[keep]
    foot = spacing_rad[keep] * np.sqrt(np.einsum("ij,ij->i", pk, pk)) / r_k
    cu, cv = col_i // geo.stride, row_i // geo.stride
    K = params.max_splat_px
    # half-widths rounded to whole pixels: a spacing of 0.7 px already needs its neighbours covered
    ku = np.minimum(K, params.splat_scale * foot * geo.ppr_u[cv, cu] + 0.5).astype(np.int16)
    kv = np.minimum(K, params.splat_scale * foot * geo.ppr_v[cv, cu] + 0.5).astype(np.int16)
    return row_i * model.width + col_i, u[keep], v[keep], r_k, ku, kv, keep


def coarse_mask(mask: Bool, stride: int) -> Bool:
    """Cells of ``stride`` x ``stride`` pixels holding any True pixel, grown by one cell."""
    H, W = mask.shape
    hp, wp = -(-H // stride) * stride, -(-W // stride) * stride
    padded = np.zeros((hp, wp), bool)
    padded[:H, :W] = mask
    cells = np.asarray(padded.reshape(hp // stride, stride, wp // stride, stride).any(axis=(1, 3)), np.uint8)
    out: Bool = cv2.dilate(cells, np.ones((3, 3), np.uint8)) > 0
    return out
