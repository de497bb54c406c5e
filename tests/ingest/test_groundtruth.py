"""The GT z-buffer keeps exactly the nearest (or, as an ablation, the farthest) point of each pixel;
the equirect disparity and its stability mask."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from calibration.rig import REFERENCE_RIG, read_rig
from calibration.spherical import Equirectangular
from ingest.train.gt.groundtruth import GtParams, equirect_disparity, in_view, px_per_rad, splat_to_pixels
from ingest.train.trajectory.planes import Normals

MODEL = read_rig(REFERENCE_RIG).upper.model.scaled(0.125)  # 240 x 150: many points per pixel


@pytest.mark.parametrize("zbuffer", ["nearest", "farthest"])
def test_splat_keeps_the_nearest_point_per_pixel_like_a_lexsort(zbuffer):
    rng = np.random.default_rng(6)
    rays, ok = MODEL.unproject(rng.uniform(0, [MODEL.width, MODEL.height], (100_000, 2)))
    pts = rays[ok] * rng.uniform(0.5, 30.0, ok.sum())[:, None]
    pts[:50] = pts[50:100]  # exact ties: the earlier point wins, as a stable sort keeps it
    no_planes = Normals(np.zeros_like(pts), np.zeros(len(pts), bool))  # ranges stay the points' own
    params = replace(GtParams(), zbuffer=zbuffer)
    splat = splat_to_pixels(MODEL, pts, no_planes, params)

    seen, cols, rows = in_view(MODEL, pts)
    idx = np.nonzero(seen)[0]
    flat = rows[idx].astype(np.int64) * MODEL.width + cols[idx].astype(np.int64)
    r = np.linalg.norm(pts[idx], axis=1)
    order = np.lexsort((r if zbuffer == "nearest" else -r, flat))
    first = np.r_[True, flat[order][1:] != flat[order][:-1]]
    assert len(splat.pixel) < len(idx) / 2  # ~3 candidates per pixel
    np.testing.assert_array_equal(splat.pixel, flat[order][first])
    np.testing.assert_array_equal(splat.point, idx[order][first])
    np.testing.assert_allclose(splat.range_m, r[order][first], rtol=1e-12)


@pytest.mark.parametrize("cos_incidence", [0.3, 0.5, 0.8])
def test_a_corner_point_more_than_a_centre_pixel_off_its_ray_gets_the_plane_correction(cos_incidence):
    """At the reference fisheye's corner a pixel spans more angle than at the principal ray: a point
    at pixel (0.49, 0.49) is 1.25 centre-pixels off pixel (0, 0)'s ray. On a plane through it (normal
    in the plane of the two rays, at the given incidence) its range along the pixel's ray is the exact
    ray-plane intersection, which moves the range by more than one centre-pixel's gradient."""
    model = read_rig(REFERENCE_RIG).upper.model
    rays, ok = model.unproject(np.array([[0.0, 0.0], [0.49, 0.49]]))
    assert ok.all()
    ray, towards = rays
    p = 5.0 * towards
    across = towards - ray * (ray @ towards)
    across /= np.linalg.norm(across)
    n = cos_incidence * ray + np.sqrt(1.0 - cos_incidence**2) * across
    exact_m = (n @ p) / (n @ ray)
    splat = splat_to_pixels(model, p[None], Normals(n[None], np.array([True])), GtParams())
    assert splat.pixel.tolist() == [0]
    assert splat.range_m[0] == pytest.approx(exact_m, abs=1e-9)
    centre_pixel_m = 5.0 * np.tan(np.arccos(cos_incidence)) / px_per_rad(model)
    assert abs(exact_m - 5.0) > 1.2 * centre_pixel_m  # more than a centre pixel of gradient


def test_equirect_disparity_counts_the_unstable_pixels_it_leaves_without_disparity():
    """`equirect_disparity`: every splatted pixel keeps its range; the stable ones get DESIGN.md's disparity.

    Five points on pixel-centre rays of the full 512-row sphere, baseline 0.3 m. Three are
    stable (a 0.5 px disparity error changes their range by at most 50 %); one at 40 m near the
    equator (1.2 px) and one at 1 m in row 2, by the pole (0.6 px), are not: the range at
    disparity - 0.5 px is more than 1.5 times theirs. `unstable` counts those two.
    """
    eq = Equirectangular(512)
    baseline_m = 0.3
    rows = np.array([2.0, 200.0, 255.0, 255.0, 300.0])  # in pixel order
    cols = np.array([900.0, 512.0, 100.0, 700.0, 300.0])
    range_m = np.array([1.0, 3.0, 1.0, 40.0, 2.0])
    rays, ok = eq.unproject(np.c_[cols, rows])
    assert ok.all()
    pts = rays * range_m[:, None]
    no_planes = Normals(np.zeros_like(pts), np.zeros(len(pts), bool))
    disp_img, range_img, unstable = equirect_disparity(eq, np.eye(3), pts, no_planes, baseline_m, GtParams())

    flat = rows.astype(np.int64) * eq.width + cols.astype(np.int64)
    np.testing.assert_array_equal(range_img.pixel, flat)
    np.testing.assert_allclose(range_img.value, range_m, rtol=1e-7)
    theta = (rows + 0.5) * np.pi / 512  # latitude from up of the pixel-centre rows
    rho = np.arctan2(np.sin(theta), range_m / baseline_m + np.cos(theta))  # disparity angle
    with np.errstate(divide="ignore", invalid="ignore"):
        r_far = baseline_m * np.sin(theta - (rho - 0.5 * eq.pitch_rad)) / np.sin(rho - 0.5 * eq.pitch_rad)
    r_near = baseline_m * np.sin(theta - (rho + 0.5 * eq.pitch_rad)) / np.sin(rho + 0.5 * eq.pitch_rad)
    stable = (rho > 0.5 * eq.pitch_rad) & (np.maximum(r_far - range_m, range_m - r_near) <= 0.5 * range_m)
    assert stable.tolist() == [False, True, True, False, True]
    np.testing.assert_array_equal(disp_img.pixel, flat[stable])
    np.testing.assert_allclose(disp_img.value, rho[stable] / eq.pitch_rad, rtol=1e-6)
    assert unstable == 2 == range_img.count - disp_img.count
