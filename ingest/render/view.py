"""Render a view of dense scans: RGB + range per pixel, with splats, a z-buffer and masks.

Recipe for one camera (any `CameraModel`: fisheye, equirect, Cassini, pinhole,
crops) at `T_world_cam`:

1. Select: every scan of the bundle gives the points the view needs
   (`ingest.render.lod.select`: frustum culling of voxel buckets and a prefix
   per bucket for about `points_per_px` points per pixel).
2. Project: points into the camera (float32), range from the camera centre,
   and each point's footprint in pixels along u and v: its spacing on the
   surface (scanner angular spacing times its range from its own scanner)
   over its range from the camera, times the camera's local pixels per radian.
3. Z-buffer: a point's key packs its range (0.1 mm steps) above its index in
   one int64, so a per-pixel minimum (`np.minimum.at`) yields both the nearest
   range and which point it is. Two buffers: "own", the nearest point inside
   each pixel, and "splat", the nearest point whose footprint covers it.
   Splats are image-space: points are grouped by footprint half-widths
   (ku, kv) and each group's buffer is eroded (min filter, cv2.erode on the
   keys viewed as float64, which orders positive keys the same) by an ellipse
   of that size: one erode per group instead of one write per covered pixel.
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
   (a few passes outwards), else the splat's raw range.
6. Masks: mask points (a label) and mask clouds render into their own splat
   buffer; pixels whose mask surface is not behind the rendered one are
   invalid. Ranges beyond `clip_m` are invalid (`clip_mode="invalid"`, colour
   kept) or their points are not rendered at all (`"drop"`).

Every pixel with a ray ends as a surface with a range, masked, clipped, or a
hole (no data). RGB is the own point's colour, else the splat's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property, lru_cache
from typing import Any, Literal

import cv2
import numpy as np

from calibration.camera import CameraModel
from calibration.transforms import invert
from calibration.types import F32, F64, I64, U8, Bool
from calibration.virtual import project_f32
from ingest.render.lod import ScanIndex, select

I16 = np.ndarray[Any, np.dtype[np.int16]]
RANGE_QUANTUM_M = 1e-4  # z-buffer key resolution
_IDX_BITS = 28  # points per buffer per view < 2^28
_Q_MAX = (1 << 25) - 1  # ranges up to 3.3 km
# Keys sit above the bit pattern of 1.0 so, viewed as float64, they are normal positive numbers
# ordered like the integers; the empty key is the pattern of +inf.
_KEY_BASE = 0x3FF0_0000_0000_0000
_EMPTY = 0x7FF0_0000_0000_0000
PPR_STRIDE = 8  # coarse pixels-per-radian map: one node every 8 pixels
# Oversampled corners of an image (a Cassini's or equirect's poles) get no more points per solid
# angle than this many times the image's median resolution: there splats close the surface, and
# a 195-degree Cassini window stays at ~2 points per pixel instead of drawing the whole scan.
LOD_PPR_CAP = 2.0


@dataclass(frozen=True)
class RenderParams:
    """Renderer settings (metres, pixels)."""

    points_per_px: float | None = 2.0  # LOD density target; None = every point in the frustum
    splat_scale: float = 1.5  # footprint half-width = scale x point spacing in the image (random points)
    max_splat_px: int = 6
    near_m: float = 0.05  # points nearer to the camera centre are ignored
    tau_m: float = 0.01  # same-surface tolerance, see `tolerance`
    tau_rel: float = 0.01
    max_incidence_deg: float = 80.0
    clip_m: float | None = None
    clip_mode: Literal["invalid", "drop"] = "invalid"
    fill_passes: int = 3
    average_samples: bool = True  # mean of a pixel's same-surface samples, not just the nearest
    frustum_culling: bool = True  # False: project every point of every scan (the naive baseline)

    def tolerance(self, range_m: Any, dist_px: Any, ppr: Any) -> Any:
        """Largest range difference (m) between two samples of one surface ``dist_px`` apart.

        tau_m + range * (tau_rel + tan(max_incidence) * dist_px / ppr): the
        slope term admits surfaces up to `max_incidence_deg` from the view ray.
        """
        slope = math.tan(math.radians(self.max_incidence_deg))
        return self.tau_m + range_m * (self.tau_rel + slope * dist_px / ppr)


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


@lru_cache(maxsize=24)
def pixel_geometry(model: CameraModel) -> PixelGeometry:
    """Cached per (hashable) model: ray validity of every pixel and local angular resolution."""
    _, valid = model.unproject(model.pixel_grid())
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
class _Points:
    """Points in the image: flat pixel, sub-pixel position, range, footprint half-widths, colour, mask."""

    pix: I64
    u: F32
    v: F32
    r: F32
    ku: I16
    kv: I16
    rgb: U8
    masked: Bool


def _points_in_view(
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


def _coarse_mask(mask: Bool, stride: int) -> Bool:
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
) -> tuple[_Points, _Points, dict[str, int]]:
    """Selected points of every scan, and every mask point, in the camera."""
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
            xyz = src.xyz[idx]
        else:  # the naive baseline: every point, with its bucket's spacing
            idx = np.arange(src.n_points)
            sp = np.repeat(src.voxel_spacing_rad, np.diff(src.voxel_start))
            xyz = src.xyz
        stats["points_touched"] += len(idx)
        *proj, kept = _points_in_view(model, geo, T_cam_scan, xyz, sp, params)
        stats["points_in_image"] += len(kept)
        sel_idx = idx[kept]
        masked = src.masked[sel_idx] if src.masked is not None else np.zeros(len(kept), bool)
        parts.append((*proj, src.rgb[sel_idx], masked))
        if masked.any():  # labelled points render into the mask buffer too
            mask_parts.append(tuple(a[masked] for a in parts[-1]))
        if len(src.mask_xyz):
            *mproj, mkept = _points_in_view(
                model, geo, T_cam_scan, src.mask_xyz, src.mask_spacing_rad, params
            )
            mask_parts.append((*mproj, np.zeros((len(mkept), 3), np.uint8), np.ones(len(mkept), bool)))
    return _concat(parts), _concat(mask_parts), stats


def _concat(parts: list[tuple[Any, ...]]) -> _Points:
    if not parts:
        f, i, k = np.zeros(0, np.float32), np.zeros(0, np.int64), np.zeros(0, np.int16)
        return _Points(i, f, f, f, k, k, np.zeros((0, 3), np.uint8), np.zeros(0, bool))
    if len(parts) == 1:
        return _Points(*parts[0])
    return _Points(*(np.concatenate([p[k] for p in parts]) for k in range(8)))


def _zbuffer(pts: _Points, H: int, W: int) -> tuple[I64, I64]:
    """(own, splat) int64 key images, flat (H*W,); `_EMPTY` where no point.

    key = BASE + (round(range / RANGE_QUANTUM_M) << 28) + point index: the
    minimum key is the nearest point, and the key names it.
    """
    P = H * W
    own = np.full(P, _EMPTY, np.int64)
    splat = np.full(P, _EMPTY, np.int64)
    n = len(pts.pix)
    if n == 0:
        return own, splat
    if n >= 1 << _IDX_BITS:
        raise ValueError(f"a view can z-buffer at most 2^{_IDX_BITS} points, got {n}")
    q = np.minimum(np.round(pts.r / np.float32(RANGE_QUANTUM_M)).astype(np.int64), _Q_MAX)
    key = _KEY_BASE + (q << _IDX_BITS) + np.arange(n, dtype=np.int64)
    K = int(max(pts.ku.max(), pts.kv.max())) + 1
    cls = pts.ku * K + pts.kv
    order = np.argsort(cls, kind="stable")
    bounds = np.r_[0, np.cumsum(np.bincount(cls, minlength=K * K))]
    layer = np.empty(P, np.int64)
    for c in np.flatnonzero(np.diff(bounds)):
        sel = order[bounds[c] : bounds[c + 1]]
        pix = pts.pix[sel]
        layer.fill(_EMPTY)
        np.minimum.at(layer, pix, key[sel])
        np.minimum(own, layer, out=own)
        ku, kv = divmod(int(c), K)
        if ku == 0 and kv == 0:
            np.minimum(splat, layer, out=splat)
            continue
        # erode only the window holding this group's points (plus the kernel)
        rows = pix // W
        cols = pix - rows * W
        r0, r1 = max(0, int(rows.min()) - kv), min(H, int(rows.max()) + kv + 1)
        c0, c1 = max(0, int(cols.min()) - ku), min(W, int(cols.max()) + ku + 1)
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * ku + 1, 2 * kv + 1))
        win = layer.view(np.float64).reshape(H, W)[r0:r1, c0:c1]
        eroded = cv2.erode(win, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=np.inf)
        target = splat.reshape(H, W)[r0:r1, c0:c1]
        np.minimum(target, eroded.view(np.int64), out=target)
    return own, splat


def _winner(key: I64) -> tuple[Bool, I64]:
    """(has a point, index of the point) per pixel of a key image."""
    return key != _EMPTY, key & ((1 << _IDX_BITS) - 1)


def _pad(img: np.ndarray[Any, Any], k: int, fill: Any) -> np.ndarray[Any, Any]:
    return np.pad(img, k, mode="constant", constant_values=fill)


def _padded_index(flat: I64, W: int, k: int) -> I64:
    row, col = np.divmod(flat, W)
    out: I64 = (row + k) * (W + 2 * k) + col + k
    return out


_AXES = ((0, 1), (1, 0), (1, 1), (1, -1))  # 4 axes through a pixel (drow, dcol)
_NB8 = ((0, 1), (0, -1), (1, 0), (-1, 0), (1, 1), (-1, -1), (1, -1), (-1, 1))  # opposite pairs adjacent


def _leaks(r_own: F32, candidates: I64, thr: F32, K: int) -> Bool:
    """For flat pixels ``candidates``: own points nearer than ``thr`` on two opposite sides within K px."""
    W = r_own.shape[1]
    rp = _pad(r_own, K, np.inf).reshape(-1)
    Wp = W + 2 * K
    pc = _padded_index(candidates, W, K)
    out = np.zeros(len(candidates), bool)
    for dr, dc in _AXES:
        a = np.zeros(len(candidates), bool)
        b = np.zeros(len(candidates), bool)
        for t in range(1, K + 1):
            off = t * (dr * Wp + dc)
            a |= rp[pc + off] < thr
            b |= rp[pc - off] < thr
        out |= a & b
    return out


def _solve_gradient(a11: Any, a12: Any, a22: Any, b1: Any, b2: Any) -> tuple[Any, Any, Any]:
    """2x2 least squares per pixel; one axis alone where only it is determined. Returns (gu, gv, solved)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        det = a11 * a22 - a12 * a12
        full = det > 0.25
        inv = np.where(full, 1.0 / np.where(full, det, 1.0), 0.0)
        gu = (a22 * b1 - a12 * b2) * inv
        gv = (a11 * b2 - a12 * b1) * inv
        only_u = ~full & (a11 > 0.25)
        only_v = ~full & (a22 > 0.25)
        gu = np.where(only_u, b1 / np.where(only_u, a11, 1.0), gu)
        gv = np.where(only_v, b2 / np.where(only_v, a22, 1.0), gv)
    return gu, gv, full


