"""Dense ingest end to end at full resolution: samples/s with 1 and 2 workers, stage times, GT scores.

The recording is a simulated 1920x1200 outdoor walk (noise-free, JPEG
images; simulated once into out/bench/dense_speed/, about 10 minutes for
4 s, or pass --bag with a recording that has its `<bag>.truth` beside it).
Each run is `ingest(..., gt="dense")` from a cold start: the trajectory pass,
then every `--every`-th frame pair as a sample (default every one, as
`sensorbox ingest` runs; the trajectory pass and the plane blocks are fixed
costs per second of data, so fewer samples share them). Runs with 1 and 2 workers
alternate (`--runs` rounds) and the table gives each one's median; the
GT of the last run is scored against the simulator's exact truth. CPU
seconds per sample are the main process's (start-up, trajectory pass, bag
reading) and its reaped workers' over the whole run. numpy's BLAS runs on
one thread, as under the `sensorbox` command. The
targets: >= 2 samples/s on 2 cores, trajectory pass included, and
the trajectory alone faster than real time on one core.
"""

from __future__ import annotations

import os

# as the `sensorbox` command runs (sensorbox/cli/__init__.py): numpy's BLAS on one thread, set before
# numpy is imported
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import shutil
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import OUT_DIR, cpu_s, machine_line

from ingest.train.run.pipeline import ingest
from ingest.train.run.settings import IngestConfig
from ingest.train.run.summary import IngestSummary
from sensorbox.sim.config import SimConfig
from sensorbox.sim.run import simulate
from sensorbox.sim.score import score_dataset
from sensorbox.sim.truth import Truth

STAGES = ("clouds", "ground_truth", "images", "write")


def recording(root: Path, duration_s: float) -> Path:
    """The full-resolution walk, simulated once into `root`."""
    bag = root / f"walk{duration_s:g}s"
    if (bag / "metadata.yaml").exists():
        return bag
    shutil.rmtree(bag, ignore_errors=True)
    print(f"simulating a {duration_s:g} s 1920x1200 walk into {bag} (once) ...", flush=True)
    cfg = SimConfig(
        scene="outdoor", trajectory="walk", duration_s=duration_s, image="jpeg", range_noise_m=0.0
    )
    out: Path = simulate(cfg, bag).bag
    return out


Cpu = tuple[float, float]  # (main process, workers) CPU seconds


def run_once(bag: Path, out: Path, workers: int, every: int) -> tuple[float, Cpu, IngestSummary]:
    """Wall seconds, (main, workers) CPU seconds and the summary of one ingest."""
    shutil.rmtree(out, ignore_errors=True)
    rig = Truth.load(bag).path / "rig.yaml"
    cpu0 = cpu_s()
    t0 = time.perf_counter()
    summary = ingest([bag], IngestConfig(rig=rig, out=out, workers=workers, every=every, gt="dense"))
    wall = time.perf_counter() - t0
    cpu1 = cpu_s()
    return wall, (cpu1[0] - cpu0[0], cpu1[1] - cpu0[1]), summary


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bag", type=Path, default=None, help="a recording with <bag>.truth beside it")
    ap.add_argument("--duration", type=float, default=4.0, help="seconds of walk to simulate")
    ap.add_argument("--every", type=int, default=1, help="every n-th frame pair is a sample (ingest: 1)")
    ap.add_argument("--runs", type=int, default=2, help="rounds of (1 worker, 2 workers)")
    ap.add_argument("--out", type=Path, default=OUT_DIR / "dense_speed")
    args = ap.parse_args()
    bag = args.bag or recording(args.out, args.duration)
    print(machine_line(), flush=True)
    walls: dict[int, list[float]] = {1: [], 2: []}
    cpus: dict[int, list[Cpu]] = {1: [], 2: []}
    summaries: dict[int, list[IngestSummary]] = {1: [], 2: []}
    for _ in range(args.runs):
        for workers in (1, 2):
            wall, cpu, summary = run_once(bag, args.out / f"train_w{workers}", workers, args.every)
            walls[workers].append(wall)
            cpus[workers].append(cpu)
            summaries[workers].append(summary)
            print(f"  {workers} worker(s): {summary.written} samples in {wall:.1f} s, CPU s main {cpu[0]:.1f}"
                  f" workers {cpu[1]:.1f}", flush=True)  # fmt: skip
    span_s = summaries[1][0].trajectory.span_s if summaries[1][0].trajectory else float("nan")
    print(f"\n{bag.name}: {span_s:.1f} s of data, every {args.every}th frame pair, median of {args.runs}\n")
    head = ("workers", "samples", "wall s", "trajectory s", "s per s of data",
            "CPU s per sample (main + workers)", "samples/s", "target")  # fmt: skip
    print("| " + " | ".join(head) + " |")
    print("|" + "|".join("---" for _ in head) + "|")
    for workers in (1, 2):
        wall = statistics.median(walls[workers])
        traj_s = statistics.median(s.trajectory.seconds for s in summaries[workers] if s.trajectory)
        n = summaries[workers][-1].written
        target = ">= 2 (NOT met)" if n / wall < 2 else ">= 2 (met)"
        main_s, workers_s = (statistics.median(c[i] for c in cpus[workers]) / max(n, 1) for i in (0, 1))
        cpu_text = f"{main_s + workers_s:.2f} ({main_s:.2f} + {workers_s:.2f})"
        print(f"| {workers} | {n} | {wall:.1f} | {traj_s:.1f} | {traj_s / span_s:.2f} | {cpu_text} | "
              f"{n / wall:.2f} | {target if workers == 2 else ''} |")  # fmt: skip
    print(f"\n2 workers / 1 worker: x{statistics.median(walls[1]) / statistics.median(walls[2]):.2f}")
    last = summaries[1][-1]
    print("\nper sample in one worker (median ms): " + ", ".join(
        f"{k} {np.median(last.stage_ms[k]):.0f}" for k in STAGES if k in last.stage_ms
    ))  # fmt: skip
    scores = score_dataset(args.out / "train_w2", Truth.load(bag))
    print(
        f"GT vs truth ({len(scores)} samples, medians):"
        f" density {np.median(summaries[2][-1].density) * 100:.1f} %,"
        f" range {np.median([s.depth_median_abs_m for s in scores]) * 1e3:.2f} mm, outliers"
        f" {np.median([s.depth_outlier_rate for s in scores]) * 100:.3f} %, disparity"
        f" {np.median([s.disp_median_abs_px for s in scores]):.4f} px, > 1 px"
        f" {np.median([s.disp_over_1px_rate for s in scores]) * 100:.3f} %"
    )
    chart(last, args.out.parent / "dense_speed.png")


def chart(summary: IngestSummary, path: Path) -> None:
    """Per-sample stage times of one worker as one stacked bar (where a dense sample's time goes)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 1.8))
    left = 0.0
    for k in STAGES:
        ms = float(np.median(summary.stage_ms.get(k, [0.0])))
        ax.barh([0], [ms], left=left, label=f"{k} {ms:.0f} ms")
        left += ms
    ax.set_yticks([])
    ax.set_xlabel("ms per sample, one worker (median)")
    ax.legend(ncol=4, fontsize=7, loc="upper center", bbox_to_anchor=(0.5, 1.45))
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"chart: {path}")


if __name__ == "__main__":
    main()
