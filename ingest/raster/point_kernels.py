"""Compiled (numba, parallel) per-point stages of the renderer: transform, view test, z-buffer, average.

Each kernel does in one pass over the points what `ingest.raster.reference` and
`ingest.raster.visibility` do in numpy with one full-length temporary per
operation: the numpy path reads and writes every point's arrays a dozen
times, a fused loop once. The arithmetic is the numpy path's, operation by
operation and in the same precision (float32 where numpy keeps float32,
float64 where numpy promotes), so both give the same numbers.

The points in view are packed by groups of ROW_GROUP image rows (a stable
counting sort: inside a group they keep their selection order), so the
scatters that follow (z-buffer, per-pixel sums) write a few rows at a time,
and run in parallel bands of groups: a band reads the points of its groups
(and, for footprints, of the groups beside them) and writes only its own
rows, so no two threads write one pixel and every pixel sees its points in
selection order, as numpy does. Each point carries its index in selection
order, which the z-buffer keys use, so ties resolve as in numpy.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import njit, prange

from calibration.types import I64

CHUNK = 1 << 16  # points per parallel work item where output positions need a prefix sum
ROW_GROUP = 8  # rows per sort bin: 8 rows of keys and sums stay in a core's L2


def n_bands(n_groups: int) -> int:
    """Bands of row groups for the scatter kernels: four per thread (balance), at most one per group."""
    return max(1, min(n_groups, 4 * numba.get_num_threads()))


def n_groups(H: int) -> int:
    return -(-H // ROW_GROUP)


@njit(cache=True, nogil=True, inline="always")
def _to_camera(xyz, j, R, t):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Point ``xyz[j]`` in the camera (R, t) and its range from the scan origin."""
    px, py, pz = xyz[j, 0], xyz[j, 1], xyz[j, 2]
    x = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t[0]
    y = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t[1]
    z = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t[2]
    return x, y, z, np.sqrt(px * px + py * py + pz * pz)


