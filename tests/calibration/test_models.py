"""Camera models: published vectors, OpenCV equivalence, round trips and validity."""

import math
from typing import Any

import cv2
import numpy as np
import pytest

from calibration import (
    CalibrationError,
    DoubleSphere,
    ExtendedUnified,
    Fov,
    KannalaBrandt,
    Omni,
    Pinhole,
    RadTan,
    Unified,
    field_of_view,
)

TUMVI_CAM0 = DoubleSphere(
    158.28600034966977, 158.2743455478755, 254.96116578191653, 256.8894394501779,
    -0.17213086034353243, 0.5931177593944744, 512, 512,
)  # fmt: skip
EUROC_CAM0 = DoubleSphere(
    349.7560023050409, 348.72454229977037, 365.89440762590149, 249.32995565708704,
    -0.2409573942178872, 0.566996899163044, 752, 480,
)  # fmt: skip
EUROC_CAM1 = DoubleSphere(
    361.6713883800533, 360.5856493689301, 379.40818394080869, 255.9772968522045,
    -0.21300835384809328, 0.5767008625037023, 752, 480,
)  # fmt: skip
REF_DS = DoubleSphere(500.23, 500.07, 962.41, 597.86, -0.18, 0.59, 1920, 1200)


def ds_geometric(model, p):
    """DS by its geometric construction: two unit spheres xi apart, then a pinhole
    alpha/(1-alpha) behind the second sphere (Usenko et al. 2018, Fig. 2)."""
    x, y, z = (float(c) for c in p)
    n1 = math.sqrt(x * x + y * y + z * z)
    xs, ys, zs = x / n1, y / n1, z / n1 + model.xi
    n2 = math.sqrt(xs * xs + ys * ys + zs * zs)
    x2, y2, z2 = xs / n2, ys / n2, zs / n2
    shift = model.alpha / (1.0 - model.alpha)
    return (
        model.fx / (1.0 - model.alpha) * x2 / (z2 + shift) + model.cx,
        model.fy / (1.0 - model.alpha) * y2 / (z2 + shift) + model.cy,
    )


# Listed in notes/cameras.md for basalt's TUM VI cam0 (rounded to 1e-4 px there).
TUMVI_VECTORS = [
    ((0.0, 0.0, 1.0), (254.9612, 256.8894)),
    ((1.0, 0.0, 1.0), (405.4837, 256.8894)),
    ((0.3, -0.2, 1.0), (310.0420, 220.1716)),
    ((1.0, 1.0, 0.2), (447.8565, 449.7706)),
    ((0.0, 1.0, -0.5), (254.9612, 616.8588)),
]


def sphere_rays(n, max_angle_rad, seed=0):
    """Unit rays spread evenly over the cap within max_angle_rad of +z."""
    rng = np.random.default_rng(seed)
    cos_t = rng.uniform(math.cos(max_angle_rad), 1.0, n)
    phi = rng.uniform(-math.pi, math.pi, n)
    s = np.sqrt(1.0 - cos_t**2)
    return np.stack([s * np.cos(phi), s * np.sin(phi), cos_t], axis=-1)


def angle_between(a, b):
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))


@pytest.mark.parametrize(("point", "pixel"), TUMVI_VECTORS)
def test_tumvi_published_pixels(point, pixel):
    uv, valid = TUMVI_CAM0.project(np.array(point))
    assert valid
    assert np.abs(uv - np.array(pixel)).max() < 1e-4 + 0.5e-4  # vectors are rounded to 1e-4


def test_geometric_reference_reproduces_tumvi():
    for point, pixel in TUMVI_VECTORS:
        assert np.abs(np.array(ds_geometric(TUMVI_CAM0, point)) - pixel).max() < 1e-4


