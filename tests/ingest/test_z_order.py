"""Z-order of points: Morton codes of their cubes, and the permutation that sorts by them."""

import numpy as np

from ingest.raster.z_order import morton_codes, z_order


def test_the_eight_cubes_of_a_2x2x2_block_count_x_fastest():
    corner = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], float)
    np.testing.assert_array_equal(morton_codes(corner + 0.5, 1.0), np.arange(8))


def test_bits_interleave_x_then_y_then_z():
    # cube (5, 3, 6) = x 101, y 011, z 110 -> bits z2 y2 x2 z1 y1 x1 z0 y0 x0 = 1 0 1 1 1 0 0 1 1
    pts = np.array([[0.0, 0.0, 0.0], [5.2, 3.7, 6.1]])
    assert morton_codes(pts, 1.0)[1] == 0b101110011


def test_a_block_is_walked_before_the_next_and_a_cube_keeps_its_order():
    rng = np.random.default_rng(3)
    pts = rng.uniform(0.0, 4.0, size=(5000, 3))
    order = z_order(pts, 1.0)
    assert sorted(order.tolist()) == list(range(len(pts)))
    cube = np.floor(pts[order]).astype(int)
    block = cube // 2  # each 2x2x2 block of cubes is one contiguous run
    runs = np.flatnonzero(np.any(np.diff(block, axis=0) != 0, axis=1)) + 1
    assert len(runs) + 1 == len(np.unique(block, axis=0))
    same = np.all(np.diff(cube, axis=0) == 0, axis=1)  # consecutive points in one cube: input order
    assert (np.diff(order)[same] > 0).all()


def test_far_coordinates_saturate_instead_of_wrapping():
    pts = np.array([[0.0, 0.0, 0.0], [1e9, 0.0, 0.0], [2e9, 0.0, 0.0]])
    codes = morton_codes(pts, 0.01)
    assert codes[1] == codes[2] > codes[0] >= 0


def test_no_points_no_order():
    assert len(z_order(np.zeros((0, 3)))) == 0
