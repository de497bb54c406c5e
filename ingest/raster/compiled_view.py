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
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numba
import numpy as np

from calibration.camera import CameraModel
from calibration.fisheye import DoubleSphere
from calibration.kernels import fork_safe_numba_threads
from calibration.spherical import Equirectangular
from calibration.transforms import invert
from calibration.types import F32, F64, I64, Bool
from calibration.virtual import project_f32
from ingest.raster import pixel_kernels as px
from ingest.raster import point_kernels as pk
from ingest.raster.kernels import ellipse_offsets
from ingest.raster.lod import ScanIndex, select
from ingest.raster.view import PixelGeometry, Rendering, coarse_mask, pixel_geometry, points_in_view
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

fork_safe_numba_threads()  # before any parallel kernel runs in this process

f32 = np.float32
IDX_MASK = (1 << IDX_BITS) - 1
# Smaller views run their kernels on one thread: starting a parallel region costs tens of
# microseconds on an idle machine and milliseconds on a busy one, more than such a view saves.
SMALL_VIEW_PX = 250_000
SMALL_VIEW_POINTS = 1_000_000


def _slope(params: RenderParams) -> float:
    return math.tan(math.radians(params.max_incidence_deg))


def _selected_in_view(
    src: ScanIndex, idx: I64, sp: F32, model: CameraModel, geo: PixelGeometry, T_cam_scan: F64,
    params: RenderParams,
) -> tuple[Any, ...]:  # fmt: skip
    """`view.points_in_view` of ``src.xyz[idx]`` in compiled passes, packed by row group.

    Returns (pix, u, v, r, ku, kv, rgb, kept scan index, index in selection
    order, where each row group starts, points per footprint class (ku, kv)).
    """
    n = len(idx)
    R = np.ascontiguousarray(T_cam_scan[:3, :3], np.float32)
    t = np.ascontiguousarray(T_cam_scan[:3, 3], np.float32)
    near = f32(params.near_m)
    far = f32(params.clip_m) if params.clip_m is not None and params.clip_mode == "drop" else f32(np.inf)
    H, W = model.height, model.width
    counts = np.empty((pk.chunks(n), pk.n_groups(H)), np.int64)
    r, pn = np.empty(n, np.float32), np.empty(n, np.float32)
    if type(model) is DoubleSphere:  # projected in the same pass
        c = model
        ds = np.array([c.xi, c.alpha, 1.0 - c.alpha, -c.w2, c.fx, c.fy, c.cx, c.cy], np.float32)
        u, v, ok = np.empty(n, np.float32), np.empty(n, np.float32), np.empty(n, bool)
        pk.transform_ds(src.xyz, idx, R, t, ds, u, v, ok, r, pn)
    elif type(model) is Equirectangular and model.pole_axis == "y":  # projected in the same pass
        e = model
        eq = np.array([math.pi, e.pitch_rad, 0.5, e.col_offset, e.row_offset], np.float32)
        u, v, ok = np.empty(n, np.float32), np.empty(n, np.float32), np.empty(n, bool)
        pk.transform_equirect(src.xyz, idx, R, t, eq, u, v, ok, r, pn)
    else:
        x, y, z = (np.empty(n, np.float32) for _ in range(3))
        pk.transform(src.xyz, idx, R, t, x, y, z, r, pn)
        u, v, ok = project_f32(model, x, y, z)
        del x, y, z
    pk.count_in_view(u, v, ok, r, near, far, W, H, counts)
    offsets, chunk_base, group_start, m = pk.in_view_offsets(counts)
    K = params.max_splat_px
    hist = np.empty((len(counts), (K + 1) ** 2), np.int64)
    # no colour: black points (pages of zeros cost nothing until read)
    rgb = np.empty((m, 3), np.uint8) if params.colour else np.zeros((m, 3), np.uint8)
    out = (np.empty(m, np.int64), np.empty(m, np.float32), np.empty(m, np.float32), np.empty(m, np.float32),
           np.empty(m, np.int16), np.empty(m, np.int16), np.empty(m, np.int64), np.empty(m, np.int64),
           rgb)  # fmt: skip
    pk.write_in_view(u, v, ok, r, pn, sp, idx, src.rgb, params.colour, near, far, W, H, offsets, chunk_base,
                     geo.ppr_u, geo.ppr_v, geo.stride, f32(params.splat_scale), K, hist, *out)  # fmt: skip
    pix, u_k, v_k, r_k, ku, kv, kept, order, rgb = out
    return pix, u_k, v_k, r_k, ku, kv, rgb, kept, order, group_start, hist.sum(axis=0).reshape(K + 1, K + 1)