@pytest.mark.parametrize("model", [EUROC_CAM0, EUROC_CAM1, TUMVI_CAM0])
def test_ds_matches_geometric_construction(model):
    pts = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.3, -0.2, 1.0], [-2.0, 1.0, 0.3], [0.5, 0.5, 3.0]])
    uv, valid = model.project(pts)
    assert valid.all()
    ref = np.array([ds_geometric(model, p) for p in pts])
    assert np.abs(uv - ref).max() < 1e-9


def test_ds_validity_limits_tumvi():
    # w2 = 0.57689 -> max angle 125.2 deg; unprojection stops at r = 2.317 (366.8 px).
    assert TUMVI_CAM0.w2 == pytest.approx(0.57689, abs=1e-5)
    limit = math.acos(-TUMVI_CAM0.w2)
    assert math.degrees(limit) == pytest.approx(125.2, abs=0.05)
    inside = np.array([math.sin(limit - 1e-3), 0.0, math.cos(limit - 1e-3)])
    outside = np.array([math.sin(limit + 1e-3), 0.0, math.cos(limit + 1e-3)])
    uv, valid = TUMVI_CAM0.project(np.stack([inside, outside]))
    assert valid.tolist() == [True, False]
    assert np.isfinite(uv[0]).all() and np.isnan(uv[1]).all()
    # The alpha circle r^2 <= 1/(2 alpha - 1) bounds the formula; with xi < 0 the limit ray
    # lands inside it (r = 2.31681 < 2.31723) and the ring between unprojects past the limit.
    r_circle = 1.0 / math.sqrt(2 * TUMVI_CAM0.alpha - 1)
    assert r_circle == pytest.approx(2.31723, abs=1e-5)
    at_limit = np.array([math.sin(limit - 1e-12), 0.0, math.cos(limit - 1e-12)])
    r_fold = (TUMVI_CAM0.project(at_limit)[0][0] - TUMVI_CAM0.cx) / TUMVI_CAM0.fx
    assert r_fold == pytest.approx(2.31681, abs=1e-5)
    r = np.array([r_fold - 1e-6, r_fold + 1e-6, 0.5 * (r_fold + r_circle), r_circle - 1e-9, r_circle + 1e-6])
    px = np.stack([TUMVI_CAM0.cx + r * TUMVI_CAM0.fx, np.full(r.size, TUMVI_CAM0.cy)], axis=-1)
    rays, valid = TUMVI_CAM0.unproject(px)
    assert valid.tolist() == [True, False, False, False, False]
    assert np.isnan(rays[1:]).all()
    back, ok = TUMVI_CAM0.project(rays[0])
    assert ok and np.abs(back - px[0]).max() < 1e-9


def test_ds_beyond_90_degrees_round_trip():
    rays = sphere_rays(20000, math.radians(100.0))
    assert (rays[:, 2] < 0).sum() > 1000  # really behind the image plane
    uv, valid = REF_DS.project(rays)
    assert valid.all()
    back, valid2 = REF_DS.unproject(uv)
    assert valid2.all()
    assert angle_between(back, rays).max() < 1e-9


CLOSED_FORM: dict[str, tuple[Any, float]] = {
    "ds": (REF_DS, 100.0),
    "ds_alpha_low": (DoubleSphere(300.0, 300.0, 320.0, 240.0, 0.3, 0.4, 640, 480), 95.0),
    "eucm": (ExtendedUnified(380.0, 380.0, 640.0, 512.0, 0.63, 1.04, 1280, 1024), 100.0),
    "eucm_alpha_low": (ExtendedUnified(300.0, 302.0, 320.0, 240.0, 0.45, 1.2, 640, 480), 100.0),
    "ucm": (Unified(400.0, 401.0, 640.0, 512.0, 0.6, 1280, 1024), 100.0),
    "pinhole": (Pinhole(500.0, 505.0, 320.0, 240.0, 640, 480), 70.0),
    "pinhole_fov": (Pinhole(500.0, 505.0, 320.0, 240.0, 640, 480, Fov(0.9)), 70.0),
    "omni": (Omni(0.9, 700.0, 700.0, 640.0, 512.0, 1280, 1024), 100.0),
    "omni_xi_gt_1": (Omni(1.3, 900.0, 900.0, 640.0, 512.0, 1280, 1024), 95.0),
}
ITERATIVE: dict[str, tuple[Any, float]] = {
    "kb": (KannalaBrandt(380.0, 380.5, 640.0, 512.0, 0.02, -0.01, 0.003, -0.0005, 1280, 1024), 110.0),
    "pinhole_radtan": (
        Pinhole(500.0, 505.0, 320.0, 240.0, 640, 480, RadTan(-0.28, 0.07, 1e-4, -2e-4)),
        55.0,
    ),
    "omni_radtan": (
        Omni(0.9, 700.0, 700.0, 640.0, 512.0, 1280, 1024, RadTan(-0.05, 0.01, 3e-4, -1e-4)),
        90.0,
    ),
}


