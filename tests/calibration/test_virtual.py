"""Virtual benchmark cameras: FOV laws, true FOV, level poses, stereo partners, crops, float32 projection."""

import math
from pathlib import Path

import numpy as np
import pytest

from calibration import CalibrationError, DoubleSphere, field_of_view, read_rig
from calibration.pinhole import Pinhole
from calibration.spherical import Cassini, Equirectangular, pinhole_for_fov
from calibration.virtual import (
    CroppedModel,
    R_up_cam,
    crop_bounds,
    partner_pose,
    project_f32,
    virtual_ds,
    virtual_fisheye,
)

RIG = Path(__file__).resolve().parents[2] / "calibration" / "sensorbox.yaml"


@pytest.fixture(scope="module")
def ref():
    return read_rig(RIG).camera("cam0").model


def test_laws_at_180_on_the_reference_image(ref):
    # DESIGN.md: f * n * 180/FOV, xi (1 - m FOV/180), alpha + m (1 - alpha) FOV/180, m = 0.2, n = 1.25;
    # by hand from the reference camchain (f 500.2314/500.0693, xi -0.18153, alpha 0.59021)
    m = virtual_ds(ref, 180.0, 1920, 1200)
    assert m.fx == pytest.approx(625.28925, abs=1e-9)
    assert m.fy == pytest.approx(625.086625, abs=1e-9)
    assert m.xi == pytest.approx(-0.145224, abs=1e-12)
    assert m.alpha == pytest.approx(0.672168, abs=1e-12)
    assert (m.cx, m.cy) == (959.5, 599.5)


def test_laws_at_120_and_width_scaling(ref):
    a = virtual_ds(ref, 120.0, 1920, 1200)
    b = virtual_ds(ref, 120.0, 3840, 2160)
    assert a.fx == pytest.approx(500.2314 * 1.25 * 1.5)
    assert a.xi == pytest.approx(-0.18153 * (1 - 0.2 * 120 / 180))
    assert a.alpha == pytest.approx(0.59021 + 0.2 * 0.40979 * 120 / 180)
    assert b.fx == pytest.approx(2.0 * a.fx) and b.fy == pytest.approx(2.0 * a.fy)
    assert (b.xi, b.alpha) == (a.xi, a.alpha)
    assert (b.cx, b.cy, b.width, b.height) == (1919.5, 1079.5, 3840, 2160)


def test_true_fov_grows_with_the_nominal_one_and_is_measured_at_the_border(ref):
    cams = [virtual_fisheye(ref, f, 2048, 1152) for f in (120, 140, 165, 195)]
    h = [c.fov.horizontal_rad for c in cams]
    assert h == sorted(h) and len(set(h)) == 4
    assert math.degrees(h[-1]) > 180.0  # the 195 lens sees behind its image plane
    # the border-limited 120 lens: a ray at half the true HFOV lands on the image's left/right edge
    c = cams[0]
    half = c.fov.horizontal_rad / 2
    uv, ok = c.model.project(
        np.array([[math.sin(half), 0, math.cos(half)], [-math.sin(half), 0, math.cos(half)]])
    )
    assert ok.all()
    assert uv[0, 0] == pytest.approx(2047.5, abs=0.05) and uv[1, 0] == pytest.approx(-0.5, abs=0.05)
    rep = c.report()
    assert rep["nominal_fov_deg"] == 120.0 and rep["model"] == "ds"
    assert rep["true_fov_deg"]["horizontal"] == pytest.approx(math.degrees(half * 2), abs=1e-3)
    assert rep["fx"] == c.model.fx and rep["width"] == 2048


@pytest.mark.parametrize("fov", [0.0, -10.0, 360.0, float("nan")])
def test_bad_fov_is_refused(ref, fov):
    with pytest.raises(CalibrationError, match="FOV"):
        virtual_ds(ref, fov, 640, 480)


def test_level_camera_axes():
    R = R_up_cam(0.0)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-15)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R[:, 2], [1, 0, 0], atol=1e-15)  # forward = +x
    np.testing.assert_allclose(R[:, 0], [0, -1, 0], atol=1e-15)  # right = -y (y is left)
    np.testing.assert_allclose(R[:, 1], [0, 0, -1], atol=1e-15)  # down = -z
    R90 = R_up_cam(math.pi / 2)
    np.testing.assert_allclose(R90[:, 2], [0, 1, 0], atol=1e-15)  # yaw turns towards +y
    Rp = R_up_cam(0.0, math.radians(30))
    np.testing.assert_allclose(Rp[:, 2], [math.cos(math.radians(30)), 0, 0.5], atol=1e-15)  # pitch up
    assert Rp[2, 1] < 0  # image "down" still points below the horizon


