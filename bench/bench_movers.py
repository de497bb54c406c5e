"""Dense GT's movers filter against the simulator's truth: what it removes where nothing moves, and trails.

Three scenes, noise-free, simulated once each (`sensorbox.analysis.dense_study`'s
recordings: the odometry places every sweep): the static room, the outdoor
walk and the walk with movers. Each is scored on `--samples` frames with
dense GT at +-`--window-ms`, the free-space test off and on, at `--scale` x
the reference rig's resolution (1.0: 1920x1200). Per scene and setting:
accumulated points removed as movers (% of all the window's points), GT
density, density with the filter as % of density without it, mover trail
and outliers (GT on the sky included) as % of GT pixels, seconds per sample
(a worker's: the free-space bits looked up, GT rendered) and the stream
pass's free-space test per 1 s block (one process, numba's threads). The
targets: static scenes <= 1 % removed and >= 95 % of the density;
movers: trail <= 0.01 %, outliers <= 0.05 %.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import OUT_DIR, machine_line, markdown_table

from calibration.rig import REFERENCE_RIG, read_rig
from ingest.train.run.sample_job import Geometry
from sensorbox.analysis.dense_study import MS, Method, Recording, evaluate, record
from sensorbox.sim.config import SimConfig
from sensorbox.sim.run import scaled_rig


def scenes(walk_s: float) -> dict[str, SimConfig]:
    """The static room, the outdoor walk and the walk with movers (noise-free, small images)."""
    base = SimConfig(scale=0.125, image="jpeg", range_noise_m=0.0, dust_fraction=0.0, seed=11)
    return {
        "static room": replace(base, scene="indoor", trajectory="static", duration_s=3.0),
        "outdoor walk": replace(base, scene="outdoor", trajectory="walk", duration_s=walk_s),
        "walk with movers": replace(base, scene="outdoor", trajectory="walk", duration_s=walk_s, movers=True),
    }


def free_space_s(rec: Recording) -> float:
    """Seconds per 1 s block the stream pass's free-space test took: the blocks' time with it, less their
    time without it (the same plane fits)."""
    with_test = [p for k, p in rec.planes.items() if k[-1] is not None]
    without = [p for k, p in rec.planes.items() if k[-1] is None]
    if not with_test or not without:
        return float("nan")
    on, off = with_test[0], without[0]
    return (on.seconds - off.seconds) / max(on.blocks_fitted, 1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=3, help="samples per scene")
    ap.add_argument("--walk-s", type=float, default=4.0, help="length of both walks (s)")
    ap.add_argument("--window-ms", type=int, default=500, help="dense GT's +- window")
    ap.add_argument("--scale", type=float, default=0.25, help="scoring resolution x the reference rig's")
    ap.add_argument("--out", type=Path, default=OUT_DIR / "movers")
    args = ap.parse_args()
    print(machine_line())
    geo = Geometry.from_rig(scaled_rig(read_rig(REFERENCE_RIG), args.scale))
    model = geo.rig.upper.model
    size = f"{model.width}x{model.height}"
    print(f"scoring camera: {size}, +-{args.window_ms} ms, {args.samples} samples per scene")
    header = ["scene", "removed", "density off", "density on", "on / off", "trail on", "trail off",
              "outliers on", "outliers off", "s/sample on", "free space s/block"]  # fmt: skip
    table = []
    for scene, cfg in scenes(args.walk_s).items():
        rec = record(scene.replace(" ", "_"), cfg, args.out)
        t0, t1 = int(rec.trajectory.stamps_ns[0]), int(rec.trajectory.stamps_ns[-1])
        margin = args.window_ms * MS + 600 * MS
        stamps = np.linspace(t0 + margin, t1 - margin, args.samples).astype(np.int64).tolist()
        off = evaluate(rec, geo, Method("odometry", args.window_ms), stamps, args.out / "samples")
        on = evaluate(
            rec, geo, Method("odometry + movers filter", args.window_ms), stamps, args.out / "samples"
        )
        row = [scene, f"{100 * on['removed']:.2f} %", f"{100 * off['density']:.2f} %",
               f"{100 * on['density']:.2f} %", f"{100 * on['density'] / max(off['density'], 1e-12):.1f} %",
               f"{100 * on['trail']:.4f} %", f"{100 * off['trail']:.4f} %", f"{100 * on['outliers']:.3f} %",
               f"{100 * off['outliers']:.3f} %", f"{on['s_per_sample']:.1f}",
               f"{free_space_s(rec):.2f}"]  # fmt: skip
        print(" | ".join(row), flush=True)
        table.append(row)
    markdown_table(header, table)


if __name__ == "__main__":
    main()
