"""Score written ground truth against the simulator's exact truth (used by tests and bench/).

Depth: `depth_fisheye` (decoded from its uint16 PNG) vs the exact range along
each GT pixel's centre ray at the sample's stamp; an outlier is |e| > max(5 cm,
3 %). Disparity: `disp_equirect` vs the exact disparity at each GT pixel.
Every rate is also given inside the edge band: pixels within `band_px` of an
exact depth discontinuity (a 3x3 range step > max(5 cm, 3 %)).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from calibration.spherical import Equirectangular
from ingest.dataset.layout import DEPTH_SCALE, DISP_SCALE, read_png_u16
from ingest.dataset.meta import read_meta
from sensorbox.sim.truth import Truth


@dataclass(frozen=True)
class SampleScore:
    """Accuracy of one sample's GT (metres and pixels)."""

    sid: str
    depth_pixels: int
    depth_median_abs_m: float
    depth_bias_m: float
    depth_outlier_rate: float
    depth_edge_share: float  # share of GT pixels inside the edge band
    depth_edge_outlier_rate: float
    disp_pixels: int
    disp_median_abs_px: float
    disp_over_1px_rate: float
    depth_no_surface_rate: float = 0.0  # share of GT pixels whose ray hits nothing (sky)
    mover_trail_rate: float = 0.0  # share of GT pixels showing a mover where it was, not where it is


def _edge_band(truth: Truth, stamp_ns: int, band_px: int) -> np.ndarray:
    model = truth.rig.upper.model
    full = truth.range_at(model, model.pixel_grid().reshape(-1, 2), stamp_ns).reshape(
        model.height, model.width
    )
    full = np.nan_to_num(full, nan=0.0).astype(np.float32)
    kernel = np.ones((3, 3), np.uint8)
    step = cv2.dilate(full, kernel) - cv2.erode(full, kernel)
    edges = (step > np.maximum(0.05, 0.03 * full)).astype(np.uint8)
    band: np.ndarray = cv2.dilate(edges, np.ones((2 * band_px + 1, 2 * band_px + 1), np.uint8)) > 0
    return band


def score_sample(
    out: Path, truth: Truth, sid: str, band_px: int = 3, trail_window_ns: int = 500_000_000
) -> SampleScore:
    """Depth and disparity accuracy of sample `sid` of the dataset at `out`.

    With movers, `mover_trail_rate` looks for their earlier (and later)
    positions within +-`trail_window_ns` of the sample's stamp.
    """
    stamp = truth.exposure_ns(read_meta(out, sid).stamp_ns)  # the bag's stamp, moved to the true exposure
    model = truth.rig.upper.model
    depth = read_png_u16(out / "depth_fisheye" / f"{sid}.png", DEPTH_SCALE)
    rows, cols = np.nonzero(depth)
    exact = truth.range_at(model, np.stack([cols, rows], 1).astype(float), stamp)
    e = depth[rows, cols] - exact
    ok = np.isfinite(e)
    outlier = np.abs(e[ok]) > np.maximum(0.05, 0.03 * exact[ok])
    band = _edge_band(truth, stamp, band_px)[rows, cols][ok]
    doc = yaml.safe_load((out / "dataset.yaml").read_text())
    eq = Equirectangular(int(doc["height_full"]))
    disp = read_png_u16(out / "disp_equirect" / f"{sid}.png", DISP_SCALE)
    r2, c2 = np.nonzero(disp)
    ed = disp[r2, c2] - truth.disparity_at(eq, np.stack([c2, r2], 1).astype(float), stamp)
    ed = ed[np.isfinite(ed)]
    trail = _mover_trail(truth, model, rows, cols, depth[rows, cols], exact, stamp, trail_window_ns)
    return SampleScore(
        sid, int(ok.sum()), float(np.median(np.abs(e[ok]))), float(np.median(e[ok])), float(outlier.mean()),
        float(band.mean()), float(outlier[band].mean()) if band.any() else 0.0,
        len(ed), float(np.median(np.abs(ed))), float((np.abs(ed) > 1.0).mean()),
        float((~ok).mean()) if len(ok) else 0.0, float(trail.mean()) if len(trail) else 0.0,
    )  # fmt: skip


def _mover_trail(
    truth: Truth, model: Any, rows: Any, cols: Any, gt_m: Any, exact_m: Any, stamp: int, window_ns: int
) -> np.ndarray:
    """GT pixels that are wrong now but match a mover's surface at some time of the window (10 ms steps)."""
    wrong = ~(np.abs(gt_m - exact_m) <= np.maximum(0.05, 0.03 * np.nan_to_num(exact_m, nan=np.inf)))
    trail = np.zeros(len(gt_m), bool)
    if not truth.movers or not wrong.any():
        return trail
    idx = np.flatnonzero(wrong)
    rays, _ = model.unproject(np.stack([cols[idx], rows[idx]], 1).astype(float))
    for t in range(stamp - window_ns, stamp + window_ns + 1, 10_000_000):
        r = truth.mover_range_along(rays, stamp, t)
        with np.errstate(invalid="ignore"):
            trail[idx] |= np.abs(gt_m[idx] - r) <= np.maximum(0.05, 0.03 * r)
    return trail


def score_dataset(out: Path, truth: Truth) -> list[SampleScore]:
    """Scores of every written sample, in id order."""
    return [score_sample(out, truth, m.stem) for m in sorted((out / "meta").glob("*.json"))]