def _gather(
    sources: list[ScanIndex], model: CameraModel, geo: PixelGeometry, T_world_cam: F64, params: RenderParams,
    pixel_mask: Bool | None,
) -> tuple[ViewPoints, I64, I64, I64, ViewPoints, dict[str, int]]:  # fmt: skip
    """`view._gather`: every scan's selected points (by row group), their order, group starts and
    footprint class counts (ku, kv); the mask points."""
    T_cam_world = invert(T_world_cam)
    coarse = None if pixel_mask is None else coarse_mask(pixel_mask, geo.stride)
    parts: list[tuple[Any, ...]] = []
    orders: list[I64] = []
    segs: list[I64] = []
    classes = np.zeros((params.max_splat_px + 1,) * 2, np.int64)
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
            sp = src.point_spacing_rad()
        stats["points_touched"] += len(idx)
        *proj, rgb, kept, order, group_start, n_cls = _selected_in_view(src, idx, sp, model, geo, T_cam_scan,
                                                                         params)  # fmt: skip
        classes = classes + n_cls
        orders.append(order + stats["points_in_image"])
        segs.append(group_start + stats["points_in_image"])
        stats["points_in_image"] += len(kept)
        masked = src.masked[kept] if src.masked is not None else np.zeros(len(kept), bool)
        parts.append((*proj, rgb, masked))
        if masked.any():  # labelled points, in the recipe's order (the mask z-buffer breaks ties by it)
            lab = np.flatnonzero(masked)
            lab = lab[np.argsort(order[lab])]
            mask_parts.append(tuple(a[lab] for a in parts[-1]))
        if len(src.mask_xyz):  # a small cloud: the numpy projection
            sp_m = src.mask_spacing_rad
            *mproj, mkept = points_in_view(model, geo, T_cam_scan, src.mask_xyz, sp_m, params)
            mask_parts.append((*mproj, np.zeros((len(mkept), 3), np.uint8), np.ones(len(mkept), bool)))
    order_all = orders[0] if len(orders) == 1 else np.concatenate(orders) if orders else np.zeros(0, np.int64)
    seg = np.stack(segs) if segs else np.zeros((0, pk.n_groups(model.height) + 1), np.int64)
    return concat_points(parts), order_all, seg, classes, concat_points(mask_parts), stats


def zbuffer(
    pts: ViewPoints, order: I64, seg: I64, classes: I64, H: int, W: int, with_own: bool = True,
    bands: int | None = None,
) -> tuple[I64, I64]:  # fmt: skip
    """`visibility.zbuffer` in parallel bands: the same (own, splat) key images, indices from ``order``.

    ``seg`` (sources, groups + 1): where each source's points of each row group start (`_gather`);
    points not packed by rows need one band (``bands=1``) whose segment holds them all.
    ``classes[ku, kv]`` counts the points per footprint.
    """
    own = np.full(H * W if with_own else 0, EMPTY_KEY, np.int64)
    splat = np.full(H * W, EMPTY_KEY, np.int64)
    n = len(pts.pix)
    if n:
        if n >= 1 << IDX_BITS:
            raise ValueError(f"a view can z-buffer at most 2^{IDX_BITS} points, got {n}")
        k_max = k_max_of(classes)
        spans = pk.ellipse_spans(*ellipse_offsets(k_max))
        layer_of, layer_cls = _dense_classes(classes, k_max, H * W)
        layers = np.full((len(layer_cls), H * W), EMPTY_KEY, np.int64)
        bands = bands or pk.n_bands(seg.shape[1] - 1)
        pk.zbuffer_bands(pts.pix, order, pts.r, pts.ku, pts.kv, seg, k_max + 1, k_max, *spans, layer_of, H, W,
                         bands, f32(RANGE_QUANTUM_M), KEY_BASE, Q_MAX, IDX_BITS, own, splat, layers,
                         with_own)  # fmt: skip
        if len(layer_cls):
            span_start, span_dr, span_c0, span_c1 = spans
            if not (span_c0 == -span_c1).all():
                raise ValueError("footprint spans must be symmetric (-w..w) to dilate a layer")
            pk.dilate_layers(layers, layer_cls, span_start, span_dr, span_c1, H, W, splat)
    return own, splat


def k_max_of(classes: I64) -> int:
    """The largest footprint half-width with a point (0 when none)."""
    ku, kv = np.nonzero(classes)
    return int(max(ku.max(), kv.max())) if len(ku) else 0


