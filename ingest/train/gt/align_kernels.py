"""The photometric alignment's Gauss-Newton step as one compiled pass (`ingest.train.gt.align`).

At 15-40k points a sample, the step's numpy form spends most of its time on
temporaries (the sampled channels, the (N, 8) Jacobian rows, their weighted
copy); this pass reads each point once to sample the image and form its
residual, and once more to add its weighted row to the normal equations.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from calibration.types import F32, F64


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