@pytest.mark.parametrize("name", sorted(CLOSED_FORM) + sorted(ITERATIVE))
def test_round_trip(name):
    # Closed forms are exact to rounding; the iterative inverses stop at a residual of
    # 1e-12 normalised units / 1e-13 rad (documented), which also keeps them under 1e-9 rad.
    model, max_deg = {**CLOSED_FORM, **ITERATIVE}[name]
    rays = sphere_rays(50000, math.radians(max_deg), seed=1)
    uv, valid = model.project(rays)
    assert valid.all()
    back, valid2 = model.unproject(uv)
    assert valid2.all()
    assert angle_between(back, rays).max() < 1e-9
    # and pixel -> ray -> pixel on the dense image grid, where the model is valid
    grid = model.pixel_grid()[::7, ::7].reshape(-1, 2)
    rays2, ok = model.unproject(grid)
    uv2, ok2 = model.project(rays2[ok])
    assert ok2.all()
    assert np.abs(uv2 - grid[ok]).max() < 1e-6


def test_ds_xi_zero_equals_ucm():
    ds = DoubleSphere(400.0, 401.0, 640.0, 512.0, 0.0, 0.6, 1280, 1024)
    ucm = Unified(400.0, 401.0, 640.0, 512.0, 0.6, 1280, 1024)
    rays = sphere_rays(10000, math.radians(110.0), seed=3)
    uv_ds, v_ds = ds.project(rays)
    uv_ucm, v_ucm = ucm.project(rays)
    assert np.array_equal(v_ds, v_ucm)
    assert np.abs(uv_ds[v_ds] - uv_ucm[v_ucm]).max() < 1e-9
    grid = ds.pixel_grid()[::11, ::11].reshape(-1, 2)
    r1, ok1 = ds.unproject(grid)
    r2, ok2 = ucm.unproject(grid)
    assert np.array_equal(ok1, ok2)
    assert np.abs(r1[ok1] - r2[ok2]).max() < 1e-9


def test_eucm_beta_one_equals_ucm():
    e = ExtendedUnified(400.0, 401.0, 640.0, 512.0, 0.6, 1.0, 1280, 1024)
    u = Unified(400.0, 401.0, 640.0, 512.0, 0.6, 1280, 1024)
    rays = sphere_rays(5000, math.radians(100.0), seed=4)
    assert np.abs(e.project(rays)[0] - u.project(rays)[0]).max() < 1e-12


def test_eucm_unprojection_circle_scales_with_beta():
    """EUCM unprojects where r^2 <= 1/(beta (2 alpha - 1)) (Khomutenko et al. 2016): alpha = 0.7 and
    beta = 0.5 give r^2 <= 5, twice the UCM circle 1/(2 alpha - 1) = 2.5. Pixels between the two
    circles are valid and round trip; just past r^2 = 5 none is."""
    e = ExtendedUnified(100.0, 100.0, 640.0, 512.0, 0.7, 0.5, 1280, 1024)
    r = np.array([math.sqrt(3.75), math.sqrt(5.0) - 1e-6, math.sqrt(5.0) + 1e-6])
    px = np.stack([e.cx + r * e.fx, np.full(r.size, e.cy)], axis=-1)
    rays, valid = e.unproject(px)
    assert valid.tolist() == [True, True, False]
    back, ok = e.project(rays[:2])
    assert ok.all() and np.abs(back - px[:2]).max() < 1e-6


