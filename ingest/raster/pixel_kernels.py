"""Compiled (numba, parallel) per-pixel stages of the renderer: winners, leaks, gradient, gap fill, masks.

The numpy reference (`ingest.raster.reference`, `ingest.raster.visibility`) gathers
whole images per step; here each pixel is one loop iteration that reads its
few neighbours. The arithmetic is the numpy path's, in the same order and
precision: tolerances in float32 as numpy computes them (Python constants
rounded to float32), the leak distance and the weak-gradient solve in
float64 where numpy promotes to it. Images are flat (H*W,) arrays. The
recipe's thresholds (`RenderParams`) come in as arguments.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from ingest.raster.params import AXES, NB8

AX_DR = np.array([dr for dr, _ in AXES], np.int64)  # the leak test's axes
AX_DC = np.array([dc for _, dc in AXES], np.int64)
NB_DR = np.array([dr for dr, _ in NB8], np.int64)  # the 8-neighbours, opposite pairs adjacent
NB_DC = np.array([dc for _, dc in NB8], np.int64)


@njit(parallel=True, cache=True, nogil=True)
def decode(own_key, splat_key, inv, r, empty, idx_mask, own_ok, own_i, splat_i, r_own, r_splat):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Winners of the two key images: point (``inv`` of the key's index; n: none), range (inf: none)."""
    n = r.shape[0]
    inf = np.float32(np.inf)
    for p in prange(own_key.shape[0]):
        ok = own_key[p] != empty
        own_ok[p] = ok
        i = inv[own_key[p] & idx_mask] if ok else n
        own_i[p] = i
        r_own[p] = r[i] if ok else inf
        s = inv[splat_key[p] & idx_mask] if splat_key[p] != empty else n
        splat_i[p] = s
        r_splat[p] = r[s] if s < n else inf


@njit(parallel=True, cache=True, nogil=True)
def leaking(  # type: ignore[no-untyped-def]  # pragma: no cover
    own_ok, r_own, r_splat, splat_i, u, v, ppr, W, K, tau_m, tau_rel, slope, slope1, slope_k, half, leak
):  # fmt: skip
    """`reference.leaking` per pixel: an own point behind a nearer splat, nearer own points on opposite sides.

    ``slope1``, ``slope_k``: the slope times `LEAK_MIN_PX` and K + `HALF_PX` (float32); ``half``: `HALF_PX`.
    """
    P = own_ok.shape[0]
    H = P // W
    inv_w = 1.0 / W
    tm64, tr64, sl64 = np.float64(tau_m), np.float64(tau_rel), np.float64(slope)
    for p in prange(P):
        leak[p] = False
        if not own_ok[p]:
            continue
        ro, rs, pp = r_own[p], r_splat[p], ppr[p]
        if not (ro > rs + (tau_m + rs * (tau_rel + slope1 / pp))):
            continue
        row = np.int64((p + 0.5) * inv_w)  # p // W without an integer division
        col = p - row * W
        s = splat_i[p]
        d = math.hypot(np.float64(u[s]) - col, np.float64(v[s]) - row)
        rs64 = np.float64(rs)
        if not (np.float64(ro) > rs64 + (tm64 + rs64 * (tr64 + sl64 * (d + half) / np.float64(pp)))):
            continue
        thr = ro - (tau_m + ro * (tau_rel + slope_k / pp))
        for a in range(4):
            dr, dc = AX_DR[a], AX_DC[a]
            fwd = False
            bwd = False
            for t in range(1, K + 1):
                rr, cc = row + t * dr, col + t * dc
                if 0 <= rr < H and 0 <= cc < W and r_own[rr * W + cc] < thr:
                    fwd = True
                rr, cc = row - t * dr, col - t * dc
                if 0 <= rr < H and 0 <= cc < W and r_own[rr * W + cc] < thr:
                    bwd = True
            if fwd and bwd:
                leak[p] = True
                break


