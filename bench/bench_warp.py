"""Fisheye 1920x1200 -> equirect (full 2048x4096 and the covering crop).

Maps are built once (timed separately); the warp is then timed as the median
of 10 runs and compared with a bare cv2.remap of the same output size measured
in the same run. Writes out/bench/bench_warp.png.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import OUT_DIR, median_seconds

from calibration import CameraModel, read_rig
from calibration.rectify import rectify_rig
from calibration.spherical import Equirectangular
from calibration.warp import build_maps, clear_map_cache, covering_crop, default_height_full, warp

RUNS = 10
RIG = Path(__file__).resolve().parents[1] / "calibration" / "sensorbox.yaml"


def remap_call(img: np.ndarray, m1: np.ndarray, m2: np.ndarray) -> Callable[[], object]:
    """A bare cv2.remap, the alternative a user would write by hand."""
    return lambda: cv2.remap(img, m1, m2, cv2.INTER_LINEAR)


def warp_call(img: np.ndarray, src: CameraModel, dst: CameraModel, R: np.ndarray) -> Callable[[], object]:
    """SensorBox's warp with cached maps."""
    return lambda: warp(img, src, dst, R)


def main() -> None:
    cv2.setNumThreads(2)
    rig = read_rig(RIG)
    cam0 = rig.upper.model
    R = rectify_rig(rig).R_cam0_rect
    hf = default_height_full(cam0)
    targets = [("full sphere", Equirectangular(hf)), ("covering crop", covering_crop(cam0, R, hf))]
    img = (np.random.default_rng(0).random((cam0.height, cam0.width, 3)) * 255).astype(np.uint8)
    rows = []
    for name, eq in targets:
        clear_map_cache()
        t0 = time.perf_counter()
        build_maps(cam0, eq, R)
        t_build = time.perf_counter() - t0
        t_warp = median_seconds(warp_call(img, cam0, eq, R), RUNS)
        mx = np.random.default_rng(1).uniform(0, cam0.width - 1, (eq.height, eq.width)).astype(np.float32)
        my = np.random.default_rng(2).uniform(0, cam0.height - 1, (eq.height, eq.width)).astype(np.float32)
        maps = build_maps(cam0, eq, R)
        fixed = cv2.convertMaps(maps.map_x, maps.map_y, cv2.CV_16SC2)
        t_bare = median_seconds(remap_call(img, maps.map_x, maps.map_y), RUNS)
        t_fixed = median_seconds(remap_call(img, fixed[0], fixed[1]), RUNS)
        t_rand = median_seconds(remap_call(img, mx, my), RUNS)
        rows.append((name, f"{eq.width}x{eq.height}", t_build, t_warp, t_bare, t_rand, t_fixed))

    print(f"\nfisheye {cam0.width}x{cam0.height} RGB -> equirect, H_full = {hf}, median of {RUNS} runs, "
          f"cv2 threads = {cv2.getNumThreads()}\n")  # fmt: skip
    print("| target        | size      | build maps [ms] | warp [ms] | bare remap, same maps [ms] | "
          "warp / bare | bare remap, fixed-point maps [ms] | bare remap, random maps [ms] |")  # fmt: skip
    print("|---------------|-----------|-----------------|-----------|----------------------------|"
          "-------------|-----------------------------------|------------------------------|")  # fmt: skip
    for name, size, tb, tw, tr, trr, tf in rows:
        print(f"| {name:<13} | {size:<9} | {tb * 1e3:15.0f} | {tw * 1e3:9.1f} | {tr * 1e3:26.1f} | "
              f"{tw / tr:11.2f} | {tf * 1e3:33.1f} | {trr * 1e3:28.1f} |")  # fmt: skip

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4))
    x = np.arange(len(rows))
    ax.bar(x - 0.2, [r[3] * 1e3 for r in rows], 0.4, label="sensorbox warp (cached maps)")
    ax.bar(x + 0.2, [r[4] * 1e3 for r in rows], 0.4, label="bare cv2.remap, same size")
    ax.set_xticks(x, [f"{r[0]}\n{r[1]}" for r in rows])
    ax.set_ylabel("ms per frame (median of 10)")
    ax.set_title(f"fisheye {cam0.width}x{cam0.height} -> equirect")
    ax.legend()
    fig.tight_layout()
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    fig.savefig(OUT_DIR / "bench_warp.png", dpi=110)
    print(f"\nchart: {OUT_DIR / 'bench_warp.png'}")


if __name__ == "__main__":
    main()
