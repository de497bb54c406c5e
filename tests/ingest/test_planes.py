"""Local planes (Open3D k-NN covariances) and the sweep's self-registration velocity fit."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from ingest.train.trajectory.clouds import estimate_velocity
from ingest.train.trajectory.planes import (
    extreme_eigenvalues,
    knn_covariances,
    knn_planes,
    neighbour_covariances,
    normals_from_covariances,
    plane_normals,
)


def test_knn_covariances_equal_a_kdtree_query_with_numpy():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(3000, 3)) * [3.0, 2.0, 0.02] + [20.0, -4.0, 1.0]  # a noisy slab 20 m away
    _, idx = cKDTree(pts).query(pts, k=8)
    np.testing.assert_allclose(knn_covariances(pts, 8), neighbour_covariances(pts, idx), rtol=0, atol=1e-11)


def test_plane_normals_of_a_tilted_plane_and_a_blob():
    rng = np.random.default_rng(1)
    n = np.array([1.0, 2.0, 2.0]) / 3.0
    u = np.cross(n, [0.0, 0.0, 1.0])
    u /= np.linalg.norm(u)
    w = np.cross(n, u)
    ab = rng.uniform(-1.0, 1.0, size=(2000, 2))
    plane = [0.0, 0.0, 5.0] + ab[:, :1] * u + ab[:, 1:] * w
    blob = rng.normal(scale=0.05, size=(500, 3)) + np.array([0.0, 3.0, 5.0])  # isotropic: no plane
    normals = plane_normals(np.concatenate([plane, blob]), 8, max_flatness=0.05)
    assert normals.planar[:2000].all()
    assert normals.planar[2000:].mean() < 0.2  # 8 random points are flat by chance now and then (11 %)
    np.testing.assert_allclose(np.abs(normals.normal[:2000] @ n), 1.0, atol=1e-9)


def test_extreme_eigenvalues_from_the_smallest_eigenvector_equal_lapack():
    rng = np.random.default_rng(2)
    a = rng.normal(size=(500, 3, 3)) * [1.0, 0.3, 0.01]  # from isotropic to nearly flat spreads
    cov = np.einsum("nij,nkj->nik", a, a)
    w, v = np.linalg.eigh(cov)
    lam_min, lam_max = extreme_eigenvalues(cov, v[:, :, 0])
    np.testing.assert_allclose(lam_min, w[:, 0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(lam_max, w[:, 2], rtol=1e-10, atol=1e-12)


def test_open3d_planes_equal_the_numpy_reference():
    """knn_planes' normals and plane_normals' decisions equal sym3_smallest on the same covariances."""
    rng = np.random.default_rng(3)
    floor = np.c_[rng.uniform(-5, 5, (3000, 2)), np.full(3000, -1.5)] + rng.normal(
        scale=0.005, size=(3000, 3)
    )
    wall = np.c_[rng.uniform(-5, 5, 2000), rng.uniform(-1.5, 2.0, 2000), np.full(2000, 6.0)]
    clutter = rng.normal(scale=0.3, size=(1000, 3)) + np.array([1.0, 0.0, 3.0])
    pts = np.concatenate([floor, wall, clutter])
    cov, normal = knn_planes(pts, 8)
    np.testing.assert_allclose(cov, knn_covariances(pts, 8), rtol=0, atol=1e-15)
    ref = normals_from_covariances(cov, pts, 0.05)
    w = np.linalg.eigvalsh(cov)
    defined = (w[:, 1] - w[:, 0]) > 1e-3 * (w[:, 2] - w[:, 0])  # the smallest eigenvector is unique
    np.testing.assert_allclose(np.abs(np.einsum("ij,ij->i", normal, ref.normal))[defined], 1.0, atol=1e-9)
    fast = plane_normals(pts, 8, 0.05)
    np.testing.assert_array_equal(fast.planar, ref.planar)
    assert fast.planar[:5000].mean() > 0.99 and fast.planar[5000:].mean() < 0.2


def test_plane_normals_of_fewer_than_three_points_are_never_planar():
    out = plane_normals(np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 1.0]]), 8, 0.05)
    assert out.normal.shape == (2, 3) and not out.planar.any()


def _room_sweep(velocity: np.ndarray, seed: int, n: int = 30_000) -> tuple[np.ndarray, np.ndarray]:
    """Points on the six walls of a 8 x 3 x 6 m room seen from a rig moving at `velocity` (m/s).

    Each point is measured at dt in [-50, 50] ms from the frame time, in cam0
    at that moment, so p_measured = p_world - velocity * dt (the rig is at the
    origin at the frame time).
    """
    rng = np.random.default_rng(seed)
    half = np.array([4.0, 1.5, 3.0])
    pts = rng.uniform(-half, half, size=(n, 3))
    axis = rng.integers(0, 3, n)
    side = rng.choice([-1.0, 1.0], n)
    pts[np.arange(n), axis] = side * half[axis]
    dt = np.sort(rng.uniform(-0.05, 0.05, n))
    return pts - velocity * dt[:, None], dt


@pytest.mark.parametrize("velocity", [[1.2, -0.1, 0.4], [0.0, 0.0, 1.5], [0.0, 0.0, 0.0]])
def test_velocity_of_a_rig_moving_through_a_room(velocity: list[float]) -> None:
    v = np.array(velocity)
    pts, dt = _room_sweep(v, seed=3)
    est = estimate_velocity(pts, dt)
    assert est is not None
    np.testing.assert_allclose(est.velocity_cam0_mps, v, atol=3e-3)  # 0.15 mm over the window
    assert est.residual_m < 0.005  # the walls line up again (uncompensated they are ~6 cm apart)


def test_velocity_is_not_determined_by_a_single_plane():
    rng = np.random.default_rng(4)
    pts = np.column_stack([rng.uniform(-3, 3, 20_000), rng.uniform(-3, 3, 20_000), np.full(20_000, 4.0)])
    dt = np.sort(rng.uniform(-0.05, 0.05, 20_000))
    assert estimate_velocity(pts, dt) is None  # motion along the wall is invisible


def test_velocity_from_a_one_sided_window():
    """At the start of a bag every point lies after the frame time; the split is at the median."""
    v = np.array([0.8, 0.0, -0.6])
    pts, dt = _room_sweep(v, seed=5)
    est = estimate_velocity(pts, dt - dt.min())
    assert est is not None
    np.testing.assert_allclose(est.velocity_cam0_mps, v, atol=3e-3)  # 0.15 mm over the window