@njit(parallel=True, cache=True, nogil=True)
def own_samples(own_ok, leak, own_i, r, u, v, W, ok2, R, U, V):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Own points left after the leak test: range (NaN where none) and sub-pixel offset (0 where none)."""
    nan, zero = np.float32(np.nan), np.float32(0.0)
    inv_w = 1.0 / W
    for p in prange(own_ok.shape[0]):
        ok = own_ok[p] and not leak[p]
        ok2[p] = ok
        if ok:
            i = own_i[p]
            row = np.int64((p + 0.5) * inv_w)  # p // W without an integer division
            R[p] = r[i]
            U[p] = u[i] - np.float32(p - row * W)
            V[p] = v[i] - np.float32(row)
        else:
            R[p], U[p], V[p] = nan, zero, zero


@njit(cache=True, nogil=True)
def _solve(a11, a12, a22, b1, b2, one, zero, min_det, min_axis):  # type: ignore[no-untyped-def]  # pragma: no cover
    """`visibility.solve_gradient` for one pixel, in the type of ``one``."""
    det = a11 * a22 - a12 * a12
    full = det > min_det
    inv = one / det if full else zero
    gu = (a22 * b1 - a12 * b2) * inv
    gv = (a11 * b2 - a12 * b1) * inv
    if not full and a11 > min_axis:
        gu = b1 / a11
    if not full and a22 > min_axis:
        gv = b2 / a22
    return gu, gv, full


@njit(cache=True, nogil=True)
def _terms(Rn, Un, Vn, Rc, Uc, Vc, dr, dc, gate):  # type: ignore[no-untyped-def]  # pragma: no cover
    """One neighbour's (du, dv, dR) as `fit_gradient` weighs it: zero when off the surface (or NaN)."""
    dR = Rn - Rc
    ok = abs(dR) <= gate
    okf = np.float32(1.0) if ok else np.float32(0.0)
    du = (dc + Un - Uc) * okf
    dv = (dr + Vn - Vc) * okf
    return du, dv, dR if ok else np.float32(0.0)


@njit(cache=True, nogil=True)
def _neighbour_sums(R, U, V, W, H, row, col, gate, k0, k1, a11, a12, a22, b1, b2):  # type: ignore[no-untyped-def]  # pragma: no cover
    """The normal equations of neighbours `NB_DR/NB_DC[k0:k1]` added to (a11, a12, a22, b1, b2).

    The sums stay in the type they come in (float32 for the direct
    neighbours, float64 once the diagonal ones join), as in numpy's recipe.
    """
    p = row * W + col
    Rc, Uc, Vc = R[p], U[p], V[p]
    for k in range(k0, k1):
        dr, dc = NB_DR[k], NB_DC[k]
        rr, cc = row + dr, col + dc
        if 0 <= rr < H and 0 <= cc < W:
            q = rr * W + cc
            Rn, Un, Vn = R[q], U[q], V[q]
        else:
            Rn, Un, Vn = np.float32(np.nan), np.float32(0.0), np.float32(0.0)
        du, dv, dR = _terms(Rn, Un, Vn, Rc, Uc, Vc, np.float32(dr), np.float32(dc), gate)
        a11 += du * du
        a12 += du * dv
        a22 += dv * dv
        b1 += du * dR
        b2 += dv * dR
    return a11, a12, a22, b1, b2


@njit(parallel=True, cache=True, nogil=True)
def gradient_value(  # type: ignore[no-untyped-def]  # pragma: no cover
    R, U, V, ppr, W, tau_m, tau_rel, slope1, gate1, gate2, min_det, min_axis, fit, gu, gv, value
):  # fmt: skip
    """`visibility.fit_gradient` per pixel, then the value on the pixel-centre ray, R - gu U - gv V.

    ``slope1``: the incidence slope (float32); ``gate1``, ``gate2``: `GATE_DIRECT_PX`, `GATE_DIAGONAL_PX`
    (float32); ``min_det``, ``min_axis``: `FIT_MIN_DET`, `FIT_MIN_AXIS`. A pixel without an own point
    (R NaN) has no neighbour on its surface: gradient 0, value NaN, as in numpy.
    """
    H = R.shape[0] // W
    one32, zero32 = np.float32(1.0), np.float32(0.0)
    for row in prange(H):
        for col in range(W):
            p = row * W + col
            Rc, Uc, Vc = R[p], U[p], V[p]
            if not fit or not np.isfinite(Rc):
                gu[p], gv[p] = zero32, zero32
                value[p] = Rc - zero32 * Uc - zero32 * Vc
                continue
            sl = (tau_m + (tau_rel + slope1 / ppr[p])) - tau_m
            gate = tau_m + Rc * sl * gate1
            z = zero32  # the four direct neighbours, summed in float32
            a11, a12, a22, b1, b2 = _neighbour_sums(R, U, V, W, H, row, col, gate, 0, 4, z, z, z, z, z)
            g_u, g_v, full = _solve(a11, a12, a22, b1, b2, one32, zero32, min_det, min_axis)
            if not full:  # the diagonal neighbours join, in float64
                g = tau_m + Rc * sl * gate2
                s11, s12, s22, t1, t2 = _neighbour_sums(
                    R, U, V, W, H, row, col, g, 4, 8, np.float64(a11), np.float64(a12), np.float64(a22),
                    np.float64(b1), np.float64(b2),
                )  # fmt: skip
                w_u, w_v, _ = _solve(s11, s12, s22, t1, t2, 1.0, 0.0, min_det, min_axis)
                g_u, g_v = np.float32(w_u), np.float32(w_v)
            gu[p] = g_u
            gv[p] = g_v
            value[p] = Rc - g_u * Uc - g_v * Vc


