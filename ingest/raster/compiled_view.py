"""`render_view` with compiled kernels: the recipe of `ingest.raster.view`, each stage one parallel pass.

Same stages, same numbers as the numpy recipe (`RenderParams.backend="numpy"`):
level-of-detail selection and the camera model's projection stay numpy (one
vectorised call each); the transform, view test and footprints of the points
(`ingest.raster.point_kernels`), the z-buffers, the leak test, the gradient
fit, the same-surface average, the gap fill and the masks
(`ingest.raster.pixel_kernels`) are numba loops that touch each point or pixel
once instead of once per numpy operation.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from calibration.camera import CameraModel
from calibration.transforms import invert
from calibration.types import F32, F64, I64, Bool
from calibration.virtual import project_f32
from ingest.raster import pixel_kernels as px
from ingest.raster import point_kernels as pk
from ingest.raster.kernels import ellipse_offsets
from ingest.raster.lod import ScanIndex, select
from ingest.raster.view import PixelGeometry, Rendering, _coarse_mask, _points_in_view, pixel_geometry
from ingest.raster.visibility import (
    EMPTY_KEY,
    IDX_BITS,
    KEY_BASE,
    Q_MAX,
    RANGE_QUANTUM_M,
    RenderParams,
    ViewPoints,
    concat_points,
)

f32 = np.float32
IDX_MASK = (1 << IDX_BITS) - 1


def _slope(params: RenderParams) -> float:
    return math.tan(math.radians(params.max_incidence_deg))


def _selected_in_view(
    src: ScanIndex, idx: I64, sp: F32, model: CameraModel, geo: PixelGeometry, T_cam_scan: F64,
    params: RenderParams,
) -> tuple[Any, ...]:  # fmt: skip
    """`view._points_in_view` of ``src.xyz[idx]`` in compiled passes: (pix, u, v, r, ku, kv, kept scan index)."""
    n = len(idx)
    x, y, z, r, pn = (np.empty(n, np.float32) for _ in range(5))
    R = np.ascontiguousarray(T_cam_scan[:3, :3], np.float32)
    t = np.ascontiguousarray(T_cam_scan[:3, 3], np.float32)
    pk.transform(src.xyz, idx, R, t, x, y, z, r, pn)
    u, v, ok = project_f32(model, x, y, z)
    del x, y, z
    near = f32(params.near_m)
    far = f32(params.clip_m) if params.clip_m is not None and params.clip_mode == "drop" else f32(np.inf)
    counts = np.empty(pk.chunks(n), np.int64)
    H, W = model.height, model.width
    pk.count_in_view(u, v, ok, r, near, far, W, H, counts)
    offsets, m = pk.in_view_offsets(counts)
    out = (np.empty(m, np.int64), np.empty(m, np.float32), np.empty(m, np.float32), np.empty(m, np.float32),
           np.empty(m, np.int16), np.empty(m, np.int16), np.empty(m, np.int64))  # fmt: skip
    pk.write_in_view(u, v, ok, r, pn, sp, idx, near, far, W, H, offsets, geo.ppr_u, geo.ppr_v, geo.stride,
                     f32(params.splat_scale), params.max_splat_px, *out)  # fmt: skip
    return out


def _gather(
    sources: list[ScanIndex], model: CameraModel, geo: PixelGeometry, T_world_cam: F64, params: RenderParams,
    pixel_mask: Bool | None,
) -> tuple[ViewPoints, ViewPoints, dict[str, int]]:  # fmt: skip
    """`view._gather`: selected points of every scan, and every mask point, in the camera."""
    T_cam_world = invert(T_world_cam)
    coarse = None if pixel_mask is None else _coarse_mask(pixel_mask, geo.stride)
    parts: list[tuple[Any, ...]] = []
    mask_parts: list[tuple[Any, ...]] = []
    stats = {"points_total": 0, "points_touched": 0, "points_in_image": 0}
    for src in sources:
        T_cam_scan = T_cam_world @ src.T_world_scan
        stats["points_total"] += src.n_points
        if params.frustum_culling:
            sel = select(src, model, T_cam_scan, geo.coarse, params.points_per_px, coarse)
            idx, sp = sel.idx, sel.spacing_rad
        else:
            idx = np.arange(src.n_points)
            sp = np.repeat(src.voxel_spacing_rad, np.diff(src.voxel_start))
        stats["points_touched"] += len(idx)
        *proj, kept = _selected_in_view(src, idx, sp, model, geo, T_cam_scan, params)
        stats["points_in_image"] += len(kept)
        masked = src.masked[kept] if src.masked is not None else np.zeros(len(kept), bool)
        parts.append((*proj, src.rgb[kept], masked))
        if masked.any():
            mask_parts.append(tuple(a[masked] for a in parts[-1]))
        if len(src.mask_xyz):  # a small cloud: the numpy projection
            *mproj, mkept = _points_in_view(model, geo, T_cam_scan, src.mask_xyz, src.mask_spacing_rad, params)
            mask_parts.append((*mproj, np.zeros((len(mkept), 3), np.uint8), np.ones(len(mkept), bool)))
    return concat_points(parts), concat_points(mask_parts), stats


def zbuffer(pts: ViewPoints, H: int, W: int, with_own: bool = True) -> tuple[I64, I64]:
    """`visibility.zbuffer` in parallel row bands: the same (own, splat) key images."""
    own = np.full(H * W if with_own else 0, EMPTY_KEY, np.int64)
    splat = np.full(H * W, EMPTY_KEY, np.int64)
    n = len(pts.pix)
    if n:
        if n >= 1 << IDX_BITS:
            raise ValueError(f"a view can z-buffer at most 2^{IDX_BITS} points, got {n}")
        k_max = int(max(pts.ku.max(), pts.kv.max()))
        start, drow, dcol = ellipse_offsets(k_max)
        pk.zbuffer_bands(pts.pix, pts.r, pts.ku, pts.kv, k_max + 1, start, drow, dcol, H, W, pk.n_bands(H),
                         f32(RANGE_QUANTUM_M), KEY_BASE, Q_MAX, IDX_BITS, own, splat, with_own)  # fmt: skip
    return own, splat


def _fill(value: F32, gu: F32, gv: F32, need: I64, ppr: F32, W: int, params: RenderParams) -> Bool:
    """`visibility.fill_gaps` in place on flat images; which pixels of ``need`` got a value."""
    got_all = np.zeros(len(need), bool)
    todo = np.arange(len(need))
    weight = np.array([1.0] * 4 + [1.0 / math.sqrt(2.0)] * 4, np.float32)
    c = (f32(params.tau_m), f32(params.tau_rel), f32(_slope(params) * 1.5))
    for _ in range(params.fill_passes):
        if todo.size == 0:
            break
        pixels = need[todo]
        m = len(pixels)
        pred, gnu, gnv = (np.empty((m, 8), np.float32) for _ in range(3))
        new, got = np.empty((m, 3), np.float32), np.empty(m, bool)
        px.fill_pass(pixels, value, gu, gv, ppr, W, *c, weight, pred, gnu, gnv, new, got)
        done = pixels[got]
        value[done], gu[done], gv[done] = new[got, 0], new[got, 1], new[got, 2]
        got_all[todo[got]] = True
        todo = todo[~got]
    return got_all


def _mask_buffer(mask_pts: ViewPoints, H: int, W: int) -> I64:
    """The mask points' splat keys (empty array: no mask point)."""
    if not len(mask_pts.pix):
        return np.zeros(0, np.int64)
    return zbuffer(mask_pts, H, W, with_own=False)[1]


