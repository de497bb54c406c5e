"""Stability masks against unstable regions built from first principles.

Each test makes the error happen (perturbed pixels, triangulated rays, the
lower camera's projection into a cubemap, SGBM on rendered faces, displaced
LiDAR points through the real GT stages) and checks that the mask removes
where it is large while keeping where it is small.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import cv2
import numpy as np
import pytest

from calibration.fisheye import DoubleSphere
from calibration.linalg3 import rotvec_to_matrix
from calibration.rig import REFERENCE_RIG, read_rig
from calibration.spherical import Cubemap
from calibration.stereo import disparity_stability_mask, rotate_for_stereo, unrotate_from_stereo
from calibration.types import F64
from ingest.train.gt.groundtruth import (
    GtParams,
    in_view,
    occlusion_filter,
    px_per_rad,
    splat_to_pixels,
    surface_normals,
)
from ingest.train.trajectory.planes import Normals
from sensorbox.analysis.stability import (
    cubemap_seam_mask,
    cubemap_stereo_faces,
    disparity_range_error,
    displacement_mask,
    ds_radial_resolution,
    ds_stability_mask,
    ds_stable_angle_rad,
    ds_validity_limit_rad,
    extrinsic_displacement_px,
    extrinsic_range_error_m,
    time_offset_displacement_px,
    time_offset_range_error_m,
)

_UPPER = read_rig(REFERENCE_RIG).upper.model
assert isinstance(_UPPER, DoubleSphere)
DS: DoubleSphere = _UPPER


# -- 1. Double Sphere near its validity limit ---------------------------------------------


def test_ds_radial_resolution_matches_finite_differences_of_project() -> None:
    theta = np.radians(np.arange(0.0, 125.0, 5.0))
    eps = 1e-6
    rays = np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], 1)
    rays2 = np.stack([np.sin(theta + eps), np.zeros_like(theta), np.cos(theta + eps)], 1)
    uv, ok = DS.project(rays)
    uv2, ok2 = DS.project(rays2)
    assert ok.all() and ok2.all()
    numeric = (uv2[:, 0] - uv[:, 0]) / eps  # along x: fx, the closed form uses (fx + fy) / 2
    assert ds_radial_resolution(DS, theta) == pytest.approx(numeric * (DS.fx + DS.fy) / (2 * DS.fx), rel=1e-5)
    # at the projection's validity limit it is down to 5 % of the centre's; 1 degree later it folds
    limit = ds_validity_limit_rad(DS)
    assert math.degrees(limit) == pytest.approx(125.47, abs=0.01)
    assert 0 < float(ds_radial_resolution(DS, limit)) < 0.06 * float(ds_radial_resolution(DS, 0.0))
    assert float(ds_radial_resolution(DS, limit + math.radians(1.1))) < 0


def test_ds_mask_removes_pixels_where_half_a_pixel_costs_twice_the_centre_angle() -> None:
    """Perturb every pixel by +-0.25 px radially and measure the angle between the unprojected rays."""
    big = replace(DS.scaled(0.125), width=330, height=330, cx=164.5, cy=164.5)  # extends past the circle
    uv = big.pixel_grid().reshape(-1, 2)
    radial = uv - [big.cx, big.cy]
    radial /= np.maximum(np.linalg.norm(radial, axis=1, keepdims=True), 1e-9)
    a, ok_a = big.unproject(uv - 0.25 * radial)
    b, ok_b = big.unproject(uv + 0.25 * radial)
    angle = np.arccos(np.clip(np.einsum("ij,ij->i", a, b), -1.0, 1.0))  # rad per 0.5 px
    centre = 0.5 / float(ds_radial_resolution(big, 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        numeric_ratio = np.where(ok_a & ok_b, centre / angle, 0.0)  # resolution / centre resolution
    mask = ds_stability_mask(big, uv, min_ratio=0.5)
    unstable = numeric_ratio < 0.5 * 0.99
    stable = numeric_ratio > 0.5 * 1.01
    assert unstable.sum() > 2_000 and stable.sum() > 40_000  # both regions are really there
    assert not (mask & unstable).any()
    assert mask[stable].all()
    # the boundary is a circle at the angle the bisection finds
    rays, ok = big.unproject(uv[mask])
    assert ok.all()
    assert np.degrees(np.arccos(rays[:, 2]).max()) == pytest.approx(
        math.degrees(ds_stable_angle_rad(big, 0.5)), abs=0.2
    )


# -- 2. Disparity -> depth near the poles and at small disparities ------------------------


def _triangulated_range(theta: F64, lower_theta: F64, baseline_m: float) -> F64:
    """Range along cam0's ray at latitude theta where it meets cam1's ray at lower_theta (inf: never)."""
    # rays in the (y, z) plane of the rectified frame: (-cos t, sin t); cam1 sits at (B, 0)
    u0 = np.stack([-np.cos(theta), np.sin(theta)], -1)
    u1 = np.stack([-np.cos(lower_theta), np.sin(lower_theta)], -1)
    # s u0 = (B, 0) + t u1  ->  [u0, -u1] (s, t) = (B, 0)
    det = -u0[..., 0] * u1[..., 1] + u1[..., 0] * u0[..., 1]
    with np.errstate(all="ignore"):
        s = (-baseline_m * u1[..., 1]) / det
        t = (-u0[..., 1] * baseline_m) / det
    out: F64 = np.where((s > 0) & (t > 0) & (np.abs(det) > 1e-15), s, np.inf)
    return out


def test_disparity_mask_matches_triangulation_with_perturbed_disparity() -> None:
    B, H, err_px, max_rel = 0.12, 2048, 0.5, 0.1
    theta = np.radians(np.linspace(0.5, 179.5, 359))[:, None]
    r = np.geomspace(0.3, 200.0, 300)[None, :]
    theta, r = np.broadcast_arrays(theta, r)
    # where cam1 sees the point (its latitude from "up"), then +-err px of disparity
    p = np.stack([-r * np.cos(theta) - B, r * np.sin(theta)], -1)
    lower = np.arctan2(p[..., 1], -p[..., 0])
    assert np.allclose(_triangulated_range(theta, lower, B), r, rtol=1e-9)
    step = err_px * math.pi / H
    worst = (
        np.maximum(
            np.abs(_triangulated_range(theta, lower - step, B) - r),
            np.abs(_triangulated_range(theta, lower + step, B) - r),
        )
        / r
    )
    assert disparity_range_error(theta, r, B, H, err_px) == pytest.approx(worst, rel=1e-6)
    mask = disparity_stability_mask(theta, r, B, H, max_rel, err_px)
    unstable, stable = worst > max_rel * 1.0001, worst < max_rel * 0.9999
    assert unstable.mean() > 0.3 and stable.mean() > 0.2
    assert not (mask & unstable).any() and mask[stable].all()
    # near the poles nothing is stable even at arm's length; at the equator 2 m is
    assert not mask[np.degrees(theta[:, 0]) < 2.0].any()
    assert mask[np.argmin(np.abs(np.degrees(theta[:, 0]) - 90)), np.argmin(np.abs(r[0] - 2.0))]


# -- 3. Cubemap seams ---------------------------------------------------------------------


def test_only_side_faces_are_vertical_stereo_pairs() -> None:
    assert cubemap_stereo_faces([0.0, 1.0, 0.0]) == ("front", "right", "back", "left")
    assert cubemap_stereo_faces([0.0, -1.0, 0.0]) == ()  # the baseline must point down the image
    assert cubemap_stereo_faces([0.0, 1.0, 0.01]) == ()  # and lie in the face plane


def test_seam_mask_is_where_the_lower_cameras_projection_stays_on_the_face() -> None:
    """Project the scene point of every side-face pixel from cam1's centre into the cubemap."""
    F, B, m = 96, 0.12, 2
    cube = Cubemap(F)
    grid = cube.pixel_grid().reshape(-1, 2)
    rays, ok = cube.unproject(grid)
    assert ok.all()
    face = (grid[:, 0] + 0.5) // F
    rng = np.random.default_rng(3)
    r = rng.uniform(0.4, 3.0, len(rays))  # any scene: a random range per pixel
    pts = rays * r[:, None]
    uv1, ok1 = cube.project(pts - [0.0, B, 0.0])  # cam1, rectified into cam0's orientation
    face1 = (uv1[:, 0] + 0.5) // F
    u1, v1 = uv1[:, 0] - face1 * F, uv1[:, 1]
    u0, v0 = grid[:, 0] - face * F, grid[:, 1]
    in_face = (u0 >= m) & (u0 <= F - 1 - m) & (v0 <= F - 1 - m)
    matchable = ok1 & (face1 == face) & in_face & (v1 >= m) & (v1 <= F - 1 - m)
    z = np.einsum("ij,ij->i", pts, np.stack([R[:, 2] for _, _, R in cube.faces()])[face.astype(int)])
    disp = (F / 2.0) * B / z
    names = [n for n, _, _ in cube.faces()]
    side = np.isin(np.array(names)[face.astype(int)], cubemap_stereo_faces([0.0, 1.0, 0.0]))
    mask = side & cubemap_seam_mask(u0, v0, disp, F, m)
    assert np.array_equal(mask[side], matchable[side])
    assert (~mask[side]).sum() > 0.1 * side.sum()  # the seam loses a real band
    # on the side faces the match is in the same column (vertical epipolar lines)
    assert np.abs(u1 - u0)[side & matchable].max() < 1e-6


