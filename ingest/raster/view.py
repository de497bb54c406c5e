"""Render a view of dense scans: RGB + range per pixel, with splats, a z-buffer and masks.

Recipe for one camera (any `CameraModel`: fisheye, equirect, Cassini, pinhole,
crops) at `T_world_cam`:

1. Select: every scan of the bundle gives the points the view needs
   (`ingest.raster.lod.select`: frustum culling of voxel buckets and a prefix
   per bucket for about `points_per_px` points per pixel).
2. Project: points into the camera (float32), range from the camera centre,
   and each point's footprint in pixels along u and v: its spacing on the
   surface (scanner angular spacing times its range from its own scanner)
   over its range from the camera, times the camera's local pixels per radian.
3. Z-buffer: a point's key packs its range (0.1 mm steps) above its index in
   one int64, so a per-pixel minimum yields both the nearest
   range and which point it is. Two buffers: "own", the nearest point inside
   each pixel, and "splat", the nearest point whose footprint covers it.
   Splats are image-space ellipses of half-widths (ku, kv), written by a
   compiled loop over the points (`ingest.raster.kernels`).
4. Occlusion: an own point is background leaking through a gap of a nearer
   surface when a splat covering it is nearer by more than the same-surface
   tolerance (`RenderParams.tolerance`) and nearer own points lie on two
   opposite sides of it; with nearer points on one side only it sits beside
   that surface's silhouette and stays (no foreground fattening).
5. Value on the pixel-centre ray: a point sits up to half a pixel off the
   centre, on an oblique surface half a pixel of range gradient. The gradient
   is fitted per pixel from its 4-neighbours' own points on the same surface
   (least squares on their sub-pixel offsets); every same-surface point in the
   pixel is moved to the centre along it and averaged (noise). Pixels with a
   surface but no own point take the planar prediction of their neighbours
   (a few passes outwards), else the splat's raw range (or stay invalid:
   `RenderParams.raw_fallback` off, as ground truth wants).
6. Masks: mask points (a label) and mask clouds render into their own splat
   buffer; pixels whose mask surface is not behind the rendered one are
   invalid. Ranges beyond `clip_m` are invalid (`clip_mode="invalid"`, colour
   kept) or their points are not rendered at all (`"drop"`).

Every pixel with a ray ends as a surface with a range, masked, clipped, or a
hole (no data). RGB is the own point's colour, else the splat's.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property, lru_cache
from typing import Any

import cv2
import numpy as np

from calibration.camera import CameraModel
from calibration.transforms import invert
from calibration.types import F32, F64, I64, U8, Bool
from calibration.virtual import project_f32
from ingest.raster.lod import ScanIndex, select
from ingest.raster.visibility import (
    RenderParams,
    ViewPoints,
    average_surface,
    concat_points,
    fill_gaps,
    fit_gradient,
    leaks,
    winner,
    zbuffer,
)

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


def _gather(
    sources: list[ScanIndex],
    model: CameraModel,
    geo: PixelGeometry,
    T_world_cam: F64,
    params: RenderParams,
    pixel_mask: Bool | None = None,
) -> tuple[ViewPoints, ViewPoints, dict[str, int]]:
    """Selected points of every scan, and every mask point, in the camera."""
    T_cam_world = invert(T_world_cam)
    coarse = None if pixel_mask is None else coarse_mask(pixel_mask, geo.stride)
    parts: list[tuple[Any, ...]] = []
    mask_parts: list[tuple[Any, ...]] = []
    stats = {"points_total": 0, "points_touched": 0, "points_in_image": 0}
    for src in sources:
        T_cam_scan = T_cam_world @ src.T_world_scan
        stats["points_total"] += src.n_points
        if params.frustum_culling:
            sel = select(src, model, T_cam_scan, geo.coarse, params.points_per_px, coarse)
            idx, sp = sel.idx, sel.spacing_rad
            xyz = src.xyz[idx]
        else:  # the naive baseline: every point, with its bucket's spacing
            idx = np.arange(src.n_points)
            sp = src.point_spacing_rad()
            xyz = src.xyz
        stats["points_touched"] += len(idx)
        *proj, kept = points_in_view(model, geo, T_cam_scan, xyz, sp, params)
        stats["points_in_image"] += len(kept)
        sel_idx = idx[kept]
        masked = src.masked[sel_idx] if src.masked is not None else np.zeros(len(kept), bool)
        parts.append((*proj, src.rgb[sel_idx], masked))
        if masked.any():  # labelled points render into the mask buffer too
            mask_parts.append(tuple(a[masked] for a in parts[-1]))
        if len(src.mask_xyz):
            *mproj, mkept = points_in_view(model, geo, T_cam_scan, src.mask_xyz, src.mask_spacing_rad, params)
            mask_parts.append((*mproj, np.zeros((len(mkept), 3), np.uint8), np.ones(len(mkept), bool)))
    return concat_points(parts), concat_points(mask_parts), stats


def _leaking(
    pts: ViewPoints,
    r_own: F32,
    r_splat: F32,
    own_ok: Bool,
    splat_i: I64,
    ppr: F32,
    params: RenderParams,
    W: int,
) -> Bool:
    """Own points behind a nearer splat, with nearer own points around them: seen through a surface."""
    H = len(own_ok) // W
    cand = np.flatnonzero(own_ok & (r_own > r_splat + params.tolerance(r_splat, 1.0, ppr.reshape(-1))))
    leak = np.zeros(H * W, bool)
    if cand.size:
        cu, cv = np.divmod(cand, W)[::-1]
        d = np.hypot(pts.u[splat_i[cand]] - cu, pts.v[splat_i[cand]] - cv)
        behind = r_own[cand] > r_splat[cand] + params.tolerance(r_splat[cand], d + 0.5, ppr.reshape(-1)[cand])
        cand = cand[behind]
        K = int(min(3, max(1, int(pts.ku.max()), int(pts.kv.max()))))
        thr = r_own[cand] - params.tolerance(r_own[cand], K + 0.5, ppr.reshape(-1)[cand])
        leak[cand[leaks(r_own.reshape(H, W), cand, thr, K)]] = True
    return leak


def _masked(mask_pts: ViewPoints, surf: Bool, value: F32, ppr: F32, params: RenderParams) -> Bool:
    """Surface pixels whose value lies on (or behind) a mask cloud's surface: reflective or transparent."""
    H, W = surf.shape
    if not len(mask_pts.pix):
        return np.zeros((H, W), bool)
    _, mask_key = zbuffer(mask_pts, H, W)
    m_ok, m_i = winner(mask_key)
    m_i = np.where(m_ok, m_i, len(mask_pts.r))
    r_mask = np.r_[mask_pts.r, np.float32(np.inf)][m_i].reshape(H, W)
    cols = np.arange(W, dtype=np.float32)[None, :]
    rows = np.arange(H, dtype=np.float32)[:, None]
    d_mask = np.hypot(np.r_[mask_pts.u, 0.0][m_i].reshape(H, W) - cols,
                      np.r_[mask_pts.v, 0.0][m_i].reshape(H, W) - rows)  # fmt: skip
    with np.errstate(invalid="ignore"):
        masked: Bool = surf & (r_mask <= value + params.tolerance(value, d_mask + 0.5, ppr))
    return masked


