"""Shared helpers for the bench scripts: timing and output folder."""

from __future__ import annotations

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
