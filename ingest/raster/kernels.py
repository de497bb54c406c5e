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


@njit(cache=True, nogil=True)
def _point(range_src, rays_src, r, c, out):  # type: ignore[no-untyped-def]  # pragma: no cover
    """The source point of pixel (r, c) into ``out``; False when it has none."""
    H, W = range_src.shape
    if r < 0 or r >= H or c < 0 or c >= W:
        return False
    rng = range_src[r, c]
    if not rng > 0.0:
        return False
    out[0] = rays_src[r, c, 0] * rng
    out[1] = rays_src[r, c, 1] * rng
    out[2] = rays_src[r, c, 2] * rng
    return True


@njit(cache=True, nogil=True)
def _tangent(range_src, rays_src, r, c, dr, dc, p0, a, b, t):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Tangent at pixel (r, c) along (dr, dc) into ``t``: across both neighbours, else towards one."""
    has_a = _point(range_src, rays_src, r - dr, c - dc, a)
    has_b = _point(range_src, rays_src, r + dr, c + dc, b)
    if has_a and has_b:
        for i in range(3):
            t[i] = b[i] - a[i]
    elif has_b:
        for i in range(3):
            t[i] = b[i] - p0[i]
    elif has_a:
        for i in range(3):
            t[i] = p0[i] - a[i]
    else:
        return 0
    return int(has_a) + int(has_b)


@njit(cache=True, nogil=True)
def _resample(range_src, rays_src, uv, rays_dst, min_cos, tol_m, tol_rel, out):  # type: ignore[no-untyped-def]  # pragma: no cover
    buf = np.empty((5, 3), np.float64)
    p0, a, b, tu, tv = buf[0], buf[1], buf[2], buf[3], buf[4]
    for j in range(uv.shape[0]):
        out[j] = 0.0
        uf, vf = uv[j, 0], uv[j, 1]
        if not (uf > -0.5 and vf > -0.5):  # also NaN: no projection
            continue
        c = int(uf + 0.5)
        r = int(vf + 0.5)
        if not _point(range_src, rays_src, r, c, p0):
            continue
        if _tangent(range_src, rays_src, r, c, 0, 1, p0, a, b, tu) == 0:
            continue
        if _tangent(range_src, rays_src, r, c, 1, 0, p0, a, b, tv) == 0:
            continue
        nx = tu[1] * tv[2] - tu[2] * tv[1]
        ny = tu[2] * tv[0] - tu[0] * tv[2]
        nz = tu[0] * tv[1] - tu[1] * tv[0]
        norm = np.sqrt(nx * nx + ny * ny + nz * nz)
        if norm == 0.0:
            continue
        nx, ny, nz = nx / norm, ny / norm, nz / norm
        # the 3x3 neighbours that hold a point must lie on that plane
        rng0 = range_src[r, c]
        tol = tol_m + tol_rel * rng0
        flat = True
        for dr in range(-1, 2):
            for dc in range(-1, 2):
                off = (
                    _point(range_src, rays_src, r + dr, c + dc, a)
                    and abs(nx * (a[0] - p0[0]) + ny * (a[1] - p0[1]) + nz * (a[2] - p0[2])) > tol
                )
                if off:
                    flat = False
        if not flat:
            continue
        dx, dy, dz = rays_dst[j, 0], rays_dst[j, 1], rays_dst[j, 2]
        cos = nx * dx + ny * dy + nz * dz
        if abs(cos) < min_cos:
            continue
        t = (nx * p0[0] + ny * p0[1] + nz * p0[2]) / cos
        if t > 0.0 and abs(t - rng0) <= tol + 0.05 * rng0:
            out[j] = t


def planar_resample(
    range_src: F32, rays_src: F32, uv: F32, rays_dst: F32, min_cos: float, tol_m: float, tol_rel: float
) -> F32:
    """Range (m) along each ray of a second view with the same centre, from a range image's local planes.

    `range_src` (H, W) holds ranges along the unit rays `rays_src` (H, W, 3)
    (0: no value); `uv` (N, 2) is where each of the N `rays_dst` (unit, in
    the source view's frame) projects in the source image (pixel centres at
    integers; NaN: nowhere). A ray gets a range only where the four source
    pixels around its projection all hold one and their points lie on one
    plane within `tol_m` + `tol_rel` x range: the ray meets that plane there
    (exact on planes), unless it grazes it (|n . ray| < `min_cos`) or the
    result leaves the four ranges' span by more than the tolerance. 0 elsewhere.
    """
    out = np.empty(len(uv), np.float32)
    _resample(range_src, rays_src, uv, rays_dst, min_cos, tol_m, tol_rel, out)
    return out
