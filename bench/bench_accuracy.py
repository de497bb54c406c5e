"""Ground-truth accuracy of `sensorbox ingest` against the simulator's exact truth (full resolution).

Cases: noise-free static indoor; noise-free outdoor walk with motion compensation
on, and off for contrast; static outdoor with 2 cm range noise. Prints one row
per case (pixel-weighted over its samples) and writes out/bench/bench_accuracy.png.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from ingest.train.run.pipeline import ingest
from ingest.train.run.sample_job import SampleParams
from ingest.train.run.settings import IngestConfig
from sensorbox.sim.config import SimConfig
from sensorbox.sim.run import simulate
from sensorbox.sim.score import SampleScore, score_dataset
from sensorbox.sim.truth import Truth

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import OUT_DIR

STATIC_INDOOR = SimConfig(scene="indoor", duration_s=0.3, image="jpeg", range_noise_m=0.0, seed=1)
WALK_OUTDOOR = SimConfig(
    scene="outdoor", trajectory="walk", duration_s=0.3, image="jpeg", range_noise_m=0.0, seed=2
)
NOISY_OUTDOOR = SimConfig(scene="outdoor", duration_s=0.3, image="jpeg", range_noise_m=0.02, seed=4)
CASES: list[tuple[str, SimConfig, SampleParams]] = [
    ("static indoor, exact", STATIC_INDOOR, SampleParams()),
    ("walk outdoor, exact, compensation on", WALK_OUTDOOR, SampleParams()),
    ("walk outdoor, exact, compensation off", WALK_OUTDOOR, SampleParams(min_motion_px=1e9)),
    ("static outdoor, 2 cm noise", NOISY_OUTDOOR, SampleParams()),
]


def _weighted(scores: list[SampleScore], value: str, weight: str) -> float:
    w = np.array([getattr(s, weight) for s in scores], float)
    v = np.array([getattr(s, value) for s in scores], float)
    return float((v * w).sum() / max(w.sum(), 1.0))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--scale", type=float, default=1.0, help="image scale of the simulated rig")
    args = parser.parse_args()
    rows: list[tuple[str, int, float, float, float, float, float, float, float]] = []
    with tempfile.TemporaryDirectory() as tmp:
        bags: dict[str, Path] = {}
        for name, sim, params in CASES:
            key = repr((sim.scene, sim.trajectory, sim.range_noise_m, sim.seed))
            if key not in bags:
                bags[key] = simulate(
                    SimConfig(**{**sim.__dict__, "scale": args.scale}), Path(tmp) / f"bag{len(bags)}"
                ).bag
            bag = bags[key]
            out = Path(tmp) / f"ds{len(rows)}"
            ingest(
                [bag], IngestConfig(rig=Truth.load(bag).path / "rig.yaml", out=out, workers=2, sample=params)
            )
            scores = score_dataset(out, Truth.load(bag))
            rows.append((
                name, len(scores),
                float(np.median([s.depth_median_abs_m for s in scores])) * 1e3,
                _weighted(scores, "depth_outlier_rate", "depth_pixels") * 100,
                _weighted(scores, "depth_edge_share", "depth_pixels") * 100,
                _weighted(scores, "depth_edge_outlier_rate", "depth_pixels") * 100,
                float(np.median([s.depth_bias_m for s in scores])) * 1e3,
                float(np.median([s.disp_median_abs_px for s in scores])),
                _weighted(scores, "disp_over_1px_rate", "disp_pixels") * 100,
            ))  # fmt: skip
    head = (
        "| case | samples | depth median abs mm | outliers % | edge-band share % | outliers in band % "
        "| bias mm | disp median abs px | disp >1 px % |"
    )
    print(f"GT accuracy vs simulator truth, image scale {args.scale}")
    print("(targets: median <= 2 mm, outliers <= 0.5 %, disp median <= 0.05 px, >1 px <= 0.5 %;")
    print(" 2 cm noise: median <= 15 mm)\n")
    print(head)
    print("|" + "---|" * 9)
    for r in rows:
        cells = (str(r[1]), f"{r[2]:.2f}", f"{r[3]:.2f}", f"{r[4]:.1f}", f"{r[5]:.2f}", f"{r[6]:+.2f}")
        print(f"| {r[0]} | " + " | ".join(cells) + f" | {r[7]:.3f} | {r[8]:.2f} |")
    fig, ax = plt.subplots(1, 2, figsize=(12, 4), constrained_layout=True)
    names = [r[0] for r in rows]
    ax[0].barh(names, [r[2] for r in rows])
    ax[0].axvline(2.0, color="k", ls="--", label="target (exact cases)")
    ax[0].set_xscale("log")
    ax[0].set_xlabel("median |depth error| [mm]")
    ax[0].legend()
    ax[1].barh(names, [r[3] for r in rows], label="all GT pixels")
    ax[1].barh(names, [r[5] for r in rows], alpha=0.5, label="3 px edge band")
    ax[1].axvline(0.5, color="k", ls="--")
    ax[1].set_xlabel("outliers: |e| > max(5 cm, 3 %) [%]")
    ax[1].set_yticks([])
    ax[1].legend()
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    path = OUT_DIR / "bench_accuracy.png"
    fig.savefig(path, dpi=100)
    print(f"\nchart: {path}")


if __name__ == "__main__":
    main()
