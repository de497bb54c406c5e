"""Project and unproject 1M points per camera model; median of 5 runs.

Prints million points per second for SensorBox's vectorised numpy models and,
where OpenCV has the same model, for OpenCV's projectPoints measured in the
same run; for the closed-form models also the ratio of our `project` to a
minimal numpy implementation of the same formula (no NaN filling, no input
checks), timed interleaved with it. Writes a bar chart to
out/bench/bench_models.png.
"""

from __future__ import annotations

import math
import statistics
import sys
import time
from collections.abc import Callable

import cv2
import numpy as np

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parent))
from _common import OUT_DIR, machine_line, median_seconds

from calibration import (
    CameraModel,
    DoubleSphere,
    ExtendedUnified,
    Fov,
    KannalaBrandt,
    Omni,
    Pinhole,
    RadTan,
    Unified,
)

N = 1_000_000
RUNS = 5


def rays(n: int, max_deg: float) -> np.ndarray:
    rng = np.random.default_rng(0)
    cos_t = rng.uniform(math.cos(math.radians(max_deg)), 1.0, n)
    phi = rng.uniform(-math.pi, math.pi, n)
    s = np.sqrt(1 - cos_t**2)
    return np.stack([s * np.cos(phi), s * np.sin(phi), cos_t], axis=-1) * rng.uniform(0.5, 20, (n, 1))


def opencv_projector(model: CameraModel, pts: np.ndarray):  # type: ignore[no-untyped-def]
    z = np.zeros(3)
    obj = pts.reshape(-1, 1, 3)
    if isinstance(model, KannalaBrandt):
        K = np.array([[model.fx, 0, model.cx], [0, model.fy, model.cy], [0, 0, 1.0]])
        D = np.array([model.k1, model.k2, model.k3, model.k4])
        return lambda: cv2.fisheye.projectPoints(obj, z, z, K, D)
    if isinstance(model, Pinhole) and isinstance(model.distortion, RadTan):
        d = model.distortion
        D = np.array([d.k1, d.k2, d.p1, d.p2])
        return lambda: cv2.projectPoints(pts, z, z, model.K, D)
    if isinstance(model, Omni):
        K = np.array([[model.fx, 0, model.cx], [0, model.fy, model.cy], [0, 0, 1.0]])
        d = model.distortion or RadTan(0, 0, 0, 0)
        D = np.array([[d.k1, d.k2, d.p1, d.p2]])
        return lambda: cv2.omnidir.projectPoints(pts.reshape(1, -1, 3), z, z, K, model.xi, D)
    return None


def minimal_projector(model: CameraModel, pts: np.ndarray):  # type: ignore[no-untyped-def]
    """The model's projection formula in plain numpy, as a user would write it (None: not closed-form)."""
    x, y, z = pts[:, 0], pts[:, 1], pts[:, 2]

    def affine(mx: np.ndarray, my: np.ndarray) -> np.ndarray:
        return np.stack([model.fx * mx + model.cx, model.fy * my + model.cy], axis=-1)  # type: ignore[attr-defined]

    if isinstance(model, DoubleSphere):
        a, xi = model.alpha, model.xi

        def ds() -> tuple[np.ndarray, np.ndarray]:
            d1 = np.sqrt(x * x + y * y + z * z)
            k = xi * d1 + z
            n = a * np.sqrt(x * x + y * y + k * k) + (1 - a) * k
            return affine(x / n, y / n), z > -model.w2 * d1

        return ds
    if isinstance(model, ExtendedUnified | Unified):
        a, b = model.alpha, getattr(model, "beta", 1.0)
        w1 = a / (1 - a) if a > 0.5 else (1 - a) / a

        def eucm() -> tuple[np.ndarray, np.ndarray]:
            d = np.sqrt(b * (x * x + y * y) + z * z)
            n = a * d + (1 - a) * z
            return affine(x / n, y / n), z > -w1 * d

        return eucm
    if type(model) is Pinhole and model.distortion is None:
        return lambda: (affine(x / z, y / z), z > 0)
    return None


def interleaved_medians(fns: list[Callable[[], object]], runs: int) -> list[float]:
    """Median seconds of each function, the functions called in turn each round (shared load)."""
    for fn in fns:
        fn()
    times: list[list[float]] = [[] for _ in fns]
    for _ in range(runs):
        for k, fn in enumerate(fns):
            t0 = time.perf_counter()
            fn()
            times[k].append(time.perf_counter() - t0)
    return [statistics.median(t) for t in times]


