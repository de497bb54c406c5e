"""Compiled (numba) helpers of the camera-model contract, imported on first use.

`finish_projection` turns a model's raw (u, v, valid) into the contract's
(uv, valid) in one pass: valid only where the model says so and every input
coordinate and output pixel is finite, NaN elsewhere. In numpy that took
about eight passes over the points (finiteness of five arrays, the mask, the
stacking, the NaN fill), more than the Double Sphere formula itself.
"""

from __future__ import annotations

import math
import os

import numba
import numpy as np
from numba import njit

from calibration.types import F64, Bool


@njit(cache=True, nogil=True)
def _finish(u, v, valid, x, y, z, uv, ok):  # type: ignore[no-untyped-def]  # pragma: no cover
    for i in range(u.shape[0]):
        good = (
            valid[i]
            and math.isfinite(u[i])
            and math.isfinite(v[i])
            and math.isfinite(x[i])
            and math.isfinite(y[i])
            and math.isfinite(z[i])
        )
        ok[i] = good
        if good:
            uv[i, 0] = u[i]
            uv[i, 1] = v[i]
        else:
            uv[i, 0] = np.nan
            uv[i, 1] = np.nan


def finish_projection(u: F64, v: F64, valid: Bool, x: F64, y: F64, z: F64) -> tuple[F64, Bool]:
    """(uv (N, 2), valid (N,)) from flat model outputs and inputs; NaN where not valid."""
    n = len(x)
    uv = np.empty((n, 2), np.float64)
    ok = np.empty(n, np.bool_)
    _finish(
        np.broadcast_to(np.asarray(u, np.float64), (n,)),
        np.broadcast_to(np.asarray(v, np.float64), (n,)),
        np.broadcast_to(np.asarray(valid, np.bool_), (n,)),
        x, y, z, uv, ok,
    )  # fmt: skip
    return uv, ok


@njit(cache=True, nogil=True)
def _store(i, u, v, good, uv, ok):  # type: ignore[no-untyped-def]  # pragma: no cover
    good = good and math.isfinite(u) and math.isfinite(v)
    ok[i] = good
    uv[i, 0] = u if good else np.nan
    uv[i, 1] = v if good else np.nan


@njit(cache=True, nogil=True)
def _finite3(x, y, z):  # type: ignore[no-untyped-def]  # pragma: no cover
    return math.isfinite(x) and math.isfinite(y) and math.isfinite(z)


@njit(cache=True, nogil=True, error_model="numpy")  # x / 0 gives inf or NaN, as numpy
def double_sphere_pixel(x, y, z, fx, fy, cx, cy, xi, alpha, w2):  # type: ignore[no-untyped-def]  # pragma: no cover
    """One point's Double Sphere pixel (u, v) and whether the projection is valid there (before the
    pixel's own finiteness check): the formula every compiled Double Sphere projection calls."""
    r2 = x * x + y * y
    d1 = math.sqrt(z * z + r2)
    k = d1 * xi + z
    n = math.sqrt(k * k + r2) * alpha + k * (1.0 - alpha)
    good = _finite3(x, y, z) and z > -w2 * d1 and n > 0.0
    return x / n * fx + cx, y / n * fy + cy, good


@njit(cache=True, nogil=True, error_model="numpy")
def _double_sphere(p, fx, fy, cx, cy, xi, alpha, w2, uv, ok):  # type: ignore[no-untyped-def]  # pragma: no cover
    for i in range(p.shape[0]):
        u, v, good = double_sphere_pixel(p[i, 0], p[i, 1], p[i, 2], fx, fy, cx, cy, xi, alpha, w2)
        _store(i, u, v, good, uv, ok)


@njit(cache=True, nogil=True, error_model="numpy")  # x / 0 gives inf or NaN, as numpy
def _extended_unified(p, fx, fy, cx, cy, alpha, beta, w1, uv, ok):  # type: ignore[no-untyped-def]  # pragma: no cover
    for i in range(p.shape[0]):
        x, y, z = p[i, 0], p[i, 1], p[i, 2]
        d = math.sqrt((x * x + y * y) * beta + z * z)
        n = z * (1.0 - alpha) + alpha * d
        good = _finite3(x, y, z) and z > -w1 * d and n > 0.0
        _store(i, x / n * fx + cx, y / n * fy + cy, good, uv, ok)


