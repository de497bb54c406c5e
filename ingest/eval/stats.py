"""Dataset statistics: depth distribution, GT density and image texture (local entropy).

Per depth GT map (train: `depth_fisheye/<id>.png` with `left_fisheye/<id>.png`;
benchmark: `.../CENTER/depth/<view>.png` with `.../CENTER/<view>.png`):

- depth distribution: valid GT pixels counted in the bins 0-1, 1-2, 2-5, 5-10
  and 10+ m (each bin closed below, open above);
- GT density: valid GT pixels / all pixels of the map;
- texture: the mean over the whole image of the local Shannon entropy (bits)
  of its 8-bit grey levels (OpenCV's BGR->grey weights) in an 11 x 11 square
  window, as skimage.filters.rank.entropy computes it: 256 bins, base 2, and
  at the border only the window's pixels inside the image count.

A depth map of another size than its image, or than the fisheye size of a
training set's dataset.yaml, is refused naming it and the size expected.

Pooled numbers weigh every pixel the same (depth shares) or every sample the
same (density, entropy).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from calibration.types import F32, U8
from ingest.dataset.description import read_description
from ingest.dataset.png import read_image
from ingest.errors import EvalError
from ingest.eval.evaluate import GtFile, Layout, discover_gt, json_safe, read_gt

DEPTH_EDGES_M = (0.0, 1.0, 2.0, 5.0, 10.0, math.inf)
DEPTH_BIN_LABELS = ("0-1 m", "1-2 m", "2-5 m", "5-10 m", "10+ m")
ENTROPY_WINDOW = 11


def depth_bin_counts(depth_m: np.ndarray[Any, Any]) -> np.ndarray[Any, np.dtype[np.int64]]:
    """Valid (finite, > 0) depths counted in `DEPTH_EDGES_M` bins (5 counts)."""
    d = np.asarray(depth_m, np.float64).ravel()
    with np.errstate(invalid="ignore"):
        d = d[np.isfinite(d) & (d > 0)]
    idx = np.searchsorted(np.asarray(DEPTH_EDGES_M[1:-1]), d, side="right")
    return np.bincount(idx, minlength=len(DEPTH_BIN_LABELS)).astype(np.int64)


def local_entropy(gray: U8, size: int = ENTROPY_WINDOW) -> F32:
    """Shannon entropy (bits) of the grey-level histogram in a `size` x `size` window at every pixel.

    With c_b the count of grey level b among the N window pixels inside the
    image, H = log2 N - (1/N) sum_b c_b log2 c_b. Each present grey level is
    one box filter of its indicator image (uint8 counts, then a c log2 c
    lookup table), so the cost is about 256 separable box filters, whatever
    the window size. Float32 sums: within 1e-5 bits of the exact value.
    """
    if gray.dtype != np.uint8 or gray.ndim != 2:
        raise ValueError(f"local_entropy needs a 2-D uint8 image, got {gray.dtype} {gray.shape}")
    if size < 1 or size % 2 == 0 or size * size > 255:
        raise ValueError(f"window size {size}: expected an odd number from 1 to 15")
    ksize = (size, size)
    border = cv2.BORDER_CONSTANT  # pixels outside the image count nowhere
    inside = cv2.boxFilter(np.ones_like(gray), cv2.CV_32F, ksize, normalize=False, borderType=border)
    lut = np.zeros(256, np.float32)
    c = np.arange(1, 256, dtype=np.float64)
    lut[1:] = c * np.log2(c)
    sum_clogc = np.zeros(gray.shape, np.float32)
    indicator = np.empty(gray.shape, np.bool_)
    for level in np.flatnonzero(np.bincount(gray.ravel(), minlength=256)):
        np.equal(gray, level, out=indicator)
        counts = cv2.boxFilter(indicator.view(np.uint8), -1, ksize, normalize=False, borderType=border)
        sum_clogc += cv2.LUT(counts, lut)
    out: F32 = (np.log2(inside) - sum_clogc / inside).astype(np.float32)
    return np.maximum(out, np.float32(0.0))  # float rounding of a constant window: -1e-7 -> 0


@dataclass(frozen=True)
class SampleStats:
    """Statistics of one depth GT map and its image."""

    rel: str
    image: str | None  # the image's path relative to the dataset (None: not found)
    scene: str | None
    fov_deg: float | None
    baseline_mm: float | None
    view: str | None
    depth_counts: tuple[int, ...]  # per DEPTH_BIN_LABELS
    valid_px: int
    total_px: int
    density: float  # valid / total
    depth_mean_m: float
    entropy_bits: float  # mean local entropy of the image (NaN without an image)


@dataclass(frozen=True)
class DatasetStats:
    """Pooled statistics of a dataset and every sample's own."""

    dataset: Path
    layout: Layout
    bins: tuple[str, ...]
    depth_counts: tuple[int, ...]
    depth_shares: tuple[float, ...]  # of all valid GT pixels
    density_mean: float
    entropy_mean_bits: float  # over the samples that have an image
    missing_images: tuple[str, ...]
    samples: tuple[SampleStats, ...]
    missing_gt: tuple[str, ...] = ()  # train layout: finished samples (meta/<id>.json) without a depth map

    def to_json(self) -> dict[str, Any]:
        """A JSON-ready dict (NaN -> null)."""
        doc = asdict(self)
        doc["dataset"] = str(self.dataset)
        return json_safe(doc)  # type: ignore[no-any-return]


