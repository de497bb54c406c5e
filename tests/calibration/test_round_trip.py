"""Every pixel a model unprojects projects back onto itself, and no FOV passes the model's limit.

Issue 19: on a real Double Sphere calibration with xi < 0, `unproject` accepted
46-76 corner pixels per camera whose rays `project` refused, and the diagonal
FOV came out at 250.3 deg, beyond the model's own 247.9 deg. `ISSUE_CAM0` and
`ISSUE_CAM1` reproduce that geometry (the old code accepted 66 and 56 such
pixels and reported 250.3 and 250.0 deg against limits of 248.1 and 247.9).
"""

import math

import numpy as np
import pytest

from calibration import (
    DoubleSphere,
    ExtendedUnified,
    Fov,
    KannalaBrandt,
    Omni,
    Pinhole,
    RadTan,
    Unified,
    field_of_view,
    read_rig,
)
from calibration.camera import CameraModel
from calibration.rig import REFERENCE_RIG
from calibration.spherical import Cassini, Cubemap, Equirectangular

ISSUE_CAM0 = DoubleSphere(480.1, 479.9, 962.4, 597.9, -0.19, 0.594, 1920, 1200)
ISSUE_CAM1 = DoubleSphere(483.0, 482.9, 957.3, 603.2, -0.185, 0.5955, 1920, 1200)

# Realistic wide lenses, at a quarter of 1920x1200 to keep the sweep fast; most
# have pixels past their model's domain so that the boundary is exercised. The
# reference rig's cameras (the simulator's), also at a quarter size, close the list.
QUARTER_MODELS = {
    "ds_xi_negative": DoubleSphere(87.5, 87.4, 240.3, 150.1, -0.2, 0.57, 480, 300),
    "ds_xi_positive": DoubleSphere(75.0, 75.0, 240.0, 150.0, 0.3, 0.6, 480, 300),
    "eucm": ExtendedUnified(75.0, 75.0, 240.0, 150.0, 0.63, 1.1, 480, 300),
    "ucm": Unified(75.0, 75.0, 240.0, 150.0, 0.6, 480, 300),
    "kannala_brandt": KannalaBrandt(75.0, 75.0, 240.0, 150.0, 0.02, -0.01, 0.003, -0.0005, 480, 300),
    "omni_radtan": Omni(0.9, 125.0, 125.0, 240.0, 150.0, 480, 300, RadTan(-0.2, 0.04, 0.001, 0.001)),
    "omni_xi_above_1": Omni(1.5, 200.0, 200.0, 240.0, 150.0, 480, 300),
    "pinhole_radtan": Pinhole(100.0, 100.0, 240.0, 150.0, 480, 300, RadTan(-0.3, 0.08, 0.001, 0.001)),
    "pinhole_fov": Pinhole(75.0, 75.0, 240.0, 150.0, 480, 300, Fov(0.9)),
    "equirectangular": Equirectangular(150),
    "equirectangular_crop": Equirectangular(300, width=200, height=120, row_offset=40, col_offset=250),
    "cassini": Cassini(150),
    "cubemap": Cubemap(64),
    **{f"reference_{c.name}": c.model.scaled(0.25) for c in read_rig(REFERENCE_RIG).cameras},
}


def round_trip(model: CameraModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(unprojection valid, projection of the ray valid, distance back to the pixel in px) per pixel."""
    grid = model.pixel_grid()
    rays, ok = model.unproject(grid)
    back, back_ok = model.project(np.where(ok[..., None], rays, 0.0))
    return ok, back_ok, np.hypot(*np.moveaxis(back - grid, -1, 0))


def normalised_radius(model: DoubleSphere) -> np.ndarray:
    grid = model.pixel_grid()
    return np.hypot((grid[..., 0] - model.cx) / model.fx, (grid[..., 1] - model.cy) / model.fy)


def fold_radius(model: DoubleSphere) -> float:
    """Normalised radius where the limit ray z = -w2 |p| lands (just inside the limit)."""
    t = model.max_off_axis_rad - 1e-12
    uv, ok = model.project(np.array([math.sin(t), 0.0, math.cos(t)]))
    assert ok
    return float((uv[0] - model.cx) / model.fx)


@pytest.mark.parametrize(("model", "ring_px"), [(ISSUE_CAM0, 66), (ISSUE_CAM1, 56)])
def test_issue_ds_every_pixel_round_trips(model, ring_px):
    ok, back_ok, err = round_trip(model)
    assert not (ok & ~back_ok).any()
    assert err[ok].max() < 1e-6
    # The refused pixels are exactly those past the fold; the ring between the fold and
    # the alpha circle (what the old bound accepted) holds the issue's corner pixels.
    r = normalised_radius(model)
    r_fold = fold_radius(model)
    r_circle = 1.0 / math.sqrt(2.0 * model.alpha - 1.0)
    assert r_fold < r_circle
    assert (ok == (r < r_fold)).all()
    assert int(((r >= r_fold) & (r <= r_circle)).sum()) == ring_px


@pytest.mark.parametrize(("model", "limit_deg"), [(ISSUE_CAM0, 248.123), (ISSUE_CAM1, 247.919)])
def test_issue_ds_fov_stops_at_the_model_limit(model, limit_deg):
    fov = field_of_view(model)
    assert math.degrees(fov.limit_rad) == pytest.approx(limit_deg, abs=1e-3)
    # The corners lie past the fold on both diagonals: the diagonal FOV is the limit itself.
    assert fov.diagonal_rad <= fov.limit_rad
    assert fov.diagonal_rad == pytest.approx(fov.limit_rad, abs=1e-6)
    assert fov.horizontal_rad < fov.diagonal_rad


@pytest.mark.parametrize("name", sorted(QUARTER_MODELS))
def test_every_pixel_round_trips(name):
    model = QUARTER_MODELS[name]
    ok, back_ok, err = round_trip(model)
    assert ok.mean() > 0.3, f"{name}: only {ok.mean():.0%} of pixels valid"
    assert not (ok & ~back_ok).any(), f"{name}: {int((ok & ~back_ok).sum())} rays refused by project"
    assert err[ok].max() < 1e-3


@pytest.mark.parametrize("name", sorted(QUARTER_MODELS))
def test_field_of_view_never_exceeds_the_model_limit(name):
    model = QUARTER_MODELS[name]
    fov = field_of_view(model, samples=501)
    for angle in (fov.horizontal_rad, fov.vertical_rad, fov.diagonal_rad):
        assert 0.0 < angle <= fov.limit_rad + 1e-12


def test_pixels_on_the_ucm_circle_are_refused():
    """alpha > 0.5: a pixel on the circle r^2 = 1/(2 alpha - 1) unprojects to the limit ray itself."""
    model = Unified(300.0, 300.0, 960.0, 600.0, 0.6, 1920, 1200)
    on_circle = np.array([[300.0, 480.0], [1620.0, 720.0]])  # (660^2 + 120^2) / 300^2 = 5 exactly
    inside = on_circle + np.array([[1e-6, 0.0], [-1e-6, 0.0]])
    rays, ok = model.unproject(np.concatenate([on_circle, inside]))
    assert ok.tolist() == [False, False, True, True]
    back, back_ok = model.project(rays[2:])
    assert back_ok.all() and np.abs(back - inside).max() < 1e-6
