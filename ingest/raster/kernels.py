"""Compiled (numba) kernels of the renderer's per-point loops, and dense GT's planar resampling.

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


@njit(cache=True, nogil=True, inline="always")
def _point(range_src, rays_src, r, c):  # type: ignore[no-untyped-def]  # pragma: no cover
    """The source point (x, y, z) of pixel (r, c) and whether it has one."""
    H, W = range_src.shape
    if r < 0 or r >= H or c < 0 or c >= W:
        return False, 0.0, 0.0, 0.0
    rng = np.float64(range_src[r, c])
    if not rng > 0.0:
        return False, 0.0, 0.0, 0.0
    return True, rays_src[r, c, 0] * rng, rays_src[r, c, 1] * rng, rays_src[r, c, 2] * rng


@njit(cache=True, nogil=True, inline="always")
def _tangent(has, nb, lo, hi, centre):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Tangent through neighbour rows ``lo``, ``centre``, ``hi`` of ``nb``: across both, else towards the
    one with a point; and whether there is one."""
    if has[lo] and has[hi]:
        return True, nb[hi, 0] - nb[lo, 0], nb[hi, 1] - nb[lo, 1], nb[hi, 2] - nb[lo, 2]
    if has[hi]:
        return True, nb[hi, 0] - nb[centre, 0], nb[hi, 1] - nb[centre, 1], nb[hi, 2] - nb[centre, 2]
    if has[lo]:
        return True, nb[centre, 0] - nb[lo, 0], nb[centre, 1] - nb[lo, 1], nb[centre, 2] - nb[lo, 2]
    return False, 0.0, 0.0, 0.0


@njit(cache=True, nogil=True, error_model="numpy")
def _resample(range_src, rays_src, pixels, start, order, rays_dst, min_cos, tol_m, tol_rel, max_change, out):  # type: ignore[no-untyped-def]  # pragma: no cover
    W = range_src.shape[1]
    nb = np.empty((9, 3), np.float64)  # the 3x3 neighbourhood's points, row-major; centre 4
    has = np.empty(9, np.bool_)
    for i in range(pixels.shape[0]):
        q = pixels[i]
        if start[q] == start[q + 1]:
            continue
        r = q // W
        c = q - r * W
        n_pts = 0
        for k in range(9):
            has[k], nb[k, 0], nb[k, 1], nb[k, 2] = _point(range_src, rays_src, r + k // 3 - 1, c + k % 3 - 1)
            n_pts += has[k]
        if not has[4] or n_pts < 4:  # three points always lie on a plane: at least one must check it
            continue
        has_u, ux, uy, uz = _tangent(has, nb, 3, 5, 4)
        has_v, vx, vy, vz = _tangent(has, nb, 1, 7, 4)
        if not (has_u and has_v):
            continue
        nx = uy * vz - uz * vy
        ny = uz * vx - ux * vz
        nz = ux * vy - uy * vx
        norm = np.sqrt(nx * nx + ny * ny + nz * nz)
        if not norm > 1e-9 * np.sqrt((ux * ux + uy * uy + uz * uz) * (vx * vx + vy * vy + vz * vz)):
            continue  # (nearly) parallel tangents: no plane
        nx, ny, nz = nx / norm, ny / norm, nz / norm
        # the 3x3 neighbours that hold a point must lie on that plane
        x0, y0, z0 = nb[4, 0], nb[4, 1], nb[4, 2]
        rng0 = np.float64(range_src[r, c])
        tol = tol_m + tol_rel * rng0
        flat = True
        for k in range(9):
            if has[k] and abs(nx * (nb[k, 0] - x0) + ny * (nb[k, 1] - y0) + nz * (nb[k, 2] - z0)) > tol:
                flat = False
        if not flat:
            continue
        d0 = nx * x0 + ny * y0 + nz * z0
        for k in range(start[q], start[q + 1]):
            j = order[k]
            cos = nx * rays_dst[j, 0] + ny * rays_dst[j, 1] + nz * rays_dst[j, 2]
            if abs(cos) < min_cos:
                continue
            t = d0 / cos
            if t > 0.0 and abs(t - rng0) <= max_change * rng0:
                out[j] = t


def nearest_pixel_groups(uv: F64, width: int, height: int) -> tuple[I64, I32]:
    """The rays grouped by their nearest source pixel: (start (H W + 1), order) as in CSR.

    `uv` (N, 2) are where N rays project in a (height, width) image (pixel
    centres at integers; NaN: nowhere). The rays whose nearest pixel is
    flat pixel q are ``order[start[q]:start[q + 1]]`` (int32).
    """
    with np.errstate(invalid="ignore"):
        near = np.floor(uv + 0.5)
        ok = (near[:, 0] >= 0) & (near[:, 0] < width) & (near[:, 1] >= 0) & (near[:, 1] < height)
    q = (near[ok, 1] * width + near[ok, 0]).astype(np.int64)
    rays = np.flatnonzero(ok)
    by_pixel = np.argsort(q, kind="stable")
    start = np.zeros(width * height + 1, np.int64)
    np.cumsum(np.bincount(q, minlength=width * height), out=start[1:])
    return start, rays[by_pixel].astype(np.int32)


def planar_resample(
    range_src: F32, rays_src: F32, pixels: I64, start: I64, order: I32, rays_dst: F32, min_cos: float,
    tol_m: float, tol_rel: float, max_change: float,
) -> F32:  # fmt: skip
    """Range (m) along each ray of a second view with the same centre, from a range image's local planes.

    `range_src` (H, W) holds ranges along the unit rays `rays_src` (H, W, 3)
    (0: no value) at the flat `pixels`; (`start`, `order`) group the N
    `rays_dst` (unit, in the source view's frame) by their nearest source
    pixel (`nearest_pixel_groups`). A ray gets a range only where its
    nearest pixel holds one, has a neighbour with one along each image axis
    and at least four of its 3x3 pixels hold one, all within `tol_m` +
    `tol_rel` x range of one plane (the plane through the pixel's point and
    its tangents across those neighbours): the ray meets that plane there,
    exact on planes, unless it grazes it (|n . ray| < `min_cos`) or the
    result differs from the pixel's range by more than `max_change` of it.
    0 elsewhere.
    """
    out = np.zeros(len(rays_dst), np.float32)
    _resample(range_src, rays_src, pixels, start, order, rays_dst, min_cos, tol_m, tol_rel, max_change, out)
    return out