@njit(cache=True, nogil=True, error_model="numpy")  # x / 0 gives inf or NaN, as numpy
def _pinhole(p, fx, fy, cx, cy, uv, ok):  # type: ignore[no-untyped-def]  # pragma: no cover
    for i in range(p.shape[0]):
        x, y, z = p[i, 0], p[i, 1], p[i, 2]
        good = _finite3(x, y, z) and z > 0.0
        _store(i, x / z * fx + cx, y / z * fy + cy, good, uv, ok)


@njit(cache=True, nogil=True, error_model="numpy")
def _equirect(p, R, pitch, u0, v0, uv, ok):  # type: ignore[no-untyped-def]  # pragma: no cover
    for i in range(p.shape[0]):
        # model frame -> the standard frame (pole on -y): R^T p
        x = R[0, 0] * p[i, 0] + R[1, 0] * p[i, 1] + R[2, 0] * p[i, 2]
        y = R[0, 1] * p[i, 0] + R[1, 1] * p[i, 1] + R[2, 1] * p[i, 2]
        z = R[0, 2] * p[i, 0] + R[1, 2] * p[i, 1] + R[2, 2] * p[i, 2]
        theta = math.atan2(math.hypot(x, z), -y)
        phi = math.atan2(x, z)
        good = _finite3(x, y, z) and x * x + y * y + z * z > 0.0
        _store(i, (phi + math.pi) / pitch - u0, theta / pitch - v0, good, uv, ok)


@njit(cache=True, nogil=True, error_model="numpy")  # sqrt(<0) and x / 0 give NaN or inf, as numpy
def _unproject_double_sphere(uv, fx, fy, cx, cy, xi, alpha, w2, rays, ok):  # type: ignore[no-untyped-def]  # pragma: no cover
    circle = 1.0 / (2.0 * alpha - 1.0) if alpha > 0.5 else np.inf  # r2 beyond it: no ray
    for i in range(uv.shape[0]):
        mx = (uv[i, 0] - cx) / fx
        my = (uv[i, 1] - cy) / fy
        r2 = mx * mx + my * my
        mz = (1.0 - alpha * alpha * r2) / (alpha * math.sqrt(1.0 - (2.0 * alpha - 1.0) * r2) + 1.0 - alpha)
        s = (mz * xi + math.sqrt(mz * mz + (1.0 - xi * xi) * r2)) / (mz * mz + r2)
        x, y, z = s * mx, s * my, s * mz - xi
        norm = math.sqrt(x * x + y * y + z * z)
        x, y, z = x / norm, y / norm, z / norm
        # z > -w2 |p| on the unit ray: the ray lies inside the projection's domain (not past the fold)
        good = r2 <= circle and z > -w2 and norm > 0.0 and _finite3(x, y, z)
        ok[i] = good
        rays[i, 0] = x if good else np.nan
        rays[i, 1] = y if good else np.nan
        rays[i, 2] = z if good else np.nan


def unproject_double_sphere(
    uv: F64, fx: float, fy: float, cx: float, cy: float, xi: float, alpha: float, w2: float
) -> tuple[F64, Bool]:
    """Double Sphere unprojection of (N, 2) pixels to unit rays (N, 3) and validity, in one pass
    (the numpy path's formula, normalisation and NaN fill fused)."""
    rays = np.empty((uv.shape[0], 3), np.float64)
    ok = np.empty(uv.shape[0], np.bool_)
    _unproject_double_sphere(uv, fx, fy, cx, cy, xi, alpha, w2, rays, ok)
    return rays, ok


def _outputs(p: F64) -> tuple[F64, Bool]:
    return np.empty((p.shape[0], 2), np.float64), np.empty(p.shape[0], np.bool_)


def project_double_sphere(
    p: F64, fx: float, fy: float, cx: float, cy: float, xi: float, alpha: float, w2: float
) -> tuple[F64, Bool]:
    """Double Sphere projection of (N, 3) points fused with `finish_projection`: one pass."""
    uv, ok = _outputs(p)
    _double_sphere(p, fx, fy, cx, cy, xi, alpha, w2, uv, ok)
    return uv, ok