def render_compiled(
    sources: list[ScanIndex], model: CameraModel, T_world_cam: F64, params: RenderParams,
    pixel_mask: Bool | None = None,
) -> Rendering:  # fmt: skip
    """`ingest.raster.view.render_view` with compiled kernels (see module doc); the same `Rendering`."""
    H, W = model.height, model.width
    P = H * W
    geo = pixel_geometry(model)
    ppr = geo.ppr.reshape(-1)
    pts, mask_pts, stats = _gather(sources, model, geo, T_world_cam, params, pixel_mask)
    own_key, splat_key = zbuffer(pts, H, W)
    own_ok, leak = np.empty(P, bool), np.empty(P, bool)
    own_i, splat_i = np.empty(P, np.int64), np.empty(P, np.int64)
    r_own, r_splat = np.empty(P, np.float32), np.empty(P, np.float32)
    px.decode(own_key, splat_key, pts.r, EMPTY_KEY, IDX_MASK, own_ok, own_i, splat_i, r_own, r_splat)
    surface = splat_key != EMPTY_KEY
    del own_key, splat_key
    tau_m, tau_rel, slope = f32(params.tau_m), f32(params.tau_rel), _slope(params)
    K = int(min(3, max(1, int(pts.ku.max()), int(pts.kv.max())))) if len(pts.r) else 1
    px.leaking(own_ok, r_own, r_splat, splat_i, pts.u, pts.v, ppr, W, K, tau_m, tau_rel, slope,
               f32(slope * 1.0), f32(slope * (K + 0.5)), leak)  # fmt: skip
    own2 = np.empty(P, bool)
    R, U, V = (np.empty(P, np.float32) for _ in range(3))
    px.own_samples(own_ok, leak, own_i, pts.r, pts.u, pts.v, W, own2, R, U, V)
    del r_own

    # values on the pixel-centre rays: own points moved along the fitted gradient, averaged, gaps filled
    gu, gv, value = (np.empty(P, np.float32) for _ in range(3))
    px.gradient_value(R, U, V, ppr, W, tau_m, tau_rel, f32(slope * 1.0), params.fit_gradient, gu, gv, value)
    if params.average_samples and len(pts.r):
        pk.average_bands(pts.pix, pts.u, pts.v, pts.r, own2, R, gu, gv, ppr, tau_m, tau_rel, f32(slope * 1.0),
                         W, pk.n_bands(H), value)  # fmt: skip
    need = np.flatnonzero(surface & ~own2)
    got = _fill(value, gu, gv, need, ppr, W, params)
    raw_px = need[~got]  # a surface but no own point and no neighbour: the splat's nearest range
    value[raw_px] = r_splat[raw_px] if params.raw_fallback else np.float32(np.nan)

    # masks, clipping, colour
    rays = geo.valid if pixel_mask is None else geo.valid & pixel_mask
    surf, masked, clipped, good = (np.empty(P, bool) for _ in range(4))
    range_m, bgr = np.empty(P, np.float32), np.empty((P, 3), np.uint8)
    clip = f32(np.inf) if params.clip_m is None else f32(params.clip_m)
    rgb = pts.rgb if len(pts.rgb) else np.zeros((1, 3), np.uint8)
    px.finish(value, surface, own2, own_i, splat_i, rays.reshape(-1), rgb, ppr, W, _mask_buffer(mask_pts, H, W),
              mask_pts.r, mask_pts.u, mask_pts.v, EMPTY_KEY, IDX_MASK, tau_m, tau_rel, f32(slope), clip,
              surf, masked, clipped, good, range_m, bgr)  # fmt: skip
    stats.update(
        pixels_with_ray=int(rays.sum()),
        surface_px=int(surf.sum()),
        own_px=int((own2 & surf).sum()),
        filled_px=int(surf[need[got]].sum()),
        raw_px=int(surf[raw_px].sum()),
        leak_rejected_px=int((leak & surf).sum()),
        masked_px=int(masked.sum()),
        clipped_px=int(clipped.sum()),
        hole_px=int((rays.reshape(-1) & ~surf).sum()),
        valid_px=int(good.sum()),
    )
    shape = (H, W)
    return Rendering(bgr.reshape(H, W, 3), range_m.reshape(shape), surf.reshape(shape), masked.reshape(shape),
                     clipped.reshape(shape), rays, stats)  # fmt: skip
