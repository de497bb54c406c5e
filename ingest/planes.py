"""Local planes of a point cloud: k-nearest-neighbour covariances and PCA normals.

Both per-point hot paths of a sample need them: the ground truth moves each
range onto its pixel's ray along the local plane, and the velocity fit pairs
points across time on local planes. The neighbour search and the 3x3
covariances run in Open3D's C++ (`estimate_covariances`, a k-d tree query per
point); the same numbers from scipy's cKDTree plus numpy take 2-3x the CPU
time (bench/bench_ingest.py). The eigen-solve is `ingest.linalg3`'s closed form.
Open3D is imported with this module (~0.5 s), in the main process, so forked
ingest workers inherit it instead of each paying for it in their first sample.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import open3d as o3d

from calibration.types import F64, Bool
from ingest.linalg3 import sym3_smallest


@dataclass(frozen=True)
class Normals:
    """Unit normals (N,3) and whether each neighbourhood was planar enough to trust."""

    normal: F64
    planar: Bool


def knn_covariances(pts: F64, k: int) -> F64:
    """Covariance (N, 3, 3) in m^2 of each point's k nearest neighbours in `pts` (itself included).

    Population covariance (divided by k). Open3D accumulates E[p p^T] - E[p] E[p]^T,
    which loses about 1e-16 * |p|^2 m^2 to cancellation: 3e-13 m^2 at 50 m, far
    below the variance of any neighbourhood a LiDAR samples. Fewer than three
    neighbours give the identity (never planar).
    """
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(pts, np.float64)))
    cloud.estimate_covariances(o3d.geometry.KDTreeSearchParamKNN(int(k)))
    out: F64 = np.asarray(cloud.covariances)
    return out


def neighbour_covariances(pts: F64, idx: np.ndarray[Any, Any]) -> F64:
    """Covariance (N, 3, 3) of the neighbourhoods `pts[idx]` given as indices (N, k)."""
    nb = pts[idx]
    centred = nb - nb.mean(axis=1, keepdims=True)
    out: F64 = np.einsum("nki,nkj->nij", centred, centred) / idx.shape[1]
    return out


def normals_from_covariances(cov: F64, pts: F64, max_flatness: float) -> Normals:
    """PCA normals of neighbourhoods with covariances `cov` (N, 3, 3) around the points `pts` (N, 3).

    Planar means: the smallest eigenvalue is at most `max_flatness` of their
    sum, and the neighbourhood is local (its largest spread below a tenth of
    the point's range plus 5 cm, so that a sparse far cloud does not fit one
    "plane" through several surfaces).
    """
    evals, normal = sym3_smallest(cov)  # ascending
    flatness = evals[:, 0] / np.maximum(evals.sum(axis=1), 1e-30)
    spread = np.sqrt(np.maximum(evals[:, 2], 0.0))
    local = spread < 0.1 * np.linalg.norm(pts, axis=1) + 0.05
    return Normals(normal, (flatness <= max_flatness) & local)


def plane_normals(pts: F64, k: int, max_flatness: float) -> Normals:
    """PCA normal of each point's k-neighbourhood among `pts` (the point included)."""
    n = len(pts)
    if n < 3:
        return Normals(np.zeros((n, 3)), np.zeros(n, bool))
    return normals_from_covariances(knn_covariances(pts, min(k, n)), pts, max_flatness)
