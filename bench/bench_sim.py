"""Simulator cost per sensor: wall seconds per simulated second, outdoor walk, full resolution.

Each configuration (mcap/raw baseline, mcap/jpeg, db3/raw, bag/raw; both 1920x1200
cameras, both Mid-360s, both IMUs) simulates `--seconds` of the outdoor `walk`
trajectory at scale 1.0; the table gives the median over `--repeats` runs of each
stage's wall time divided by the simulated seconds, and ratios against the
mcap/raw baseline measured in the same run. "other" is the per-run fixed cost
(scene setup, closing the bag, writing the truth folder), shown in seconds.

`--full` (default) then runs the acceptance case once: outdoor, walk, 5.0 s,
scale 1.0, mcap, raw images, and prints its wall time, seconds per simulated
second, bag size and messages per topic. Bags go to a temporary folder that is
deleted afterwards (a 5 s raw full-resolution mcap is about 0.9 GB, zstd).
Writes a stacked bar chart to out/bench/bench_sim.png.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import OUT_DIR

from sensorbox.live.bagwriter import BagFormat
from sensorbox.sim.config import SimConfig
from sensorbox.sim.lidar import SWEEP_PERIOD_NS
from sensorbox.sim.run import SimSummary, simulate

STAGES = ("cameras", "lidars", "imu", "write")
THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")  # echoed: they change the camera cost
FULL_SECONDS = 5.0
WARMUP_SECONDS = 0.1  # fills the per-model ray cache and the lazy imports of each bag writer


@dataclass(frozen=True)
class Case:
    """One benchmark configuration; only the bag format and the image encoding vary."""

    fmt: BagFormat
    image: Literal["raw", "jpeg"]

    @property
    def label(self) -> str:
        return f"{self.fmt} {self.image}"

    def config(self, seconds: float) -> SimConfig:
        return SimConfig(
            scene="outdoor", trajectory="walk", duration_s=seconds, scale=1.0, format=self.fmt,
            image=self.image,
        )  # fmt: skip


CASES = (Case("mcap", "raw"), Case("mcap", "jpeg"), Case("db3", "raw"), Case("bag", "raw"))


@dataclass(frozen=True)
class Row:
    """Median cost of one configuration: per stage and in total, per simulated second."""

    label: str
    per_s: dict[str, float]  # stage -> wall s per simulated s
    other_s: float  # fixed cost per run: setup, bag close, truth folder
    total_per_s: float
    mb_per_s: float
    sim_seconds: float
    runs: int


def run_once(case: Case, seconds: float, tmp: Path, tag: str) -> SimSummary:
    """Simulate one bag into `tmp`, delete it, and return its summary."""
    out = tmp / tag
    summary = simulate(case.config(seconds), out)
    _remove(summary)
    return summary


def _remove(summary: SimSummary) -> None:
    for p in (summary.bag, summary.truth):
        if p.is_dir():
            shutil.rmtree(p)
        elif p.exists():
            p.unlink()


def measure(cases: tuple[Case, ...], seconds: float, repeats: int, tmp: Path) -> list[Row]:
    """Median over `repeats` runs per case, after one short warm-up run each.

    The cases are interleaved (round k runs every case once) so that a slow
    spell of the machine hits every configuration alike and the ratios hold.
    """
    for case in cases:
        run_once(case, WARMUP_SECONDS, tmp, f"warmup_{case.fmt}_{case.image}")
    runs: dict[Case, list[SimSummary]] = {case: [] for case in cases}
    for k in range(repeats):
        for case in cases:
            s = run_once(case, seconds, tmp, f"{case.fmt}_{case.image}_{k}")
            per = ", ".join(f"{n} {s.stage_seconds[n]:.2f}" for n in STAGES)
            print(f"  round {k + 1}/{repeats} {case.label:<10} {s.seconds:6.1f} s  ({per})", flush=True)
            runs[case].append(s)
    return [
        Row(
            case.label,
            {n: statistics.median(r.stage_seconds[n] for r in rs) / seconds for n in STAGES},
            statistics.median(r.seconds - sum(r.stage_seconds.values()) for r in rs),
            statistics.median(r.seconds for r in rs) / seconds,
            statistics.median(r.size_bytes for r in rs) / 1e6 / seconds,
            seconds,
            repeats,
        )
        for case, rs in runs.items()
    ]


def full_run(tmp: Path) -> tuple[Row, SimSummary]:
    """The acceptance case, once, with a progress bar on stderr."""
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    case = Case("mcap", "raw")
    cfg = case.config(FULL_SECONDS)
    columns = (
        TextColumn("full run"), BarColumn(), TextColumn("{task.completed:.1f}/{task.total:.1f} sim s"),
        TimeElapsedColumn(), TimeRemainingColumn(),
    )  # fmt: skip
    last_print = [time.perf_counter()]
    console = Console(stderr=True)

    def progress(done: float) -> None:
        bar.update(task, completed=done)
        if not console.is_terminal and time.perf_counter() - last_print[0] > 20:
            last_print[0] = time.perf_counter()  # piped output: a plain line every ~20 s
            print(f"  full run: {done:.1f}/{FULL_SECONDS:.1f} sim s", flush=True)

    with Progress(*columns, console=console, transient=True) as bar:
        task = bar.add_task("sim", total=FULL_SECONDS)
        summary = simulate(cfg, tmp / "full", progress=progress)
    _remove(summary)
    row = Row(
        f"full {FULL_SECONDS:g} s mcap raw",
        {n: summary.stage_seconds[n] / FULL_SECONDS for n in STAGES},
        summary.seconds - sum(summary.stage_seconds.values()),
        summary.seconds / FULL_SECONDS,
        summary.size_bytes / 1e6 / FULL_SECONDS,
        FULL_SECONDS,
        1,
    )
    return row, summary


def print_table(rows: list[Row], seconds: float, repeats: int) -> None:
    base = rows[0]
    cfg = SimConfig()
    print(
        f"\noutdoor walk, scale 1.0 (2x 1920x1200 cameras @ {cfg.camera_rate_hz:g} Hz, "
        f"2x Mid-360 @ {1e9 / SWEEP_PERIOD_NS:g} Hz, 2x IMU @ {cfg.imu_rate_hz:g} Hz), "
        f"{seconds:g} s simulated, median of {repeats} runs; wall seconds per simulated second\n"
    )
    print("| config      | cameras | lidars |   imu | write | total | x mcap raw | write x mcap raw "
          "| other [s] | bag MB / sim s |")  # fmt: skip
    print("|-------------|---------|--------|-------|-------|-------|------------|------------------"
          "|-----------|----------------|")  # fmt: skip
    for r in rows:
        p = r.per_s
        ratio, write_ratio = r.total_per_s / base.total_per_s, p["write"] / base.per_s["write"]
        print(f"| {r.label:<11} | {p['cameras']:7.2f} | {p['lidars']:6.3f} | {p['imu']:5.3f} | "
              f"{p['write']:5.2f} | {r.total_per_s:5.2f} | {ratio:10.2f} | "
              f"{write_ratio:16.2f} | {r.other_s:9.2f} | {r.mb_per_s:14.1f} |")  # fmt: skip


def print_full(row: Row, summary: SimSummary) -> None:
    print(f"\nfull run (acceptance case): outdoor, walk, {FULL_SECONDS:g} s, scale 1.0, mcap, raw images\n")
    p = row.per_s
    print(f"  total wall time        {summary.seconds:8.1f} s")
    print(f"  per simulated second   {row.total_per_s:8.2f} s  (cameras {p['cameras']:.2f}, "
          f"lidars {p['lidars']:.3f}, imu {p['imu']:.3f}, write {p['write']:.2f}, "
          f"other {row.other_s:.1f} s per run)")  # fmt: skip
    print(f"  bag size               {summary.size_bytes / 1e6:8.1f} MB")
    print("\n| topic                                                 | messages | rate [Hz] |")
    print(f"|{'-' * 55}|{'-' * 10}|{'-' * 11}|")
    for topic, n in summary.counts.items():
        print(f"| {topic:<53} | {n:8d} | {n / FULL_SECONDS:9.1f} |")


def chart(rows: list[Row], seconds: float, repeats: int) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, ax = plt.subplots(figsize=(9, 4.8))
    x = np.arange(len(rows))
    bottom = np.zeros(len(rows))
    parts = [(n, [r.per_s[n] for r in rows]) for n in STAGES]
    parts.append(("other (setup, close, truth) / sim s", [r.other_s / r.sim_seconds for r in rows]))
    for name, values in parts:
        ax.bar(x, values, 0.6, bottom=bottom, label=name)
        bottom += np.asarray(values)
    for xi, total in enumerate(bottom.tolist()):
        ax.text(xi, total, f"{total:.1f}", ha="center", va="bottom")
    ax.set_xticks(x, [r.label.replace(" mcap raw", "\nmcap raw") for r in rows])
    ax.set_ylabel("wall s per simulated s")
    ax.set_title(
        f"sensorbox simulate: outdoor walk, 1920x1200, {os.cpu_count()} cores "
        f"({seconds:g} s runs, median of {repeats})"
    )
    ax.legend(fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    path = OUT_DIR / "bench_sim.png"
    fig.savefig(path, dpi=110)
    return path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--repeats", type=int, default=3, help="runs per configuration (median)")
    ap.add_argument("--seconds", type=float, default=1.0, help="simulated seconds per short run")
    ap.add_argument(
        "--full", action=argparse.BooleanOptionalAction, default=True,
        help=f"also run the {FULL_SECONDS:g} s acceptance case once (--no-full to skip)",
    )  # fmt: skip
    args = ap.parse_args()
    if args.repeats < 1 or not args.seconds > 0:
        ap.error("--repeats must be >= 1 and --seconds > 0")
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    threads = ", ".join(f"{v}={os.environ.get(v, 'unset')}" for v in THREAD_VARS)
    print(f"cores available: {cores}; {threads}", flush=True)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench_sim_") as d:
        tmp = Path(d)
        rows = measure(CASES, args.seconds, args.repeats, tmp)
        full = full_run(tmp) if args.full else None
    print_table(rows, args.seconds, args.repeats)
    if full is not None:
        print_full(*full)
    path = chart(rows + ([full[0]] if full is not None else []), args.seconds, args.repeats)
    print(f"\nbenchmark wall time: {time.perf_counter() - t0:.0f} s")
    print(f"\nchart: {path}")


if __name__ == "__main__":
    main()
