"""The generic warp against analytic renders, and a checkerboard round trip."""

import math

import cv2
import numpy as np
import pytest

from calibration import DoubleSphere, read_rig
from calibration.errors import CalibrationError
from calibration.rectify import rectify_rig
from calibration.spherical import Cassini, Cubemap, Equirectangular, pinhole_for_fov
from calibration.warp import (
    SPHERE_BYTES_PER_PX,
    SPHERE_PX_PER_CAMERA_PX,
    RemapMaps,
    build_maps,
    check_height_full,
    covering_crop,
    default_height_full,
    remap_spans,
    warp,
)

REF_RIG = read_rig(
    __import__("pathlib").Path(__file__).resolve().parents[2] / "calibration" / "sensorbox.yaml"
)
FISHEYE = REF_RIG.upper.model.scaled(0.25)  # 480 x 300
R_CAM0_RECT = rectify_rig(REF_RIG).R_cam0_rect


def texture(rays_cam):
    """A smooth analytic texture on the sphere of directions (grey levels, float)."""
    x, y, z = rays_cam[..., 0], rays_cam[..., 1], rays_cam[..., 2]
    return 128.0 + 60.0 * np.sin(16.0 * x + 3.0 * y) * np.cos(14.0 * y - 5.0 * z) + 30.0 * np.sin(11.0 * z)


def render(model, R_cam_model=None):
    rays, ok = model.unproject(model.pixel_grid())
    if R_cam_model is not None:
        rays = rays @ R_cam_model.T
    out = np.where(ok, texture(np.nan_to_num(rays)), 0.0).astype(np.float32)
    return out, ok