def main() -> None:
    models: list[tuple[str, CameraModel, float]] = [
        ("DoubleSphere", DoubleSphere(500.2, 500.1, 962.4, 597.9, -0.18, 0.59, 1920, 1200), 110),
        ("ExtendedUnified", ExtendedUnified(380.0, 380.0, 640.0, 512.0, 0.63, 1.04, 1280, 1024), 100),
        ("Unified", Unified(400.0, 400.0, 640.0, 512.0, 0.6, 1280, 1024), 100),
        (
            "KannalaBrandt (iter.)",
            KannalaBrandt(380.0, 380.0, 640.0, 512.0, 0.02, -0.01, 0.003, -5e-4, 1280, 1024),
            100,
        ),
        ("Pinhole", Pinhole(500.0, 500.0, 320.0, 240.0, 640, 480), 60),
        ("Pinhole+fov", Pinhole(500.0, 500.0, 320.0, 240.0, 640, 480, Fov(0.9)), 60),
        (
            "Pinhole+radtan (iter.)",
            Pinhole(500.0, 500.0, 320.0, 240.0, 640, 480, RadTan(-0.28, 0.07, 1e-4, -2e-4)),
            50,
        ),
        (
            "Omni+radtan (iter.)",
            Omni(0.9, 700.0, 700.0, 640.0, 512.0, 1280, 1024, RadTan(-0.05, 0.01, 3e-4, -1e-4)),
            90,
        ),
    ]
    rows = []
    minimal_ratio: dict[str, float] = {}
    for name, model, max_deg in models:
        pts = rays(N, max_deg)
        uv, _ = model.project(pts)
        t_proj = median_seconds(lambda m=model, p=pts: m.project(p), RUNS)  # type: ignore[misc]
        t_unproj = median_seconds(lambda m=model, q=uv: m.unproject(q), RUNS)  # type: ignore[misc]
        cv = opencv_projector(model, pts)
        t_cv = median_seconds(cv, RUNS) if cv is not None else None
        rows.append((name, N / t_proj / 1e6, N / t_unproj / 1e6, None if t_cv is None else N / t_cv / 1e6))
        minimal = minimal_projector(model, pts)
        if minimal is not None:
            t_ours, t_min = interleaved_medians([lambda m=model, p=pts: m.project(p), minimal], 3 * RUNS)  # type: ignore[misc]
            minimal_ratio[name] = t_ours / t_min

    print(f"\n{machine_line()}")
    print(f"{N:,} points per call, median of {RUNS} runs (million points / second)\n")
    header = ("model", "project", "unproject", "OpenCV project", "ours/OpenCV", "time ours/minimal")
    print("| {:<24} | {:>8} | {:>9} | {:>14} | {:>11} | {:>17} |".format(*header))
    print(f"|{'-' * 26}|{'-' * 10}|{'-' * 11}|{'-' * 16}|{'-' * 13}|{'-' * 19}|")
    for name, p, u, c in rows:
        cv_txt = f"{c:14.1f}" if c is not None else f"{'-':>14}"
        ratio = f"{p / c:11.2f}" if c is not None else f"{'-':>11}"
        mr = f"{minimal_ratio[name]:17.2f}" if name in minimal_ratio else f"{'-':>17}"
        print(f"| {name:<24} | {p:8.1f} | {u:9.1f} | {cv_txt} | {ratio} | {mr} |")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10, 4.5))
    y = np.arange(len(rows))
    ax.barh(y - 0.27, [r[1] for r in rows], 0.27, label="project")
    ax.barh(y, [r[2] for r in rows], 0.27, label="unproject")
    ax.barh(y + 0.27, [r[3] or 0 for r in rows], 0.27, label="OpenCV project")
    ax.set_yticks(y, [r[0] for r in rows])
    ax.invert_yaxis()
    ax.set_xlabel("million points / second (1M points, median of 5)")
    ax.legend()
    ax.grid(axis="x", alpha=0.3)
    fig.tight_layout()
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    fig.savefig(OUT_DIR / "bench_models.png", dpi=110)
    print(f"\nchart: {OUT_DIR / 'bench_models.png'}")


if __name__ == "__main__":
    main()