def project_extended_unified(
    p: F64, fx: float, fy: float, cx: float, cy: float, alpha: float, beta: float, w1: float
) -> tuple[F64, Bool]:
    """EUCM (UCM with beta = 1) projection of (N, 3) points fused with `finish_projection`."""
    uv, ok = _outputs(p)
    _extended_unified(p, fx, fy, cx, cy, alpha, beta, w1, uv, ok)
    return uv, ok


def project_pinhole(p: F64, fx: float, fy: float, cx: float, cy: float) -> tuple[F64, Bool]:
    """Undistorted pinhole projection of (N, 3) points fused with `finish_projection`."""
    uv, ok = _outputs(p)
    _pinhole(p, fx, fy, cx, cy, uv, ok)
    return uv, ok


def project_equirect(p: F64, R_model_std: F64, pitch_rad: float, u0: float, v0: float) -> tuple[F64, Bool]:
    """Equirectangular projection of (N, 3) points fused with `finish_projection`: one pass.

    `R_model_std` turns the standard frame (pole on -y) into the model's; a
    point's pixel is u = (phi + pi) / pitch - u0, v = theta / pitch - v0.
    """
    uv, ok = _outputs(p)
    _equirect(p, np.ascontiguousarray(R_model_std, np.float64), pitch_rad, u0, v0, uv, ok)
    return uv, ok


@njit(cache=True, nogil=True, error_model="numpy")  # x / 0 gives inf or NaN, as numpy
def _disparity_stability(r, theta, B, k, e, max_rel, disp, stable):  # type: ignore[no-untyped-def]  # pragma: no cover
    tau = math.tan(e / k)  # the disparity error as an angle's tangent
    for i in range(r.shape[0]):
        ri, ti = r[i], theta[i]
        s, c = math.sin(ti), math.cos(ti)
        den = ri / B + c
        d = k * math.atan2(s, den)
        if not (math.isfinite(d) and math.isfinite(ri) and ri > 0.0 and d > 0.0):
            disp[i] = 0.0
            stable[i] = False
            continue
        disp[i] = d
        # range = B (sin(theta) cot(rho) - cos(theta)) at rho = rho_d +- delta, with tan(rho_d) = s / den:
        # cot(rho_d +- delta) = (1 -+ T tau) / (T +- tau), no further sines
        T = s / den
        ok = d - e > 0.0 and (d + e) / k < ti  # both angles in (0, theta): the rays still meet
        if ok:
            r_lo = B * (s * (1.0 - T * tau) / (T + tau) - c)
            r_hi = B * (s * (1.0 + T * tau) / (T - tau) - c)
            ok = (
                math.isfinite(r_lo)
                and math.isfinite(r_hi)
                and r_lo > 0.0
                and r_hi > 0.0
                and max(abs(ri - r_lo), abs(r_hi - ri)) / ri <= max_rel
            )
        stable[i] = ok


def disparity_stability(
    range_m: F64,
    theta_rad: F64,
    baseline_m: float,
    height_full_px: int,
    max_rel_error: float,
    disp_error_px: float,
) -> tuple[F64, Bool]:
    """`calibration.stereo.disparity_and_stability` in one compiled pass over (N,) float64 arrays."""
    n = len(range_m)
    disp, stable = np.empty(n, np.float64), np.empty(n, np.bool_)
    k = height_full_px / math.pi
    _disparity_stability(
        range_m, theta_rad, float(baseline_m), k, float(disp_error_px), float(max_rel_error), disp, stable
    )
    return disp, stable


def fork_safe_numba_threads() -> None:
    """Make numba's thread pool one that forked workers survive; call before its first parallel use.

    Renders run in forked workers (render-benchmark, dense ground truth in
    ingest) whose parent may have used numba's threads already: GNU OpenMP,
    numba's usual pick on Linux, aborts such a child ("fork() called from a
    process already using GNU OpenMP"). numba's own workqueue layer is fork
    safe and always there; it takes one parallel call at a time per process,
    as the renderer makes them (naming it also spares numba's probe of an
    older system TBB, which warns). NUMBA_THREADING_LAYER, when set, wins.
    """
    if "NUMBA_THREADING_LAYER" not in os.environ:
        numba.config.THREADING_LAYER = "workqueue"  # type: ignore[attr-defined]
