"""The free-space test's ray rule (`ingest.train.gt.free_space`) and the GT margin around what it removed."""

from dataclasses import replace

import numpy as np

from ingest.train.gt.dense import DenseParams, free_space_filter, mover_margins, near_movers

ORIGIN = np.zeros(3)


def _rays(ends: list[list[float]], slices: list[int]) -> tuple[np.ndarray, np.ndarray]:
    return np.array(ends, np.float64), np.array(slices, np.int64)


def test_a_ray_skimming_a_plane_past_a_point_does_not_clear_it():
    """The ground (z = -0.5) 20 m ahead: rays of two slices aimed 3 cm above a ground point come down on
    the ground 1.28 m beyond it, farther than the margin (0.1 m + 3 % of 20 m). By distance alone they
    passed the point within its tolerance and went on; they never crossed its plane beside it."""
    ground = np.array([[20.0, 0.0, -0.5]])
    hit = 20.0 * 0.5 / 0.47  # where a ray through (20, y, -0.47) meets z = -0.5
    ends, slices = _rays([[hit, 0.0, -0.5], [hit, 0.01 * hit / 20.0, -0.5]], [0, 1])
    pts, slice_id = np.concatenate([ends, ground]), np.r_[slices, 2]
    refs = [(0, ORIGIN), (1, ORIGIN)]
    up = np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    assert free_space_filter(pts, slice_id, refs, DenseParams(), normal=up)[-1]
    assert not free_space_filter(pts, slice_id, refs, DenseParams())[-1]  # without its plane it went


def test_a_surface_that_moved_goes_once_two_slice_times_saw_through_it():
    """A point of a wall at 5 m (slice 2) that rays of slices 0 and 1 crossed 1 cm beside it on their way to
    12 m: removed; with one of them only, or with both slices the two LiDARs of one time, kept."""
    wall = np.array([[5.0, 0.0, 0.0]])
    ends, slices = _rays([[12.0, 0.024, 0.0], [12.0, 0.0, 0.024]], [0, 1])
    pts, slice_id = np.concatenate([ends, wall]), np.r_[slices, 2]
    facing = np.tile([1.0, 0.0, 0.0], (len(pts), 1))
    both = [(0, ORIGIN), (1, ORIGIN)]
    assert not free_space_filter(pts, slice_id, both, DenseParams(), normal=facing)[-1]
    assert free_space_filter(pts, slice_id, both[:1], DenseParams(), normal=facing)[-1]
    assert free_space_filter(pts, slice_id, both, DenseParams(), normal=facing, lidars=2)[-1]
    one = replace(DenseParams(), free_min_slices=1)
    assert not free_space_filter(pts, slice_id, both[:1], one, normal=facing)[-1]


def test_a_ray_clears_only_within_its_footprint_or_the_pass_distance():
    """Rays of two slices to 30 m pass a point at 10 m 3.4 cm away (clears: within 0.0035 x 10 m) and one
    at 4 m 3.4 cm away (kept: beyond max(3 cm, 0.0035 x 4 m))."""
    far, near = np.array([[10.0, 0.034, 0.0]]), np.array([[4.0, 0.034, 0.0]])
    ends, slices = _rays([[30.0, 0.0, 0.0], [30.0, 0.0, 0.0]], [0, 1])
    pts, slice_id = np.concatenate([ends, far, near]), np.r_[slices, 2, 2]
    keep = free_space_filter(pts, slice_id, [(0, ORIGIN), (1, ORIGIN)], DenseParams())
    assert keep[-2:].tolist() == [False, True]


def test_rays_start_where_their_lidar_was_at_each_points_time():
    """The reference's origin groups its rays; each ray is cast from its own origin: a ray from (0, 0.5, 0)
    to (12, 0.5, 0) crosses (5, 0.5, 0), which the reference origin's line to the same end misses by 29 cm."""
    ends, slices = _rays([[12.0, 0.5, 0.0], [12.0, 0.5, 0.0]], [0, 1])
    pts, slice_id = np.concatenate([ends, [[5.0, 0.5, 0.0]]]), np.r_[slices, 2]
    refs = [(0, ORIGIN), (1, ORIGIN)]
    own = np.array([[0.0, 0.5, 0.0], [0.0, 0.5, 0.0], [0.0, 0.0, 0.0]])
    assert not free_space_filter(pts, slice_id, refs, DenseParams(), ray_origin=own)[-1]
    assert free_space_filter(pts, slice_id, refs, DenseParams())[-1]


def test_a_movers_margin_follows_its_extent():
    """A 0.6 m x 0.6 m patch of removed points 5 m out (extent 0.42 m, 0.085 rad) gets 0.25 x that; a lone
    point, 0.005 rad; a 4 m row 4 m out (2 m from its centre, 0.5 rad), the cap of 0.035 rad."""
    g = np.linspace(-0.3, 0.3, 7)
    patch = np.array([[x, y, 5.0] for x in g for y in g])
    lone = np.array([[3.0, 0.0, 8.0]])
    row = np.c_[np.linspace(-2.0, 2.0, 41), np.zeros(41), np.full(41, 4.0)]
    margin = mover_margins(np.concatenate([patch, lone, row]), DenseParams())
    np.testing.assert_allclose(margin[: len(patch)], 0.25 * np.sqrt(0.18) / 5.0)
    assert margin[len(patch)] == 0.005
    np.testing.assert_allclose(margin[len(patch) + 1 :], 0.035)
    assert len(mover_margins(np.zeros((0, 3)), DenseParams())) == 0


def test_near_movers_draws_each_points_own_disc():
    """Two removed points with margins of 0.035 and 0.02 rad (5 and 3 px at 150 px/rad): their two discs."""
    from calibration.fisheye import DoubleSphere

    model = DoubleSphere(120.0, 120.0, 160.0, 100.0, -0.2, 0.6, 320, 200)
    pts = np.array([[0.0, 0.0, 5.0], [0.0, 0.0, 5.0]])
    pts[1] = model.unproject(np.array([[200.0, 100.0]]))[0][0] * 5.0
    rows, cols = np.mgrid[: model.height, : model.width]
    want = ((cols - 160) ** 2 + (rows - 100) ** 2 <= 25) | ((cols - 200) ** 2 + (rows - 100) ** 2 <= 9)
    np.testing.assert_array_equal(near_movers(model, pts, np.array([0.035, 0.02])), want)
    assert not near_movers(model, pts, np.zeros(2)).any()
