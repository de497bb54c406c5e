"""The renderer's per-pixel algorithms in numpy: the reference backend's (`ingest.raster.reference`) parts.

A z-buffer on range over point footprints (splats), the two-sided occlusion
test that rejects points seen through a nearer surface, a local plane fit of
range over the pixel grid, same-surface averaging and moving each value onto
its pixel-centre ray, and gap filling along that plane (see `ingest.raster.recipe`)."""

from __future__ import annotations

from typing import Any

import numpy as np

from calibration.types import F32, I64, Bool
from ingest.raster.geometry import ViewPoints
from ingest.raster.kernels import zbuffer_keys
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


def zbuffer(pts: ViewPoints, H: int, W: int) -> tuple[I64, I64]:
    """(own, splat) int64 key images, flat (H*W,); `EMPTY_KEY` where no point.

    key = BASE + (round(range / RANGE_QUANTUM_M) << 28) + point index: the
    minimum key is the nearest point, and the key names it. "own" holds the
    nearest point inside each pixel, "splat" the nearest whose footprint
    ellipse covers it (a compiled loop over the points:
    `ingest.raster.kernels.zbuffer_keys`).
    """
    own = np.full(H * W, EMPTY_KEY, np.int64)
    splat = np.full(H * W, EMPTY_KEY, np.int64)
    if len(pts.pix):
        zbuffer_keys(pts.pix, _keys(pts), pts.ku, pts.kv, H, W, own, splat)
    return own, splat


def _keys(pts: ViewPoints) -> I64:
    n = len(pts.pix)
    if n >= 1 << IDX_BITS:
        raise ValueError(f"a view can z-buffer at most 2^{IDX_BITS} points, got {n}")
    q = np.minimum(np.round(pts.r / np.float32(RANGE_QUANTUM_M)).astype(np.int64), Q_MAX)
    out: I64 = KEY_BASE + (q << IDX_BITS) + np.arange(n, dtype=np.int64)
    return out


def winner(key: I64) -> tuple[Bool, I64]:
    """(has a point, index of the point) per pixel of a key image."""
    return key != EMPTY_KEY, key & IDX_MASK


def pad(img: np.ndarray[Any, Any], k: int, fill: Any) -> np.ndarray[Any, Any]:
    return np.pad(img, k, mode="constant", constant_values=fill)


def padded_index(flat: I64, W: int, k: int) -> I64:
    row, col = np.divmod(flat, W)
    out: I64 = (row + k) * (W + 2 * k) + col + k
    return out


def leaks(r_own: F32, candidates: I64, thr: F32, K: int) -> Bool:
    """For flat pixels ``candidates``: own points nearer than ``thr`` on two opposite sides within K px."""
    W = r_own.shape[1]
    rp = pad(r_own, K, np.inf).reshape(-1)
    Wp = W + 2 * K
    pc = padded_index(candidates, W, K)
    out = np.zeros(len(candidates), bool)
    for dr, dc in AXES:
        a = np.zeros(len(candidates), bool)
        b = np.zeros(len(candidates), bool)
        for t in range(1, K + 1):
            off = t * (dr * Wp + dc)
            a |= rp[pc + off] < thr
            b |= rp[pc - off] < thr
        out |= a & b
    return out


