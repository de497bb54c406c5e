"""Compiled (numba) kernels of the renderer's per-point loops.

The z-buffer writes every point's key into its own pixel and into each pixel
of its footprint ellipse, keeping the minimum: one pass over the points,
whose cost is the sum of the footprints. The numpy alternative
(`ingest.raster.visibility.zbuffer_erode`) has to erode a full-image buffer
once per footprint class instead, which costs the image size times the number
of classes whatever the number of points, and dominated the dense GT render.
The footprints are cv2's own elliptic structuring elements, so both give the
same keys bit for bit.

Kernels are compiled on first use and cached on disk (`cache=True`).
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np
from numba import njit

from calibration.types import F32, F64, I64, Bool

I32 = np.ndarray[tuple[int], np.dtype[np.int32]]


@lru_cache(maxsize=8)
def ellipse_offsets(k_max: int) -> tuple[I64, I32, I32]:
    """Pixel offsets of every footprint ellipse with half-widths (ku, kv) in 0..k_max.

    Class c = ku * (k_max + 1) + kv holds offsets ``start[c]:start[c + 1]`` of
    (drow, dcol): the pixels a point covers, i.e. those whose erosion by
    `cv2.getStructuringElement(MORPH_ELLIPSE, (2 ku + 1, 2 kv + 1))` reaches it.
    """
    k1 = k_max + 1
    starts = [0]
    drow: list[int] = []
    dcol: list[int] = []
    for ku in range(k1):
        for kv in range(k1):
            kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * ku + 1, 2 * kv + 1))
            rows, cols = np.nonzero(kernel)
            # erode: dst(y, x) = min src(y + dy, x + dx) over the kernel's (dy, dx), so a point at
            # (r, c) reaches the pixels (r - dy, c - dx)
            drow.extend((kv - rows).tolist())
            dcol.extend((ku - cols).tolist())
            starts.append(len(drow))
    return np.array(starts, np.int64), np.array(drow, np.int32), np.array(dcol, np.int32)


@njit(cache=True, nogil=True)
def _zbuffer(pix, key, ku, kv, k1, start, drow, dcol, H, W, own, splat):  # type: ignore[no-untyped-def]  # pragma: no cover
    for i in range(pix.shape[0]):
        p = pix[i]
        k = key[i]
        if k < own[p]:
            own[p] = k
        r = p // W
        c = p - r * W
        cls = ku[i] * k1 + kv[i]
        for j in range(start[cls], start[cls + 1]):
            rr = r + drow[j]
            cc = c + dcol[j]
            if rr >= 0 and rr < H and cc >= 0 and cc < W:
                q = rr * W + cc
                if k < splat[q]:
                    splat[q] = k


def zbuffer_keys(
    pix: I64, key: I64, ku: np.ndarray, kv: np.ndarray, H: int, W: int, own: I64, splat: I64
) -> None:
    """Minimum key per pixel into `own` (the point's pixel) and `splat` (its footprint), in place."""
    k_max = int(max(ku.max(), kv.max())) if len(ku) else 0
    start, drow, dcol = ellipse_offsets(k_max)
    _zbuffer(pix, key, ku, kv, k_max + 1, start, drow, dcol, H, W, own, splat)


@njit(cache=True, nogil=True)
def _snap(pts, normal, cols, rows, allowed, rays, ray_ok, radius, min_cos, out):  # type: ignore[no-untyped-def]  # pragma: no cover
    H, W = allowed.shape
    n_out = 0
    for i in range(pts.shape[0]):
        px, py, pz = pts[i, 0], pts[i, 1], pts[i, 2]
        nx, ny, nz = normal[i, 0], normal[i, 1], normal[i, 2]
        d = nx * px + ny * py + nz * pz
        for du in range(-radius, radius + 1):
            for dv in range(-radius, radius + 1):
                c = cols[i] + du
                r = rows[i] + dv
                if c < 0 or c >= W or r < 0 or r >= H or not allowed[r, c] or not ray_ok[r, c]:
                    continue
                rx, ry, rz = rays[r, c, 0], rays[r, c, 1], rays[r, c, 2]
                cos = nx * rx + ny * ry + nz * rz
                if abs(cos) < min_cos:
                    continue
                t = d / cos
                if not (t > 0.0 and t < np.inf):
                    continue
                out[n_out, 0] = rx * t
                out[n_out, 1] = ry * t
                out[n_out, 2] = rz * t
                n_out += 1
    return n_out


def snap_planar(
    pts: F64, normal: F64, cols: I64, rows: I64, allowed: Bool, rays: F32, ray_ok: Bool, radius: int,
    min_cos: float,
) -> F64:  # fmt: skip
    """Points where the pixel-centre rays around each point's pixel meet its plane (model frame, m).

    For every point and every pixel within `radius` of (cols, rows) that is
    `allowed` and has a ray (`rays`, (H, W, 3) unit vectors), the point
    t * ray with n . (t * ray) = n . p, unless the ray grazes the plane
    (|n . ray| < `min_cos`) or meets it behind the camera.
    """
    side = 2 * radius + 1
    out = np.empty((len(pts) * side * side, 3), np.float64)
    n_out = _snap(pts, normal, cols, rows, allowed, rays, ray_ok, radius, min_cos, out)
    kept: F64 = out[:n_out]
    return kept
