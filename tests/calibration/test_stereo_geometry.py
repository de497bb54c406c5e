"""Vertical-stereo rectification and depth <-> disparity against independent geometry."""

import math

import numpy as np
import pytest

from calibration import DoubleSphere
from calibration.rectify import rectify_stereo
from calibration.spherical import Equirectangular
from calibration.stereo import (
    depth_to_disparity,
    disparity_and_stability,
    disparity_stability_mask,
    disparity_to_depth,
    pinhole_depth_to_disparity,
    pinhole_disparity_to_depth,
    rotate_for_stereo,
    unrotate_from_stereo,
)
from calibration.transforms import make_transform, rodrigues

H_FULL = 2048
CAM0 = DoubleSphere(500.2, 500.1, 962.4, 597.9, -0.18, 0.59, 1920, 1200)
CAM1 = DoubleSphere(498.9, 498.8, 956.7, 603.2, -0.179, 0.589, 1920, 1200)
# Non-trivial relative pose: ~3 degrees of rotation, baseline mostly down with x/z components.
R_C1_C0 = rodrigues([0.03, -0.035, 0.02])
C1_IN_C0 = np.array([0.004, 0.12, -0.003])
T_C1_C0 = make_transform(R_C1_C0, -R_C1_C0 @ C1_IN_C0)


def points_seen_by_both(n, seed=0):
    rng = np.random.default_rng(seed)
    rays, ok = CAM0.unproject(np.column_stack([rng.uniform(0, 1919, 4 * n), rng.uniform(0, 1199, 4 * n)]))
    rng_m = rng.uniform(0.3, 40.0, 4 * n)
    p0 = rays[ok] * rng_m[ok, None]
    p1 = p0 @ T_C1_C0[:3, :3].T + T_C1_C0[:3, 3]
    uv1, ok1 = CAM1.project(p1)
    keep = ok1 & CAM1.in_image(uv1)
    return p0[keep][:n], p1[keep][:n]


def test_rectified_frame_axes():
    rect = rectify_stereo(T_C1_C0)
    R = rect.R_cam0_rect
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-14) and np.linalg.det(R) == pytest.approx(1.0)
    assert rect.baseline_m == pytest.approx(np.linalg.norm(C1_IN_C0), abs=1e-15)
    assert np.allclose(R[:, 1], C1_IN_C0 / np.linalg.norm(C1_IN_C0), atol=1e-15)  # y along the baseline
    # cam1's centre sits at +B along y_rect
    assert np.allclose(R.T @ C1_IN_C0, [0.0, rect.baseline_m, 0.0], atol=1e-15)
    # z is the mean optical axis, orthogonalised
    z_mean = np.array([0, 0, 1.0]) + R_C1_C0.T[:, 2]
    assert np.cross(R[:, 2], z_mean - (z_mean @ R[:, 1]) * R[:, 1]) == pytest.approx(np.zeros(3), abs=1e-15)


def test_geometric_truth_columns_rows_and_inverse():
    rect = rectify_stereo(T_C1_C0)
    eq = Equirectangular(H_FULL)
    p0, p1 = points_seen_by_both(20000)
    assert len(p0) == 20000
    uv0, ok0 = eq.project(p0 @ rect.R_cam0_rect)  # R_rect_cam0 = R_cam0_rect^T (row vectors)
    uv1, ok1 = eq.project(p1 @ rect.R_cam1_rect)
    assert ok0.all() and ok1.all()
    assert np.abs(uv0[:, 0] - uv1[:, 0]).max() < 1e-9  # same column: columns are epipolar lines
    range_m = np.linalg.norm(p0, axis=1)
    theta = eq.theta_of_row(uv0[:, 1])
    disp = depth_to_disparity(range_m, theta, rect.baseline_m, H_FULL)
    assert (disp > 0).all()
    assert np.abs((uv0[:, 1] - uv1[:, 1]) - disp).max() < 1e-6  # lower camera sees the point higher
    stable = disparity_stability_mask(theta, range_m, rect.baseline_m, H_FULL, max_rel_error=0.05)
    assert 0.1 < stable.mean() < 1.0  # ranges up to 40 m: far points are not stable
    back = disparity_to_depth(disp, theta, rect.baseline_m, H_FULL)
    rel = np.abs(back - range_m) / range_m
    assert rel[stable].max() < 1e-9


