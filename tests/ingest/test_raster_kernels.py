"""The compiled z-buffer against the numpy (erode) one and against footprints counted by hand."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ingest.raster.geometry import ViewPoints
from ingest.raster.kernels import ellipse_offsets, nearest_range
from ingest.raster.params import EMPTY_KEY
from ingest.raster.visibility import winner, zbuffer
from tests.ingest.oracles import zbuffer_erode


def _view_points(pix: list[int], u: list[float], v: list[float], r: list[float], ku: list[int],
                 kv: list[int]) -> ViewPoints:  # fmt: skip
    n = len(pix)
    f32, i16 = np.float32, np.int16
    return ViewPoints(
        np.array(pix, np.int64), np.array(u, f32), np.array(v, f32), np.array(r, f32),
        np.array(ku, i16), np.array(kv, i16), np.zeros((n, 3), np.uint8), np.zeros(n, bool),
    )  # fmt: skip


def _points(rng: np.random.Generator, n: int, H: int, W: int, k_max: int) -> ViewPoints:
    pix = rng.integers(0, H * W, n)
    row, col = np.divmod(pix, W)
    return ViewPoints(
        pix=pix.astype(np.int64),
        u=(col + rng.uniform(-0.5, 0.5, n)).astype(np.float32),
        v=(row + rng.uniform(-0.5, 0.5, n)).astype(np.float32),
        r=rng.uniform(0.3, 80.0, n).astype(np.float32),
        ku=rng.integers(0, k_max + 1, n).astype(np.int16),
        kv=rng.integers(0, k_max + 1, n).astype(np.int16),
        rgb=np.zeros((n, 3), np.uint8),
        masked=np.zeros(n, bool),
    )


@pytest.mark.parametrize(("n", "H", "W", "k_max"), [(1, 9, 11, 3), (500, 40, 70, 6), (20_000, 120, 90, 4)])
def test_compiled_zbuffer_gives_the_erode_keys_bit_for_bit(n: int, H: int, W: int, k_max: int) -> None:
    pts = _points(np.random.default_rng(n), n, H, W, k_max)
    own, splat = zbuffer(pts, H, W)
    own_ref, splat_ref = zbuffer_erode(pts, H, W)
    np.testing.assert_array_equal(own, own_ref)
    np.testing.assert_array_equal(splat, splat_ref)


def test_one_point_covers_exactly_its_ellipse_clipped_at_the_border() -> None:
    H, W, ku, kv = 12, 15, 4, 2
    for row, col in [(6, 7), (0, 1), (11, 14)]:
        pts = _view_points([row * W + col], [col], [row], [2.5], [ku], [kv])
        own, splat = zbuffer(pts, H, W)
        expected = np.zeros((H + 2 * kv, W + 2 * ku), bool)
        ellipse = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * ku + 1, 2 * kv + 1)) > 0
        expected[row : row + 2 * kv + 1, col : col + 2 * ku + 1] = ellipse
        covered, idx = winner(splat)
        np.testing.assert_array_equal(covered.reshape(H, W), expected[kv : kv + H, ku : ku + W])
        assert set(idx[covered].tolist()) == {0}
        assert np.flatnonzero(own != EMPTY_KEY).tolist() == [row * W + col]


def test_nearest_point_wins_each_pixel() -> None:
    W = 5
    # point 1 is the nearest; its footprint covers point 0's pixel
    pts = _view_points([7, 8, 7], [2, 3, 2], [1, 1, 1], [3.0, 2.0, 4.0], [0, 1, 0], [0, 1, 0])
    own, splat = zbuffer(pts, 3, W)  # (3, 3) ellipse: a cross
    assert winner(own)[1][7] == 0 and winner(own)[1][8] == 1
    assert winner(splat)[1][[7, 8, 9]].tolist() == [1, 1, 1]


def test_ellipse_offsets_have_one_class_per_half_width_pair() -> None:
    start, drow, dcol = ellipse_offsets(2)
    assert len(start) == 10 and start[1] == 1  # (0, 0): the pixel itself
    cls = 2 * 3 + 1  # ku=2, kv=1
    span = slice(start[cls], start[cls + 1])
    offs = set(zip(drow[span].tolist(), dcol[span].tolist(), strict=True))
    assert (0, 2) in offs and (0, -2) in offs and (1, 0) in offs and (1, 2) not in offs


def test_nearest_range_is_the_least_range_per_pixel_and_inf_where_none() -> None:
    """The compiled pass against numpy's minimum.at: 5000 points on a 30 x 40 image, several per pixel."""
    rng = np.random.default_rng(3)
    rows, cols = rng.integers(0, 30, 5000), rng.integers(0, 40, 5000)
    range_m = rng.uniform(0.3, 80.0, 5000).astype(np.float32)
    want = np.full((30, 40), np.inf, np.float32)
    np.minimum.at(want, (rows, cols), range_m)
    got = nearest_range(rows, cols, range_m, 30, 40)
    assert got.dtype == np.float32 and np.isinf(got).sum() == np.isinf(want).sum() > 0
    np.testing.assert_array_equal(got, want)