def test_partners_sit_down_and_right_of_the_reference():
    T = np.eye(4)
    T[:3, :3] = R_up_cam(math.radians(40))
    T[:3, 3] = [1.0, 2.0, 1.5]
    down = partner_pose(T, "DOWN", 0.12)
    right = partner_pose(T, "RIGHT", 0.3)
    np.testing.assert_allclose(down[:3, 3], [1.0, 2.0, 1.38], atol=1e-12)
    np.testing.assert_allclose(right[:3, 3] - T[:3, 3], 0.3 * T[:3, 0], atol=1e-12)
    np.testing.assert_allclose(down[:3, :3], T[:3, :3])
    with pytest.raises(CalibrationError, match="partner"):
        partner_pose(T, "LEFT", 0.1)


def test_cropped_model_is_a_window_of_its_base():
    base = Cassini(256)
    crop = CroppedModel(base, 40, 100, 120, 200)
    rays = np.random.default_rng(1).normal(size=(500, 3))
    uv_b, ok_b = base.project(rays)
    uv_c, ok_c = crop.project(rays)
    np.testing.assert_array_equal(ok_b, ok_c)
    np.testing.assert_allclose(uv_c, uv_b - [40, 100])
    back, ok = crop.unproject(crop.pixel_grid().reshape(-1, 2))
    ref_rays, _ = base.unproject(crop.pixel_grid().reshape(-1, 2) + np.array([40, 100]))
    assert ok.all()
    np.testing.assert_allclose(back, ref_rays)
    with pytest.raises(CalibrationError, match="does not fit"):
        CroppedModel(base, 200, 0, 100, 10)


def test_crop_bounds_with_margin():
    mask = np.zeros((50, 80), bool)
    mask[10:20, 30:41] = True
    assert crop_bounds(mask, 2) == (28, 8, 15, 14)
    assert crop_bounds(mask, 0) == (30, 10, 11, 10)
    with pytest.raises(CalibrationError, match="empty"):
        crop_bounds(np.zeros((3, 3), bool))


@pytest.mark.parametrize(
    "model",
    [
        DoubleSphere(615.7, 615.6, 1023.5, 575.5, -0.1422, 0.679, 2048, 1152),
        Equirectangular(1024).crop(100, 300, 600, 900),
        Cassini(1024),
        pinhole_for_fov(math.radians(90), 2048, 1152),
        CroppedModel(Pinhole(500, 500, 320, 240, 640, 480), 10, 20, 300, 200),
    ],
    ids=["ds", "equirect_crop", "cassini", "pinhole", "pinhole_crop"],
)
def test_float32_projection_matches_float64(model):
    v = np.random.default_rng(2).normal(size=(20000, 3)) * [1, 1, 0.5] + [0, 0, 0.8]
    v *= np.random.default_rng(3).uniform(0.5, 40.0, (len(v), 1))
    uv, ok = model.project(v)
    p = v.astype(np.float32)
    u, w, ok32 = project_f32(model, p[:, 0], p[:, 1], p[:, 2])
    assert u.dtype == np.float32 and w.dtype == np.float32
    inside = ok & model.in_image(uv)
    assert (inside & ~ok32).mean() < 1e-3  # only rays on the validity edge may differ
    agree = inside & ok32
    err = np.hypot(u[agree] - uv[agree, 0], w[agree] - uv[agree, 1])
    # float32 keeps a thousandth of a pixel on a 2048 px image (Cassini's arcsin: 0.05 px near its poles)
    assert np.percentile(err, 99.9) < 2e-3 and err.max() < 0.05


def test_true_fov_of_virtual_equals_field_of_view(ref):
    c = virtual_fisheye(ref, 165, 1024, 576)
    f = field_of_view(c.model)
    assert (c.fov.horizontal_rad, c.fov.vertical_rad, c.fov.diagonal_rad) == (
        f.horizontal_rad,
        f.vertical_rad,
        f.diagonal_rad,
    )
