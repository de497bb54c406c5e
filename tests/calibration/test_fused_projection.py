"""The compiled one-pass `project` of the closed-form models equals their numpy formula point by point."""

from __future__ import annotations

import numpy as np
import pytest

from calibration import DoubleSphere, ExtendedUnified, Fov, Pinhole, Unified
from calibration.kernels import finish_projection
from calibration.spherical import Equirectangular

MODELS = [
    DoubleSphere(500.2, 500.1, 962.4, 597.9, -0.18, 0.59, 1920, 1200),
    DoubleSphere(300.0, 301.0, 640.0, 400.0, 0.3, 0.7, 1280, 800),
    ExtendedUnified(380.0, 380.0, 640.0, 512.0, 0.63, 1.04, 1280, 1024),
    Unified(400.0, 400.0, 640.0, 512.0, 0.4, 1280, 1024),
    Pinhole(500.0, 500.0, 320.0, 240.0, 640, 480),
    Equirectangular(2048),
    Equirectangular(2048, 2668, 1310, 369, 714),
    Equirectangular(1024, pole_axis="x"),
]


def _points() -> np.ndarray:
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(20_000, 3)) * rng.uniform(0.1, 30.0, (20_000, 1))
    pts[::97] = np.nan  # non-finite inputs
    pts[1::89, 2] = 0.0  # on the pinhole's image plane: x / 0
    pts[2::83] = 0.0  # the centre
    pts[3::79, 0] = np.inf
    pts[4::73] = [0.0, 0.0, -1.0]  # straight behind
    return pts


@pytest.mark.parametrize("model", MODELS, ids=lambda m: type(m).__name__)
def test_fused_projection_matches_the_numpy_formula(model):
    pts = _points()
    assert model._project_fused(pts) is not None
    uv, ok = model.project(pts)
    x, y, z = pts[:, 0], pts[:, 1], pts[:, 2]
    with np.errstate(all="ignore"):
        u, v, valid = model._project(x, y, z)
    uv_ref, ok_ref = finish_projection(u, v, valid, x, y, z)
    assert np.array_equal(ok, ok_ref) and 0.4 < ok.mean() < 0.99
    assert np.isnan(uv[~ok]).all()
    np.testing.assert_allclose(uv[ok], uv_ref[ok], rtol=0, atol=1e-9)


@pytest.mark.parametrize("model", MODELS[:2], ids=["reference rig", "xi > 0"])
def test_fused_double_sphere_unprojection_matches_the_numpy_formula(model):
    rng = np.random.default_rng(4)
    uv = np.concatenate([
        model.pixel_grid().reshape(-1, 2)[::7],
        rng.uniform(-2000.0, 4000.0, (20_000, 2)),  # far outside the image: past the circle and the fold
        [[np.nan, 3.0], [model.cx, model.cy], [np.inf, 0.0]],
    ])  # fmt: skip
    rays, ok = model.unproject(uv)
    rays_ref, ok_ref = model._unproject_numpy(uv)
    assert np.array_equal(ok, ok_ref) and 0.1 < ok.mean() < 0.95 and not ok[-3] and ok[-2] and not ok[-1]
    assert np.isnan(rays[~ok]).all()
    np.testing.assert_allclose(rays[ok], rays_ref[ok], rtol=0, atol=1e-12)


def test_models_with_distortion_keep_the_numpy_path():
    assert Pinhole(500.0, 500.0, 320.0, 240.0, 640, 480, Fov(0.9))._project_fused(np.zeros((1, 3))) is None
