"""The renderer's stages in PyTorch: the recipe on tensors of any device (CPU in CI, CUDA on a GPU).

`RenderParams.backend` "torch" runs it on the CPU, "cuda" on the GPU. The
level-of-detail selection stays on the host (numpy, voxel level: small);
the points' transform, projection, view test and footprints, the z-buffers
(int64 keys reduced by ``scatter_reduce(amin)``), the leak test, gradient
fit, same-surface average, gap fill, masks and colour run on the device as
whole-tensor operations, the numpy reference's (`ingest.raster.reference`)
step by step and in its precisions; the recipe that composes them is
`ingest.raster.recipe`'s. A scan's arrays go to the device once per
`ScanIndex` (kept while the index lives). Double Sphere cameras project on
the device; other models project on the host in numpy float32.

Same output as the other backends: the keys are the same integers, so the
same point wins every pixel and the holes are the same; per-pixel float64
sums may add in another order on a GPU (float32 results within rounding).
Needs only numpy and torch (no Open3D, no numba), so a GPU machine can time
it on a synthetic scan (`bench/bench_gpu.py`).
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from calibration.camera import CameraModel
from calibration.fisheye import DoubleSphere
from calibration.transforms import invert
from calibration.types import F64, Bool
from calibration.virtual import project_f32
from ingest.raster import recipe
from ingest.raster.geometry import PixelGeometry, Rendering, coarse_mask
from ingest.raster.kernels import ellipse_offsets
from ingest.raster.lod import ScanIndex, candidates
from ingest.raster.params import (
    AXES,
    EMPTY_KEY,
    IDX_BITS,
    IDX_MASK,
    KEY_BASE,
    NB8,
    Q_MAX,
    RANGE_QUANTUM_M,
    RenderParams,
)
from ingest.raster.recipe import Finished, OwnSamples, Winners

T = torch.Tensor
_ON_DEVICE: weakref.WeakKeyDictionary[ScanIndex, dict[str, Any]] = weakref.WeakKeyDictionary()


def _scan_on(src: ScanIndex, dev: torch.device) -> dict[str, T]:
    """The scan's points and colours on ``dev`` (copied once per index and device)."""
    per = _ON_DEVICE.setdefault(src, {})
    key = str(dev)
    if key not in per:
        per[key] = {
            "xyz": torch.from_numpy(src.xyz).to(dev),
            "rgb": torch.from_numpy(src.rgb).to(dev),
            "masked": None if src.masked is None else torch.from_numpy(src.masked).to(dev),
        }
    out: dict[str, T] = per[key]
    return out


def _sqrt(a: T) -> T:
    """Correctly rounded square root in the dtype of ``a``: torch's vectorised float32 sqrt on the CPU
    is off by one ulp in about a sixth of cases; float64's, rounded to float32, never is."""
    return torch.sqrt(a.double()).to(a.dtype)


def _project(model: CameraModel, x: T, y: T, z: T) -> tuple[T, T, T]:
    """`calibration.virtual.project_f32` on tensors: Double Sphere on the device, others via the host."""
    if isinstance(model, DoubleSphere):  # `DoubleSphere._project_normalised`, float32 as numpy runs it
        r2 = x * x + y * y
        d1 = _sqrt(z * z + r2)
        k = d1 * model.xi + z
        n = _sqrt(k * k + r2) * model.alpha + k * (1.0 - model.alpha)
        valid = (z > d1 * -model.w2) & (n > 0.0)
        inv = 1.0 / n
        u = x * inv * model.fx + model.cx
        v = y * inv * model.fy + model.cy
        return u, v, valid & torch.isfinite(u) & torch.isfinite(v)
    u_np, v_np, ok = project_f32(model, *(a.cpu().numpy() for a in (x, y, z)))
    dev = x.device
    return torch.from_numpy(u_np).to(dev), torch.from_numpy(v_np).to(dev), torch.from_numpy(ok).to(dev)