def _texture(points_xy: F64, noise: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """Grey level of a plane's smooth random texture at plane coordinates in [-2, 2] m."""
    scale = (noise.shape[0] - 1) / 4.0
    mx = ((points_xy[..., 0] + 2.0) * scale).astype(np.float32)
    my = ((points_xy[..., 1] + 2.0) * scale).astype(np.float32)
    return cv2.remap(noise, mx, my, cv2.INTER_LINEAR)


def test_sgbm_on_the_front_face_fails_where_the_seam_mask_says() -> None:
    """Render a textured wall 0.4 m ahead into both cameras' front faces and run SGBM."""
    F, B, z0, block = 128, 0.12, 0.4, 5
    rng = np.random.default_rng(7)
    small: np.ndarray[Any, Any] = rng.uniform(0, 255, (160, 160)).astype(np.float32)
    noise = cv2.resize(small, (1024, 1024), interpolation=cv2.INTER_CUBIC)
    face = Cubemap(F).face_model
    rays, _ = face.unproject(face.pixel_grid())
    images = []
    for centre_y in (0.0, B):
        t = z0 / rays[..., 2]
        xy = np.stack([rays[..., 0] * t, rays[..., 1] * t + centre_y], -1)
        images.append(np.clip(_texture(xy, noise), 0, 255).astype(np.uint8))
    d_true = (F / 2.0) * B / z0  # 19.2 px everywhere on a fronto-parallel wall
    sgbm = cv2.StereoSGBM.create(0, 32, block, 8 * block * block, 32 * block * block, uniquenessRatio=5)
    raw = sgbm.compute(rotate_for_stereo(images[0]), rotate_for_stereo(images[1]))
    disp = unrotate_from_stereo(raw).astype(np.float64) / 16.0
    v, u = np.mgrid[0:F, 0:F].astype(np.float64)
    good = (disp >= 0) & (np.abs(disp - d_true) <= 1.0)
    off_face = v - d_true < 0  # the lower camera sees these points on the "up" face
    assert good[off_face].mean() < 0.01
    # SGBM needs its whole search range (32 px) on the face, not only the match
    geometric = cubemap_seam_mask(u, v, np.full((F, F), d_true), F, block // 2)
    assert good[geometric].mean() < 0.95
    mask = cubemap_seam_mask(u, v, np.full((F, F), d_true), F, block // 2, search_px=32)
    assert good[mask].mean() > 0.99
    assert 0.6 < mask.mean() < 0.75


# -- 4. Time offsets and 5. extrinsic errors, through the real GT stages ------------------

LIDAR_IN_CAM_M = np.array([0.0, -0.09, -0.02])
MODEL = DS.scaled(0.25)  # 480 x 300
GT = GtParams()
_BOXES = (((-0.6, -0.4, 1.5), (0.3, 0.5, 2.0)), ((0.8, -1.0, 3.0), (1.2, 1.2, 3.3)))


def _cast(origins: F64, dirs: F64) -> F64:
    """Exact range along unit `dirs` in a room (walls at x = +-3, z = 5, floor y = 1.2, ceiling -2) with two boxes."""
    t = np.full(len(dirs), np.inf)
    with np.errstate(all="ignore"):
        for axis, value in ((2, 5.0), (1, 1.2), (1, -2.0), (0, -3.0), (0, 3.0)):
            hit = (value - origins[:, axis]) / dirs[:, axis]
            t = np.where((hit > 0) & (hit < t), hit, t)
        for lo, hi in _BOXES:
            t1, t2 = (np.array(lo) - origins) / dirs, (np.array(hi) - origins) / dirs
            near = np.nanmax(np.minimum(t1, t2), axis=1)
            far = np.nanmin(np.maximum(t1, t2), axis=1)
            t = np.where((near <= far) & (near > 0) & (near < t), near, t)
    return t


@pytest.fixture(scope="module")
def lidar_points() -> F64:
    """A dense LiDAR scan of the room from the LiDAR's centre (cam0 frame at the frame time)."""
    rng = np.random.default_rng(0)
    dirs = rng.normal(size=(150_000, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    dirs = dirs[dirs[:, 2] > -0.2]
    origins = np.broadcast_to(LIDAR_IN_CAM_M, dirs.shape)
    pts: F64 = origins + dirs * _cast(origins, dirs)[:, None]
    return pts[np.isfinite(pts).all(axis=1)]


def _gt_and_truth(pts: F64) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
    """GT range image from the pipeline's stages, and the exact range at its pixels."""
    seen, _, _ = in_view(MODEL, pts)
    normals = surface_normals(pts, GT.plane_neighbours, GT.plane_max_flatness, query=seen)
    visible = occlusion_filter(MODEL, pts, GT)
    kept = Normals(normals.normal[visible[seen]], normals.planar[visible[seen]])
    splat = splat_to_pixels(MODEL, pts[visible], kept, GT)
    gt = np.zeros(MODEL.height * MODEL.width, np.float32)
    truth = np.zeros(MODEL.height * MODEL.width)
    gt[splat.pixel] = splat.range_m
    truth[splat.pixel] = _cast(np.zeros_like(splat.ray), splat.ray)
    return gt.reshape(MODEL.height, MODEL.width), truth.reshape(MODEL.height, MODEL.width)


def _outliers(gt: np.ndarray[Any, Any], truth: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    out: np.ndarray[Any, Any] = (gt > 0) & (np.abs(gt - truth) > np.maximum(0.05, 0.03 * truth))
    return out


def _check_mask(pts: F64, moved: F64, displacement: Any, range_error: float, min_kept: float) -> None:
    base = _outliers(*_gt_and_truth(pts))
    gt, truth = _gt_and_truth(moved)
    bad = _outliers(gt, truth)
    new = bad & ~base  # outliers the displacement made
    mask = displacement_mask(gt, displacement(gt) if callable(displacement) else displacement, range_error)
    stable = (gt > 0) & ~bad
    assert new.sum() >= 100, "the injected error must create outliers"
    assert (new & mask).sum() <= 0.02 * new.sum()
    assert (bad & mask).sum() <= 0.001 * mask.sum()  # kept GT is clean: far below the 0.5 % target
    assert bad.sum() >= 5 * (bad & mask).sum()
    assert (mask & stable).sum() >= min_kept * stable.sum()


@pytest.mark.parametrize("angle_deg", [0.5, 1.0])
def test_extrinsic_rotation_error_mask(lidar_points: F64, angle_deg: float) -> None:
    """T_cam0_lidar off by 0.5 or 1 degree: 0.5-1 % of the GT are outliers, the mask keeps half the rest."""
    angle = math.radians(angle_deg)
    axis = np.array([0.3, 0.8, 0.5]) / np.linalg.norm([0.3, 0.8, 0.5])
    R = rotvec_to_matrix((axis * angle)[None])[0]
    moved = LIDAR_IN_CAM_M + np.einsum("ij,nj->ni", R, lidar_points - LIDAR_IN_CAM_M)
    lever = float(np.linalg.norm(LIDAR_IN_CAM_M))
    ppr = px_per_rad(MODEL)
    _check_mask(
        lidar_points,
        moved,
        lambda gt: extrinsic_displacement_px(angle, np.where(gt > 0, gt, 1.0), lever, ppr),
        extrinsic_range_error_m(angle, lever),
        min_kept=0.45,
    )


@pytest.mark.parametrize(("dt", "min_kept"), [(0.010, 0.45), (0.020, 0.25)])
def test_time_offset_mask(lidar_points: F64, dt: float, min_kept: float) -> None:
    """10 or 20 ms at 60 deg/s and 1.2 m/s: points placed where the rig was dt earlier.

    At 20 ms 4 % of the GT are outliers and 24 mm of the 5 cm budget go to the
    along-ray motion alone, so the mask keeps only a quarter of the rest.
    """
    omega, speed = math.radians(60.0), 1.2
    axis = np.array([0.2, 1.0, 0.1]) / np.linalg.norm([0.2, 1.0, 0.1])
    v = speed * np.array([0.6, 0.0, 0.8])
    R = rotvec_to_matrix((axis * omega * dt)[None])[0]
    moved = np.einsum("ij,nj->ni", R, lidar_points) + v * dt
    ppr = px_per_rad(MODEL)
    _check_mask(
        lidar_points,
        moved,
        lambda gt: time_offset_displacement_px(dt, omega, speed, np.where(gt > 0, gt, 1.0), ppr),
        time_offset_range_error_m(dt, speed),
        min_kept=min_kept,
    )


def test_displacement_mask_rejects_everything_when_the_range_error_alone_is_too_large() -> None:
    gt = np.zeros((20, 20), np.float32)
    gt[5:15, 5:15] = 1.0
    assert displacement_mask(gt, 0.0, 0.0).sum() == 100
    assert displacement_mask(gt, 0.0, 0.051).sum() == 0  # 5 cm tolerance at 1 m
    step = gt.copy()
    step[5:15, 10:15] = 2.0
    keep = displacement_mask(step, 2.0, 0.0, gap_px=0.0)
    assert not keep[5:15, 8:12].any() and keep[5:15, 5:8].all() and keep[5:15, 12:15].all()


def test_displacement_mask_reaches_the_whole_disc_and_little_more() -> None:
    """One near GT pixel amid far ones: every far pixel within the reach sees it, none far beyond does."""
    size, c = 161, 80
    gt = np.full((size, size), 5.0, np.float32)
    gt[c, c] = 1.0
    dy, dx = np.mgrid[-c : size - c, -c : size - c]
    dist = np.hypot(dx, dy)
    for reach in (2.0, 7.5, 30.0, 61.0):
        keep = displacement_mask(gt, reach, 0.0, gap_px=0.0)
        assert not keep[c, c]
        assert not keep[(dist <= reach)].any()  # the rounded-up ladder never falls short
        assert keep[dist > 1.1 * reach + 2.5].all()  # and adds at most one rung and a pixel


def test_seam_mask_counts_the_padding_above_the_face() -> None:
    """A face padded `pad_px` rows above gives the match (v - d) that much room: v = 10, d = 20 and a
    3 px block need v + pad - d >= 3, so pad 13 keeps the pixel and pad 12 does not."""
    got = [bool(cubemap_seam_mask(50.0, 10.0, 20.0, 100, 3, pad_px=pad)) for pad in (0, 12, 13)]
    assert got == [False, False, True]


def test_displacement_bounds_are_the_same_for_either_sign_of_the_offset() -> None:
    """px_per_rad |dt| (|omega| + |v| / r): 500 px/rad x 0.01 s x (1 rad/s + 2 m/s / 4 m) = 7.5 px whether
    the LiDAR clock runs 10 ms ahead or behind; a rotation error of -0.002 rad with a 0.1 m lever
    at 0.5 m gives 500 x 0.002 x (1 + 0.2) = 1.2 px and 0.2 mm along the ray."""
    for dt in (0.01, -0.01):
        assert time_offset_displacement_px(dt, -1.0, -2.0, np.array([4.0]), 500.0).tolist() == pytest.approx(
            [7.5]
        )
        assert time_offset_range_error_m(dt, -2.0) == pytest.approx(0.02)
    assert extrinsic_displacement_px(-0.002, np.array([0.5]), 0.1, 500.0).tolist() == pytest.approx([1.2])
    assert extrinsic_range_error_m(-0.002, 0.1) == pytest.approx(0.0002)
