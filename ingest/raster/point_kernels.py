"""Compiled (numba, parallel) per-point stages of the renderer: transform, view test, footprint, z-buffer, average.

Each kernel does in one pass over the points what `ingest.raster.view` and
`ingest.raster.visibility` do in numpy with one full-length temporary per
operation: the numpy path reads and writes every point's arrays a dozen
times, a fused loop once. The arithmetic is the numpy path's, operation by
operation and in the same precision (float32 where numpy keeps float32,
float64 where numpy promotes), so both give the same numbers.

Work that scatters into pixels (z-buffer, per-pixel sums) runs in row bands:
every band reads all points and writes only its own rows, so no two threads
write one pixel and each pixel sees its points in point order, as in numpy.
"""

from __future__ import annotations

import numba
import numpy as np
from numba import njit, prange

from calibration.types import I64

CHUNK = 1 << 16  # points per parallel work item where output positions need a prefix sum


def n_bands(H: int) -> int:
    """Row bands for the scatter kernels: two per thread (some balance), never more than the rows."""
    return max(1, min(H, 2 * numba.get_num_threads()))


@njit(parallel=True, cache=True, nogil=True)
def transform(xyz, idx, R, t, x, y, z, r, pn):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Points ``xyz[idx]`` into the camera (x, y, z), their range from it and from the scan origin (float32)."""
    for i in prange(idx.shape[0]):
        j = idx[i]
        px, py, pz = xyz[j, 0], xyz[j, 1], xyz[j, 2]
        xi = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t[0]
        yi = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t[1]
        zi = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t[2]
        x[i] = xi
        y[i] = yi
        z[i] = zi
        r[i] = np.sqrt(xi * xi + yi * yi + zi * zi)
        pn[i] = np.sqrt(px * px + py * py + pz * pz)


@njit(parallel=True, cache=True, nogil=True)
def count_in_view(u, v, ok, r, near, far, W, H, counts):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Per chunk of CHUNK points: how many project into the image, nearer than ``far``, farther than ``near``."""
    n = u.shape[0]
    half = np.float32(0.5)
    for c in prange(counts.shape[0]):
        m = 0
        for i in range(c * CHUNK, min(n, (c + 1) * CHUNK)):
            if ok[i] and r[i] > near and r[i] <= far:
                col = np.floor(u[i] + half)
                row = np.floor(v[i] + half)
                if col >= 0 and col < W and row >= 0 and row < H:
                    m += 1
        counts[c] = m


@njit(parallel=True, cache=True, nogil=True)
def write_in_view(  # type: ignore[no-untyped-def]  # pragma: no cover
    u, v, ok, r, pn, sp, idx, near, far, W, H, offsets, ppr_u, ppr_v, stride, scale, k_max,
    out_pix, out_u, out_v, out_r, out_ku, out_kv, out_src,
):  # fmt: skip
    """The points `count_in_view` counted, packed in order: pixel, sub-pixel position, range, footprint.

    Footprint half-widths: scale x spacing at the scanner x range from the
    scanner / range from the camera x local pixels per radian, + 0.5 and
    truncated (whole pixels), at most ``k_max``. ``out_src`` is each kept
    point's index into the scan.
    """
    n = u.shape[0]
    half = np.float32(0.5)
    kf = np.float32(k_max)
    for c in prange(offsets.shape[0]):
        o = offsets[c]
        for i in range(c * CHUNK, min(n, (c + 1) * CHUNK)):
            if not (ok[i] and r[i] > near and r[i] <= far):
                continue
            colf = np.floor(u[i] + half)
            rowf = np.floor(v[i] + half)
            if not (colf >= 0 and colf < W and rowf >= 0 and rowf < H):
                continue
            col, row = np.int64(colf), np.int64(rowf)
            foot = sp[i] * pn[i] / r[i]
            cu, cv = col // stride, row // stride
            out_pix[o] = row * W + col
            out_u[o] = u[i]
            out_v[o] = v[i]
            out_r[o] = r[i]
            out_ku[o] = np.int16(min(kf, scale * foot * ppr_u[cv, cu] + half))
            out_kv[o] = np.int16(min(kf, scale * foot * ppr_v[cv, cu] + half))
            out_src[o] = idx[i]
            o += 1


@njit(cache=True, nogil=True)
def _key(r, i, quantum, base, q_max, idx_bits):  # type: ignore[no-untyped-def]  # pragma: no cover
    q = min(np.int64(np.rint(r / quantum)), q_max)
    return base + (q << idx_bits) + i


@njit(parallel=True, cache=True, nogil=True)
def zbuffer_bands(  # type: ignore[no-untyped-def]  # pragma: no cover
    pix, r, ku, kv, k1, start, drow, dcol, H, W, bands, quantum, base, q_max, idx_bits, own, splat, with_own
):  # fmt: skip
    """`ingest.raster.kernels.zbuffer_keys` with the keys made here, in ``bands`` row bands in parallel."""
    n = pix.shape[0]
    for b in prange(bands):
        r0 = b * H // bands
        r1 = (b + 1) * H // bands
        for i in range(n):
            p = pix[i]
            row = p // W
            if row + kv[i] < r0 or row - kv[i] >= r1:
                continue
            k = _key(r[i], i, quantum, base, q_max, idx_bits)
            if with_own and row >= r0 and row < r1 and k < own[p]:
                own[p] = k
            c = p - row * W
            cls = ku[i] * k1 + kv[i]
            for j in range(start[cls], start[cls + 1]):
                rr = row + drow[j]
                cc = c + dcol[j]
                if rr >= r0 and rr < r1 and cc >= 0 and cc < W:
                    q = rr * W + cc
                    if k < splat[q]:
                        splat[q] = k


@njit(parallel=True, cache=True, nogil=True)
def average_bands(  # type: ignore[no-untyped-def]  # pragma: no cover
    pix, u, v, r, own_ok, R, gu, gv, ppr, tau_m, tau_rel, slope1, W, bands, value
):  # fmt: skip
    """`ingest.raster.visibility.average_surface` in row bands: same-surface points moved and averaged, in place.

    A point counts when its pixel has an own point and its range is within
    the one-pixel tolerance of that point's (float32); it is moved to the
    pixel centre along the gradient in float64 and the float64 sum of a
    pixel runs in point order, as `np.bincount` does.
    """
    n = pix.shape[0]
    H = value.shape[0] // W
    sums = np.zeros(value.shape[0], np.float64)
    counts = np.zeros(value.shape[0], np.int64)
    for b in prange(bands):
        p0 = (b * H // bands) * W
        p1 = ((b + 1) * H // bands) * W
        for i in range(n):
            p = pix[i]
            if p < p0 or p >= p1 or not own_ok[p]:
                continue
            ref = R[p]
            if not (r[i] <= ref + (tau_m + ref * (tau_rel + slope1 / ppr[p]))):
                continue
            row = p // W
            col = p - row * W
            du = np.float64(u[i]) - col
            dv = np.float64(v[i]) - row
            sums[p] += np.float64(r[i]) - np.float64(gu[p]) * du - np.float64(gv[p]) * dv
            counts[p] += 1
        for p in range(p0, p1):
            if counts[p] > 0:
                value[p] = np.float32(sums[p] / counts[p])


def in_view_offsets(counts: I64) -> tuple[I64, int]:
    """Start of each chunk's kept points, and their total."""
    offsets: I64 = np.zeros(len(counts), np.int64)
    np.cumsum(counts[:-1], out=offsets[1:])
    return offsets, int(counts.sum())


def chunks(n: int) -> int:
    return max(1, -(-n // CHUNK))