def _in_view(
    xyz: T, sp: T, model: CameraModel, geo: PixelGeometry, T_cam_scan: F64, params: RenderParams
) -> tuple[T, ...]:
    """`geometry.points_in_view` on tensors: (pix, u, v, r, ku, kv, kept row of ``xyz``)."""
    dev = xyz.device
    R = torch.from_numpy(T_cam_scan[:3, :3].astype(np.float32)).to(dev)
    t = torch.from_numpy(T_cam_scan[:3, 3].astype(np.float32)).to(dev)
    px, py, pz = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    x = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t[0]
    y = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t[1]
    z = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t[2]
    r = _sqrt(x * x + y * y + z * z)
    u, v, ok = _project(model, x, y, z)
    ok &= r > params.near_m
    if params.clip_m is not None and params.clip_mode == "drop":
        ok &= r <= params.clip_m
    col, row = torch.floor(u + 0.5), torch.floor(v + 0.5)
    ok &= (col >= 0) & (col < model.width) & (row >= 0) & (row < model.height)
    keep = torch.nonzero(ok).squeeze(1)
    col_i, row_i, r_k, pk = col[keep].long(), row[keep].long(), r[keep], xyz[keep]
    foot = sp[keep] * _sqrt(pk[:, 0] * pk[:, 0] + pk[:, 1] * pk[:, 1] + pk[:, 2] * pk[:, 2]) / r_k
    cu, cv = col_i // geo.stride, row_i // geo.stride
    K, s = float(params.max_splat_px), params.splat_scale
    ppr_u, ppr_v = (torch.from_numpy(a).to(dev) for a in (geo.ppr_u, geo.ppr_v))
    ku = torch.clamp(s * foot * ppr_u[cv, cu] + 0.5, max=K).to(torch.int16)
    kv = torch.clamp(s * foot * ppr_v[cv, cu] + 0.5, max=K).to(torch.int16)
    return row_i * model.width + col_i, u[keep], v[keep], r_k, ku, kv, keep


@dataclass(frozen=True, eq=False)
class TorchView:
    """The points of a view and its mask points (pix, u, v, r, ku, kv, rgb, masked), in selection order."""

    pts: dict[str, T]
    mask_pts: dict[str, T]
    stats: dict[str, int]

    @property
    def n(self) -> int:
        return len(self.pts["r"])

    @property
    def k_max(self) -> int:
        return int(max(int(self.pts["ku"].max()), int(self.pts["kv"].max()))) if self.n else 0


def _gather(
    sources: list[ScanIndex], model: CameraModel, geo: PixelGeometry, T_world_cam: F64, params: RenderParams,
    pixel_mask: Bool | None, dev: torch.device,
) -> TorchView:  # fmt: skip
    """`reference.gather` on tensors: every scan's selected points and the mask points, in the camera."""
    T_cam_world = invert(T_world_cam)
    coarse = None if pixel_mask is None else coarse_mask(pixel_mask, geo.stride)
    names = ("pix", "u", "v", "r", "ku", "kv", "rgb", "masked")
    parts: list[tuple[T, ...]] = []
    mask_parts: list[tuple[T, ...]] = []
    stats = {"points_total": 0, "points_touched": 0, "points_in_image": 0}
    for src in sources:
        on = _scan_on(src, dev)
        T_cam_scan = T_cam_world @ src.T_world_scan
        stats["points_total"] += src.n_points
        picked, spacing = candidates(
            src, model, T_cam_scan, geo.coarse, params.points_per_px, coarse, params.frustum_culling
        )
        idx, sp = torch.from_numpy(picked).to(dev), torch.from_numpy(spacing).to(dev)
        stats["points_touched"] += len(idx)
        *proj, kept = _in_view(on["xyz"][idx], sp, model, geo, T_cam_scan, params)
        stats["points_in_image"] += len(kept)
        rows = idx[kept]
        masked = (
            on["masked"][rows]
            if on["masked"] is not None
            else torch.zeros(len(kept), dtype=torch.bool, device=dev)
        )
        parts.append((*proj, on["rgb"][rows], masked))
        if bool(masked.any()):
            mask_parts.append(tuple(a[masked] for a in parts[-1]))
        if len(src.mask_xyz):
            m_xyz = torch.from_numpy(src.mask_xyz).to(dev)
            m_sp = torch.from_numpy(src.mask_spacing_rad).to(dev)
            *mproj, mkept = _in_view(m_xyz, m_sp, model, geo, T_cam_scan, params)
            n_m = len(mkept)
            mask_parts.append((*mproj, torch.zeros((n_m, 3), dtype=torch.uint8, device=dev),
                               torch.ones(n_m, dtype=torch.bool, device=dev)))  # fmt: skip
    return TorchView(_concat(parts, names, dev), _concat(mask_parts, names, dev), stats)