@njit(parallel=True, cache=True, nogil=True)
def transform(xyz, idx, R, t, x, y, z, r, pn):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Points ``xyz[idx]`` into the camera (x, y, z), their range from it and from the scan origin."""
    for i in prange(idx.shape[0]):
        xi, yi, zi, pn[i] = _to_camera(xyz, idx[i], R, t)
        x[i] = xi
        y[i] = yi
        z[i] = zi
        r[i] = np.sqrt(xi * xi + yi * yi + zi * zi)


@njit(parallel=True, cache=True, nogil=True)
def transform_ds(xyz, idx, R, t, ds, u, v, ok, r, pn):  # type: ignore[no-untyped-def]  # pragma: no cover
    """`transform` and the Double Sphere projection in one pass (float32, in numpy's order of operations).

    ``ds`` = float32 (xi, alpha, 1 - alpha, -w2, fx, fy, cx, cy): the
    operations of `DoubleSphere._project_normalised` and `FocalModel._project`,
    validity as `calibration.virtual.project_f32` gives it.
    """
    one = np.float32(1.0)
    xi, alpha, beta, mw2, fx, fy, cx, cy = ds[0], ds[1], ds[2], ds[3], ds[4], ds[5], ds[6], ds[7]
    for i in prange(idx.shape[0]):
        x, y, z, pn[i] = _to_camera(xyz, idx[i], R, t)
        r[i] = np.sqrt(x * x + y * y + z * z)
        r2 = x * x + y * y
        d1 = np.sqrt(z * z + r2)
        k = d1 * xi + z
        m = np.sqrt(k * k + r2) * alpha + k * beta
        valid = (z > d1 * mw2) & (m > 0)
        m = one / m
        ui = x * m * fx + cx
        vi = y * m * fy + cy
        u[i] = ui
        v[i] = vi
        ok[i] = valid & np.isfinite(ui) & np.isfinite(vi)


@njit(parallel=True, cache=True, nogil=True)
def count_in_view(u, v, ok, r, near, far, W, H, counts):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Per chunk of CHUNK points and row group: how many land there, within (``near``, ``far``].

    ``counts`` is (chunks, row groups).
    """
    n = u.shape[0]
    half = np.float32(0.5)
    for c in prange(counts.shape[0]):
        counts[c, :] = 0
        for i in range(c * CHUNK, min(n, (c + 1) * CHUNK)):
            if ok[i] and r[i] > near and r[i] <= far:
                col = np.floor(u[i] + half)
                row = np.floor(v[i] + half)
                if col >= 0 and col < W and row >= 0 and row < H:
                    counts[c, np.int64(row) // ROW_GROUP] += 1


@njit(parallel=True, cache=True, nogil=True)
def write_in_view(  # type: ignore[no-untyped-def]  # pragma: no cover
    u, v, ok, r, pn, sp, idx, rgb, colour, near, far, W, H, offsets, chunk_base, ppr_u, ppr_v, stride, scale,
    k_max, hist, out_pix, out_u, out_v, out_r, out_ku, out_kv, out_src, out_order, out_rgb,
):  # fmt: skip
    """The points `count_in_view` counted, packed by row group: pixel, position, range, footprint.

    ``offsets[c, g]`` is where chunk c's points of group g start. Footprint
    half-widths: scale x spacing at the scanner x range from the scanner /
    range from the camera x local pixels per radian, + 0.5 and truncated
    (whole pixels), at most ``k_max``; ``hist[c]`` counts chunk c's points
    per (ku, kv) as ku * (k_max + 1) + kv. ``out_src`` is each point's index
    into the scan, ``out_order`` its index in selection order, ``out_rgb``
    its colour (left as it is when ``colour`` is off).
    """
    n = u.shape[0]
    half = np.float32(0.5)
    kf = np.float32(k_max)
    inv_s = 1.0 / stride
    for c in prange(offsets.shape[0]):
        o = offsets[c].copy()
        m = chunk_base[c]
        hist[c, :] = 0
        for i in range(c * CHUNK, min(n, (c + 1) * CHUNK)):
            if not (ok[i] and r[i] > near and r[i] <= far):
                continue
            colf = np.floor(u[i] + half)
            rowf = np.floor(v[i] + half)
            if not (colf >= 0 and colf < W and rowf >= 0 and rowf < H):
                continue
            col, row = np.int64(colf), np.int64(rowf)
            foot = sp[i] * pn[i] / r[i]
            cu, cv = np.int64((colf + half) * inv_s), np.int64((rowf + half) * inv_s)
            g = row // ROW_GROUP
            j = o[g]
            o[g] += 1
            out_pix[j] = row * W + col
            out_u[j] = u[i]
            out_v[j] = v[i]
            out_r[j] = r[i]
            a = np.int16(min(kf, scale * foot * ppr_u[cv, cu] + half))
            b = np.int16(min(kf, scale * foot * ppr_v[cv, cu] + half))
            out_ku[j] = a
            out_kv[j] = b
            hist[c, a * (k_max + 1) + b] += 1
            s = idx[i]
            out_src[j] = s
            out_order[j] = m
            if colour:
                out_rgb[j, 0] = rgb[s, 0]
                out_rgb[j, 1] = rgb[s, 1]
                out_rgb[j, 2] = rgb[s, 2]
            m += 1


@njit(cache=True, nogil=True)
def _key(r, i, quantum, base, q_max, idx_bits):  # type: ignore[no-untyped-def]  # pragma: no cover
    q = min(np.int64(np.rint(r / quantum)), q_max)
    return base + (q << idx_bits) + i


@njit(parallel=True, cache=True, nogil=True)
def zbuffer_bands(  # type: ignore[no-untyped-def]  # pragma: no cover
    pix, order, r, ku, kv, seg, k1, k_max, span_start, span_dr, span_c0, span_c1, layer_of, H, W, bands,
    quantum, base, q_max, idx_bits, own, splat, layers, with_own,
):  # fmt: skip
    """`ingest.raster.kernels.zbuffer_keys` with the keys made here, in parallel bands of row groups.

    ``seg[s, g]`` is where source s's points of row group g start. A point
    covers, per footprint class cls = ku * k1 + kv, the row spans
    ``span_start[cls]:span_start[cls + 1]`` of (drow, dcol0..dcol1). Points of
    a class with a layer (``layer_of[cls]`` >= 0: a class with many points)
    only write their own pixel's minimum into that layer, which
    `dilate_layers` spreads over the spans afterwards; the others write their
    spans here.
    """
    G = seg.shape[1] - 1
    reach = -(-k_max // ROW_GROUP)
    inv_w = 1.0 / W
    for b in prange(bands):
        g0 = b * G // bands
        g1 = (b + 1) * G // bands
        r0 = g0 * ROW_GROUP
        r1 = min(H, g1 * ROW_GROUP)
        for s in range(seg.shape[0]):
            for i in range(seg[s, max(0, g0 - reach)], seg[s, min(G, g1 + reach)]):
                p = pix[i]
                row = np.int64((p + 0.5) * inv_w)  # p // W without an integer division
                if row + kv[i] < r0 or row - kv[i] >= r1:
                    continue
                k = _key(r[i], order[i], quantum, base, q_max, idx_bits)
                inside = row >= r0 and row < r1
                if with_own and inside and k < own[p]:
                    own[p] = k
                cls = ku[i] * k1 + kv[i]
                li = layer_of[cls]
                if li >= 0:
                    if inside and k < layers[li, p]:
                        layers[li, p] = k
                    continue
                c = p - row * W
                for j in range(span_start[cls], span_start[cls + 1]):
                    rr = row + span_dr[j]
                    if rr < r0 or rr >= r1:
                        continue
                    q0 = rr * W
                    for cc in range(max(0, c + span_c0[j]), min(W, c + span_c1[j] + 1)):
                        splat[q0 + cc] = min(splat[q0 + cc], k)


DILATE_ROWS = 32  # output rows per parallel work item of `dilate_layers`


@njit(parallel=True, cache=True, nogil=True)
def dilate_layers(layers, layer_cls, span_start, span_dr, span_w, H, W, splat):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Spread each layer's keys over its class's spans into ``splat`` (a min filter, in parallel row blocks).

    Spans are symmetric (columns -w..w, as every ellipse's are): pixel (q, x)
    takes, for each span (drow, w), the minimum of the layer's row q - drow
    over columns x - w .. x + w (clipped to the image). Those row minima are
    built once per source row and width, each width from the one before
    (for w >= 2 the minimum over x - w .. x + w is that of the width w - 1
    minima at x - 1 and x + 1), so a span costs one comparison per pixel
    whatever its width.
    """
    n_blocks = (H + DILATE_ROWS - 1) // DILATE_ROWS
    for b in prange(n_blocks):
        q0 = b * DILATE_ROWS
        q1 = min(H, q0 + DILATE_ROWS)
        for li in range(layers.shape[0]):
            cls = layer_cls[li]
            a, e = span_start[cls], span_start[cls + 1]
            if a == e:
                continue
            d_lo, d_hi, w_cls = span_dr[a], span_dr[a], 0
            for j in range(a, e):
                d_lo = min(d_lo, span_dr[j])
                d_hi = max(d_hi, span_dr[j])
                w_cls = max(w_cls, span_w[j])
            s0 = max(0, q0 - d_hi)
            s1 = min(H, q1 - d_lo)
            if s1 <= s0:
                continue
            rowmin = np.empty((s1 - s0, w_cls + 1, W), np.int64)
            for sr in range(s0, s1):
                m = rowmin[sr - s0]
                m[0, :] = layers[li, sr * W : (sr + 1) * W]
                for w in range(1, w_cls + 1):
                    prev, cur = m[w - 1], m[w]
                    cur[0] = min(prev[0], prev[min(1, W - 1)])
                    if w == 1:
                        for x in range(1, W - 1):
                            cur[x] = min(prev[x - 1], min(prev[x], prev[x + 1]))
                    else:  # the two width w - 1 windows overlap: they cover x - w .. x + w
                        for x in range(1, W - 1):
                            cur[x] = min(prev[x - 1], prev[x + 1])
                    cur[W - 1] = min(prev[max(W - 2, 0)], prev[W - 1])
            for q in range(q0, q1):
                out = splat[q * W : (q + 1) * W]
                for j in range(a, e):
                    sr = q - span_dr[j]
                    if sr < s0 or sr >= s1:
                        continue
                    v = rowmin[sr - s0, span_w[j]]
                    for x in range(W):
                        out[x] = min(out[x], v[x])


@njit(parallel=True, cache=True, nogil=True)
def average_bands(  # type: ignore[no-untyped-def]  # pragma: no cover
    pix, u, v, r, seg, own_ok, R, gu, gv, ppr, tau_m, tau_rel, slope1, W, bands, value
):  # fmt: skip
    """`ingest.raster.visibility.average_surface` in bands of row groups: points moved and averaged, in place.

    A point counts when its pixel has an own point and its range is within
    the one-pixel tolerance of that point's (float32); it is moved to the
    pixel centre along the gradient in float64 and the float64 sum of a
    pixel runs in selection order, as `np.bincount` does.
    """
    G = seg.shape[1] - 1
    H = value.shape[0] // W
    inv_w = 1.0 / W
    for b in prange(bands):
        g0 = b * G // bands
        g1 = (b + 1) * G // bands
        p0 = g0 * ROW_GROUP * W
        p1 = min(H, g1 * ROW_GROUP) * W
        sums = np.zeros(p1 - p0, np.float64)
        counts = np.zeros(p1 - p0, np.int64)
        for s in range(seg.shape[0]):
            for i in range(seg[s, g0], seg[s, g1]):
                p = pix[i]
                if not own_ok[p]:
                    continue
                ref = R[p]
                if not (r[i] <= ref + (tau_m + ref * (tau_rel + slope1 / ppr[p]))):
                    continue
                row = np.int64((p + 0.5) * inv_w)  # p // W without an integer division
                col = p - row * W
                du = np.float64(u[i]) - col
                dv = np.float64(v[i]) - row
                sums[p - p0] += np.float64(r[i]) - np.float64(gu[p]) * du - np.float64(gv[p]) * dv
                counts[p - p0] += 1
        for p in range(p0, p1):
            if counts[p - p0] > 0:
                value[p] = np.float32(sums[p - p0] / counts[p - p0])


def in_view_offsets(counts: I64) -> tuple[I64, I64, I64, int]:
    """From (chunks, groups) counts: where each chunk's points of each group start (groups in order, then
    chunks), how many points precede each chunk in selection order, where each group starts, the total."""
    flat = np.ascontiguousarray(counts.T).reshape(-1)  # over (group, chunk)
    starts = np.zeros(len(flat) + 1, np.int64)
    np.cumsum(flat, out=starts[1:])
    n_chunks, groups = counts.shape
    offsets: I64 = np.ascontiguousarray(starts[:-1].reshape(groups, n_chunks).T)
    per_chunk = counts.sum(axis=1)
    chunk_base = np.zeros(n_chunks, np.int64)
    np.cumsum(per_chunk[:-1], out=chunk_base[1:])
    group_start: I64 = starts[::n_chunks].copy()
    return offsets, chunk_base, group_start, int(starts[-1])


def ellipse_spans(start: I64, drow: np.ndarray, dcol: np.ndarray) -> tuple[I64, I64, I64, I64]:
    """`kernels.ellipse_offsets` as row runs per class: (span_start, drow, dcol0, dcol1), dcol1 inclusive."""
    s_start: list[int] = [0]
    s_dr: list[int] = []
    s_c0: list[int] = []
    s_c1: list[int] = []
    for c in range(len(start) - 1):
        a, b = start[c], start[c + 1]
        cells = sorted(zip(drow[a:b].tolist(), dcol[a:b].tolist(), strict=True))
        for dr, dc in cells:
            if s_dr and len(s_dr) > s_start[-1] and s_dr[-1] == dr and s_c1[-1] == dc - 1:
                s_c1[-1] = dc
            else:
                s_dr.append(dr)
                s_c0.append(dc)
                s_c1.append(dc)
        s_start.append(len(s_dr))
    return tuple(np.array(a, np.int64) for a in (s_start, s_dr, s_c0, s_c1))  # type: ignore[return-value]


# atan(t) = t + t^3 P(t^2) on |t| <= tan(pi/8): least squares on Chebyshev nodes, 4.5e-16 rad at most
_ATAN_P = (
    -0.33333333333145027, 0.19999999965801685, -0.14285711953394978, 0.11111029048374284,
    -0.09089216756095257, 0.0767060167553234, -0.06489846530297048, 0.049765973385356765,
    -0.02471432071364193,
)  # fmt: skip
_TAN_PI_8 = 0.41421356237309503


@njit(cache=True, nogil=True, inline="always")
def atan2(y, x):  # type: ignore[no-untyped-def]  # pragma: no cover
    """`math.atan2` in float64 within 1e-15 rad, about 4x faster than the libm call numba makes.

    Octant folding, one more halving of the range (atan a = pi/4 + atan((a - 1)/(a + 1))) and a
    polynomial; zero and non-finite arguments go to `math.atan2` (signed zeros, infinities).
    """
    ax, ay = abs(x), abs(y)
    hi, lo = max(ax, ay), min(ax, ay)
    if not (hi > 0.0 and math.isfinite(x) and math.isfinite(y)):
        return math.atan2(y, x)
    a = lo / hi
    big = a > _TAN_PI_8
    t = (a - 1.0) / (a + 1.0) if big else a  # selects, not branches: the octants come in random order
    s = t * t
    c0, c1, c2, c3, c4, c5, c6, c7, c8 = _ATAN_P
    p = (((((((c8 * s + c7) * s + c6) * s + c5) * s + c4) * s + c3) * s + c2) * s + c1) * s + c0
    th = (math.pi / 4.0 if big else 0.0) + (t + t * s * p)
    th = math.pi / 2.0 - th if ay > ax else th
    th = math.pi - th if x < 0.0 else th
    return -th if math.copysign(1.0, y) < 0.0 else th


@njit(cache=True, nogil=True)
def sphere_cells(xyz, n_u, n_az, cell, counts):  # type: ignore[no-untyped-def]  # pragma: no cover
    """`lod.angular_spacing`'s equal-area cell of each point (cos polar x azimuth) and the points per cell.

    float32 as numpy computes it (``counts`` zeroed by the caller), but the
    azimuth is the float64 arctangent rounded to float32: libm's float32
    arctangent (numpy's) is sometimes an ulp off, and a point that close to a
    cell's edge may fall on its other side.
    """
    half_u = np.float32(n_u / 2.0)
    per_rad = np.float32(n_az / (2.0 * np.pi))
    pi, one, tiny = np.float32(np.pi), np.float32(1.0), np.float32(1e-12)
    for i in range(xyz.shape[0]):
        x, y, z = xyz[i, 0], xyz[i, 1], xyz[i, 2]
        r = np.sqrt(x * x + y * y + z * z)
        fu = (z / max(r, tiny) + one) * half_u
        cu = min(max(np.int64(fu), 0), n_u - 1) if fu >= 0 else 0  # NaN: cell 0, as numpy's cast and clip
        fa = (np.float32(atan2(np.float64(y), np.float64(x))) + pi) * per_rad
        ca = min(max(np.int64(fa), 0), n_az - 1) if fa >= 0 else 0
        c = cu * n_az + ca
        cell[i] = c
        counts[c] += 1


@njit(parallel=True, cache=True, nogil=True)
def invert_order(order, inv):  # type: ignore[no-untyped-def]  # pragma: no cover
    """inv[order[j]] = j: from a point's selection-order index to its position here."""
    for j in prange(order.shape[0]):
        inv[order[j]] = j


def chunks(n: int) -> int:
    return max(1, -(-n // CHUNK))
