"""Equirect, Cassini and cubemap models: round trips, crops and seam continuity."""

import math

import numpy as np
import pytest

from calibration import CalibrationError
from calibration.spherical import Cassini, Cubemap, Equirectangular, pinhole_for_fov


def all_sphere_rays(n, seed=0):
    v = np.random.default_rng(seed).normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def angle(a, b):
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))


@pytest.mark.parametrize(
    "model",
    [Equirectangular(512), Equirectangular(512, pole_axis="x"), Cassini(512), Cubemap(256)],
    ids=["equirect", "equirect_pole_x", "cassini", "cubemap"],
)
def test_full_sphere_round_trip(model):
    rays = all_sphere_rays(100000)
    uv, ok = model.project(rays)
    assert ok.all() and model.in_image(uv).all()
    back, ok2 = model.unproject(uv)
    assert ok2.all()
    assert angle(back, rays).max() < 1e-9
    grid = model.pixel_grid().reshape(-1, 2)
    r, ok3 = model.unproject(grid)
    uv2, ok4 = model.project(r)
    assert ok3.all() and ok4.all()
    assert np.abs(uv2 - grid).max() < 1e-9


def test_equirect_convention_of_design():
    eq = Equirectangular(4)  # pitch 45 deg
    assert (eq.width, eq.height) == (8, 4)
    rays, _ = eq.unproject(np.array([[4.0, 0.0], [3.5, 1.5]]))
    th, ph = 0.5 * math.pi / 4, 4.5 * math.pi / 4 - math.pi
    assert rays[0] == pytest.approx([math.sin(th) * math.sin(ph), -math.cos(th), math.sin(th) * math.cos(ph)])
    assert rays[1] == pytest.approx([0.0, 0.0, 1.0], abs=1e-15)  # forward is between the middle pixels
    uv, _ = eq.project(np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]))
    assert uv[0, 1] == -0.5 and uv[1].tolist() == [5.5, 1.5] and uv[2, 0] in (-0.5, 7.5)


def test_crop_keeps_full_sphere_pitch():
    full = Equirectangular(2048)
    crop = full.crop(449, 994, 1216, 2112)  # WideDepth's historical crop [449:1665, 994:3106]
    rays = all_sphere_rays(1000)
    uv_f, _ = full.project(rays)
    uv_c, _ = crop.project(rays)
    assert np.abs(uv_c - (uv_f - [994, 449])).max() < 1e-9
    assert crop.theta_of_row(np.array([0.0]))[0] == pytest.approx(449.5 * math.pi / 2048)
    with pytest.raises(CalibrationError, match="do not fit in the full sphere"):
        full.crop(1000, 0, 1100, 10)


def test_cubemap_seams_are_continuous():
    """Each face's border coincides with its neighbour's border at the same row (or column)
    index, and the pixels either side sit half a pixel from it: no gap, no shift at seams."""
    F = 64
    cube = Cubemap(F)
    R = {name: Rf for name, _, Rf in cube.faces()}
    idx = {name: k for k, (name, _, _) in enumerate(cube.faces())}
    t = np.arange(F, dtype=float)

    def ray(face, u, v):
        r, ok = cube.unproject(np.stack([idx[face] * F + np.broadcast_to(u, t.shape),
                                         np.broadcast_to(v, t.shape)], axis=-1))  # fmt: skip
        assert ok.all()
        return r

    def edge(face, u, v):  # the face's own pinhole at the border coordinate, rotated to the cube
        r, _ = cube.face_model.unproject(
            np.stack([np.broadcast_to(u, t.shape), np.broadcast_to(v, t.shape)], -1)
        )
        return r @ R[face].T

    seams = [  # (face a, border pixels, border coords), (face b, border pixels, border coords)
        *[((a, (F - 1.0, t), (F - 0.5, t)), (b, (0.0, t), (-0.5, t))) for a, b in
          [("front", "right"), ("right", "back"), ("back", "left"), ("left", "front")]],
        (("up", (t, F - 1.0), (t, F - 0.5)), ("front", (t, 0.0), (t, -0.5))),
        (("down", (t, 0.0), (t, -0.5)), ("front", (t, F - 1.0), (t, F - 0.5))),
    ]  # fmt: skip
    for (a, pa, ea), (b, pb, eb) in seams:
        e = edge(a, *ea)
        assert angle(e, edge(b, *eb)).max() < 1e-12, (a, b)  # one shared border, same index
        ra, rb = ray(a, *pa), ray(b, *pb)
        half_a, half_b = angle(ra, e), angle(rb, e)
        assert np.allclose(half_a, half_b, rtol=1e-9, atol=0), (a, b)
        assert half_a.max() < 0.5 * (math.pi / 2) / F  # within half a (centre) pixel of the seam


def test_cubemap_faces_are_90_degree_pinholes():
    cube = Cubemap(100)
    names = [n for n, _, _ in cube.faces()]
    assert names == ["front", "right", "back", "left", "up", "down"]
    ref = pinhole_for_fov(math.pi / 2, 100, 100)
    assert cube.face_model.fx == pytest.approx(ref.fx, rel=1e-15) and cube.face_model.cx == ref.cx
    img = np.arange(600 * 100).reshape(100, 600)
    assert cube.split(img)["back"][0, 0] == 200


def test_cubemap_strip_ends_at_its_last_pixel_edge():
    """A 6F x F strip covers u in [-0.5, 6F - 0.5): the last column (6F - 1, the "down" face) unprojects,
    the edge 6F - 0.5 and anything right of it (a seventh face) does not."""
    F = 4
    cube = Cubemap(F)
    u = np.array([-0.5, 6 * F - 1.0, 6 * F - 0.5, 6 * F + 1.0, 7 * F - 1.0])
    rays, valid = cube.unproject(np.stack([u, np.full(u.size, (F - 1) / 2.0)], axis=-1))
    assert valid.tolist() == [True, True, False, False, False]
    # the centre row of the down face's last column looks along +y (down), tilted towards +x
    assert rays[1, 1] > 0 and rays[1, 1] > abs(rays[1, 0]) and abs(rays[1, 2]) < 1e-12


def test_cassini_rows_are_horizontal_epipolar_lines():
    cas = Cassini(512)
    p = all_sphere_rays(1000) * np.random.default_rng(1).uniform(1, 10, (1000, 1))
    uv_l, _ = cas.project(p)
    uv_r, _ = cas.project(p - [0.2, 0.0, 0.0])  # right camera 0.2 m along +x
    assert np.abs(uv_l[:, 1] - uv_r[:, 1]).max() < 1e-9


@pytest.mark.parametrize("factor", [0.5, 0.3, 2.0])
def test_scaled_spherical_models_keep_their_shape(factor):
    # odd sizes: width/height must follow height_full / face_size, not be rounded on their own
    cas = Cassini(5).scaled(factor)
    assert (cas.width, cas.height) == (cas.height_full, 2 * cas.height_full)
    eq = Equirectangular(5).scaled(factor)
    assert eq.is_full and (eq.width, eq.height) == (2 * eq.height_full, eq.height_full)
    cube = Cubemap(5).scaled(factor)
    assert (cube.width, cube.height) == (6 * cube.face_size, cube.face_size)
    crop = Equirectangular(2048).crop(449, 994, 1216, 2112).scaled(factor)
    assert crop.row_offset + crop.height <= crop.height_full
    assert crop.col_offset + crop.width <= 2 * crop.height_full
    assert crop.pitch_rad == pytest.approx(math.pi / round(2048 * factor))