def _omnidir(points, xi, fx, fy, cx, cy, dist=(0.0, 0.0, 0.0, 0.0)):
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    out, _ = cv2.omnidir.projectPoints(
        points.reshape(1, -1, 3), np.zeros(3), np.zeros(3), K, float(xi), np.array([dist], dtype=np.float64)
    )
    return out.reshape(-1, 2)


def test_ucm_equals_opencv_omnidir_mei():
    # Mapping: xi = alpha / (1 - alpha), gamma = f / (1 - alpha).
    alpha, f = 0.6, 400.0
    ucm = Unified(f, f * 1.002, 640.0, 512.0, alpha, 1280, 1024)
    rays = sphere_rays(2000, math.radians(95.0), seed=5)
    uv, valid = ucm.project(rays)
    assert valid.all()
    ref = _omnidir(rays, alpha / (1 - alpha), f / (1 - alpha), f * 1.002 / (1 - alpha), 640.0, 512.0)
    assert np.abs(uv - ref).max() < 1e-8


def test_omni_radtan_equals_opencv_omnidir():
    model, _ = ITERATIVE["omni_radtan"]
    rays = sphere_rays(2000, math.radians(90.0), seed=6)
    uv, valid = model.project(rays)
    assert valid.all()
    d = model.distortion
    ref = _omnidir(rays, model.xi, model.fx, model.fy, model.cx, model.cy, (d.k1, d.k2, d.p1, d.p2))
    assert np.abs(uv - ref).max() < 1e-8


def test_kannala_brandt_equals_cv2_fisheye():
    kb, _ = ITERATIVE["kb"]
    rays = sphere_rays(2000, math.radians(85.0), seed=7)  # cv2.fisheye needs z > 0
    uv, valid = kb.project(rays)
    assert valid.all()
    K = np.array([[kb.fx, 0.0, kb.cx], [0.0, kb.fy, kb.cy], [0.0, 0.0, 1.0]])
    D = np.array([kb.k1, kb.k2, kb.k3, kb.k4])
    ref, _ = cv2.fisheye.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, D)
    assert np.abs(uv - ref.reshape(-1, 2)).max() < 1e-8


def test_kannala_brandt_fov_ends_where_theta_d_stops_increasing():
    """theta_max is the first root of d theta_d / d theta = 1 + 3 k1 t^2 + 5 k2 t^4 + 7 k3 t^6 + 9 k4 t^8:
    with k4 alone, t = (-1 / (9 k4))^(1/8) (1.35120 rad for k4 = -0.01); with k1 alone,
    t = sqrt(-1 / (3 k1)). Rays just inside project, rays just beyond do not."""
    only_k4 = KannalaBrandt(400.0, 400.0, 640.0, 512.0, 0.0, 0.0, 0.0, -0.01, 1280, 1024)
    assert only_k4.theta_max == pytest.approx((1.0 / 0.09) ** (1.0 / 8.0), rel=1e-9)
    assert only_k4.theta_max == pytest.approx(1.35120, abs=1e-5)
    only_k1 = KannalaBrandt(400.0, 400.0, 640.0, 512.0, -0.2, 0.0, 0.0, 0.0, 1280, 1024)
    assert only_k1.theta_max == pytest.approx(math.sqrt(1.0 / 0.6), rel=1e-9)
    t = only_k4.theta_max + np.array([-1e-3, 1e-3])
    _, valid = only_k4.project(np.c_[np.sin(t), np.zeros(2), np.cos(t)])
    assert valid.tolist() == [True, False]


