"""`pair_offset`: the lower rectified image's shift against the upper one where the disparity GT lays one
onto the other, on pairs made with a known shift, disparity, gain and offset."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ingest.dataset.sparse import SparseImage
from ingest.train.gt.stereo_offset import MIN_PIXELS, pair_offset

H, W = 128, 256


def _texture(seed: int = 3) -> np.ndarray:
    """Smooth random texture (grey levels about 30..220)."""
    noise = np.random.default_rng(seed).uniform(0, 255, (H, W)).astype(np.float32)
    smooth = cv2.GaussianBlur(noise, (0, 0), 2.0)
    return np.asarray(smooth, np.float64)


def _disparity(cols: np.ndarray) -> np.ndarray:
    """The scene's disparity (px) by upper column: 2 px at the left, 6 at the right."""
    return 2.0 + 4.0 * cols / (W - 1)


def _pair(dx_px: float, dy_px: float) -> tuple[np.ndarray, np.ndarray]:
    """An upper image and the lower one the disparity makes of it (row - d), then moved by (dx, dy), with
    the lower camera's gain 0.8 and offset +12 grey levels."""
    scene = _texture()
    lo, hi = scene.min(), scene.max()
    upper = np.clip(30 + 190 * (scene - lo) / (hi - lo), 0, 255)
    cols, rows = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    # the scene at upper (c, r) lies at lower (c + dx, r - d(c) + dy)
    source_cols = cols - np.float32(dx_px)
    source_rows = rows + _disparity(source_cols).astype(np.float32) - np.float32(dy_px)
    lower = cv2.remap(upper.astype(np.float32), source_cols, source_rows, cv2.INTER_CUBIC,
                      borderMode=cv2.BORDER_REFLECT)  # fmt: skip
    lower = np.clip(0.8 * lower + 12, 0, 255)
    bgr = [np.repeat(np.round(im)[..., None], 3, axis=2).astype(np.uint8) for im in (upper, lower)]
    return bgr[0], bgr[1]


def _sparse(every: int = 3) -> SparseImage:
    """Every `every`-th pixel of the disparity away from the border, as a sparse GT image."""
    mask = np.zeros((H, W), bool)
    mask[12:-12:every, 12:-12:every] = True
    cols = np.tile(np.arange(W, dtype=np.float64), (H, 1))
    return SparseImage((H, W), np.flatnonzero(mask), _disparity(cols[mask]).astype(np.float32))


@pytest.mark.parametrize(("dx", "dy"), [(0.0, 0.0), (1.0, 0.0), (-0.6, 0.3), (0.25, -1.2)])
def test_the_shift_of_a_made_pair_comes_back(dx: float, dy: float) -> None:
    upper, lower = _pair(dx, dy)
    found = pair_offset(upper, lower, _sparse())
    assert found is not None
    # bilinear sampling biases a shift between whole pixels by up to 0.05 px (0.25 -> 0.29)
    assert found.dx_px == pytest.approx(dx, abs=0.06) and found.dy_px == pytest.approx(dy, abs=0.06)
    assert found.pixels > 2000


def test_too_few_disparity_pixels_or_a_flat_pair_give_no_shift() -> None:
    upper, lower = _pair(0.0, 0.0)
    few = _sparse()
    few = SparseImage(few.shape, few.pixel[: MIN_PIXELS - 1], few.value[: MIN_PIXELS - 1])
    assert pair_offset(upper, lower, few) is None
    flat = np.full_like(upper, 128)
    assert pair_offset(flat, flat, _sparse()) is None


def test_a_pair_torn_down_the_middle_shifts_its_quadrants_apart() -> None:
    """The lower image's left half moved 1 px across the lines, its right half not: the left quadrants
    come back at 1 px, the right ones at 0, and the whole between."""
    upper, moved = _pair(1.0, 0.0)
    _, kept = _pair(0.0, 0.0)
    lower = kept.copy()
    lower[:, : W // 2] = moved[:, : W // 2]
    found = pair_offset(upper, lower, _sparse())
    assert found is not None and len(found.quadrants) == 4 and all(q is not None for q in found.quadrants)
    (ul, ur, ll, lr) = found.quadrants
    assert ul is not None and ll is not None and ur is not None and lr is not None
    for left in (ul, ll):
        assert left[0] == pytest.approx(1.0, abs=0.1) and abs(left[1]) < 0.06
    for right in (ur, lr):
        assert abs(right[0]) < 0.06 and abs(right[1]) < 0.06
    assert 0.2 < found.dx_px < 0.8