def solve_gradient(a11: Any, a12: Any, a22: Any, b1: Any, b2: Any) -> tuple[Any, Any, Any]:
    """2x2 least squares per pixel; one axis alone where only it is determined (`RenderParams.FIT_MIN_DET`,
    `FIT_MIN_AXIS`). Returns (gu, gv, solved)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        det = a11 * a22 - a12 * a12
        full = det > RenderParams.FIT_MIN_DET
        inv = np.where(full, 1.0 / np.where(full, det, 1.0), 0.0)
        gu = (a22 * b1 - a12 * b2) * inv
        gv = (a11 * b2 - a12 * b1) * inv
        only_u = ~full & (a11 > RenderParams.FIT_MIN_AXIS)
        only_v = ~full & (a22 > RenderParams.FIT_MIN_AXIS)
        gu = np.where(only_u, b1 / np.where(only_u, a11, 1.0), gu)
        gv = np.where(only_v, b2 / np.where(only_v, a22, 1.0), gv)
    return gu, gv, full


def fit_gradient(R: F32, U: F32, V: F32, ppr: F32, params: RenderParams) -> tuple[F32, F32]:
    """Range gradient (m per pixel along u, v) from each pixel's neighbours on the same surface.

    R holds each pixel's own point range (NaN where none) at sub-pixel offset
    (U, V) from the pixel centre. Least squares over the 4-neighbours within
    the same-surface tolerance; where those do not determine both components
    (sparse points), the diagonal neighbours join. 0 where nothing does.
    """
    H, W = R.shape
    Rp, Up, Vp = pad(R, 1, np.nan), pad(U, 1, 0.0), pad(V, 1, 0.0)
    acc = [np.zeros((H, W), np.float32) for _ in range(5)]  # a11, a12, a22, b1, b2
    slope = params.gate_slope(ppr).astype(np.float32)  # same-surface gate per metre and pixel
    gate = params.tau_m + R * slope * np.float32(params.GATE_DIRECT_PX)
    with np.errstate(invalid="ignore"):
        for dr, dc in NB8[:4]:
            win = (slice(1 + dr, H + 1 + dr), slice(1 + dc, W + 1 + dc))
            dR = Rp[win] - R
            ok = np.abs(dR) <= gate
            du = (dc + Up[win] - U) * ok
            dv = (dr + Vp[win] - V) * ok
            dR = np.where(ok, dR, np.float32(0.0))
            for a, term in zip(acc, (du * du, du * dv, dv * dv, du * dR, dv * dR), strict=True):
                a += term
    gu, gv, full = solve_gradient(*acc)
    weak = np.flatnonzero(~full & np.isfinite(R))
    if weak.size:  # add the diagonal neighbours, for these pixels only
        pw = padded_index(weak, W, 1)
        Rf, Uf, Vf = Rp.reshape(-1), Up.reshape(-1), Vp.reshape(-1)
        r0, u0, v0 = Rf[pw], Uf[pw], Vf[pw]
        sub = [a.reshape(-1)[weak].astype(np.float64) for a in acc]
        g = params.tau_m + r0 * slope.reshape(-1)[weak] * params.GATE_DIAGONAL_PX
        with np.errstate(invalid="ignore"):
            for dr, dc in NB8[4:]:
                q = pw + dr * (W + 2) + dc
                dR = Rf[q] - r0
                ok = np.abs(dR) <= g
                du, dv, dR = (dc + Uf[q] - u0) * ok, (dr + Vf[q] - v0) * ok, np.where(ok, dR, 0.0)
                for a, term in zip(sub, (du * du, du * dv, dv * dv, du * dR, dv * dR), strict=True):
                    a += term
        wu, wv, _ = solve_gradient(*sub)
        gu.reshape(-1)[weak] = wu
        gv.reshape(-1)[weak] = wv
    return gu.astype(np.float32), gv.astype(np.float32)


def average_surface(pts: ViewPoints, value: F32, own_ok: Bool, R: F32, gu: F32, gv: F32, ppr: F32,
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
    same = r <= ref + params.tolerance(ref, params.SAME_SURFACE_PX, ppr.reshape(-1)[pix])
    pix, r, idx = pix[same], r[same], idx[same]
    row, col = np.divmod(pix, W)
    corrected = r - gu.reshape(-1)[pix] * (pts.u[idx] - col) - gv.reshape(-1)[pix] * (pts.v[idx] - row)
    sums = np.bincount(pix, corrected, minlength=H * W)
    counts = np.bincount(pix, minlength=H * W)
    got = counts > 0
    out: F32 = np.where(got, sums / np.maximum(counts, 1), value.reshape(-1)).astype(np.float32)
    return out.reshape(H, W)


def fill_gaps(value: F32, has: Bool, gu: F32, gv: F32, need: I64, ppr: F32,
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
    vp = pad(np.where(has, value, np.nan), 1, np.nan).reshape(-1)
    gup, gvp = pad(gu, 1, 0.0).reshape(-1), pad(gv, 1, 0.0).reshape(-1)
    pn = padded_index(need, W, 1)
    got_all = np.zeros(len(need), bool)
    todo = np.arange(len(need))
    offs = np.array([dr * Wp + dc for dr, dc in NB8])
    drs = np.array([dr for dr, _ in NB8], np.float32)[:, None]
    dcs = np.array([dc for _, dc in NB8], np.float32)[:, None]
    weight = np.array(params.fill_weights, np.float32)[:, None]
    ppr_n = ppr.reshape(-1)[need]
    for _ in range(params.fill_passes):
        if todo.size == 0:
            break
        nb = pn[todo][None, :] + offs[:, None]  # (8, n)
        gnu, gnv = gup[nb], gvp[nb]
        pred = vp[nb] - gnu * dcs - gnv * drs
        fin = np.isfinite(pred)
        nearest = np.min(np.where(fin, pred, np.inf), axis=0)
        tol = params.tolerance(nearest, params.FILL_TOLERANCE_PX, ppr_n[todo])
        with np.errstate(invalid="ignore"):
            in_near = fin & (pred <= nearest + tol)
            in_far = fin & ~in_near
            pairs = (in_near[0::2] & in_near[1::2]).any(axis=0)
            use_far = ~pairs & in_far.any(axis=0)
            if use_far.any():
                far = np.min(np.where(in_far, pred, np.inf), axis=0)
                in_far &= pred <= far + params.tolerance(far, params.FILL_TOLERANCE_PX, ppr_n[todo])
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
