"""Local planes (Open3D k-NN covariances) and the sweep's self-registration velocity fit."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from ingest.clouds import estimate_velocity
from ingest.planes import knn_covariances, neighbour_covariances, plane_normals


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
