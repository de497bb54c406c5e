"""Dataset statistics: local entropy against a brute-force reference, depth bins, density."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from ingest.eval.stats import dataset_stats, depth_bin_counts, local_entropy
from tests.ingest.test_evaluate import SHAPE, imread, make_benchmark


def brute_entropy(gray: np.ndarray, size: int) -> np.ndarray:
    """skimage.filters.rank.entropy with a square footprint, written out: base 2, in-image pixels only."""
    h, w = gray.shape
    r = size // 2
    out = np.zeros((h, w))
    for y in range(h):
        for x in range(w):
            window = gray[max(0, y - r) : y + r + 1, max(0, x - r) : x + r + 1].ravel()
            counts = np.bincount(window, minlength=256)
            p = counts[counts > 0] / window.size
            out[y, x] = -(p * np.log2(p)).sum()
    return out


@pytest.mark.parametrize("size", [11, 5, 1])
def test_local_entropy_matches_the_brute_force_reference(size: int) -> None:
    rng = np.random.default_rng(size)
    gray = rng.integers(0, 256, (23, 31)).astype(np.uint8)
    gray[:6, :9] = 7  # a flat corner: 0 bits where the window sees only it
    gray[15:, 20:] = (rng.integers(0, 3, (8, 11)) * 100).astype(np.uint8)  # three levels
    got = local_entropy(gray, size)
    assert got.dtype == np.float32 and got.shape == gray.shape
    np.testing.assert_allclose(got, brute_entropy(gray, size), atol=2e-5)


def test_local_entropy_known_values() -> None:
    assert local_entropy(np.full((20, 30), 200, np.uint8)).max() < 1e-6  # float32 sums: 0 within 1e-6
    stripes = np.zeros((40, 40), np.uint8)
    stripes[:, ::2] = 255
    h = local_entropy(stripes)
    # an interior 11 x 11 window holds 6 columns of one level and 5 of the other
    expected = -(6 / 11 * math.log2(6 / 11) + 5 / 11 * math.log2(5 / 11))
    assert h[20, 20] == pytest.approx(expected, abs=1e-6) and h[20, 21] == pytest.approx(expected, abs=1e-6)
    with pytest.raises(ValueError, match="odd number"):
        local_entropy(stripes, 4)
    with pytest.raises(ValueError, match="2-D uint8"):
        local_entropy(stripes.astype(np.float32))


def test_depth_bins() -> None:
    depth = np.array([0.5, 1.0, 1.99, 2.0, 4.9, 5.0, 9.99, 10.0, 50.0, 0.0, np.nan, -1.0, np.inf])
    assert depth_bin_counts(depth).tolist() == [1, 2, 2, 2, 2]  # [0,1) [1,2) [2,5) [5,10) [10,inf)


def test_dataset_stats_on_the_benchmark_layout(tmp_path: Path) -> None:
    bench = make_benchmark(tmp_path / "bench")
    missing = bench / "002_010_000" / "195FOV" / "200mm" / "CENTER" / "pano_crop.png"
    missing.unlink()
    stats = dataset_stats(bench, image_type="pano_crop")
    assert stats.layout == "benchmark" and len(stats.samples) == 8
    first = stats.samples[0]
    assert first.rel == "001_057_000/120FOV/65mm/CENTER/depth/pano_crop"
    assert first.image == "001_057_000/120FOV/65mm/CENTER/pano_crop.png"
    raw = imread(bench / f"{first.rel}.png", cv2.IMREAD_UNCHANGED) / 1000.0
    valid = raw[raw > 0]
    bins = ((0, 1), (1, 2), (2, 5), (5, 10), (10, 99))
    expected = [int(((valid >= lo) & (valid < hi)).sum()) for lo, hi in bins]
    assert list(first.depth_counts) == expected and sum(expected) == 48
    assert (first.valid_px, first.total_px) == (48, SHAPE[0] * SHAPE[1])
    assert first.density == pytest.approx(48 / 60)
    assert first.depth_mean_m == pytest.approx(valid.mean())
    grey = imread(bench / first.image, cv2.IMREAD_GRAYSCALE)  # two-level stripes
    assert len(np.unique(grey)) == 2
    assert first.entropy_bits == pytest.approx(brute_entropy(grey, 11).mean(), abs=1e-5)
    assert stats.missing_images == ("002_010_000/195FOV/200mm/CENTER/depth/pano_crop",)
    assert math.isnan(stats.samples[-1].entropy_bits)
    assert stats.entropy_mean_bits == pytest.approx(first.entropy_bits, abs=1e-6)  # every image is the same
    assert sum(stats.depth_counts) == 8 * 48
    assert stats.depth_shares == pytest.approx([c / (8 * 48) for c in stats.depth_counts])
    doc = json.loads(json.dumps(stats.to_json()))
    assert doc["samples"][-1]["entropy_bits"] is None and doc["bins"][-1] == "10+ m"