def test_depth_disparity_known_values():
    # theta = 90 deg: disp = atan(B / r) exactly; r = 1.2 m, B = 0.12 -> atan(0.1)
    d = depth_to_disparity(1.2, math.pi / 2, 0.12, H_FULL)
    assert d == pytest.approx(math.atan(0.1) * H_FULL / math.pi, rel=1e-15)
    # on the baseline (theta = pi, straight down through cam1) there is no parallax
    assert depth_to_disparity(5.0, math.pi, 0.12, H_FULL) == pytest.approx(0.0, abs=1e-12)
    assert disparity_to_depth(d, math.pi / 2, 0.12, H_FULL) == pytest.approx(1.2, rel=1e-14)


def test_invalid_inputs_give_zero_not_nan_or_inf():
    r = np.array([-1.0, 0.0, np.nan, np.inf, 2.0, 2.0])
    t = np.array([1.0, 1.0, 1.0, 1.0, np.nan, 0.0])
    out = depth_to_disparity(r, t, 0.12, H_FULL)
    assert np.isfinite(out).all() and out.tolist() == [0.0] * 6
    d = np.array([-1.0, 0.0, np.nan, np.inf, 5.0, 3000.0])
    out = disparity_to_depth(d, np.array([1.0, 1.0, 1.0, 1.0, np.nan, 1.0]), 0.12, H_FULL)
    assert np.isfinite(out).all() and out.tolist() == [0.0] * 6
    assert pinhole_depth_to_disparity(np.array([0.0, -1.0, np.nan]), 500.0, 0.1).tolist() == [0.0] * 3
    assert pinhole_disparity_to_depth(np.array([0.0, -1.0, np.nan]), 500.0, 0.1).tolist() == [0.0] * 3


def test_pinhole_formula():
    z = np.array([0.5, 1.0, 10.0])
    d = pinhole_depth_to_disparity(z, 600.0, 0.065)
    assert d.tolist() == pytest.approx([78.0, 39.0, 3.9])
    assert pinhole_disparity_to_depth(d, 600.0, 0.065) == pytest.approx(z, rel=1e-15)


def test_stability_mask_removes_poles_and_far_points():
    theta = np.radians([1.0, 90.0, 90.0, 179.0, 90.0])
    rng = np.array([2.0, 2.0, 200.0, 2.0, 5.0])
    stable = disparity_stability_mask(theta, rng, 0.12, H_FULL, max_rel_error=0.05)
    assert stable.tolist() == [False, True, False, False, True]
    # exactly: at theta = 90, r = 5 m, d = atan(0.024) * 2048/pi = 15.64 px -> 0.5 px is ~3.2 %
    assert not disparity_stability_mask(np.pi / 2, 5.0, 0.12, H_FULL, max_rel_error=0.03)


def test_the_fused_disparity_and_stability_equal_the_two_numpy_functions():
    rng = np.random.default_rng(5)
    n = 200_000
    range_m = rng.uniform(0.01, 60.0, n)
    theta = rng.uniform(0.0, np.pi, n)
    # no range, NaN and the poles (0 / unstable); a point between the cameras (rho > 90 deg, still stable)
    range_m[:6] = [0.0, -1.0, np.nan, 2.0, 2.0, 0.05]
    theta[:6] = [1.0, 1.0, 1.0, 0.0, np.pi, 3.0]
    baseline_m, max_rel, err_px = 0.12, 0.05, 0.5
    disp, stable = disparity_and_stability(range_m, theta, baseline_m, H_FULL, max_rel, err_px)
    want_disp = depth_to_disparity(range_m, theta, baseline_m, H_FULL)
    want = disparity_stability_mask(theta, range_m, baseline_m, H_FULL, max_rel, err_px, want_disp)
    assert np.abs(disp - want_disp).max() < 1e-9
    assert disp[:3].tolist() == [0.0, 0.0, 0.0] and not stable[:5].any() and stable[5] and disp[5] > 1000
    # the mask may differ only where the relative error lies within rounding of the threshold
    with np.errstate(all="ignore"):
        r_lo = disparity_to_depth(want_disp + err_px, theta, baseline_m, H_FULL)
        r_hi = disparity_to_depth(want_disp - err_px, theta, baseline_m, H_FULL)
        rel = np.maximum(np.abs(range_m - r_lo), np.abs(r_hi - range_m)) / range_m
    differ = stable != want
    assert np.all(np.abs(rel[differ] - max_rel) < 1e-9)
    assert 0.05 < want.mean() < 0.5 and differ.sum() <= 2
    one_d, one_s = disparity_and_stability(5.0, np.pi / 2, baseline_m, H_FULL, 0.03, err_px)
    assert float(one_d) == pytest.approx(np.arctan(0.024) * H_FULL / np.pi, rel=1e-12) and not one_s