def _gradient(R: F32, U: F32, V: F32, ppr: F32, params: RenderParams) -> tuple[F32, F32]:
    """Range gradient (m per pixel along u, v) from each pixel's neighbours on the same surface.

    R holds each pixel's own point range (NaN where none) at sub-pixel offset
    (U, V) from the pixel centre. Least squares over the 4-neighbours within
    the same-surface tolerance; where those do not determine both components
    (sparse points), the diagonal neighbours join. 0 where nothing does.
    """
    H, W = R.shape
    Rp, Up, Vp = _pad(R, 1, np.nan), _pad(U, 1, 0.0), _pad(V, 1, 0.0)
    acc = [np.zeros((H, W), np.float32) for _ in range(5)]  # a11, a12, a22, b1, b2
    # same-surface gate: a generous bound on the neighbour distance (offsets are within +-0.5 px)
    slope = (params.tolerance(1.0, 1.0, ppr) - params.tau_m).astype(np.float32)  # per metre and pixel
    gate = params.tau_m + R * slope * np.float32(1.6)
    with np.errstate(invalid="ignore"):
        for dr, dc in _NB8[:4]:
            win = (slice(1 + dr, H + 1 + dr), slice(1 + dc, W + 1 + dc))
            dR = Rp[win] - R
            ok = np.abs(dR) <= gate
            du = (dc + Up[win] - U) * ok
            dv = (dr + Vp[win] - V) * ok
            dR = np.where(ok, dR, np.float32(0.0))
            for a, term in zip(acc, (du * du, du * dv, dv * dv, du * dR, dv * dR), strict=True):
                a += term
    gu, gv, full = _solve_gradient(*acc)
    weak = np.flatnonzero(~full & np.isfinite(R))
    if weak.size:  # add the diagonal neighbours, for these pixels only
        pw = _padded_index(weak, W, 1)
        Rf, Uf, Vf = Rp.reshape(-1), Up.reshape(-1), Vp.reshape(-1)
        r0, u0, v0 = Rf[pw], Uf[pw], Vf[pw]
        sub = [a.reshape(-1)[weak].astype(np.float64) for a in acc]
        g = params.tau_m + r0 * slope.reshape(-1)[weak] * 2.2
        with np.errstate(invalid="ignore"):
            for dr, dc in _NB8[4:]:
                q = pw + dr * (W + 2) + dc
                dR = Rf[q] - r0
                ok = np.abs(dR) <= g
                du, dv, dR = (dc + Uf[q] - u0) * ok, (dr + Vf[q] - v0) * ok, np.where(ok, dR, 0.0)
                for a, term in zip(sub, (du * du, du * dv, dv * dv, du * dR, dv * dR), strict=True):
                    a += term
        wu, wv, _ = _solve_gradient(*sub)
        gu.reshape(-1)[weak] = wu
        gv.reshape(-1)[weak] = wv
    return gu.astype(np.float32), gv.astype(np.float32)


