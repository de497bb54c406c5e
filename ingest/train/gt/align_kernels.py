"""The photometric alignment's hot loops as compiled passes (`ingest.train.gt.align`).

At 15-40k points a sample, numpy's form of a Gauss-Newton step spends most
of its time on temporaries (the sampled channels, the (N, 8) Jacobian rows,
their weighted copy); the step here reads each point once to sample the image
and form its residual, and once more to add its weighted row to the normal
equations. The projection into a Double Sphere camera with its
forward-difference Jacobian, and the 2-pixel z-buffer, are one pass each
too, with numpy's operations in numpy's order: the alignments are the same
to the bit.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from calibration.fisheye import DoubleSphere
from calibration.kernels import double_sphere_pixel
from calibration.types import F32, F64, Bool


@njit(cache=True, nogil=True)
def _bilinear(level, x, y, out):  # type: ignore[no-untyped-def]  # pragma: no cover
    """The channels of a float32 (H, W, C) image at (x, y) into `out` (float64): bilinear, the border
    pixels repeated outside the image (as `cv2.remap` with `INTER_LINEAR`, `BORDER_REPLICATE`)."""
    h, w = level.shape[0], level.shape[1]
    x0f, y0f = math.floor(x), math.floor(y)
    fx, fy = x - x0f, y - y0f
    x0, y0 = int(x0f), int(y0f)
    xa, xb = min(max(x0, 0), w - 1), min(max(x0 + 1, 0), w - 1)
    ya, yb = min(max(y0, 0), h - 1), min(max(y0 + 1, 0), h - 1)
    for c in range(level.shape[2]):
        top = level[ya, xa, c] * (1.0 - fx) + level[ya, xb, c] * fx
        bottom = level[yb, xa, c] * (1.0 - fx) + level[yb, xb, c] * fx
        out[c] = top * (1.0 - fy) + bottom * fy


@njit(cache=True, nogil=True, error_model="numpy")  # x / 0 gives inf or NaN, as numpy
def _pixel(p, i, ds, u_end, v_end, px):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Point i's Double Sphere pixel into px[i] (NaN where the projection is invalid, as
    `calibration.kernels` stores it) and whether it lies in the image (`CameraModel.in_image`)."""
    u, v, good = double_sphere_pixel(
        p[i, 0], p[i, 1], p[i, 2], ds[0], ds[1], ds[2], ds[3], ds[4], ds[5], ds[6]
    )
    good = good and math.isfinite(u) and math.isfinite(v)
    px[i, 0] = u if good else np.nan
    px[i, 1] = v if good else np.nan
    return good and u >= -0.5 and u < u_end and v >= -0.5 and v < v_end


@njit(cache=True, nogil=True, error_model="numpy")
def _in_image(p, ds, u_end, v_end, px, ok):  # type: ignore[no-untyped-def]  # pragma: no cover
    for i in range(p.shape[0]):
        ok[i] = _pixel(p, i, ds, u_end, v_end, px)


@njit(cache=True, nogil=True, error_model="numpy")
def _visible_jacobians(p, ds, u_end, v_end, step, px, ok, J):  # type: ignore[no-untyped-def]  # pragma: no cover
    """`_in_image`, with `ok` only where the forward-difference Jacobian is finite too, and those
    Jacobians into the first rows of `J` in the points' order; return how many. The operations of
    `ingest.train.gt.align`'s numpy form, point by point."""
    m = 0
    moved = np.empty((3, 2))
    shifted = np.empty((1, 3))
    for i in range(p.shape[0]):
        ok[i] = False
        if not _pixel(p, i, ds, u_end, v_end, px):
            continue
        for k in range(3):  # the point moved by `step` along axis k (0.0 added to the others, as numpy)
            for a in range(3):
                shifted[0, a] = p[i, a] + (step if a == k else 0.0)
            _pixel(shifted, 0, ds, u_end, v_end, moved[k:])
        total = 0.0
        for a in range(2):
            for k in range(3):
                J[m, a, k] = (moved[k, a] - px[i, a]) / step
                total += J[m, a, k]
        if math.isfinite(total):
            ok[i] = True
            m += 1
    return m


def _camera(model: DoubleSphere) -> tuple[F64, float, float]:
    ds = np.array([model.fx, model.fy, model.cx, model.cy, model.xi, model.alpha, model.w2], np.float64)
    return ds, model.width - 0.5, model.height - 0.5


def pixels_in_image(model: DoubleSphere, p: F64) -> tuple[F64, Bool]:
    """`model.project(p)` and `model.in_image` of its pixels in one pass: pixels (N, 2, NaN where the
    projection is invalid) and which lie in the image (N,)."""
    px, ok = np.empty((len(p), 2)), np.empty(len(p), np.bool_)
    _in_image(np.ascontiguousarray(p, np.float64), *_camera(model), px, ok)
    return px, ok


def visible_jacobians(model: DoubleSphere, p: F64, step: float) -> tuple[F64, F64, Bool]:
    """Pixels (N, 2) of the points `p` (N, 3, m) through `model`, NaN where the projection is invalid;
    the forward-difference Jacobians d(pixel)/d(point) (M, 2, 3, px/m, steps of `step` m) of the M points
    inside the image with a finite one; and which those are (N,)."""
    px, ok = np.empty((len(p), 2)), np.empty(len(p), np.bool_)
    J = np.empty((len(p), 2, 3))
    m = _visible_jacobians(np.ascontiguousarray(p, np.float64), *_camera(model), float(step), px, ok, J)
    return px, J[:m], ok


