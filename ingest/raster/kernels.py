"""Compiled (numba) kernels of the renderer's per-point loops, and dense GT's planar resampling.

The z-buffer writes every point's key into its own pixel and into each pixel
of its footprint ellipse, keeping the minimum: one pass over the points,
whose cost is the sum of the footprints. A numpy z-buffer (the tests'
oracle, `tests/ingest/oracles.py`) has to erode a full-image buffer once per
footprint class instead, which costs the image size times the number of
classes whatever the number of points. The footprints are cv2's own elliptic
structuring elements, so both give the same keys bit for bit.

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
def _nearest(rows, cols, range_m, out):  # type: ignore[no-untyped-def]  # pragma: no cover
    for i in range(rows.shape[0]):
        if range_m[i] < out[rows[i], cols[i]]:
            out[rows[i], cols[i]] = range_m[i]


def nearest_range(rows: I64, cols: I64, range_m: F32, H: int, W: int) -> F32:
    """(H, W) float32: the least of `range_m` (m) per pixel (rows, cols, inside the image); inf where none
    (one compiled pass: a tenth of numpy's minimum.at)."""
    out = np.full((H, W), np.inf, np.float32)
    _nearest(rows, cols, range_m, out)
    return out


@njit(cache=True, nogil=True)
def _snap(pts, normal, cols, rows, front_m, rays, ray_ok, radius, min_cos, step_abs, step_rel, out):  # type: ignore[no-untyped-def]  # pragma: no cover
    H, W = front_m.shape
    n_out = 0
    for i in range(pts.shape[0]):
        px, py, pz = pts[i, 0], pts[i, 1], pts[i, 2]
        nx, ny, nz = normal[i, 0], normal[i, 1], normal[i, 2]
        d = nx * px + ny * py + nz * pz
        for du in range(-radius, radius + 1):
            for dv in range(-radius, radius + 1):
                c = cols[i] + du
                r = rows[i] + dv
                if c < 0 or c >= W or r < 0 or r >= H or not ray_ok[r, c]:
                    continue
                rx, ry, rz = rays[r, c, 0], rays[r, c, 1], rays[r, c, 2]
                cos = nx * rx + ny * ry + nz * rz
                if abs(cos) < min_cos:
                    continue
                t = d / cos
                if not (t > 0.0 and t < np.inf):
                    continue
                if not t + max(step_abs, step_rel * t) >= front_m[r, c]:  # inf: not allowed at all
                    continue
                out[n_out, 0] = rx * t
                out[n_out, 1] = ry * t
                out[n_out, 2] = rz * t
                n_out += 1
    return n_out


def snap_planar(
    pts: F64, normal: F64, cols: I64, rows: I64, front_m: F32, rays: F32, ray_ok: Bool, radius: int,
    min_cos: float, step_abs_m: float, step_rel: float,
) -> F64:  # fmt: skip
    """Points where the pixel-centre rays around each point's pixel meet its plane (model frame, m).

    For every point and every pixel within `radius` of (cols, rows) that has
    a ray (`rays`, (H, W, 3) unit vectors), the point t * ray with
    n . (t * ray) = n . p, unless the ray grazes the plane (|n . ray| <
    `min_cos`), meets it behind the camera, or t lies in front of the
    pixel's `front_m` (m; inf: no value there) by more than a range step,
    max(`step_abs_m`, `step_rel` x t).
    """
    side = 2 * radius + 1
    out = np.empty((len(pts) * side * side, 3), np.float64)
    n_out = _snap(pts, normal, cols, rows, front_m, rays, ray_ok, radius, min_cos, step_abs_m, step_rel, out)
    kept: F64 = out[:n_out]
    return kept


@njit(cache=True, nogil=True, error_model="numpy")
def _resample(range_src, rays_src, pixels, start, order, rays_dst, min_cos, tol_m, tol_rel, max_change, out):  # type: ignore[no-untyped-def]  # pragma: no cover
    """`planar_resample` per source pixel: the plane of its 3x3 points (`_pixel_plane`), met by its rays."""
    W = range_src.shape[1]
    inv_w = 1.0 / W
    xs, ys, ws = np.empty(9), np.empty(9), np.empty(9)
    for i in range(pixels.shape[0]):
        q = pixels[i]
        if start[q] == start[q + 1]:
            continue
        r = int((q + 0.5) * inv_w)  # q // W without an integer division
        c = q - r * W
        rng0 = float(range_src[r, c])
        if not rng0 > 0.0:
            continue
        flat, nx, ny, nz, d0 = _pixel_plane(range_src, rays_src, r, c, tol_m + tol_rel * rng0, xs, ys, ws)
        if not flat:
            continue
        for k in range(start[q], start[q + 1]):
            j = order[k]
            cos = nx * rays_dst[j, 0] + ny * rays_dst[j, 1] + nz * rays_dst[j, 2]
            if abs(cos) < min_cos:
                continue
            t = d0 / cos
            if t > 0.0 and abs(t - rng0) <= max_change * rng0:
                out[j] = t


@njit(cache=True, nogil=True, error_model="numpy")
def _pixel_plane(range_src, rays_src, r, c, tol, xs, ys, ws):  # type: ignore[no-untyped-def]  # pragma: no cover
    """(flat, nx, ny, nz, d0): the plane n . x = d0 of pixel (r, c)'s 3x3 points when every one lies
    within `tol` (m) of it, found in a frame along the pixel's ray; flat is False without one.

    The frame (u, v across the ray e, e along it) has its origin at the
    pixel's point: a neighbour at range r_k along ray d_k sits at
    (u . d_k r_k, v . d_k r_k, e . d_k r_k - r_0), so the plane's fit and its
    flatness test need no second pass over world coordinates. `xs`, `ys`,
    `ws` are scratch arrays of 9.
    """
    H, W = range_src.shape
    rng0 = float(range_src[r, c])
    ex, ey, ez = float(rays_src[r, c, 0]), float(rays_src[r, c, 1]), float(rays_src[r, c, 2])
    if abs(ex) < 0.9:  # u = e x (1, 0, 0), normalised
        ux, uy, uz = 0.0, ez, -ey
    else:  # e x (0, 1, 0)
        ux, uy, uz = -ez, 0.0, ex
    un = np.sqrt(ux * ux + uy * uy + uz * uz)
    ux, uy, uz = ux / un, uy / un, uz / un
    vx, vy, vz = ey * uz - ez * uy, ez * ux - ex * uz, ex * uy - ey * ux
    n_pts = 0
    sx = sy = sw = 0.0
    for rr in range(max(r - 1, 0), min(r + 2, H)):
        for cc in range(max(c - 1, 0), min(c + 2, W)):
            rk = float(range_src[rr, cc])
            if not rk > 0.0:
                continue
            dx, dy, dz = rays_src[rr, cc, 0] * rk, rays_src[rr, cc, 1] * rk, rays_src[rr, cc, 2] * rk
            xs[n_pts] = x = ux * dx + uy * dy + uz * dz
            ys[n_pts] = y = vx * dx + vy * dy + vz * dz
            ws[n_pts] = w = ex * dx + ey * dy + ez * dz - rng0
            sx += x
            sy += y
            sw += w
            n_pts += 1
    if n_pts < 4:  # three points always lie on a plane: at least one must check it
        return False, 0.0, 0.0, 0.0, 0.0
    mx, my, mw = sx / n_pts, sy / n_pts, sw / n_pts
    # the least-squares plane w = w0 + b x + c y: range noise lies along the rays, as w does
    sxx = sxy = syy = sxw = syw = 0.0
    for k in range(n_pts):
        x, y, w = xs[k] - mx, ys[k] - my, ws[k] - mw
        xs[k], ys[k], ws[k] = x, y, w
        sxx += x * x
        sxy += x * y
        syy += y * y
        sxw += x * w
        syw += y * w
    det = sxx * syy - sxy * sxy
    if not det > 1e-12 * (sxx + syy) * (sxx + syy):  # the points lie on a line: no plane
        return False, 0.0, 0.0, 0.0, 0.0
    b = (syy * sxw - sxy * syw) / det
    c2 = (sxx * syw - sxy * sxw) / det
    norm = np.sqrt(1.0 + b * b + c2 * c2)  # |e - b u - c v|: the plane's normal before normalising
    lim = tol * norm  # every point within the tolerance of the plane (along its normal, hence the norm)
    for k in range(n_pts):
        if abs(ws[k] - b * xs[k] - c2 * ys[k]) > lim:
            return False, 0.0, 0.0, 0.0, 0.0
    nx, ny, nz = (
        (ex - b * ux - c2 * vx) / norm,
        (ey - b * uy - c2 * vy) / norm,
        (ez - b * uz - c2 * vz) / norm,
    )
    # the plane passes the points' mean, rng0 e + mx u + my v + mw e
    d0 = (mx * (nx * ux + ny * uy + nz * uz) + my * (nx * vx + ny * vy + nz * vz)
          + (rng0 + mw) * (nx * ex + ny * ey + nz * ez))  # fmt: skip
    return True, nx, ny, nz, d0


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
    nearest pixel holds one, at least four of its 3x3 pixels hold one, and
    their points lie within `tol_m` + `tol_rel` x range of their
    least-squares plane (errors along the pixel's ray, as range noise
    lies): the ray meets that plane there, exact on planes (and on noisy
    ones an average of up to nine points rather than one), unless it
    grazes it (|n . ray| < `min_cos`) or the result differs from the
    pixel's range by more than `max_change` of it. 0 elsewhere.
    """
    out = np.zeros(len(rays_dst), np.float32)
    _resample(range_src, rays_src, pixels, start, order, rays_dst, min_cos, tol_m, tol_rel, max_change, out)
    return out
