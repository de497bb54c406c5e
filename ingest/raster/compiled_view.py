"""The renderer's stages as compiled kernels (`RenderParams.backend="numba"`), each one parallel pass.

Same stages (`ingest.raster.recipe`), same numbers as the numpy reference
(`ingest.raster.reference`): level-of-detail selection and the camera
model's projection stay numpy (one vectorised call each); the transform,
view test and footprints of the points (`ingest.raster.point_kernels`), the
z-buffers, the leak test, the gradient fit, the same-surface average, the
gap fill and the masks (`ingest.raster.pixel_kernels`) are numba loops that
touch each point or pixel once instead of once per numpy operation. The
recipe's thresholds reach the kernels as arguments, from `RenderParams`.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np

from calibration.camera import CameraModel
from calibration.fisheye import DoubleSphere
from calibration.kernels import fork_safe_numba_threads
from calibration.transforms import invert
from calibration.types import F32, F64, I64, Bool
from calibration.virtual import project_f32
from ingest.raster import pixel_kernels as px
from ingest.raster import point_kernels as pk
from ingest.raster import recipe
from ingest.raster.geometry import (
    PixelGeometry,
    Rendering,
    ViewPoints,
    coarse_mask,
    concat_points,
    points_in_view,
)
from ingest.raster.kernels import ellipse_offsets
from ingest.raster.lod import ScanIndex, candidates
from ingest.raster.params import EMPTY_KEY, IDX_BITS, IDX_MASK, KEY_BASE, Q_MAX, RANGE_QUANTUM_M, RenderParams
from ingest.raster.recipe import Finished, HostArrays, OwnSamples, Winners

fork_safe_numba_threads()  # before any parallel kernel runs in this process

f32 = np.float32
# Smaller views run their kernels on one thread: starting a parallel region costs tens of
# microseconds on an idle machine and milliseconds on a busy one, more than such a view saves.
SMALL_VIEW_PX = 250_000
SMALL_VIEW_POINTS = 1_000_000


def _selected_in_view(
    src: ScanIndex, idx: I64, sp: F32, model: CameraModel, geo: PixelGeometry, T_cam_scan: F64,
    params: RenderParams,
) -> tuple[Any, ...]:  # fmt: skip
    """`geometry.points_in_view` of ``src.xyz[idx]`` in compiled passes, packed by row group.

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
    else:  # the reference's numpy projection: a float32 arctan2 (equirect, Cassini) in a numba kernel is
        # libm's, an ulp off numpy's for ~40 % of points, which moves some across a pixel edge
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


@dataclass(frozen=True, eq=False)
class CompiledView:
    """The points of a view packed by row group, and its mask points.

    ``order``: each point's index in selection order; ``seg`` (sources, groups + 1): where each
    source's points of each row group start; ``classes[ku, kv]``: points per footprint.
    """

    pts: ViewPoints
    order: I64
    seg: I64
    classes: I64
    mask_pts: ViewPoints
    stats: dict[str, int]

    @property
    def n(self) -> int:
        return len(self.pts.r)

    @property
    def k_max(self) -> int:
        return k_max_of(self.classes)


def gather(
    sources: list[ScanIndex], model: CameraModel, geo: PixelGeometry, T_world_cam: F64, params: RenderParams,
    pixel_mask: Bool | None,
) -> CompiledView:  # fmt: skip
    """`reference.gather`: every scan's selected points (by row group), their order, group starts and
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
        idx, sp = candidates(
            src, model, T_cam_scan, geo.coarse, params.points_per_px, coarse, params.frustum_culling
        )
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
    return CompiledView(concat_points(parts), order_all, seg, classes, concat_points(mask_parts), stats)


def zbuffer(
    pts: ViewPoints, order: I64, seg: I64, classes: I64, H: int, W: int, with_own: bool = True,
    bands: int | None = None,
) -> tuple[I64, I64]:  # fmt: skip
    """`visibility.zbuffer` in parallel bands: the same (own, splat) key images, indices from ``order``.

    ``seg`` (sources, groups + 1): where each source's points of each row group start (`gather`);
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


def winners(view: CompiledView, H: int, W: int) -> Winners:
    """Both z-buffers in parallel bands, decoded: nearest points (index n, range inf: none)."""
    P = H * W
    own_key, splat_key = zbuffer(view.pts, view.order, view.seg, view.classes, H, W)
    inv = np.empty(len(view.order), np.int64)
    pk.invert_order(view.order, inv)
    own_ok = np.empty(P, bool)
    own_i, splat_i = np.empty(P, np.int64), np.empty(P, np.int64)
    r_own, r_splat = np.empty(P, np.float32), np.empty(P, np.float32)
    r = view.pts.r
    px.decode(own_key, splat_key, inv, r, EMPTY_KEY, IDX_MASK, own_ok, own_i, splat_i, r_own, r_splat)
    return Winners(own_ok, own_i, splat_i, r_own, r_splat, splat_key != EMPTY_KEY)


def leaking(view: CompiledView, win: Winners, ppr: F32, params: RenderParams, W: int, K: int) -> Bool:
    """`reference.leaking` per pixel (`pixel_kernels.leaking`)."""
    leak = np.empty(len(ppr), bool)
    slope = params.incidence_slope
    px.leaking(win.own_ok, win.r_own, win.r_splat, win.splat_i, view.pts.u, view.pts.v, ppr, W, K,
               f32(params.tau_m), f32(params.tau_rel), slope, f32(slope * params.LEAK_MIN_PX),
               f32(slope * (K + params.HALF_PX)), params.HALF_PX, leak)  # fmt: skip
    return leak