def render_view(
    sources: list[ScanIndex],
    model: CameraModel,
    T_world_cam: F64,
    params: RenderParams | None = None,
    pixel_mask: Bool | None = None,
) -> Rendering:
    """Render RGB + range of ``model`` at ``T_world_cam`` from the scans ``sources`` (see module doc).

    ``pixel_mask`` (H, W) limits the output to some pixels (e.g. the part of an
    equirect crop a fisheye sees); outside it everything is 0.
    """
    params = params or RenderParams()
    if params.backend == "numba":
        from ingest.raster.compiled_view import render_compiled

        return render_compiled(sources, model, T_world_cam, params, pixel_mask)
    if params.backend in ("torch", "cuda"):
        from ingest.raster.torch_view import render_torch

        device = "cuda" if params.backend == "cuda" else "cpu"
        return render_torch(sources, model, T_world_cam, params, pixel_mask, device)
    H, W = model.height, model.width
    geo = pixel_geometry(model)
    ppr = geo.ppr
    pts, mask_pts, stats = _gather(sources, model, geo, T_world_cam, params, pixel_mask)
    own_key, splat_key = zbuffer(pts, H, W)
    own_ok, own_i = winner(own_key)
    surface, splat_i = winner(splat_key)
    del own_key, splat_key
    n = len(pts.r)
    r_all = np.r_[pts.r, np.float32(np.inf)]  # index n: no point
    own_i = np.where(own_ok, own_i, n)
    splat_i = np.where(surface, splat_i, n)

    r_splat = r_all[splat_i]
    leak = _leaking(pts, r_all[own_i], r_splat, own_ok, splat_i, ppr, params, W)
    own_ok &= ~leak
    own_i = np.where(own_ok, own_i, n)
    u_all = np.r_[pts.u, np.float32(0.0)]
    v_all = np.r_[pts.v, np.float32(0.0)]
    cols = np.arange(W, dtype=np.float32)[None, :]
    rows = np.arange(H, dtype=np.float32)[:, None]
    own2 = own_ok.reshape(H, W)
    R = np.where(own2, r_all[own_i].reshape(H, W), np.float32(np.nan))
    U = np.where(own2, u_all[own_i].reshape(H, W) - cols, np.float32(0.0))
    V = np.where(own2, v_all[own_i].reshape(H, W) - rows, np.float32(0.0))

    # values on the pixel-centre rays: own points moved along the fitted gradient, then gaps filled
    flat = np.zeros((H, W), np.float32)  # points on pixel-centre rays need no gradient
    gu, gv = fit_gradient(R, U, V, ppr, params) if params.fit_gradient else (flat, flat)
    value = (R - gu * U - gv * V).astype(np.float32)
    if params.average_samples and n:
        value = average_surface(pts, value, own2, R, gu, gv, ppr, params)
    need = np.flatnonzero(surface & ~own_ok)
    value, got = fill_gaps(value, own2, gu, gv, need, ppr, params)
    raw_px = need[~got]  # a surface but no own point and no neighbour: the splat's nearest range
    value.reshape(-1)[raw_px] = r_splat[raw_px] if params.raw_fallback else np.float32(np.nan)

    # masks and clipping
    rays = geo.valid if pixel_mask is None else geo.valid & pixel_mask
    surf = surface.reshape(H, W) & rays
    masked = _masked(mask_pts, surf, value, ppr, params)
    clipped = np.zeros((H, W), bool)
    if params.clip_m is not None:  # "drop" removed the far points; planar fills may still pass clip_m
        clipped = surf & ~masked & (value > params.clip_m)
    good = surf & ~masked & ~clipped & np.isfinite(value) & (value > 0)
    range_m = np.where(good, value, np.float32(0.0))

    # colour: the own point, else the splat's
    bgr = np.zeros((H * W, 3), np.uint8)
    if n and params.colour:
        src = np.where(own_ok, own_i, splat_i)
        show = np.flatnonzero(surf)
        bgr[show] = pts.rgb[src[show]][:, ::-1]
    stats.update(
        pixels_with_ray=int(rays.sum()),
        surface_px=int(surf.sum()),
        own_px=int((own2 & surf).sum()),
        filled_px=int(surf.reshape(-1)[need[got]].sum()),
        raw_px=int(surf.reshape(-1)[raw_px].sum()),
        leak_rejected_px=int(leak.reshape(H, W)[surf].sum()),
        masked_px=int(masked.sum()),
        clipped_px=int(clipped.sum()),
        hole_px=int((rays & ~surf).sum()),
        valid_px=int(good.sum()),
    )
    return Rendering(bgr.reshape(H, W, 3), range_m, surf, masked, clipped, rays, stats)