def _average(pts: _Points, value: F32, own_ok: Bool, R: F32, gu: F32, gv: F32, ppr: F32,
             params: RenderParams) -> F32:  # fmt: skip
    """Mean of every same-surface point in each pixel, each moved to the pixel centre along the gradient.

    With range noise this removes the nearest-point bias and divides the
    noise by the square root of the points per pixel.
    """
    H, W = value.shape
    flat = own_ok.reshape(-1)[pts.pix]
    idx = np.flatnonzero(flat)
    pix = pts.pix[idx]
    ref = R.reshape(-1)[pix]
    r = pts.r[idx]
    same = r <= ref + params.tolerance(ref, 1.0, ppr.reshape(-1)[pix])
    pix, r, idx = pix[same], r[same], idx[same]
    row, col = np.divmod(pix, W)
    corrected = r - gu.reshape(-1)[pix] * (pts.u[idx] - col) - gv.reshape(-1)[pix] * (pts.v[idx] - row)
    sums = np.bincount(pix, corrected, minlength=H * W)
    counts = np.bincount(pix, minlength=H * W)
    got = counts > 0
    out: F32 = np.where(got, sums / np.maximum(counts, 1), value.reshape(-1)).astype(np.float32)
    return out.reshape(H, W)


def _fill(value: F32, has: Bool, gu: F32, gv: F32, need: I64, ppr: F32,
          params: RenderParams) -> tuple[F32, Bool]:  # fmt: skip
    """Give the flat pixels ``need`` the planar prediction of their 8-neighbours, passes outwards.

    Each valued neighbour predicts value + gradient * offset. Predictions
    within the tolerance of the nearest one form the near group; it wins
    where it surrounds the pixel (an opposite pair) or nothing else is there,
    else the far group does: a gap inside a surface takes that surface, a
    pixel beside a silhouette keeps its background. Returns the new value
    image and which pixels of ``need`` got one.
    """
    H, W = value.shape
    Wp = W + 2
    vp = _pad(np.where(has, value, np.nan), 1, np.nan).reshape(-1)
    gup, gvp = _pad(gu, 1, 0.0).reshape(-1), _pad(gv, 1, 0.0).reshape(-1)
    pn = _padded_index(need, W, 1)
    got_all = np.zeros(len(need), bool)
    todo = np.arange(len(need))
    offs = np.array([dr * Wp + dc for dr, dc in _NB8])
    drs = np.array([dr for dr, _ in _NB8], np.float32)[:, None]
    dcs = np.array([dc for _, dc in _NB8], np.float32)[:, None]
    weight = np.array([1.0] * 4 + [1.0 / math.sqrt(2.0)] * 4, np.float32)[:, None]
    ppr_n = ppr.reshape(-1)[need]
    for _ in range(params.fill_passes):
        if todo.size == 0:
            break
        nb = pn[todo][None, :] + offs[:, None]  # (8, n)
        gnu, gnv = gup[nb], gvp[nb]
        pred = vp[nb] - gnu * dcs - gnv * drs
        fin = np.isfinite(pred)
        nearest = np.min(np.where(fin, pred, np.inf), axis=0)
        tol = params.tolerance(nearest, 1.5, ppr_n[todo])
        with np.errstate(invalid="ignore"):
            in_near = fin & (pred <= nearest + tol)
            in_far = fin & ~in_near
            pairs = (in_near[0::2] & in_near[1::2]).any(axis=0)
            use_far = ~pairs & in_far.any(axis=0)
            if use_far.any():
                far = np.min(np.where(in_far, pred, np.inf), axis=0)
                in_far &= pred <= far + params.tolerance(far, 1.5, ppr_n[todo])
        w = weight * np.where(use_far, in_far, in_near)
        wsum = w.sum(axis=0)
        got = wsum > 0
        safe = np.where(got, wsum, 1.0)
        new_v = (w * np.nan_to_num(pred)).sum(axis=0) / safe
        new_gu = (w * gnu).sum(axis=0) / safe
        new_gv = (w * gnv).sum(axis=0) / safe
        # write after the pass: every prediction of a pass reads the previous pass
        done = todo[got]
        vp[pn[done]] = new_v[got]
        gup[pn[done]] = new_gu[got]
        gvp[pn[done]] = new_gv[got]
        got_all[done] = True
        todo = todo[~got]
    out: F32 = vp.reshape(H + 2, W + 2)[1:-1, 1:-1].astype(np.float32)
    return out, got_all


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
    H, W = model.height, model.width
    geo = pixel_geometry(model)
    ppr = geo.ppr
    pts, mask_pts, stats = _gather(sources, model, geo, T_world_cam, params, pixel_mask)
    own_key, splat_key = _zbuffer(pts, H, W)
    own_ok, own_i = _winner(own_key)
    surface, splat_i = _winner(splat_key)
    del own_key, splat_key
    n = len(pts.r)
    r_all = np.r_[pts.r, np.float32(np.inf)]  # index n: no point
    own_i = np.where(own_ok, own_i, n)
    splat_i = np.where(surface, splat_i, n)

    # occlusion: own points behind a nearer splat, with nearer own points around them, are leaks
    r_own = r_all[own_i]
    r_splat = r_all[splat_i]
    cand = np.flatnonzero(own_ok & (r_own > r_splat + params.tolerance(r_splat, 1.0, ppr.reshape(-1))))
    leak = np.zeros(H * W, bool)
    if cand.size:
        cu, cv = np.divmod(cand, W)[::-1]
        d = np.hypot(pts.u[splat_i[cand]] - cu, pts.v[splat_i[cand]] - cv)
        behind = r_own[cand] > r_splat[cand] + params.tolerance(r_splat[cand], d + 0.5, ppr.reshape(-1)[cand])
        cand = cand[behind]
        K = int(min(3, max(1, int(pts.ku.max()), int(pts.kv.max()))))
        thr = r_own[cand] - params.tolerance(r_own[cand], K + 0.5, ppr.reshape(-1)[cand])
        leak[cand[_leaks(r_own.reshape(H, W), cand, thr, K)]] = True
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
    gu, gv = _gradient(R, U, V, ppr, params)
    value = (R - gu * U - gv * V).astype(np.float32)
    if params.average_samples and n:
        value = _average(pts, value, own2, R, gu, gv, ppr, params)
    need = np.flatnonzero(surface & ~own_ok)
    value, got = _fill(value, own2, gu, gv, need, ppr, params)
    raw_px = need[~got]  # a surface but no own point and no neighbour: the splat's nearest range
    value.reshape(-1)[raw_px] = r_splat[raw_px]

    # masks and clipping
    rays = geo.valid if pixel_mask is None else geo.valid & pixel_mask
    surf = surface.reshape(H, W) & rays
    masked = np.zeros((H, W), bool)
    if len(mask_pts.pix):
        _, mask_key = _zbuffer(mask_pts, H, W)
        m_ok, m_i = _winner(mask_key)
        m_i = np.where(m_ok, m_i, len(mask_pts.r))
        r_mask = np.r_[mask_pts.r, np.float32(np.inf)][m_i].reshape(H, W)
        d_mask = np.hypot(np.r_[mask_pts.u, 0.0][m_i].reshape(H, W) - cols,
                          np.r_[mask_pts.v, 0.0][m_i].reshape(H, W) - rows)  # fmt: skip
        with np.errstate(invalid="ignore"):
            masked = surf & (r_mask <= value + params.tolerance(value, d_mask + 0.5, ppr))
    clipped = np.zeros((H, W), bool)
    if params.clip_m is not None:  # "drop" removed the far points; planar fills may still pass clip_m
        clipped = surf & ~masked & (value > params.clip_m)
    good = surf & ~masked & ~clipped & np.isfinite(value) & (value > 0)
    range_m = np.where(good, value, np.float32(0.0))

    # colour: the own point, else the splat's
    bgr = np.zeros((H * W, 3), np.uint8)
    if n:
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
