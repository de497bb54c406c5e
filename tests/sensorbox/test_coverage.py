"""The live monitor's coverage preview on exact geometry: known pixels -> a plane -> the gyro -> the same pixels."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.rig import REFERENCE_RIG, read_rig
from calibration.transforms import rodrigues
from sensorbox.live.coverage import coverage, draw_coverage, gyro_orientations, orientation_at, place_sweeps

MODEL = read_rig(REFERENCE_RIG).upper.model.scaled(0.25)  # 480 x 300, the preview of a 1920 x 1200 image
W_RAD_S = np.array([0.1, 0.6, -0.2])  # a turn while walking: mostly yaw (about cam0's y, which points down)


def plane_points(pixels_uv: np.ndarray, depth_m: float) -> np.ndarray:
    """The points of the plane z = depth_m (camera frame) seen at the given pixel centres (each ray at
    least 0.2 forward: the fisheye's corners look beyond 90 degrees, where the plane is not)."""
    rays, valid = MODEL.unproject(pixels_uv.astype(np.float64))
    assert valid.all() and (rays[:, 2] > 0.2).all()
    return rays * (depth_m / rays[:, 2:3])


def gyro(t0_s: float, t1_s: float, hz: float = 200.0) -> tuple[np.ndarray, np.ndarray]:
    stamps = np.round(np.arange(t0_s, t1_s, 1 / hz) * 1e9).astype(np.int64)
    return stamps, np.tile(W_RAD_S, (len(stamps), 1))


def test_gyro_integration_turns_by_rate_times_time():
    stamps, rates = gyro(0.0, 1.0)
    Rs = gyro_orientations(stamps, rates)
    R = orientation_at(stamps, rates, Rs, 700_000_000)  # between samples 140 and 141: exact too
    np.testing.assert_allclose(R, rodrigues(W_RAD_S * 0.7), atol=1e-12)
    np.testing.assert_array_equal(orientation_at(stamps, rates, Rs, -5), np.eye(3))


def test_points_of_a_plane_cover_exactly_their_pixels_after_the_gyro_turn():
    # a block of 60 x 40 pixels plus a sparse grid of 11 x 9 (each within 78 degrees of the axis):
    # 2400 + 99 minus the 2 grid pixels inside the block
    block = np.stack(np.meshgrid(np.arange(200, 260), np.arange(100, 140)), -1).reshape(-1, 2)
    grid = np.stack(np.meshgrid(np.arange(80, 420, 32), np.arange(20, 290, 30)), -1).reshape(-1, 2)
    pixels = np.unique(np.concatenate([block, grid]), axis=0)
    expected = {(int(u), int(v)) for u, v in pixels}
    p_image = plane_points(pixels, 3.0)  # where the points are when the image is taken
    stamps, rates = gyro(0.0, 1.0)
    # two sweeps seen 0.8 s and 0.35 s before the image, as the rig was turning: at time t a point is
    # R(t)^T R(image) p_image in cam0
    Rs = gyro_orientations(stamps, rates)
    image_ns = 900_000_000
    R_image = orientation_at(stamps, rates, Rs, image_ns)
    half = len(p_image) // 2
    sweeps = []
    for t_ns, pts in ((100_000_000, p_image[:half]), (550_000_000, p_image[half:])):
        R_t = orientation_at(stamps, rates, Rs, t_ns)
        sweeps.append((t_ns, pts @ (R_t.T @ R_image).T))
    # plus a point behind the camera and one above the image's top edge: they cover nothing
    sweeps.append((image_ns, np.array([[0.0, 0.0, -2.0], [0.0, -50.0, 0.1]])))

    placed = place_sweeps(sweeps, stamps, rates, image_ns)
    cov = coverage(placed, MODEL)

    assert {(int(u), int(v)) for u, v in cov.pixels} == expected
    assert cov.covered.sum() == len(expected) == 2400 + 99 - 2
    assert cov.fraction == len(expected) / (480 * 300)
    np.testing.assert_allclose(np.sort(cov.range_m), np.sort(np.linalg.norm(p_image, axis=1)), rtol=1e-9)
    # without the gyro (the sweeps taken as seen) the turn smears them elsewhere: the rotation matters
    still = coverage(place_sweeps(sweeps, stamps, np.zeros_like(rates), image_ns), MODEL)
    assert len({(int(u), int(v)) for u, v in still.pixels} & expected) < len(expected) // 10


def test_no_points_cover_nothing_and_the_drawing_keeps_the_image_size():
    cov = coverage(np.zeros((0, 3)), MODEL)
    assert cov.fraction == 0.0 and not cov.covered.any()
    image = np.zeros((300, 480, 3), np.uint8)
    one = coverage(plane_points(np.array([[100, 50]]), 1.0), MODEL)
    drawn = draw_coverage(image, one, 1.0)
    assert drawn.shape == image.shape and drawn[50, 100].any()  # the point is painted
    assert not image.any()  # the input is left as it was


@pytest.mark.parametrize("width, factor", [(1920, 4), (640, 1), (480, 1), (1280, 2), (8000, 8)])
def test_preview_factor(width, factor):
    from sensorbox.live.coverage import preview_factor

    assert preview_factor(width) == factor


def test_the_view_places_points_at_the_frame_time_or_at_the_newest_sweep_when_clocks_differ(caplog):
    """A frame within 0.5 s of the newest sweep: the sweeps are turned to its time by the gyro; a frame
    stamped 20 s off (a camera on another clock) would turn them by a gyro integrated over the gap, so
    they are placed at the newest sweep's time and one warning names the offset."""
    from sensorbox.live.monitor_channels import CloudCam0, Gyro, Preview, streams_of
    from sensorbox.live.monitor_view import CoverageView

    rig = read_rig(REFERENCE_RIG)
    streams = {s.kind + s.name: s for s in streams_of(rig).values()}
    t_sweep = 1_000_000_000
    pixels = np.array([[240, 150], [100, 200]])
    pts = plane_points(pixels, 2.0)
    frame = np.zeros((300, 480, 3), np.uint8)
    stamps, rates = gyro(0.0, 2.0)
    cloud = CloudCam0(t_sweep, t_sweep, pts.astype(np.float32), np.zeros(2, np.float32))
    views = []
    for frame_ns in (t_sweep, t_sweep + 20_000_000_000):
        view = CoverageView(rig, 1.0)
        view.feed(streams["imageupper"], Preview(frame_ns, frame, 4))
        view.feed(streams["lidarlidar_top"], cloud)
        for t_ns, w in zip(stamps, rates, strict=True):
            view.feed(streams["imuimu_top"], Gyro(int(t_ns), w, np.zeros(3)))
        views.append(view)
    on_time, off_clock = (v.render() for v in views)
    assert on_time is not None and off_clock is not None
    # same time: no turn, the points land on their pixels
    assert {(int(u), int(v)) for u, v in on_time.coverage.pixels} == {(240, 150), (100, 200)}
    # 20 s off: placed at the sweep's time as well (not turned by 20 s of gyro), the caption says so
    assert {(int(u), int(v)) for u, v in off_clock.coverage.pixels} == {(240, 150), (100, 200)}
    assert caplog.messages == [
        "monitor: upper frames are stamped +20.0 s off the LiDARs' clock: the coverage preview places the "
        "points at the newest sweep's time"
    ]
