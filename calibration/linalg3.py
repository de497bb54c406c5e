"""Batched 3x3 linear algebra in closed form, for the per-point hot paths of ingest.

`np.linalg.eigh` and scipy's `Rotation`/`Slerp` handle stacks of small
matrices one LAPACK call or Python object at a time: for the ~30k points of a
sample that is tens of milliseconds each (bench_ingest). The closed forms
below are a handful of vectorised array operations instead; tests compare them
with `np.linalg.eigh` and scipy to 1e-9.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from calibration.types import F64

DEGENERATE_GAP = 1e-4  # (lambda_mid - lambda_min) / (lambda_max - lambda_min) below this: ask LAPACK


def sym3_eigvals(cov: F64) -> F64:
    """Ascending eigenvalues (N, 3) of symmetric 3x3 matrices (N, 3, 3), trigonometric method.

    Simple roots are Newton-polished to ~1e-12 of the eigenvalue spread; a
    (nearly) repeated pair keeps the ~1e-8 relative error of arccos near +-1.
    """
    a00, a11, a22 = cov[:, 0, 0], cov[:, 1, 1], cov[:, 2, 2]
    a01, a02, a12 = cov[:, 0, 1], cov[:, 0, 2], cov[:, 1, 2]
    q = (a00 + a11 + a22) / 3.0
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p = np.sqrt((b00**2 + b11**2 + b22**2 + 2.0 * (a01**2 + a02**2 + a12**2)) / 6.0)
    safe = np.where(p > 0, p, 1.0)
    det = (
        b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02)
    ) / safe**3
    phi = np.arccos(np.clip(det / 2.0, -1.0, 1.0)) / 3.0
    hi = _newton(cov, q + 2.0 * p * np.cos(phi), p)
    lo = _newton(cov, q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0), p)
    out: F64 = np.stack([lo, 3.0 * q - hi - lo, hi], axis=1)
    return out


def _newton(cov: F64, lam: F64, scale: F64, steps: int = 2) -> F64:
    """Polish roots of det(A - lambda I): arccos near +-1 leaves ~1e-8 relative error, Newton removes it.

    A step is taken only where it is small against the matrix scale (near a
    double root the derivative vanishes and the step would be meaningless).
    """
    a01, a02, a12 = cov[:, 0, 1], cov[:, 0, 2], cov[:, 1, 2]
    for _ in range(steps):
        c00, c11, c22 = cov[:, 0, 0] - lam, cov[:, 1, 1] - lam, cov[:, 2, 2] - lam
        m0, m1, m2 = c11 * c22 - a12 * a12, c00 * c22 - a02 * a02, c00 * c11 - a01 * a01
        f = c00 * m0 - a01 * (a01 * c22 - a12 * a02) + a02 * (a01 * a12 - c11 * a02)
        df = -(m0 + m1 + m2)
        with np.errstate(divide="ignore", invalid="ignore"):
            step = f / df
        ok = np.isfinite(step) & (np.abs(step) <= 1e-6 * scale)
        lam = np.where(ok, lam - np.where(ok, step, 0.0), lam)
    return lam


def sym3_smallest(cov: F64) -> tuple[F64, F64]:
    """Ascending eigenvalues (N, 3) and the unit eigenvector (N, 3) of the smallest one.

    The eigenvector is the largest cross product of two rows of (A - lambda_min I),
    which span the plane orthogonal to it. Where the two smallest eigenvalues
    (nearly) coincide that vector is not defined by the matrix; those few rows
    fall back to `np.linalg.eigh`, so the result is what LAPACK would give.
    """
    evals = sym3_eigvals(cov)
    m = cov - evals[:, 0, None, None] * np.eye(3)
    r0, r1, r2 = m[:, 0], m[:, 1], m[:, 2]
    cands = np.stack([np.cross(r0, r1), np.cross(r0, r2), np.cross(r1, r2)], axis=1)  # (N, 3, 3)
    norms = np.einsum("nij,nij->ni", cands, cands)
    best = np.argmax(norms, axis=1)
    rows = np.arange(len(cov))
    vec = cands[rows, best]
    size = np.sqrt(norms[rows, best])
    span = evals[:, 2] - evals[:, 0]
    ok = size > DEGENERATE_GAP * span**2
    vec[ok] /= size[ok, None]
    if not ok.all():
        w, v = np.linalg.eigh(cov[~ok])
        evals[~ok], vec[~ok] = w, v[:, :, 0]
    return evals, vec


def rotvec_to_matrix(rotvec: F64) -> F64:
    """Rotation matrices (N, 3, 3) from rotation vectors (N, 3) (Rodrigues, series near zero)."""
    theta2 = np.einsum("ij,ij->i", rotvec, rotvec)
    theta = np.sqrt(theta2)
    small = theta < 1e-4
    t = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta2 / 6.0, np.sin(t) / t)  # sin(theta)/theta
    b = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(t)) / t**2)  # (1 - cos)/theta^2
    x, y, z = rotvec[:, 0], rotvec[:, 1], rotvec[:, 2]
    out = np.empty((len(rotvec), 3, 3))
    out[:, 0, 0] = 1.0 - b * (y * y + z * z)
    out[:, 1, 1] = 1.0 - b * (x * x + z * z)
    out[:, 2, 2] = 1.0 - b * (x * x + y * y)
    out[:, 0, 1] = b * x * y - a * z
    out[:, 1, 0] = b * x * y + a * z
    out[:, 0, 2] = b * x * z + a * y
    out[:, 2, 0] = b * x * z - a * y
    out[:, 1, 2] = b * y * z - a * x
    out[:, 2, 1] = b * y * z + a * x
    return out


def apply_rotations(R: F64, pts: F64) -> F64:
    """Per-point rotations (N, 3, 3) applied to points (N, 3)."""
    out: F64 = np.einsum("nij,nj->ni", R, pts)
    return out


def rotation_angle(R: np.ndarray[Any, Any]) -> F64:
    """Rotation angle (rad) of each matrix in a stack (N, 3, 3)."""
    cos = (np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0
    out: F64 = np.arccos(np.clip(cos, -1.0, 1.0))
    return out
