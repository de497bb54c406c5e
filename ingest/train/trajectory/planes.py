"""Local planes of a point cloud: k-nearest-neighbour covariances and PCA normals.

Both per-point hot paths of a sample need them: the ground truth moves each
range onto its pixel's ray along the local plane, and the velocity fit pairs
points across time on local planes. The neighbour search and the 3x3
covariances run in Open3D's C++ (`estimate_covariances`, a k-d tree query per
point); the same numbers from scipy's cKDTree plus numpy take 2-3x the CPU
time (bench/bench_ingest.py), and Open3D's closed-form 3x3 eigen-solve is ~4x
faster than `calibration.linalg3`'s on numpy arrays, which stays as the reference.
Open3D is imported with this module (~0.5 s), in the main process, so forked
ingest workers inherit it instead of each paying for it in their first sample.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from calibration.linalg3 import sym3_smallest
from calibration.types import F64, Bool
from ingest.runtime.o3d import o3d


@dataclass(frozen=True)
class Normals:
    """Unit normals (N,3) and whether each neighbourhood was planar enough to trust."""

    normal: F64
    planar: Bool


def _cloud(pts: F64) -> o3d.geometry.PointCloud:
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(pts, np.float64)))


def knn_covariances(pts: F64, k: int) -> F64:
    """Covariance (N, 3, 3) in m^2 of each point's k nearest neighbours in `pts` (itself included).

    Population covariance (divided by k). Open3D accumulates E[p p^T] - E[p] E[p]^T,
    which loses about 1e-16 * |p|^2 m^2 to cancellation: 3e-13 m^2 at 50 m, far
    below the variance of any neighbourhood a LiDAR samples. Fewer than three
    neighbours give the identity (never planar).
    """
    cloud = _cloud(pts)
    cloud.estimate_covariances(o3d.geometry.KDTreeSearchParamKNN(int(k)))
    out: F64 = np.asarray(cloud.covariances)
    return out


def knn_planes(pts: F64, k: int) -> tuple[F64, F64]:
    """`knn_covariances` and the unit eigenvector (N, 3) of each one's smallest eigenvalue.

    Both in Open3D's C++: `estimate_normals` reuses the covariances already on
    the cloud and solves each 3x3 in closed form (its FastEigen3x3), about 4x
    faster than `calibration.linalg3.sym3_smallest` on numpy arrays. The normals'
    signs are arbitrary; every user takes |n . x| or divides by n . ray.
    """
    cloud = _cloud(pts)
    search = o3d.geometry.KDTreeSearchParamKNN(int(k))
    cloud.estimate_covariances(search)
    cloud.estimate_normals(search)  # uses the covariances set above, no second neighbour search
    cov: F64 = np.asarray(cloud.covariances)
    normal: F64 = np.asarray(cloud.normals)
    return cov, normal


def neighbour_covariances(pts: F64, idx: np.ndarray[Any, Any]) -> F64:
    """Covariance (N, 3, 3) of the neighbourhoods `pts[idx]` given as indices (N, k)."""
    nb = pts[idx]
    centred = nb - nb.mean(axis=1, keepdims=True)
    out: F64 = np.einsum("nki,nkj->nij", centred, centred) / idx.shape[1]
    return out


def _planar(lam_min: F64, lam_max: F64, total: F64, range_m: F64, max_flatness: float) -> Bool:
    """Planar and local: see `normals_from_covariances`."""
    flatness = lam_min / np.maximum(total, 1e-30)
    spread = np.sqrt(np.maximum(lam_max, 0.0))
    local = spread < 0.1 * range_m + 0.05
    out: Bool = (flatness <= max_flatness) & local
    return out


def normals_from_covariances(cov: F64, pts: F64, max_flatness: float) -> Normals:
    """PCA normals of neighbourhoods with covariances `cov` (N, 3, 3) around the points `pts` (N, 3).

    Planar means: the smallest eigenvalue is at most `max_flatness` of their
    sum, and the neighbourhood is local (its largest spread below a tenth of
    the point's range plus 5 cm, so that a sparse far cloud does not fit one
    "plane" through several surfaces). This is the numpy reference of
    `plane_normals`' Open3D path.
    """
    return planar_normals(*sym3_smallest(cov), pts, max_flatness)


def planar_normals(evals: F64, normal: F64, pts: F64, max_flatness: float) -> Normals:
    """`normals_from_covariances` given each covariance's ascending eigenvalues (N, 3) and the unit
    eigenvector (N, 3) of the smallest (as `odometry_kernels.neighbourhood_planes` solves them)."""
    lam_min, lam_max, total = evals[:, 0], evals[:, 2], evals.sum(axis=1)
    return Normals(normal, _planar(lam_min, lam_max, total, np.linalg.norm(pts, axis=1), max_flatness))


def extreme_eigenvalues(cov: F64, normal: F64) -> tuple[F64, F64]:
    """Smallest and largest eigenvalues (N,) of symmetric 3x3 matrices, given the smallest one's eigenvector.

    The smallest is the Rayleigh quotient n^T C n. The other two are the
    roots of x^2 - s x + q with s = trace - lambda_min and q = (sum of the
    principal 2x2 minors) - lambda_min * s.
    """
    lam_min = np.einsum("ni,nij,nj->n", normal, cov, normal)
    c00, c11, c22 = cov[:, 0, 0], cov[:, 1, 1], cov[:, 2, 2]
    c01, c02, c12 = cov[:, 0, 1], cov[:, 0, 2], cov[:, 1, 2]
    minors = c00 * c11 - c01 * c01 + c00 * c22 - c02 * c02 + c11 * c22 - c12 * c12
    s = c00 + c11 + c22 - lam_min
    q = minors - lam_min * s
    lam_max: F64 = s / 2.0 + np.sqrt(np.maximum(s * s / 4.0 - q, 0.0))
    return lam_min, lam_max


def plane_normals(pts: F64, k: int, max_flatness: float, range_m: F64 | None = None) -> Normals:
    """PCA normal of each point's k-neighbourhood among `pts` (the point included).

    "Local" (`normals_from_covariances`) compares a neighbourhood's spread with
    the point's distance from the sensor: `range_m` (N,), or |pts| when the
    points are in the sensor's frame.
    """
    n = len(pts)
    if n < 3:
        return Normals(np.zeros((n, 3)), np.zeros(n, bool))
    cov, normal = knn_planes(pts, min(k, n))
    lam_min, lam_max = extreme_eigenvalues(cov, normal)
    total = np.trace(cov, axis1=1, axis2=2)
    r = np.linalg.norm(pts, axis=1) if range_m is None else range_m
    return Normals(normal, _planar(lam_min, lam_max, total, r, max_flatness))