def own_samples(view: CompiledView, win: Winners, leak: Bool, W: int) -> OwnSamples:
    """`reference.own_samples` per pixel (`pixel_kernels.own_samples`)."""
    P = len(leak)
    ok = np.empty(P, bool)
    R, U, V = (np.empty(P, np.float32) for _ in range(3))
    px.own_samples(win.own_ok, leak, win.own_i, view.pts.r, view.pts.u, view.pts.v, W, ok, R, U, V)
    return OwnSamples(ok, R, U, V)


def gradient_value(own: OwnSamples, ppr: F32, params: RenderParams, W: int) -> tuple[F32, F32, F32]:
    """`reference.gradient_value` per pixel (`pixel_kernels.gradient_value`)."""
    gu, gv, value = (np.empty(len(ppr), np.float32) for _ in range(3))
    gates = (f32(params.GATE_DIRECT_PX), f32(params.GATE_DIAGONAL_PX))
    fit_min = (params.FIT_MIN_DET, params.FIT_MIN_AXIS)
    tol = (f32(params.tau_m), f32(params.tau_rel), f32(params.incidence_slope))
    px.gradient_value(own.R, own.U, own.V, ppr, W, *tol, *gates, *fit_min, params.fit_gradient, gu, gv, value)
    return gu, gv, value


def average(
    view: CompiledView, own: OwnSamples, gu: F32, gv: F32, value: F32, ppr: F32, params: RenderParams, W: int
) -> F32:
    """`reference.average` in bands of row groups (`point_kernels.average_bands`), in place."""
    slope = f32(params.incidence_slope * params.SAME_SURFACE_PX)
    pts, seg = view.pts, view.seg
    pk.average_bands(pts.pix, pts.u, pts.v, pts.r, seg, own.ok, own.R, gu, gv, ppr, f32(params.tau_m),
                     f32(params.tau_rel), slope, W, pk.n_bands(seg.shape[1] - 1), value)  # fmt: skip
    return value


def fill(
    value: F32, own: OwnSamples, gu: F32, gv: F32, need: I64, ppr: F32, params: RenderParams, W: int
) -> tuple[F32, Bool]:
    """`reference.fill` in place on flat images (`pixel_kernels.fill_pass`); which pixels of ``need`` got a
    value."""
    got_all = np.zeros(len(need), bool)
    todo = np.arange(len(need))
    weight = np.array(params.fill_weights, np.float32)
    c = (f32(params.tau_m), f32(params.tau_rel), f32(params.incidence_slope * params.FILL_TOLERANCE_PX))
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
    return value, got_all


def finish(
    view: CompiledView, value: F32, win: Winners, own: OwnSamples, rays: Bool, ppr: F32, params: RenderParams,
    W: int,
) -> Finished:  # fmt: skip
    """`reference.finish` per pixel (`pixel_kernels.finish`)."""
    P = len(value)
    H = P // W
    surf, masked, clipped, good = (np.empty(P, bool) for _ in range(4))
    range_m = np.empty(P, np.float32)
    bgr = np.empty((P, 3), np.uint8) if params.colour else np.zeros((P, 3), np.uint8)
    clip = f32(np.inf) if params.clip_m is None else f32(params.clip_m)
    rgb = view.pts.rgb if len(view.pts.rgb) else np.zeros((1, 3), np.uint8)
    mask_pts = view.mask_pts
    mask_key = _mask_buffer(mask_pts, H, W)
    tol = (f32(params.tau_m), f32(params.tau_rel), f32(params.incidence_slope), f32(params.HALF_PX))
    px.finish(value, win.surface, own.ok, win.own_i, win.splat_i, rays.reshape(-1), rgb, params.colour, ppr,
              W, mask_key, mask_pts.r, mask_pts.u, mask_pts.v, EMPTY_KEY, IDX_MASK, *tol, clip, surf, masked,
              clipped, good, range_m, bgr)  # fmt: skip
    return Finished(surf, masked, clipped, good, range_m, bgr)


class CompiledStages(HostArrays):
    """The compiled stages as `ingest.raster.recipe.Stages`."""

    gather = staticmethod(gather)
    winners = staticmethod(winners)
    leaking = staticmethod(leaking)
    own_samples = staticmethod(own_samples)
    gradient_value = staticmethod(gradient_value)
    average = staticmethod(average)
    fill = staticmethod(fill)
    finish = staticmethod(finish)


def render_compiled(
    sources: list[ScanIndex], model: CameraModel, T_world_cam: F64, params: RenderParams,
    pixel_mask: Bool | None = None,
) -> Rendering:  # fmt: skip
    """`ingest.raster.recipe.render` with the compiled stages; small views on one thread."""
    n_points = sum(s.n_points for s in sources)
    small = model.width * model.height < SMALL_VIEW_PX and n_points < SMALL_VIEW_POINTS
    with threads_at_most(1 if small else numba.get_num_threads()):
        return recipe.render(CompiledStages(), sources, model, T_world_cam, params, pixel_mask)