def test_pinhole_radtan_equals_cv2_project_points():
    model, _ = ITERATIVE["pinhole_radtan"]
    rng = np.random.default_rng(8)
    pts = np.column_stack(
        [rng.uniform(-1, 1, 2000), rng.uniform(-0.8, 0.8, 2000), rng.uniform(1.0, 4.0, 2000)]
    )
    uv, valid = model.project(pts)
    assert valid.all()
    d = model.distortion
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), model.K, np.array([d.k1, d.k2, d.p1, d.p2]))
    assert np.abs(uv - ref.reshape(-1, 2)).max() < 1e-8


@pytest.mark.parametrize(
    "model",
    [m for m, _ in CLOSED_FORM.values()] + [m for m, _ in ITERATIVE.values()],
    ids=sorted(CLOSED_FORM) + sorted(ITERATIVE),
)
def test_invalid_points_are_nan_never_valid(model):
    pts = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [np.nan, 0.0, 1.0], [0.0, np.inf, 1.0]])
    uv, valid = model.project(pts)
    assert not valid.any()
    assert np.isnan(uv).all()
    rays, ok = model.unproject(np.array([[np.nan, 1.0], [1.0, np.inf]]))
    assert not ok.any()
    assert np.isnan(rays).all()


def test_pinhole_rejects_points_behind():
    cam = Pinhole(500.0, 500.0, 320.0, 240.0, 640, 480)
    uv, valid = cam.project(np.array([[0.1, 0.1, -1.0], [0.1, 0.1, 1.0]]))
    assert valid.tolist() == [False, True]
    assert uv[1].tolist() == pytest.approx([370.0, 290.0])


def test_shapes_are_preserved():
    pts = sphere_rays(24, 1.0).reshape(2, 3, 4, 3)
    uv, valid = REF_DS.project(pts)
    assert uv.shape == (2, 3, 4, 2) and valid.shape == (2, 3, 4)
    rays, ok = REF_DS.unproject(uv)
    assert rays.shape == (2, 3, 4, 3) and ok.shape == (2, 3, 4)
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        REF_DS.project(np.zeros((5, 2)))


def test_image_bounds_are_separate_from_validity():
    # TUM VI: (0, 1, -0.5) is model-valid (basalt) but lands at v = 616.9 > 512 (off image).
    uv, valid = TUMVI_CAM0.project(np.array([[0.0, 1.0, -0.5], [0.0, 0.0, 1.0]]))
    assert valid.all()
    assert TUMVI_CAM0.in_image(uv).tolist() == [False, True]
    edges = np.array([[-0.5, 0.0], [-0.51, 0.0], [511.49, 511.49], [511.5, 0.0]])
    assert TUMVI_CAM0.in_image(edges).tolist() == [True, False, True, False]


@pytest.mark.parametrize("factor", [0.5, 0.25, 2.0])
def test_scaled_follows_pixel_centre_convention(factor):
    small = REF_DS.scaled(factor)
    assert (small.width, small.height) == (round(1920 * factor), round(1200 * factor))
    rays = sphere_rays(1000, 1.5)
    uv, _ = REF_DS.project(rays)
    uv_s, _ = small.project(rays)
    assert np.abs(uv_s - ((uv + 0.5) * factor - 0.5)).max() < 1e-9
    assert small.xi == REF_DS.xi and small.alpha == REF_DS.alpha