def _concat(parts: list[tuple[T, ...]], names: tuple[str, ...], dev: torch.device) -> dict[str, T]:
    if not parts:
        f = torch.zeros(0, dtype=torch.float32, device=dev)
        k = torch.zeros(0, dtype=torch.int16, device=dev)
        i = torch.zeros(0, dtype=torch.int64, device=dev)
        return {"pix": i, "u": f, "v": f, "r": f, "ku": k, "kv": k,
                "rgb": torch.zeros((0, 3), dtype=torch.uint8, device=dev),
                "masked": torch.zeros(0, dtype=torch.bool, device=dev)}  # fmt: skip
    return {name: torch.cat([p[k] for p in parts]) for k, name in enumerate(names)}


def zbuffer(pts: dict[str, T], H: int, W: int) -> tuple[T, T]:
    """`visibility.zbuffer` on tensors: (own, splat) int64 key images, flat, the same keys."""
    dev = pts["pix"].device
    own = torch.full((H * W,), EMPTY_KEY, dtype=torch.int64, device=dev)
    splat = own.clone()
    n = len(pts["pix"])
    if n == 0:
        return own, splat
    q = torch.clamp(torch.round(pts["r"] / float(np.float32(RANGE_QUANTUM_M))).long(), max=Q_MAX)
    key = KEY_BASE + (q << IDX_BITS) + torch.arange(n, device=dev)
    pix = pts["pix"]
    own.scatter_reduce_(0, pix, key, "amin")
    row, col = pix // W, pix % W
    k_max = int(max(int(pts["ku"].max()), int(pts["kv"].max())))
    start, drow, dcol = ellipse_offsets(k_max)
    cls = pts["ku"].long() * (k_max + 1) + pts["kv"].long()
    for c in torch.unique(cls).tolist():
        sel = torch.nonzero(cls == c).squeeze(1)
        r_c, c_c, k_c = row[sel], col[sel], key[sel]
        for j in range(int(start[c]), int(start[c + 1])):
            rr, cc = r_c + int(drow[j]), c_c + int(dcol[j])
            ok = (rr >= 0) & (rr < H) & (cc >= 0) & (cc < W)
            splat.scatter_reduce_(0, (rr * W + cc)[ok], k_c[ok], "amin")
    return own, splat


def _shift(img: T, dr: int, dc: int, fill: float) -> T:
    """out[r, c] = img[r + dr, c + dc], ``fill`` outside the image."""
    H, W = img.shape
    out = torch.full_like(img, fill)
    r0, r1 = max(0, -dr), min(H, H - dr)
    c0, c1 = max(0, -dc), min(W, W - dc)
    if r1 > r0 and c1 > c0:
        out[r0:r1, c0:c1] = img[r0 + dr : r1 + dr, c0 + dc : c1 + dc]
    return out


def _winners(view: TorchView, H: int, W: int) -> Winners:
    """Both z-buffers and their nearest points (index n, range inf: none)."""
    n = view.n
    own_key, splat_key = zbuffer(view.pts, H, W)
    own_ok, surface = own_key != EMPTY_KEY, splat_key != EMPTY_KEY
    r_all = torch.cat([view.pts["r"], torch.tensor([math.inf], device=own_key.device)])
    own_i = torch.where(own_ok, own_key & IDX_MASK, n)
    splat_i = torch.where(surface, splat_key & IDX_MASK, n)
    return Winners(own_ok, own_i, splat_i, r_all[own_i], r_all[splat_i], surface)