def _dense_classes(classes: I64, k_max: int, P: int) -> tuple[I64, I64]:
    """Footprint classes whose points would write more footprint pixels than the image has: cheaper as a
    min filter over a layer of their own points (`point_kernels.dilate_layers`), the same minimum.

    Returns the layer of each class ku * (k_max + 1) + kv (-1: written point by point) and the class of
    each layer.
    """
    k1 = k_max + 1
    area = np.diff(ellipse_offsets(k_max)[0])
    n = classes[:k1, :k1].reshape(-1)
    layer_cls = np.flatnonzero(n * area > P)
    layer_of = np.full(k1 * k1, -1, np.int64)
    layer_of[layer_cls] = np.arange(len(layer_cls))
    return layer_of, layer_cls


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
    n = len(mask_pts.pix)
    whole = np.array([[0] + [n] * pk.n_groups(H)], np.int64)  # not packed by rows: one band reads them all
    k = int(max(mask_pts.ku.max(), mask_pts.kv.max())) + 1
    classes = np.bincount(mask_pts.ku.astype(np.int64) * k + mask_pts.kv, minlength=k * k).reshape(k, k)
    return zbuffer(mask_pts, np.arange(n), whole, classes, H, W, with_own=False, bands=1)[1]


@contextmanager
def threads_at_most(n: int) -> Iterator[None]:
    """Numba's thread count for this thread limited to ``n`` inside the block."""
    old = numba.get_num_threads()
    numba.set_num_threads(max(1, min(n, old)))
    try:
        yield
    finally:
        numba.set_num_threads(old)


def render_compiled(
    sources: list[ScanIndex], model: CameraModel, T_world_cam: F64, params: RenderParams,
    pixel_mask: Bool | None = None,
) -> Rendering:  # fmt: skip
    """`ingest.raster.view.render_view` with compiled kernels (see module doc); the same `Rendering`."""
    n_points = sum(s.n_points for s in sources)
    small = model.width * model.height < SMALL_VIEW_PX and n_points < SMALL_VIEW_POINTS
    with threads_at_most(1 if small else numba.get_num_threads()):
        return _render(sources, model, T_world_cam, params, pixel_mask)


def _render(
    sources: list[ScanIndex], model: CameraModel, T_world_cam: F64, params: RenderParams,
    pixel_mask: Bool | None,
) -> Rendering:  # fmt: skip
    H, W = model.height, model.width
    P = H * W
    geo = pixel_geometry(model)
    ppr = geo.ppr.reshape(-1)
    pts, order, seg, classes, mask_pts, stats = _gather(sources, model, geo, T_world_cam, params, pixel_mask)
    own_key, splat_key = zbuffer(pts, order, seg, classes, H, W)
    inv = np.empty(len(order), np.int64)
    pk.invert_order(order, inv)
    own_ok, leak = np.empty(P, bool), np.empty(P, bool)
    own_i, splat_i = np.empty(P, np.int64), np.empty(P, np.int64)
    r_own, r_splat = np.empty(P, np.float32), np.empty(P, np.float32)
    px.decode(own_key, splat_key, inv, pts.r, EMPTY_KEY, IDX_MASK, own_ok, own_i, splat_i, r_own, r_splat)
    surface = splat_key != EMPTY_KEY
    del own_key, splat_key
    tau_m, tau_rel, slope = f32(params.tau_m), f32(params.tau_rel), _slope(params)
    K = min(3, max(1, k_max_of(classes)))
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
        pk.average_bands(pts.pix, pts.u, pts.v, pts.r, seg, own2, R, gu, gv, ppr, tau_m, tau_rel,
                         f32(slope * 1.0), W, pk.n_bands(seg.shape[1] - 1), value)  # fmt: skip
    need = np.flatnonzero(surface & ~own2)
    got = _fill(value, gu, gv, need, ppr, W, params)
    raw_px = need[~got]  # a surface but no own point and no neighbour: the splat's nearest range
    value[raw_px] = r_splat[raw_px] if params.raw_fallback else np.float32(np.nan)

    # masks, clipping, colour
    rays = geo.valid if pixel_mask is None else geo.valid & pixel_mask
    surf, masked, clipped, good = (np.empty(P, bool) for _ in range(4))
    range_m = np.empty(P, np.float32)
    bgr = np.empty((P, 3), np.uint8) if params.colour else np.zeros((P, 3), np.uint8)
    clip = f32(np.inf) if params.clip_m is None else f32(params.clip_m)
    rgb = pts.rgb if len(pts.rgb) else np.zeros((1, 3), np.uint8)
    mask_key = _mask_buffer(mask_pts, H, W)
    px.finish(value, surface, own2, own_i, splat_i, rays.reshape(-1), rgb, params.colour, ppr, W, mask_key,
              mask_pts.r, mask_pts.u, mask_pts.v, EMPTY_KEY, IDX_MASK, tau_m, tau_rel, f32(slope), clip, surf,
              masked, clipped, good, range_m, bgr)  # fmt: skip
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