@pytest.mark.parametrize(
    "target",
    [
        Equirectangular(default_height_full(FISHEYE)),
        Cubemap(256),
        Cassini(512),
        pinhole_for_fov(math.radians(90), 320, 240),
    ],
    ids=["equirect", "cubemap", "cassini", "pinhole90"],
)
def test_warp_matches_analytic_render(target):
    src, _ = render(FISHEYE)
    warped, valid = warp(src, FISHEYE, target, R_CAM0_RECT)
    truth, ok = render(target, R_CAM0_RECT)
    assert valid.sum() > 0.1 * valid.size and not (valid & ~ok).any()
    # away from the edges of the valid region (bilinear samples mix in the fill there)
    inner = cv2.erode(valid.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    err = np.abs(warped[inner] - truth[inner])
    assert err.mean() < 0.5, err.mean()
    assert np.all(warped[~valid] == 0.0)


def test_warp_detects_a_wrong_rotation():
    # the same check must fail when the rectification is off by 0.2 degrees
    src, _ = render(FISHEYE)
    eq = Equirectangular(default_height_full(FISHEYE))
    tilt = cv2.Rodrigues(np.array([math.radians(0.2), 0.0, 0.0]))[0]
    warped, valid = warp(src, FISHEYE, eq, tilt @ R_CAM0_RECT)
    truth, _ = render(eq, R_CAM0_RECT)
    inner = cv2.erode(valid.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert np.abs(warped[inner] - truth[inner]).mean() > 0.5  # the acceptance threshold above


def checkerboard_fisheye(model, square_m=0.08, cols=9, rows=7, dist_m=0.6, ss=4):
    """Anti-aliased render of a checkerboard plane in front of the camera; returns image, corners."""
    H, W = model.height, model.width
    acc = np.zeros((H, W), np.float64)
    offs = (np.arange(ss) + 0.5) / ss - 0.5
    grid = model.pixel_grid()
    x0, y0 = -cols * square_m / 2, -rows * square_m / 2
    for dy in offs:
        for dx in offs:
            rays, ok = model.unproject(grid + np.array([dx, dy]))
            with np.errstate(all="ignore"):
                X = rays[..., 0] / rays[..., 2] * dist_m - x0
                Y = rays[..., 1] / rays[..., 2] * dist_m - y0
            i, j = np.floor(X / square_m), np.floor(Y / square_m)
            on = ok & (rays[..., 2] > 0) & (i >= 0) & (i < cols) & (j >= 0) & (j < rows)
            acc += np.where(on, np.where((i + j) % 2 == 0, 230.0, 25.0), 128.0)
    img = (acc / ss**2).astype(np.float32)
    ci, cj = np.meshgrid(np.arange(1, cols), np.arange(1, rows))
    corners3d = np.stack([x0 + ci * square_m, y0 + cj * square_m, np.full(ci.shape, dist_m)], -1).reshape(
        -1, 3
    )
    uv, ok = model.project(corners3d)
    assert ok.all()
    return img, uv


def refine(img, guesses):
    pts = guesses.astype(np.float32).reshape(-1, 1, 2).copy()
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    cv2.cornerSubPix(img, pts, (4, 4), (-1, -1), crit)
    return pts.reshape(-1, 2).astype(np.float64)


def test_fisheye_equirect_fisheye_round_trip_keeps_corners():
    fish = REF_RIG.upper.model.scaled(0.5)  # 960 x 600
    img, truth_uv = checkerboard_fisheye(fish)
    eq = Equirectangular(default_height_full(fish))
    to_eq, _ = warp(img, fish, eq, R_CAM0_RECT)
    back, _valid = warp(to_eq, eq, fish, R_CAM0_RECT.T)
    before = refine(img, truth_uv)
    after = refine(back, truth_uv)
    # cornerSubPix assumes straight edges; on fisheye-curved corners it is biased by ~0.2 px
    assert np.abs(before - truth_uv).max() < 0.3
    shift = np.linalg.norm(after - before, axis=1)
    print(
        f"corner shift after fisheye->equirect->fisheye: max {shift.max():.3f} px, median {np.median(shift):.3f}"
    )
    assert shift.max() < 0.25, shift.max()


def test_maps_are_cached_and_bounds_respected():
    eq = Equirectangular(256)
    m1 = build_maps(FISHEYE, eq, R_CAM0_RECT)
    assert build_maps(FISHEYE, eq, R_CAM0_RECT.copy()) is m1
    assert build_maps(FISHEYE, eq, np.eye(3)) is not m1
    v = m1.valid
    assert (m1.map_x[v] >= -0.5).all() and (m1.map_x[v] < FISHEYE.width - 0.5).all()
    assert (m1.map_x[~v] == -1000).all()
    with pytest.raises(ValueError, match=r"image is 10x10, but the source model is 480x300"):
        warp(np.zeros((10, 10), np.float32), FISHEYE, eq)


@pytest.mark.parametrize("interp", [cv2.INTER_NEAREST, cv2.INTER_LINEAR, cv2.INTER_CUBIC])
def test_invalid_pixels_get_exactly_the_fill(interp):
    img = np.full((FISHEYE.height, FISHEYE.width, 3), 200, np.uint8)
    out, valid = warp(img, FISHEYE, Equirectangular(256), R_CAM0_RECT, interp, fill=7)
    assert (out[~valid] == 7).all() and (~valid).sum() > 1000
    inner = cv2.erode(valid.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert (out[inner] == 200).all()


@pytest.mark.parametrize("interp", [cv2.INTER_NEAREST, cv2.INTER_LINEAR, cv2.INTER_CUBIC])
@pytest.mark.parametrize("channels", [1, 3])
def test_span_warp_equals_one_remap_of_the_whole_target(interp, channels):
    """Remapping only the spans, into a fresh or a reused buffer, gives cv2.remap's every pixel."""
    rng = np.random.default_rng(4)
    eq = Equirectangular(256)
    maps = build_maps(FISHEYE, eq, R_CAM0_RECT)
    assert sum((r1 - r0) * (c1 - c0) for r0, r1, c0, c1 in maps.spans) < 0.6 * maps.valid.size
    shape = (FISHEYE.height, FISHEYE.width, channels)[: 2 if channels == 1 else 3]
    for reuse in (False, True, True):  # the second reuse overwrites the first one's buffer
        img = rng.integers(0, 256, shape, dtype=np.uint8)
        whole = cv2.remap(
            img, maps.map_x, maps.map_y, interp, borderMode=cv2.BORDER_CONSTANT, borderValue=(9, 9, 9, 9)
        )
        out = (
            _reused(img, maps, eq, interp)
            if reuse
            else warp(img, FISHEYE, eq, R_CAM0_RECT, interp, fill=9)[0]
        )
        np.testing.assert_array_equal(out, whole)
    again = _reused(img, maps, eq, interp)
    assert again is out  # the thread's buffer, not a new array


def _reused(img: np.ndarray, maps: RemapMaps, eq: Equirectangular, interp: int) -> np.ndarray:
    """`img` remapped over the spans into this thread's scratch buffer of `maps` (fill 9)."""
    out = maps.scratch((eq.height, eq.width, *img.shape[2:]), img.dtype, 9.0)
    remap_spans(img, maps, out, interp, fill=9)
    return out


def test_nearest_samples_the_nearest_source_pixel():
    ids = np.arange(FISHEYE.height * FISHEYE.width, dtype=np.float32).reshape(FISHEYE.height, FISHEYE.width)
    eq = Equirectangular(256)
    out, valid = warp(ids, FISHEYE, eq, R_CAM0_RECT, cv2.INTER_NEAREST)
    maps = build_maps(FISHEYE, eq, R_CAM0_RECT)
    expect = np.round(maps.map_y[valid]) * FISHEYE.width + np.round(maps.map_x[valid])
    assert np.mean(out[valid] == expect) > 0.999  # ties at exact .5 may go either way


def test_default_size_and_covering_crop_for_reference_rig():
    cam0 = REF_RIG.upper.model
    assert default_height_full(cam0) == 2048
    crop = covering_crop(cam0, R_CAM0_RECT, 2048)
    full = Equirectangular(2048)
    # everything the fisheye sees is inside the crop ...
    maps_full = build_maps(cam0, full, R_CAM0_RECT)
    rows, cols = np.nonzero(maps_full.valid)
    assert rows.min() >= crop.row_offset and rows.max() < crop.row_offset + crop.height
    assert cols.min() >= crop.col_offset and cols.max() < crop.col_offset + crop.width
    # ... and the crop is tight: 1 px margin plus the outer half pixel of the fisheye border,
    # which spans a few equirect columns where longitude is stretched at the image edge
    assert rows.min() - crop.row_offset <= 3 and crop.row_offset + crop.height - rows.max() <= 4
    assert cols.min() - crop.col_offset <= 4 and crop.col_offset + crop.width - cols.max() <= 5
    # without the margin it still holds every seen pixel; the margin adds margin_px on all four sides
    tight = covering_crop(cam0, R_CAM0_RECT, 2048, margin_px=0)
    assert rows.min() >= tight.row_offset and rows.max() < tight.row_offset + tight.height
    assert cols.min() >= tight.col_offset and cols.max() < tight.col_offset + tight.width
    assert (crop.row_offset, crop.height) == (tight.row_offset - 1, tight.height + 2)
    assert (crop.col_offset, crop.width) == (tight.col_offset - 1, tight.width + 2)
    # the warped crop equals the same window of the warped full sphere
    img = (np.random.default_rng(0).random((1200, 1920)) * 255).astype(np.uint8)
    w_full, _ = warp(img, cam0, full, R_CAM0_RECT)
    w_crop, _ = warp(img, cam0, crop, R_CAM0_RECT)
    window = w_full[
        crop.row_offset : crop.row_offset + crop.height, crop.col_offset : crop.col_offset + crop.width
    ]
    assert np.array_equal(w_crop, window)


@pytest.mark.parametrize("height_full", [512, 777])
@pytest.mark.parametrize("margin_px", [0, 1, 3])
def test_a_centred_fisheye_along_the_equirect_axis_gets_a_symmetric_crop(height_full, margin_px):
    """The crop's rows and columns are [first, last] seen pixel plus the margin on both sides: for a
    fisheye centred on the equirect's forward axis the crop is symmetric about the image centre."""
    ds = DoubleSphere(300.0, 300.0, 639.5, 479.5, -0.2, 0.6, 1280, 960)
    crop = covering_crop(ds, np.eye(3), height_full, margin_px)
    assert crop.row_offset == height_full - (crop.row_offset + crop.height)
    assert crop.col_offset == 2 * height_full - (crop.col_offset + crop.width)
    tight = covering_crop(ds, np.eye(3), height_full, 0)
    assert (crop.row_offset, crop.col_offset) == (tight.row_offset - margin_px, tight.col_offset - margin_px)


def test_backward_looking_fisheye_crop_keeps_full_width():
    ds = DoubleSphere(300.0, 300.0, 639.5, 479.5, -0.2, 0.6, 1280, 960)
    R_back = np.diag([-1.0, 1.0, -1.0])  # rotation by pi about y: looks along -z of the equirect
    crop = covering_crop(ds, R_back, 512)
    assert crop.col_offset == 0 and crop.width == 1024


def test_default_height_full_is_held_by_the_camera_pixels_and_a_budget_refuses_more():
    narrow = pinhole_for_fov(math.radians(54.0), 1920, 1200)  # f 1884 px: 6144 rows at its centre pitch
    h = default_height_full(narrow)
    assert h == 4096 and 2 * h * h <= SPHERE_PX_PER_CAMERA_PX * 1920 * 1200 < 2 * (h + 256) ** 2
    wide = pinhole_for_fov(math.radians(90.0), 1920, 1200)
    assert default_height_full(wide) == 3072  # the centre pitch (960 px/rad), under the bound
    assert check_height_full(2048, budget_bytes=2 * 2048**2 * SPHERE_BYTES_PER_PX) == 2048
    with pytest.raises(CalibrationError) as err:
        check_height_full(5888, budget_bytes=4 * 10**9)
    assert str(err.value) == (
        "--height-full 5888: a full-sphere equirect of 5888 x 11776 needs about 6.2 GB, over the budget of "
        "4.0 GB (half this machine's memory); pass --height-full 4608 or less"
    )
    assert check_height_full(4608, budget_bytes=4 * 10**9) == 4608  # the suggestion fits
    with pytest.raises(CalibrationError, match=r"^--height-full must be >= 64 rows \(.*\), got -4$"):
        check_height_full(-4)
