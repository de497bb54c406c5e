"""The odometry's compiled pieces against their references: scipy's k-d tree, numpy and scipy rotations."""

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from calibration.linalg3 import sym3_smallest
from ingest.train.trajectory.clouds import integrate_gyro
from ingest.train.trajectory.odometry_kernels import (
    chain_points,
    gyro_between,
    log_rotations,
    neighbourhood_planes,
    plane_system,
)
from ingest.train.trajectory.planes import neighbour_covariances
from ingest.train.trajectory.rig_trajectory import RigTrajectory
from ingest.train.trajectory.voxel_hash import VoxelHash, VoxelSet, first_free, voxel_groups, voxel_keys


def _scene(n=20_000, seed=0):
    """A floor, a wall and some clutter (m): what a map's neighbourhoods look like."""
    rng = np.random.default_rng(seed)
    floor = np.column_stack(
        [rng.uniform(-4, 4, n // 2), rng.uniform(-4, 4, n // 2), rng.normal(0, 0.01, n // 2)]
    )
    wall = np.column_stack([rng.uniform(-4, 4, n // 4), np.full(n // 4, 3.0), rng.uniform(0, 2.5, n // 4)])
    clutter = rng.uniform(-4, 4, (n - len(floor) - len(wall), 3))
    return np.concatenate([floor, wall, clutter]), rng


@pytest.mark.parametrize("cell_m", [0.1, 0.35])
@pytest.mark.parametrize(("k", "radius_m"), [(1, 0.5), (10, 1.0), (10, 0.08)])
def test_search_finds_what_a_kd_tree_finds(cell_m, k, radius_m):
    pts, rng = _scene()
    queries = np.concatenate([pts[:500] + rng.normal(0, 0.05, (500, 3)), rng.uniform(-6, 6, (300, 3))])
    d, idx = VoxelHash.build(pts, cell_m).query(queries, k, radius_m)
    d_kd, idx_kd = cKDTree(pts).query(queries, k=k, distance_upper_bound=radius_m)
    d_kd, idx_kd = d_kd.reshape(d.shape), idx_kd.reshape(idx.shape)
    idx_kd[idx_kd == len(pts)] = -1
    assert (idx >= 0).sum() > 500  # the cases hold both hits and misses
    assert (idx < 0).sum() > 50
    np.testing.assert_array_equal(idx, idx_kd)
    np.testing.assert_array_equal(np.isinf(d), np.isinf(d_kd))
    np.testing.assert_allclose(d[np.isfinite(d)], d_kd[np.isfinite(d_kd)], atol=1e-12)


def test_empty_inputs():
    grid = VoxelHash.build(np.zeros((0, 3)), 0.5)
    d, idx = grid.query(np.ones((3, 3)), 2, 1.0)
    assert idx.shape == (3, 2) and (idx == -1).all() and np.isinf(d).all()
    assert VoxelHash.build(np.ones((4, 3)), 0.5).query(np.zeros((0, 3)), 1, 1.0)[1].shape == (0, 1)


def test_voxel_set_claims_free_voxels_as_points_come_and_go():
    """Chunk by chunk against a plain recount: first point per voxel, none where a live point sits."""
    rng = np.random.default_rng(3)
    voxels = VoxelSet()
    held_keys, held_ids = np.zeros(0, np.int64), np.zeros(0, np.int64)
    next_id = 0
    for chunk in range(40):  # enough to rebuild the table several times
        keys = voxel_keys(rng.uniform(-3, 3, (rng.integers(0, 800), 3)), 0.5)
        live_from = max(0, next_id - 1500)  # the oldest leave
        alive = held_ids >= live_from
        want = first_free(keys, held_keys[alive])
        got = voxels.claim(keys, live_from)
        np.testing.assert_array_equal(got, want, err_msg=f"chunk {chunk}")
        held_keys = np.concatenate([held_keys, keys[got]])
        held_ids = np.concatenate([held_ids, next_id + np.arange(len(got))])
        next_id += len(got)
    assert len(voxels.table_key) < 8 * 4096  # departed entries were dropped, not kept forever


def test_first_free_is_first_in_order_and_skips_taken():
    keys = np.array([5, 3, 5, 7, 3, 9, 1], np.int64)
    np.testing.assert_array_equal(first_free(keys, np.array([7, 2], np.int64)), [0, 1, 5, 6])


@pytest.mark.parametrize("voxel_m", [0.05, 2.0])  # most voxels hold one point; a few hold them all
def test_voxel_groups_are_numpys_unique_up_to_numbering(voxel_m):
    pts, _ = _scene()
    voxel, first = voxel_groups(pts, voxel_m)
    keys = voxel_keys(pts, voxel_m)
    _, first_ref, voxel_ref = np.unique(keys, return_index=True, return_inverse=True)
    assert len(first) == len(first_ref)
    np.testing.assert_array_equal(first[voxel], first_ref[voxel_ref])  # same groups, same first point
    assert (np.diff(first) > 0).all()  # numbered by first appearance
    assert voxel_groups(np.zeros((0, 3)), 0.1)[1].shape == (0,)


def test_chain_points_match_the_trajectory_pose():
    rng = np.random.default_rng(1)
    t_imu = np.arange(0, 400_000_001, 5_000_000, dtype=np.int64)
    gyro = integrate_gyro(t_imu, rng.normal(0, 1.0, (len(t_imu), 3)), np.eye(3))
    stamps = np.array([100_000_000, 150_000_000, 200_000_000], np.int64)
    R = Rotation.from_rotvec(rng.normal(0, 0.3, (3, 3))).as_matrix()
    p = rng.normal(0, 0.2, (3, 3))
    traj = RigTrajectory(stamps, R, p, np.zeros(3), gyro)
    t = rng.integers(100_000_000, 200_000_000, 300)
    pts = rng.normal(0, 5, (300, 3))
    seg, f = traj._segment(t)
    shape_next = gyro.between(stamps[:-1], stamps[1:])
    err = Rotation.from_matrix(np.swapaxes(R[:-1] @ shape_next, 1, 2) @ R[1:]).as_rotvec()
    a, world = chain_points(pts, seg, f, traj.gyro_shape(t), R, p, err)
    R_t, p_t = traj._pose_exact(t)
    np.testing.assert_allclose(a, np.einsum("nij,nj->ni", R_t, pts), atol=1e-12)
    np.testing.assert_allclose(world, a + p_t, atol=1e-12)
    # many points take the node grid, applied in one pass: the same as pose()
    t_many = rng.integers(100_000_000, 200_000_000, 2000)
    pts_many = rng.normal(0, 5, (2000, 3))
    R_g, p_g = traj.pose(t_many)
    np.testing.assert_allclose(traj.transform(pts_many, t_many), np.einsum("nij,nj->ni", R_g, pts_many) + p_g,
                               atol=1e-12)  # fmt: skip


def test_gyro_between_and_log_rotations_match_numpy_and_scipy():
    rng = np.random.default_rng(2)
    t_imu = np.arange(0, 1_000_000_001, 5_000_000, dtype=np.int64)
    gyro = integrate_gyro(t_imu, rng.normal(0, 2.0, (len(t_imu), 3)), np.eye(3))
    t0, t1 = rng.integers(-(10**7), 10**9 + 10**7, (2, 500))  # outside the track too: clamped
    np.testing.assert_allclose(gyro_between(gyro, t0, t1), gyro.between(t0, t1), atol=1e-14)
    for angle in (0.0, 1e-9, 1e-5, 0.3, 2.0, 3.1, np.pi - 1e-9):
        axis = rng.normal(size=(20, 3))
        v = axis / np.linalg.norm(axis, axis=1, keepdims=True) * angle
        np.testing.assert_allclose(log_rotations(Rotation.from_rotvec(v).as_matrix()), v, atol=1e-9)


def test_neighbourhood_planes_match_numpys_covariances_and_eigen_solve():
    rng = np.random.default_rng(4)
    pts = rng.normal(0, 3, (500, 3))
    idx = rng.integers(0, 500, (200, 10))
    flat = np.column_stack([rng.uniform(-1, 1, (10, 2)), np.zeros(10)])  # a plane: exact normal +-z
    line = np.column_stack([np.linspace(0, 1, 10), np.zeros((10, 2))])  # two zero eigenvalues: LAPACK's
    pts = np.concatenate([pts, flat, line])
    idx = np.concatenate([idx, np.arange(500, 510)[None], np.arange(510, 520)[None]])
    evals, normal = neighbourhood_planes(pts, idx)
    ref_evals, ref_normal = sym3_smallest(neighbour_covariances(pts, idx))
    np.testing.assert_allclose(evals, ref_evals, atol=1e-12)
    np.testing.assert_allclose(np.abs(np.einsum("ij,ij->i", normal, ref_normal)), 1.0, atol=1e-9)
    np.testing.assert_allclose(np.abs(normal[-2]), [0, 0, 1], atol=1e-12)


def test_plane_system_is_the_weighted_dense_jacobians_system():
    rng = np.random.default_rng(4)
    n, m = 500, 300
    a, world = rng.normal(0, 3, (n, 3)), rng.normal(0, 3, (n, 3))
    map_xyz = world[rng.integers(0, n, m)] + rng.normal(0, 0.02, (m, 3))
    nrm = rng.normal(size=(m, 3))
    nrm /= np.linalg.norm(nrm, axis=1)[:, None]
    planar = rng.uniform(size=m) < 0.8
    j = rng.integers(-1, m, n)  # unmatched, matched to a non-planar point, matched
    f, seg = rng.uniform(0, 1, n), rng.integers(0, 3, n)
    free = np.array([1, 2, 3], np.int64)
    H, g, residual, used = plane_system(a, world, j, planar, nrm, map_xyz, seg, f, free)
    ok = np.flatnonzero((j >= 0) & planar[np.maximum(j, 0)])
    nn = nrm[j[ok]]
    r = np.einsum("ij,ij->i", nn, world[ok] - map_xyz[j[ok]])
    scale = max(1.4826 * np.median(np.abs(r)), 0.005)
    w = 1.0 / (1.0 + (r / scale) ** 2)
    J = np.zeros((len(ok), 18))
    for u, k in enumerate(free):  # the dense Jacobian the kernel stands for
        wt = np.where(seg[ok] == k - 1, f[ok], 0.0) + np.where(seg[ok] == k, 1.0 - f[ok], 0.0)
        J[:, 6 * u : 6 * u + 3] = np.cross(a[ok], nn) * wt[:, None]
        J[:, 6 * u + 3 : 6 * u + 6] = nn * wt[:, None]
    assert used == len(ok) > 300
    np.testing.assert_allclose(H, J.T @ (J * w[:, None]), atol=1e-9)
    np.testing.assert_allclose(g, J.T @ (w * r), atol=1e-12)
    assert residual == pytest.approx(np.sqrt(np.average(r**2, weights=w)), rel=1e-12)
    assert np.isnan(plane_system(a, world, j, planar, nrm, map_xyz, seg, f, free, min_points=used + 1)[2])
