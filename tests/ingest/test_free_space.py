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


def test_a_movers_margin_follows_its_width():
    """A 0.6 m x 0.6 m patch of removed points 5 m out (width: twice its second principal spread, 0.4 m;
    0.08 rad) gets 0.25 x that; a lone point, 0.005 rad; a 4 m x 4 m patch 7.2 m out (width 2.4 m,
    0.33 rad), the cap of 0.035 rad; a 4 m row 4 m out (a cable cleared by rays passing beside it: no width), the
    least, 0.005 rad (by its length alone it got the cap and 2 degrees of GT around it were dropped)."""
    g = np.linspace(-0.3, 0.3, 7)
    patch = np.array([[x, y, 5.0] for x in g for y in g])
    lone = np.array([[3.0, 0.0, 8.0]])
    big = np.array([[x, y, 4.0] for x in 6.0 + np.linspace(-2, 2, 21) for y in np.linspace(-2, 2, 21)])
    row = np.c_[np.linspace(-2.0, 2.0, 41), np.zeros(41), np.full(41, 4.0)]
    margin = mover_margins(np.concatenate([patch, lone, big, row]), DenseParams())
    np.testing.assert_allclose(margin[: len(patch)], 0.25 * 0.4 / 5.0)
    assert margin[len(patch)] == 0.005
    np.testing.assert_allclose(margin[len(patch) + 1 : len(patch) + 1 + len(big)], 0.035)
    np.testing.assert_allclose(margin[len(patch) + 1 + len(big) :], 0.005)
    assert len(mover_margins(np.zeros((0, 3)), DenseParams())) == 0


def test_a_thin_pole_that_rays_pass_beside_is_kept_while_they_also_hit_it():
    """A 12 mm pole 3 m out: its point (slice 9) is passed 1.5 cm beside by a ray of each of slices 0-3 on
    the way to a wall at 6 m (within the 3 cm tolerance, so each saw through it). Each of those slices
    also returned from the pole 2.5 cm below the point (another voxel): the pole was there all along,
    the point is kept. Without those returns (a mover's old position) it goes."""
    beside, pole = [[6.0, 0.03, 0.0]] * 4, [[3.0, 0.0, -0.025]] * 4
    point = np.array([[3.0, 0.0, 0.0]])
    refs = [(k, ORIGIN) for k in range(4)]
    pts, slice_id = np.concatenate([beside, pole, point]), np.r_[np.arange(4), np.arange(4), 9]
    assert free_space_filter(pts, slice_id, refs, DenseParams())[-1]
    pts, slice_id = np.concatenate([beside, point]), np.r_[np.arange(4), 9]
    assert not free_space_filter(pts, slice_id, refs, DenseParams())[-1]


def test_a_point_is_removed_only_by_slices_outside_the_times_its_spot_was_hit():
    """A box face 4 m out hit at slices 2 and 7 (points in its voxel); rays of two slices pass 1 cm beside
    its point of slice 3 to 12 m. Slices 4 and 5 (between the hits: the box was there, the rays passed
    its edge) keep it; slices 8 and 9 (after its last hit: it has gone) remove it; so do slices 0 and 9
    (before the first and after the last)."""
    box = np.array([[4.0, 0.0, 0.0]] * 3)
    rays = [[12.0, 0.03, 0.0], [12.0, 0.0, 0.03]]
    for seen_by, removed in (((4, 5), False), ((8, 9), True), ((0, 9), True)):
        pts = np.concatenate([rays, box])
        slice_id = np.r_[seen_by, 2, 7, 3]
        refs = [(k, ORIGIN) for k in (*seen_by, 2, 7)]
        keep = free_space_filter(pts, slice_id, refs, DenseParams())
        assert keep[-1] != removed, seen_by


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


def test_stale_slices_counts_the_saw_through_bits_outside_the_span_of_the_hits_across_words():
    """Two words per half: hits at slices 10 and 70, seen through at 5, 40 and 100: 5 and 100 count (40
    lies between the hits); with no hit all three count."""
    from ingest.train.gt.free_space import stale_slices

    def row(seen: list[int], hit: list[int]) -> list[int]:
        words = [0, 0, 0, 0]
        for half, slices in ((0, seen), (2, hit)):
            for b in slices:
                words[half + b // 64] |= 1 << (b % 64)
        return words

    bits = np.array([row([5, 40, 100], [10, 70]), row([5, 40, 100], [])], np.uint64)
    assert stale_slices(bits).tolist() == [2, 3]