@njit(cache=True, nogil=True)
def _nearest_in_cell(px, range_m, cell_px, tolerance, keep):  # type: ignore[no-untyped-def]  # pragma: no cover
    """Into `keep`, whether each range is within `tolerance` of the nearest in its `cell_px` cell: the
    cells' minima on a grid over the pixels' bounding box."""
    n = px.shape[0]
    cols, rows = np.empty(n, np.int64), np.empty(n, np.int64)
    for i in range(n):
        cols[i], rows[i] = math.floor(px[i, 0] / cell_px), math.floor(px[i, 1] / cell_px)
    c0, r0 = cols.min(), rows.min()
    width = cols.max() - c0 + 1
    nearest = np.full((rows.max() - r0 + 1) * width, np.inf)
    for i in range(n):
        cell = (rows[i] - r0) * width + cols[i] - c0
        nearest[cell] = min(nearest[cell], range_m[i])
    factor = 1.0 + tolerance
    for i in range(n):
        keep[i] = range_m[i] <= nearest[(rows[i] - r0) * width + cols[i] - c0] * factor


def nearest_in_cell(px: F64, range_m: F64, cell_px: float, tolerance: float) -> Bool:
    """Whether each pixel's (N, 2) range (N, m) is within `tolerance` (a fraction) of the nearest range
    in its `cell_px` cell (a z-buffer over the pixels' bounding box: pixels and ranges finite, the
    pixels those of one image)."""
    keep = np.empty(len(px), np.bool_)
    if len(px):
        _nearest_in_cell(np.ascontiguousarray(px, np.float64), np.ascontiguousarray(range_m, np.float64),
                         float(cell_px), float(tolerance), keep)  # fmt: skip
    return keep


@njit(cache=True, nogil=True)
def _normal_equations(  # type: ignore[no-untyped-def]  # pragma: no cover
    px, ok, p, J, refl, level, gain, offset, cauchy_scale, H, g, intensity, used_refl, used_p
):
    """Fill H (8, 8) and g (8) of the robust photometric cost over the points where `ok`; return
    (points used, the residuals' robust spread, sum of weight * residual^2)."""
    n = 0
    residual = np.empty(len(px))
    grad = np.empty((len(px), 3))
    sample = np.empty(level.shape[2])
    for i in range(len(px)):
        if not ok[i]:
            continue
        _bilinear(level, px[i, 0], px[i, 1], sample)
        gx, gy = sample[1], sample[2]
        for k in range(3):
            grad[n, k] = gx * J[i, 0, k] + gy * J[i, 1, k]
            used_p[n, k] = p[i, k]
        intensity[n] = sample[0]
        used_refl[n] = refl[i]
        residual[n] = sample[0] - (gain * refl[i] + offset)
        n += 1
    r = residual[:n]
    median = np.median(r)
    spread = 1.4826 * np.median(np.abs(r - median))
    if not spread > 0:
        return n, spread, 0.0
    row = np.empty(8)
    weighted_sq = 0.0
    for m in range(n):
        px_, py_, pz_ = used_p[m, 0], used_p[m, 1], used_p[m, 2]
        gx, gy, gz = grad[m, 0], grad[m, 1], grad[m, 2]
        # d(R(dw) p)/d(dw) = -[p]x, so dI/d(dw) = p x grad: the rotation's part of the row
        row[0], row[1], row[2] = py_ * gz - pz_ * gy, pz_ * gx - px_ * gz, px_ * gy - py_ * gx
        row[3], row[4], row[5], row[6], row[7] = gx, gy, gz, -used_refl[m], -1.0
        u = r[m] / (cauchy_scale * spread)
        weight = 1.0 / (1.0 + u * u)
        weighted_sq += weight * r[m] * r[m]
        for a in range(8):
            wa = weight * row[a]
            g[a] += wa * r[m]
            for b in range(a, 8):
                H[a, b] += wa * row[b]
    for a in range(8):
        for b in range(a):
            H[a, b] = H[b, a]
    return n, spread, weighted_sq


def normal_equations(
    px: F64, ok: np.ndarray, p: F64, J: F64, refl: F64, level: F32, affine: F64, cauchy_scale: float
) -> tuple[F64, F64, int, float, float, F64, F64, F64]:
    """The robust photometric normal equations at the points where `ok` (see `ingest.train.gt.align`).

    `px` (N, 2) are the points' pixels, `p` (N, 3) the corrected points in
    cam0 (m), `J` (N, 2, 3) the projection's Jacobian (px/m), `refl` their
    reflectivity, `level` one blurred level (H, W, 3: intensity and its x
    and y gradients), `affine` the intensity model (gain, offset). Returns
    H (8, 8) and g (8) over (rotation, translation, gain, offset), the
    points used, the residuals' robust spread (1.4826 MAD, intensity
    levels), the sum of weight * residual^2, and the used points' image
    intensity, reflectivity and coordinates (for the correlation and range).
    """
    count = int(ok.sum())
    H, g = np.zeros((8, 8)), np.zeros(8)
    intensity, used_refl, used_p = np.empty(count), np.empty(count), np.empty((count, 3))
    n, spread, weighted_sq = _normal_equations(
        px, ok, p, J, refl, np.ascontiguousarray(level, np.float32), float(affine[0]), float(affine[1]),
        float(cauchy_scale), H, g, intensity, used_refl, used_p,
    )  # fmt: skip
    return H, g, int(n), float(spread), float(weighted_sq), intensity, used_refl, used_p
