"""Closed-form 3x3 routines against LAPACK (np.linalg.eigh) and scipy's rotations."""

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from calibration.linalg3 import apply_rotations, rotation_angle, rotvec_to_matrix, sym3_eigvals, sym3_smallest
from ingest.train.trajectory.clouds import integrate_gyro
from ingest.train.trajectory.rig_trajectory import RigTrajectory


def _covariances(rng: np.random.Generator, n: int) -> np.ndarray:
    """Point-cloud-like covariances: planes (one tiny axis), lines, blobs, at random orientations."""
    scales = rng.uniform(0.0, 1.0, (n, 3)) ** 3
    scales[: n // 3, 0] *= 1e-6  # near-planar
    scales[n // 3 : n // 2, :2] *= 1e-5  # line-like: two small axes
    R = Rotation.random(n, random_state=1).as_matrix()
    cov: np.ndarray = np.einsum("nij,nj,nkj->nik", R, scales, R)
    return cov


def test_eigenvalues_match_lapack():
    cov = _covariances(np.random.default_rng(0), 3000)
    ours, ref = sym3_eigvals(cov), np.linalg.eigh(cov)[0]
    span = ref[:, 2:] - ref[:, :1]
    err = np.abs(ours - ref) / span
    gaps = np.diff(ref, axis=1) / span
    isolated = np.stack([gaps[:, 0], gaps.min(axis=1), gaps[:, 1]], axis=1) > 1e-3
    assert isolated.mean() > 0.8
    assert err[isolated].max() < 1e-12  # Newton-polished simple roots
    assert err.max() < 1e-8  # a (nearly) double root keeps arccos's error


def test_smallest_eigenvector_matches_lapack_up_to_sign():
    cov = _covariances(np.random.default_rng(1), 3000)
    evals, vec = sym3_smallest(cov)
    w, v = np.linalg.eigh(cov)
    np.testing.assert_allclose(evals, w, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(vec, axis=1), 1.0, atol=1e-12)
    gap = (w[:, 1] - w[:, 0]) / (w[:, 2] - w[:, 0])
    defined = gap > 1e-3  # where the smallest eigenvalue is simple its vector is unique up to sign
    dots = np.abs(np.einsum("ni,ni->n", vec, v[:, :, 0]))
    assert defined.sum() > 2000
    assert np.all(dots[defined] > 1 - 1e-9)
    # everywhere, the vector is an eigenvector of the smallest eigenvalue
    residual = np.einsum("nij,nj->ni", cov, vec) - evals[:, :1] * vec
    assert np.abs(residual).max() < 1e-9


def test_isotropic_and_zero_matrices_fall_back_cleanly():
    cov = np.stack([np.eye(3) * 2.0, np.zeros((3, 3))])
    evals, vec = sym3_smallest(cov)
    np.testing.assert_allclose(evals, [[2, 2, 2], [0, 0, 0]], atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(vec, axis=1), 1.0)


def test_rodrigues_and_angles_match_scipy():
    rng = np.random.default_rng(2)
    rv = np.concatenate([rng.normal(size=(500, 3)), rng.normal(size=(500, 3)) * 1e-6, np.zeros((1, 3))])
    R = rotvec_to_matrix(rv)
    np.testing.assert_allclose(R, Rotation.from_rotvec(rv).as_matrix(), atol=1e-14)
    big = np.linalg.norm(rv, axis=1) > 1e-3
    np.testing.assert_allclose(rotation_angle(R)[big], Rotation.from_rotvec(rv[big]).magnitude(), atol=1e-7)
    p = rng.normal(size=(len(rv), 3))
    np.testing.assert_allclose(apply_rotations(R, p), Rotation.from_rotvec(rv).apply(p), atol=1e-12)


def test_gyro_track_between_equals_scipy_slerp():
    rng = np.random.default_rng(3)
    stamps = (
        np.arange(0, 100_000_000, 5_000_000, dtype=np.int64) + 1_000_000_000
    )  # exact as float64 for scipy
    gyro = rng.normal(scale=1.5, size=(len(stamps), 3))  # rad/s, a shaky hand
    R_cam0_imu = Rotation.from_euler("xyz", [10, -20, 30], degrees=True).as_matrix()
    track = integrate_gyro(stamps, gyro, R_cam0_imu)
    t = rng.integers(stamps[0] - 3_000_000, stamps[-1] + 3_000_000, 2000)  # incl. clamped ends
    t_ref = int(stamps[7] + 1_234_567)
    slerp = Slerp(stamps.astype(float), Rotation.from_matrix(track.rotations))
    clamp = np.clip(t, stamps[0], stamps[-1]).astype(float)
    expected = (slerp([float(t_ref)]).inv() * slerp(clamp)).as_matrix()
    np.testing.assert_allclose(track.between(np.array([t_ref]), t), expected, atol=1e-12)
    # and the integration itself: the midpoint rule step by step
    w = gyro @ R_cam0_imu.T
    R = np.eye(3)
    for k in range(len(stamps) - 1):
        R = R @ Rotation.from_rotvec(0.5 * (w[k] + w[k + 1]) * 0.005).as_matrix()
    np.testing.assert_allclose(track.rotations[-1], R, atol=1e-12)


def test_a_window_trajectory_moves_points_by_the_gyro_and_the_velocity():
    """`RigTrajectory.over_window`: a point measured at t lands at R(t_ref)^T R(t) p + v (t - t_ref) in cam0
    at t_ref, with R the gyro's slerp (scipy's), on a shaky hand's gyro whose rate jumps between readings
    (up to 3 rad/s), still and clamped stretches included. The node grid holds every reading, so its
    blend is off by (omega dt)^2 / 8 between nodes 0.64 ms apart: under 1e-6 rad, 20 micrometres at 20 m
    (uniform nodes alone, with the rate's jumps inside them, are off by 1.7e-4 rad here)."""
    rng = np.random.default_rng(4)
    stamps = np.arange(0, 60_000_000, 5_000_000, dtype=np.int64) + 2_000_000_000
    gyro = rng.normal(scale=1.0, size=(len(stamps), 3))
    gyro[4:7] = 0.0  # a still stretch: the series branch of the step exponential
    gyro[7] = 1e-7
    track = integrate_gyro(stamps, gyro, np.eye(3))
    t = np.sort(rng.integers(stamps[0] - 2_000_000, stamps[-1] + 2_000_000, 3000))
    t_ref = int(stamps[5] + 777_777)
    pts = rng.normal(scale=10.0, size=(len(t), 3))
    v = np.array([0.8, -0.1, 0.3])
    traj = RigTrajectory.over_window(track, v, t_ref, (int(t[0]), int(t[-1])))
    R = np.matmul(track.at(np.array([t_ref]))[0].T, track.at(t))
    want = apply_rotations(R, pts) + ((t - t_ref) / 1e9)[:, None] * v
    assert len(t) >= 4 * 100  # the node grid's path
    np.testing.assert_allclose(traj.to_frame(pts, t, t_ref), want, atol=2e-5)
    few = traj.to_frame(pts[:5], t[:5], t_ref)  # the exact path
    np.testing.assert_allclose(few, want[:5], atol=1e-11)
    assert rotation_angle(R).max() > 0.01  # the shaky parts really rotate