@njit(cache=True, nogil=True)
def _finite(x):  # type: ignore[no-untyped-def]  # pragma: no cover
    """np.nan_to_num for one float32."""
    if np.isnan(x):
        return np.float32(0.0)
    if np.isinf(x):
        return np.float32(3.4028235e38) if x > 0 else np.float32(-3.4028235e38)
    return x


@njit(parallel=True, cache=True, nogil=True)
def fill_pass(  # type: ignore[no-untyped-def]  # pragma: no cover
    todo, val, gu, gv, ppr, W, tau_m, tau_rel, slope_fill, weight, pred, gnu, gnv, new, got
):  # fmt: skip
    """One pass of `visibility.fill_gaps` over flat pixels ``todo``: ``new`` (v, gu, gv) and ``got``.

    Reads the previous pass only: the caller writes ``new`` into the images
    after the pass.
    """
    P = val.shape[0]
    H = P // W
    inv_w = 1.0 / W
    inf = np.float32(np.inf)
    for j in prange(todo.shape[0]):
        p = todo[j]
        row = np.int64((p + 0.5) * inv_w)  # p // W without an integer division
        col = p - row * W
        nearest = inf
        for k in range(8):
            rr, cc = row + NB_DR[k], col + NB_DC[k]
            if 0 <= rr < H and 0 <= cc < W:
                q = rr * W + cc
                vq, gnu[j, k], gnv[j, k] = val[q], gu[q], gv[q]
            else:
                vq, gnu[j, k], gnv[j, k] = np.float32(np.nan), np.float32(0.0), np.float32(0.0)
            pred[j, k] = vq - gnu[j, k] * np.float32(NB_DC[k]) - gnv[j, k] * np.float32(NB_DR[k])
            if np.isfinite(pred[j, k]) and pred[j, k] < nearest:
                nearest = pred[j, k]
        lim = nearest + (tau_m + nearest * (tau_rel + slope_fill / ppr[p]))
        pairs = False
        any_far = False
        far = inf
        for k in range(0, 8, 2):
            n0 = np.isfinite(pred[j, k]) and pred[j, k] <= lim
            n1 = np.isfinite(pred[j, k + 1]) and pred[j, k + 1] <= lim
            pairs |= n0 and n1
            for kk, near in ((k, n0), (k + 1, n1)):
                if np.isfinite(pred[j, kk]) and not near:
                    any_far = True
                    far = min(far, pred[j, kk])
        use_far = not pairs and any_far
        lim_far = far + (tau_m + far * (tau_rel + slope_fill / ppr[p]))
        wsum = sv = su = sg = np.float32(0.0)
        for k in range(8):
            x = pred[j, k]
            fin = np.isfinite(x)
            near = fin and x <= lim
            sel = (fin and not near and x <= lim_far) if use_far else near
            w = weight[k] if sel else np.float32(0.0)
            wsum += w
            sv += w * _finite(x)
            su += w * gnu[j, k]
            sg += w * gnv[j, k]
        got[j] = wsum > 0
        safe = wsum if wsum > 0 else np.float32(1.0)
        new[j, 0] = sv / safe
        new[j, 1] = su / safe
        new[j, 2] = sg / safe


@njit(parallel=True, cache=True, nogil=True)
def finish(  # type: ignore[no-untyped-def]  # pragma: no cover
    value, surface, own_ok, own_i, splat_i, rays, rgb, colour, ppr, W, mask_key, mask_r, mask_u, mask_v,
    empty, idx_mask, tau_m, tau_rel, slope, half, clip, surf, masked, clipped, good, range_m, bgr,
):  # fmt: skip
    """Masks (a mask surface not behind the value), clipping, valid range and colour of every pixel
    (``bgr`` left as it is when ``colour`` is off); ``half``: `HALF_PX` (float32)."""
    zero = np.float32(0.0)
    inv_w = 1.0 / W
    for p in prange(value.shape[0]):
        s = surface[p] and rays[p]
        surf[p] = s
        x = value[p]
        m = False
        if s and mask_key.shape[0] and mask_key[p] != empty:
            i = mask_key[p] & idx_mask
            row = np.int64((p + 0.5) * inv_w)  # p // W without an integer division
            du = np.float64(mask_u[i] - np.float32(p - row * W))
            dv = np.float64(mask_v[i] - np.float32(row))
            d = np.float32(math.sqrt(du * du + dv * dv))
            m = mask_r[i] <= x + (tau_m + x * (tau_rel + slope * (d + half) / ppr[p]))
        masked[p] = m
        c = s and not m and x > clip
        clipped[p] = c
        g = s and not m and not c and np.isfinite(x) and x > 0
        good[p] = g
        range_m[p] = x if g else zero
        if not colour:
            continue
        if s:
            src = own_i[p] if own_ok[p] else splat_i[p]
            for ch in range(3):
                bgr[p, ch] = rgb[src, 2 - ch]
        else:
            for ch in range(3):
                bgr[p, ch] = 0