def image_for(root: Path, layout: Layout, gt: GtFile) -> Path:
    """The RGB image a depth GT map belongs to."""
    if layout == "train":
        return root / "left_fisheye" / f"{gt.path.stem}.png"
    return gt.path.parent.parent / f"{gt.path.stem}.png"  # CENTER/depth/<view>.png -> CENTER/<view>.png


Size = tuple[int, int]
"""An image's (height, width), px."""


def fisheye_size(root: Path) -> tuple[Size, Path] | None:
    """The fisheye image size a training set's dataset.yaml gives (`fisheye_size`), and that file; None
    without one (a folder of PNGs alone, or the benchmark layout)."""
    path = root / "dataset.yaml"
    if not path.exists():
        return None
    doc = read_description(path, EvalError)  # a device or FIFO, malformed or cut short: one line
    size = doc.get("fisheye_size")
    if not (isinstance(size, list) and len(size) == 2 and all(isinstance(v, int) and v > 0 for v in size)):
        raise EvalError(f"{path}: fisheye_size: expected [height, width] in px, got {size!r}")
    return (size[0], size[1]), path


def _check_size(gt: GtFile, shape: tuple[int, ...], expected: Size, source: str) -> None:
    """EvalError naming the GT map when its size is not `expected` (from `source`): the sample's pixels
    would be counted against another image's."""
    if shape[:2] != expected:
        raise EvalError(
            f"{gt.path}: depth map {shape[1]}x{shape[0]} px, expected {expected[1]}x{expected[0]} "
            f"(the size of {source})"
        )


def sample_stats(
    root: Path,
    layout: Layout,
    gt: GtFile,
    window: int = ENTROPY_WINDOW,
    expected: tuple[Size, Path] | None = None,
) -> SampleStats:
    """Depth bins, density and mean local entropy of one sample.

    The depth map must have the size `expected` gives (the dataset's fisheye
    size, from its dataset.yaml) and that of its image: EvalError otherwise.
    """
    depth = read_gt(gt)
    if expected is not None:
        _check_size(gt, depth.shape, expected[0], f"{expected[1]}'s fisheye_size")
    valid = np.isfinite(depth)
    n_valid = int(valid.sum())
    image_path = image_for(root, layout, gt)
    gray: U8 | None = None
    if image_path.exists():  # a device or FIFO in its place is refused by `read_image`, not skipped
        raw = read_image(image_path, cv2.IMREAD_GRAYSCALE, EvalError)
        if raw is None:
            raise EvalError(f"{image_path}: unreadable image")
        gray = np.asarray(raw, np.uint8)
        _check_size(gt, depth.shape, (gray.shape[0], gray.shape[1]), f"its image {image_path}")
    entropy = float(local_entropy(gray, window).mean(dtype=np.float64)) if gray is not None else math.nan
    return SampleStats(
        gt.rel,
        image_path.relative_to(root).as_posix() if gray is not None else None,
        gt.scene, gt.fov_deg, gt.baseline_mm, gt.view,
        tuple(int(c) for c in depth_bin_counts(depth)),
        n_valid, int(depth.size), n_valid / depth.size,
        float(depth[valid].mean(dtype=np.float64)) if n_valid else math.nan,
        entropy,
    )  # fmt: skip


def dataset_stats(
    root: Path,
    image_type: str | None = None,
    window: int = ENTROPY_WINDOW,
    progress: Callable[[int, int], None] | None = None,
) -> DatasetStats:
    """Statistics of every depth GT map under `root` (either layout); `progress(done, total)`."""
    layout, gts = discover_gt(root, "mono", image_type)
    expected = fisheye_size(root) if layout == "train" else None
    samples = []
    for k, gt in enumerate(gts):
        samples.append(sample_stats(root, layout, gt, window, expected))
        if progress:
            progress(k + 1, len(gts))
    counts = np.zeros(len(DEPTH_BIN_LABELS), np.int64)
    for s in samples:
        counts += np.asarray(s.depth_counts, np.int64)
    total = int(counts.sum())
    entropies = [s.entropy_bits for s in samples if s.image is not None]
    return DatasetStats(
        root,
        layout,
        DEPTH_BIN_LABELS,
        tuple(int(c) for c in counts),
        tuple(float(c) / total if total else math.nan for c in counts),
        float(np.mean([s.density for s in samples])),
        float(np.mean(entropies)) if entropies else math.nan,
        tuple(s.rel for s in samples if s.image is None),
        tuple(samples),
        _missing_gt(root, gts) if layout == "train" else (),
    )


def _missing_gt(root: Path, gts: list[GtFile]) -> tuple[str, ...]:
    """The ids of a training set's finished samples (`meta/<id>.json`) that have no depth map: left out
    of the statistics, which must say so rather than describe fewer samples than the dataset holds."""
    have = {gt.path.stem for gt in gts}
    return tuple(sorted(p.stem for p in (root / "meta").glob("*.json") if p.stem not in have))
