"""The renderer's stages in numpy alone: the reference every other backend must match (the tests' oracle).

Each stage of `ingest.raster.recipe` is a few whole-array numpy operations
on flat (H*W,) images; the z-buffer is one compiled loop over the points
(`ingest.raster.kernels`) and the per-pixel algorithms are
`ingest.raster.visibility`'s. Slower than the compiled backend, and the
definition of what it computes (`RenderParams.backend="numpy"`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from calibration.camera import CameraModel
from calibration.transforms import invert
from calibration.types import F32, F64, I64, Bool
from ingest.raster.geometry import PixelGeometry, ViewPoints, coarse_mask, concat_points, points_in_view
from ingest.raster.lod import ScanIndex, candidates
from ingest.raster.params import RenderParams
from ingest.raster.recipe import Finished, HostArrays, OwnSamples, Winners
from ingest.raster.visibility import average_surface, fill_gaps, fit_gradient, leaks, winner, zbuffer


@dataclass(frozen=True, eq=False)
class NumpyView:
    """The points of a view and its mask points, in selection order."""

    pts: ViewPoints
    mask_pts: ViewPoints
    stats: dict[str, int] = field(default_factory=dict)

    @property
    def n(self) -> int:
        return len(self.pts.r)

    @property
    def k_max(self) -> int:
        return int(max(self.pts.ku.max(), self.pts.kv.max())) if self.n else 0


def gather(
    sources: list[ScanIndex], model: CameraModel, geo: PixelGeometry, T_world_cam: F64, params: RenderParams,
    pixel_mask: Bool | None = None,
) -> NumpyView:  # fmt: skip
    """Selected points of every scan, and every mask point, in the camera."""
    T_cam_world = invert(T_world_cam)
    coarse = None if pixel_mask is None else coarse_mask(pixel_mask, geo.stride)
    parts: list[tuple[Any, ...]] = []
    mask_parts: list[tuple[Any, ...]] = []
    stats = {"points_total": 0, "points_touched": 0, "points_in_image": 0}
    for src in sources:
        T_cam_scan = T_cam_world @ src.T_world_scan
        stats["points_total"] += src.n_points
        idx, sp = candidates(
            src, model, T_cam_scan, geo.coarse, params.points_per_px, coarse, params.frustum_culling
        )
        xyz = src.xyz[idx] if params.frustum_culling else src.xyz
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
    return NumpyView(concat_points(parts), concat_points(mask_parts), stats)


def winners(view: NumpyView, H: int, W: int) -> Winners:
    """Both z-buffers and their nearest points (index n, range inf: none)."""
    own_key, splat_key = zbuffer(view.pts, H, W)
    own_ok, own_i = winner(own_key)
    surface, splat_i = winner(splat_key)
    n = view.n
    r_all = np.r_[view.pts.r, np.float32(np.inf)]  # index n: no point
    own_i = np.where(own_ok, own_i, n)
    splat_i = np.where(surface, splat_i, n)
    return Winners(own_ok, own_i, splat_i, r_all[own_i], r_all[splat_i], surface)


def leaking(view: NumpyView, win: Winners, ppr: F32, params: RenderParams, W: int, K: int) -> Bool:
    """Own points behind a nearer splat, with nearer own points around them: seen through a surface."""
    r_own, r_splat, pts = win.r_own, win.r_splat, view.pts
    H = len(r_own) // W
    tol_min = params.tolerance(r_splat, params.LEAK_MIN_PX, ppr)
    cand = np.flatnonzero(win.own_ok & (r_own > r_splat + tol_min))
    leak = np.zeros(H * W, bool)
    if cand.size:
        cu, cv = np.divmod(cand, W)[::-1]
        s = win.splat_i[cand]
        d = np.hypot(pts.u[s] - cu, pts.v[s] - cv)
        behind = r_own[cand] > r_splat[cand] + params.tolerance(r_splat[cand], d + params.HALF_PX, ppr[cand])
        cand = cand[behind]
        thr = r_own[cand] - params.tolerance(r_own[cand], K + params.HALF_PX, ppr[cand])
        leak[cand[leaks(r_own.reshape(H, W), cand, thr, K)]] = True
    return leak


def own_samples(view: NumpyView, win: Winners, leak: Bool, W: int) -> OwnSamples:
    """The own points left after the leak test: range and offset from the pixel centre (NaN, 0: none)."""
    ok = win.own_ok & ~leak
    own_i = np.where(ok, win.own_i, view.n)
    u_all = np.r_[view.pts.u, np.float32(0.0)]
    v_all = np.r_[view.pts.v, np.float32(0.0)]
    row, col = np.divmod(np.arange(len(ok)), W)
    R = np.where(ok, win.r_own, np.float32(np.nan))
    U = np.where(ok, u_all[own_i] - col.astype(np.float32), np.float32(0.0))
    V = np.where(ok, v_all[own_i] - row.astype(np.float32), np.float32(0.0))
    return OwnSamples(ok, R, U, V)


def gradient_value(own: OwnSamples, ppr: F32, params: RenderParams, W: int) -> tuple[F32, F32, F32]:
    """The fitted gradient (`visibility.fit_gradient`, 0 when off) and the value on the pixel-centre ray."""
    shape = (-1, W)
    R, U, V = own.R.reshape(shape), own.U.reshape(shape), own.V.reshape(shape)
    flat = np.zeros(R.shape, np.float32)  # points on pixel-centre rays need no gradient
    gu, gv = fit_gradient(R, U, V, ppr.reshape(shape), params) if params.fit_gradient else (flat, flat)
    value = (R - gu * U - gv * V).astype(np.float32)
    return gu.reshape(-1), gv.reshape(-1), value.reshape(-1)


def average(
    view: NumpyView, own: OwnSamples, gu: F32, gv: F32, value: F32, ppr: F32, params: RenderParams, W: int
) -> F32:
    """`visibility.average_surface` on flat images."""
    shape = (-1, W)
    out = average_surface(view.pts, value.reshape(shape), own.ok.reshape(shape), own.R.reshape(shape),
                          gu.reshape(shape), gv.reshape(shape), ppr.reshape(shape), params)  # fmt: skip
    return out.reshape(-1)


def fill(
    value: F32, own: OwnSamples, gu: F32, gv: F32, need: I64, ppr: F32, params: RenderParams, W: int
) -> tuple[F32, Bool]:
    """`visibility.fill_gaps` on flat images."""
    shape = (-1, W)
    out, got = fill_gaps(value.reshape(shape), own.ok.reshape(shape), gu.reshape(shape), gv.reshape(shape),
                         need, ppr.reshape(shape), params)  # fmt: skip
    return out.reshape(-1), got


def masked(mask_pts: ViewPoints, surf: Bool, value: F32, ppr: F32, params: RenderParams, W: int) -> Bool:
    """Surface pixels whose value lies on (or behind) a mask cloud's surface: reflective or transparent."""
    P = len(surf)
    if not len(mask_pts.pix):
        return np.zeros(P, bool)
    _, mask_key = zbuffer(mask_pts, P // W, W)
    m_ok, m_i = winner(mask_key)
    m_i = np.where(m_ok, m_i, len(mask_pts.r))
    r_mask = np.r_[mask_pts.r, np.float32(np.inf)][m_i]
    row, col = np.divmod(np.arange(P), W)
    d_mask = np.hypot(np.r_[mask_pts.u, 0.0][m_i] - col.astype(np.float32),
                      np.r_[mask_pts.v, 0.0][m_i] - row.astype(np.float32))  # fmt: skip
    with np.errstate(invalid="ignore"):
        out: Bool = surf & (r_mask <= value + params.tolerance(value, d_mask + params.HALF_PX, ppr))
    return out


def finish(
    view: NumpyView, value: F32, win: Winners, own: OwnSamples, rays: Bool, ppr: F32, params: RenderParams,
    W: int,
) -> Finished:  # fmt: skip
    """Masks, clipping, the valid ranges and the colours."""
    surf = win.surface & rays.reshape(-1)
    mask = masked(view.mask_pts, surf, value, ppr, params, W)
    clipped = np.zeros(len(surf), bool)
    if params.clip_m is not None:  # "drop" removed the far points; planar fills may still pass clip_m
        clipped = surf & ~mask & (value > params.clip_m)
    good = surf & ~mask & ~clipped & np.isfinite(value) & (value > 0)
    range_m = np.where(good, value, np.float32(0.0))
    bgr = np.zeros((len(surf), 3), np.uint8)
    if view.n and params.colour:  # the own point's colour, else the splat's
        src = np.where(own.ok, win.own_i, win.splat_i)
        show = np.flatnonzero(surf)
        bgr[show] = view.pts.rgb[src[show]][:, ::-1]
    return Finished(surf, mask, clipped, good, range_m, bgr)


class NumpyStages(HostArrays):
    """The numpy stages as `ingest.raster.recipe.Stages`."""

    gather = staticmethod(gather)
    winners = staticmethod(winners)
    leaking = staticmethod(leaking)
    own_samples = staticmethod(own_samples)
    gradient_value = staticmethod(gradient_value)
    average = staticmethod(average)
    fill = staticmethod(fill)
    finish = staticmethod(finish)