def _leaking(view: TorchView, win: Winners, ppr: T, params: RenderParams, W: int, K: int) -> T:
    """`reference.leaking` on whole images: own points behind a nearer splat, nearer points on two sides."""
    pts, r_own, r_splat, own_ok = view.pts, win.r_own, win.r_splat, win.own_ok
    H = len(own_ok) // W
    cand = own_ok & (r_own > r_splat + params.tolerance(r_splat, params.LEAK_MIN_PX, ppr))
    n = len(pts["u"])
    s = torch.clamp(win.splat_i, max=max(n - 1, 0))
    p = torch.arange(H * W, device=ppr.device)
    if n:
        d = torch.hypot(pts["u"][s].double() - (p % W).double(), pts["v"][s].double() - (p // W).double())
    else:
        d = torch.zeros(H * W, dtype=torch.float64, device=ppr.device)
    tol = params.tolerance(r_splat.double(), d + params.HALF_PX, ppr.double())
    cand &= r_own.double() > r_splat.double() + tol
    thr = (r_own - params.tolerance(r_own, K + params.HALF_PX, ppr)).reshape(H, W)
    img = torch.where(own_ok, r_own, torch.inf).reshape(H, W)
    out = torch.zeros((H, W), dtype=torch.bool, device=ppr.device)
    for dr, dc in AXES:
        a = torch.zeros_like(out)
        b = torch.zeros_like(out)
        for t in range(1, K + 1):
            a |= _shift(img, t * dr, t * dc, math.inf) < thr
            b |= _shift(img, -t * dr, -t * dc, math.inf) < thr
        out |= a & b
    leak: T = cand & out.reshape(-1)
    return leak


def _own_samples(view: TorchView, win: Winners, leak: T, W: int) -> OwnSamples:
    """`reference.own_samples` on flat tensors."""
    ok = win.own_ok & ~leak
    own_i = torch.where(ok, win.own_i, view.n)
    dev = ok.device
    u_all = torch.cat([view.pts["u"], torch.zeros(1, device=dev)])
    v_all = torch.cat([view.pts["v"], torch.zeros(1, device=dev)])
    p = torch.arange(len(ok), device=dev)
    R = torch.where(ok, win.r_own, torch.nan)
    U = torch.where(ok, u_all[own_i] - (p % W).float(), 0.0)
    V = torch.where(ok, v_all[own_i] - (p // W).float(), 0.0)
    return OwnSamples(ok, R, U, V)


def _solve(a11: T, a12: T, a22: T, b1: T, b2: T) -> tuple[T, T, T]:
    """`visibility.solve_gradient` on tensors (their dtype)."""
    det = a11 * a22 - a12 * a12
    full = det > RenderParams.FIT_MIN_DET
    inv = torch.where(full, 1.0 / torch.where(full, det, 1.0), 0.0)
    gu = (a22 * b1 - a12 * b2) * inv
    gv = (a11 * b2 - a12 * b1) * inv
    only_u, only_v = ~full & (a11 > RenderParams.FIT_MIN_AXIS), ~full & (a22 > RenderParams.FIT_MIN_AXIS)
    gu = torch.where(only_u, b1 / torch.where(only_u, a11, 1.0), gu)
    gv = torch.where(only_v, b2 / torch.where(only_v, a22, 1.0), gv)
    return gu, gv, full


def _fit_gradient(R: T, U: T, V: T, ppr: T, params: RenderParams) -> tuple[T, T]:
    """`visibility.fit_gradient` on (H, W) tensors; the diagonal neighbours join in float64 where needed."""
    slope = params.gate_slope(ppr)
    acc = [torch.zeros_like(R) for _ in range(5)]

    def terms(dr: int, dc: int, gate: T) -> tuple[T, T, T]:
        dR = _shift(R, dr, dc, math.nan) - R
        ok = (torch.abs(dR) <= gate).to(R.dtype)
        du = (dc + _shift(U, dr, dc, 0.0) - U) * ok
        dv = (dr + _shift(V, dr, dc, 0.0) - V) * ok
        return du, dv, torch.where(ok > 0, dR, 0.0)

    gate = params.tau_m + R * slope * np.float32(params.GATE_DIRECT_PX)
    for dr, dc in NB8[:4]:
        du, dv, dR = terms(dr, dc, gate)
        for a, term in zip(acc, (du * du, du * dv, dv * dv, du * dR, dv * dR), strict=True):
            a += term
    gu, gv, full = _solve(*acc)
    weak = ~full & torch.isfinite(R)
    if bool(weak.any()):
        sub = [a.double() for a in acc]
        g = params.tau_m + R * slope * np.float32(params.GATE_DIAGONAL_PX)
        for dr, dc in NB8[4:]:
            du, dv, dR = terms(dr, dc, g)
            for a, term in zip(sub, (du * du, du * dv, dv * dv, du * dR, dv * dR), strict=True):
                a += term.double()
        wu, wv, _ = _solve(*sub)
        gu = torch.where(weak, wu.float(), gu)
        gv = torch.where(weak, wv.float(), gv)
    return gu, gv


def _gradient_value(own: OwnSamples, ppr: T, params: RenderParams, W: int) -> tuple[T, T, T]:
    """`reference.gradient_value` on flat tensors."""
    R, U, V = (a.reshape(-1, W) for a in (own.R, own.U, own.V))
    flat = torch.zeros_like(R)
    gu, gv = _fit_gradient(R, U, V, ppr.reshape(-1, W), params) if params.fit_gradient else (flat, flat)
    value = R - gu * U - gv * V
    return gu.reshape(-1), gv.reshape(-1), value.reshape(-1)


def _average(
    view: TorchView, own: OwnSamples, gu: T, gv: T, value: T, ppr: T, params: RenderParams, W: int
) -> T:
    """`visibility.average_surface` on flat tensors."""
    pts = view.pts
    pix = pts["pix"]
    ref = own.R[pix]
    ok = own.ok[pix] & (pts["r"] <= ref + params.tolerance(ref, params.SAME_SURFACE_PX, ppr[pix]))
    pix, r, u, v = pix[ok], pts["r"][ok], pts["u"][ok], pts["v"][ok]
    row, col = (pix // W).double(), (pix % W).double()
    g_u, g_v = gu[pix].double(), gv[pix].double()
    corrected = r.double() - g_u * (u.double() - col) - g_v * (v.double() - row)
    P = value.numel()
    sums = torch.zeros(P, dtype=torch.float64, device=pix.device).index_add_(0, pix, corrected)
    counts = torch.bincount(pix, minlength=P)
    out: T = torch.where(counts > 0, (sums / torch.clamp(counts, min=1)).float(), value)
    return out


def _fill(
    value: T, own: OwnSamples, gu: T, gv: T, need: T, ppr: T, params: RenderParams, W: int
) -> tuple[T, T]:
    """`visibility.fill_gaps` on tensors: values of the flat pixels ``need`` from their neighbours."""
    H = len(value) // W
    dev = value.device
    pad = torch.nn.functional.pad
    vp = pad(torch.where(own.ok, value, torch.nan).reshape(H, W), (1, 1, 1, 1), value=math.nan).reshape(-1)
    gup = pad(gu.reshape(H, W), (1, 1, 1, 1)).reshape(-1)
    gvp = pad(gv.reshape(H, W), (1, 1, 1, 1)).reshape(-1)
    pn = (need // W + 1) * (W + 2) + need % W + 1
    got_all = torch.zeros(len(need), dtype=torch.bool, device=dev)
    todo = torch.arange(len(need), device=dev)
    offs = torch.tensor([dr * (W + 2) + dc for dr, dc in NB8], device=dev)[:, None]
    drs = torch.tensor([dr for dr, _ in NB8], dtype=torch.float32, device=dev)[:, None]
    dcs = torch.tensor([dc for _, dc in NB8], dtype=torch.float32, device=dev)[:, None]
    weight = torch.tensor(params.fill_weights, dtype=torch.float32, device=dev)[:, None]
    ppr_n = ppr[need]
    for _ in range(params.fill_passes):
        if len(todo) == 0:
            break
        nb = pn[todo][None, :] + offs
        gnu, gnv = gup[nb], gvp[nb]
        pred = vp[nb] - gnu * dcs - gnv * drs
        fin = torch.isfinite(pred)
        nearest = torch.where(fin, pred, torch.inf).min(dim=0).values
        in_near = fin & (pred <= nearest + params.tolerance(nearest, params.FILL_TOLERANCE_PX, ppr_n[todo]))
        in_far = fin & ~in_near
        pairs = (in_near[0::2] & in_near[1::2]).any(dim=0)
        use_far = ~pairs & in_far.any(dim=0)
        far = torch.where(in_far, pred, torch.inf).min(dim=0).values
        in_far &= pred <= far + params.tolerance(far, params.FILL_TOLERANCE_PX, ppr_n[todo])
        w = weight * torch.where(use_far, in_far, in_near)
        wsum = w.sum(dim=0)
        got = wsum > 0
        safe = torch.where(got, wsum, 1.0)
        new_v = (w * torch.nan_to_num(pred)).sum(dim=0) / safe
        new_gu = (w * gnu).sum(dim=0) / safe
        new_gv = (w * gnv).sum(dim=0) / safe
        done = todo[got]
        vp[pn[done]], gup[pn[done]], gvp[pn[done]] = new_v[got], new_gu[got], new_gv[got]
        got_all[done] = True
        todo = todo[~got]
    # a copy, not the padded buffer's strided view: the recipe writes into the flat result
    return vp.reshape(H + 2, W + 2)[1:-1, 1:-1].contiguous().reshape(-1), got_all


def _masked(mask_pts: dict[str, T], surf: T, value: T, ppr: T, params: RenderParams, W: int) -> T:
    """`reference.masked` on flat tensors: surface pixels on or behind a mask surface."""
    P = len(surf)
    if not len(mask_pts["pix"]):
        return torch.zeros_like(surf)
    _, key = zbuffer(mask_pts, P // W, W)
    has = key != EMPTY_KEY
    i = torch.where(has, key & IDX_MASK, 0)
    p = torch.arange(P, device=surf.device)
    r_mask = torch.where(has, mask_pts["r"][i], torch.inf)
    du = (torch.where(has, mask_pts["u"][i], 0.0) - (p % W).float()).double()
    dv = (torch.where(has, mask_pts["v"][i], 0.0) - (p // W).float()).double()
    d = torch.sqrt(du * du + dv * dv).float()  # hypot in float32, correctly rounded
    out: T = surf & (r_mask <= value + params.tolerance(value, d + params.HALF_PX, ppr))
    return out


def _finish(
    view: TorchView, value: T, win: Winners, own: OwnSamples, rays: Bool, ppr: T, params: RenderParams, W: int
) -> Finished:
    """`reference.finish` on flat tensors."""
    dev = value.device
    surf = win.surface & torch.from_numpy(np.ascontiguousarray(rays.reshape(-1))).to(dev)
    masked = _masked(view.mask_pts, surf, value, ppr, params, W)
    clipped = torch.zeros_like(surf)
    if params.clip_m is not None:
        clipped = surf & ~masked & (value > params.clip_m)
    good = surf & ~masked & ~clipped & torch.isfinite(value) & (value > 0)
    range_m = torch.where(good, value, 0.0)
    bgr = torch.zeros((len(value), 3), dtype=torch.uint8, device=dev)
    if view.n and params.colour:
        src = torch.where(own.ok, win.own_i, win.splat_i)
        show = torch.nonzero(surf).squeeze(1)
        bgr[show] = view.pts["rgb"][src[show]].flip(1)
    return Finished(surf, masked, clipped, good, range_m, bgr)


class TorchStages:
    """The PyTorch stages on ``device`` as `ingest.raster.recipe.Stages`."""

    winners = staticmethod(_winners)
    leaking = staticmethod(_leaking)
    own_samples = staticmethod(_own_samples)
    gradient_value = staticmethod(_gradient_value)
    average = staticmethod(_average)
    fill = staticmethod(_fill)
    finish = staticmethod(_finish)

    def __init__(self, device: str) -> None:
        self.dev = torch.device(device)

    def gather(
        self, sources: list[ScanIndex], model: CameraModel, geo: PixelGeometry, T_world_cam: F64,
        params: RenderParams, pixel_mask: Bool | None,
    ) -> TorchView:  # fmt: skip
        return _gather(sources, model, geo, T_world_cam, params, pixel_mask, self.dev)

    def ppr(self, geo: PixelGeometry) -> T:
        return torch.from_numpy(geo.ppr.reshape(-1)).to(self.dev)

    @staticmethod
    def nonzero(mask: T) -> T:
        return torch.nonzero(mask).squeeze(1)

    @staticmethod
    def host(a: T) -> np.ndarray[Any, Any]:
        out: np.ndarray[Any, Any] = a.cpu().numpy()
        return out


def render_torch(
    sources: list[ScanIndex], model: CameraModel, T_world_cam: F64, params: RenderParams,
    pixel_mask: Bool | None = None, device: str = "cpu",
) -> Rendering:  # fmt: skip
    """`ingest.raster.recipe.render` with the PyTorch stages on ``device``; a host `Rendering`."""
    return recipe.render(TorchStages(device), sources, model, T_world_cam, params, pixel_mask)