def test_rotation_gives_horizontal_disparity():
    rect = rectify_stereo(T_C1_C0)
    eq = Equirectangular(256)
    p0, p1 = points_seen_by_both(50, seed=3)
    up = np.zeros((256, 512), np.uint16)
    low = np.zeros((256, 512), np.uint16)
    disp_map = np.zeros((256, 512), np.float64)
    uv0, _ = eq.project(p0 @ rect.R_cam0_rect)
    uv1, _ = eq.project(p1 @ rect.R_cam1_rect)
    theta = eq.theta_of_row(uv0[:, 1])
    disp = depth_to_disparity(np.linalg.norm(p0, axis=1), theta, rect.baseline_m, 256)
    i = int(np.argmax(disp))  # a near point: several pixels of disparity
    c, r0 = round(uv0[i, 0]), round(uv0[i, 1])
    r1 = round(uv1[i, 1])
    up[r0, c] = 1
    low[r1, c] = 1
    disp_map[r0, c] = disp[i]
    left, right, d_rot = rotate_for_stereo(up), rotate_for_stereo(low), rotate_for_stereo(disp_map)
    (yl, xl), (yr, xr) = np.argwhere(left)[0], np.argwhere(right)[0]
    assert yl == yr  # same row after the rotation
    assert xl - xr == r0 - r1 and xl - xr > 0  # x_right = x_left - disp
    assert d_rot[yl, xl] == disp[i]
    assert abs((xl - xr) - d_rot[yl, xl]) <= 1.0  # rounding of both rows
    assert np.array_equal(unrotate_from_stereo(left), up)


def test_horizontal_rectification_pinhole_and_cassini():
    from calibration.spherical import Cassini, pinhole_for_fov

    # RIGHT camera 0.2 m to the right with a small rotation
    R_r_l = rodrigues([0.01, -0.02, 0.015])
    c_r = np.array([0.2, 0.003, -0.004])
    rect = rectify_stereo(make_transform(R_r_l, -R_r_l @ c_r), "horizontal")
    assert np.allclose(rect.R_cam0_rect[:, 0], c_r / np.linalg.norm(c_r), atol=1e-15)
    rng = np.random.default_rng(5)
    p = np.column_stack([rng.uniform(-2, 2, 500), rng.uniform(-1, 1, 500), rng.uniform(1, 8, 500)])
    p_r = p @ R_r_l.T - R_r_l @ c_r
    q_l, q_r = p @ rect.R_cam0_rect, p_r @ rect.R_cam1_rect  # both in their rectified frames
    pin = pinhole_for_fov(math.radians(90), 640, 480)
    uv_l, ok_l = pin.project(q_l)
    uv_r, ok_r = pin.project(q_r)
    assert ok_l.all() and ok_r.all()
    assert np.abs(uv_l[:, 1] - uv_r[:, 1]).max() < 1e-9  # rows are epipolar lines
    disp = pinhole_depth_to_disparity(q_l[:, 2], pin.fx, rect.baseline_m)
    assert np.abs((uv_l[:, 0] - uv_r[:, 0]) - disp).max() < 1e-9  # x_right = x_left - f B / z
    cas = Cassini(512)
    assert np.abs(cas.project(q_l)[0][:, 1] - cas.project(q_r)[0][:, 1]).max() < 1e-9
