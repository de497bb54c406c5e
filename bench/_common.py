"""Shared helpers for the bench scripts: timing and output folder."""

from __future__ import annotations

import contextlib
import resource
import statistics
import time
from collections.abc import Callable
from pathlib import Path

OUT_DIR = Path(__file__).resolve().parents[1] / "out" / "bench"


def median_seconds(fn: Callable[[], object], runs: int, warmup: int = 2) -> float:
    """Median wall time of ``fn`` over ``runs`` calls after ``warmup`` calls."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def cpu_s() -> tuple[float, float]:
    """(this process, its reaped children): user + system CPU seconds so far."""
    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime, kids.ru_utime + kids.ru_stime


def machine_line() -> str:
    """The machine a figure came from: cores, CPU model, load, and a fixed numpy workload's time.

    The reference (sorting 4 M seeded float64, median of 3) lets figures from
    shared machines of differing speed and load be compared.
    """
    import os
    import platform

    import numpy as np

    model = platform.processor() or platform.machine()
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    data = np.random.default_rng(0).random(4_000_000)
    ref_ms = median_seconds(lambda: np.sort(data), 3, warmup=1) * 1e3
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return (f"machine: {os.cpu_count()} cores, {model}, load {load:.1f}, "
            f"reference sort 4M float64 {ref_ms:.0f} ms")  # fmt: skip


def markdown_table(header: list[str], rows: list[list[str]]) -> None:
    """Print a markdown table: first column left-aligned, the others right-aligned."""
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(header)]
    print("| " + " | ".join(h.ljust(w) for h, w in zip(header, widths, strict=True)) + " |")
    print("|" + "|".join("-" * (w + 2) for w in widths) + "|")
    for r in rows:
        cells = [c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths, strict=True))]
        print("| " + " | ".join(cells) + " |")