def test_field_of_view_of_reference_lens():
    fov = field_of_view(REF_DS)
    assert math.degrees(fov.horizontal_rad) == pytest.approx(181.7, abs=0.3)
    # vertical: edge rows at r = 600/500 (inside the circle) -> exact angle by unprojection
    rays, _ = REF_DS.unproject(np.array([[REF_DS.cx, -0.5], [REF_DS.cx, 1199.5]]))
    expect = sum(math.atan2(abs(r[1]), r[2]) for r in rays)
    assert fov.vertical_rad == pytest.approx(expect, abs=2e-3)
    # diagonal: the corners (r = 2.26) lie inside the DS circle (r <= 2.357)
    corners = np.array([[-0.5, -0.5], [1919.5, 1199.5], [1919.5, -0.5], [-0.5, 1199.5]])
    rays, ok = REF_DS.unproject(corners)
    assert ok.all()
    off_axis = np.arctan2(np.hypot(rays[:, 0], rays[:, 1]), rays[:, 2])
    assert fov.diagonal_rad == pytest.approx(max(off_axis[:2].sum(), off_axis[2:].sum()), abs=2e-3)
    # a lens whose image is smaller than the sensor stops where projection stops: with xi < 0
    # that is the ray z = -w2 |p|, which lands inside the alpha circle r^2 = 1/(2 alpha - 1)
    small_circle = DoubleSphere(250.0, 250.0, 959.5, 599.5, -0.18, 0.59, 1920, 1200)
    edge = small_circle.max_off_axis_rad - 1e-9
    (u_edge, _), _ = small_circle.project(np.array([math.sin(edge), 0.0, math.cos(edge)]))
    assert (u_edge - 959.5) / 250.0 < 1 / math.sqrt(0.18)
    fov = field_of_view(small_circle)
    assert fov.horizontal_rad == pytest.approx(fov.limit_rad, abs=1e-6)
    assert fov.limit_rad == pytest.approx(2 * math.acos(-small_circle.w2), abs=1e-12)


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: DoubleSphere(-1.0, 500.0, 1.0, 1.0, -0.2, 0.6, 10, 10), "fx must be a finite number > 0"),
        (lambda: DoubleSphere(500.0, 500.0, 1.0, 1.0, -0.2, 1.0, 10, 10), r"alpha must be in \[0, 1\)"),
        (lambda: DoubleSphere(500.0, 500.0, 1.0, 1.0, -0.2, 0.6, 0, 10), "width must be a positive integer"),
        (lambda: DoubleSphere(500.0, 500.0, np.nan, 1.0, -0.2, 0.6, 10, 10), "cx must be a finite number"),
        (lambda: ExtendedUnified(5.0, 5.0, 1.0, 1.0, 0.5, -1.0, 10, 10), "beta must be a finite number > 0"),
        (lambda: Omni(-0.1, 5.0, 5.0, 1.0, 1.0, 10, 10), "xi must be >= 0"),
        (lambda: Fov(0.0), r"w must be in \(0, pi\)"),
    ],
)
def test_bad_parameters_raise(make, message):
    with pytest.raises(CalibrationError, match=message):
        make()


@pytest.mark.parametrize(
    "k",
    [
        (0.271, 0.0282, -0.223, -0.1843),
        (0.5405, 0.3945, 0.1072, -0.2417),
        (-0.1309, -0.3509, 0.5218, -0.0992),
    ],
)
def test_kannala_brandt_unprojects_every_ray_it_projects_up_to_its_limit(k):
    """Plain Newton overshot where theta_d's slope nears 0 towards theta_max: rays `project` accepted
    (from 46-73 deg for these coefficients; 48-63 deg of a PADRL camchain's 63.4 deg) came back invalid,
    and `calib check` reported a smaller FOV than the lens has."""
    m = KannalaBrandt(150.0, 150.0, 1000.0, 1000.0, k[0], k[1], k[2], k[3], 2000, 2000)
    theta = np.linspace(0.01, m.theta_max * 0.999, 500)
    rays = np.stack([np.sin(theta) * np.cos(1.0), np.sin(theta) * np.sin(1.0), np.cos(theta)], axis=1)
    uv, ok = m.project(rays)
    assert ok.all()
    back, ok2 = m.unproject(uv)
    assert ok2.all()
    np.testing.assert_allclose(back, rays, atol=1e-9)
