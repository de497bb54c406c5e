"""The PyTorch renderer on a GPU (or the CPU): per-view milliseconds on a synthetic 20 M-point scan.

The scan is `ingest.raster.synthetic.room_scan` (numpy only: a box room with
a box in it, analytic ranges), sorted into its level-of-detail index, then
2048x1152 fisheye views (the reference rig's Double Sphere at 120 degrees,
as bench_render.py) rendered with `RenderParams.backend` "cuda" when torch
sees a GPU, else "torch" on the CPU: median of --runs after --warmup views
(the first copies the scan to the device). The compiled CPU renderer draws
the same view once for comparison (same holes, largest range difference).

Needs numpy, torch, numba, OpenCV, PyYAML and SciPy (what `calibration` and
`ingest.raster` import); never Open3D: the script checks that it was not
imported. Writes nothing.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine_line

from calibration import CameraModel, DoubleSphere, read_rig
from calibration.virtual import R_up_cam, partner_pose, virtual_ds
from ingest.raster.lod import build_index
from ingest.raster.synthetic import room_scan
from ingest.raster.view import Rendering, pixel_geometry, render_view
from ingest.raster.visibility import RenderParams

RIG = Path(__file__).resolve().parents[1] / "calibration" / "sensorbox.yaml"


def timed_views(
    render: Callable[[CameraModel, np.ndarray], Rendering], views: list[tuple[CameraModel, np.ndarray]],
    runs: int, warmup: int,
) -> list[float]:  # fmt: skip
    """Seconds per view over ``runs`` views after ``warmup`` (views taken round robin)."""
    times = []
    for k in range(warmup + runs):
        model, T = views[k % len(views)]
        t0 = time.perf_counter()
        render(model, T)
        if k >= warmup:
            times.append(time.perf_counter() - t0)
    return times


def compare(a: Rendering, b: Rendering) -> str:
    same = np.array_equal(a.range_m > 0, b.range_m > 0) and np.array_equal(a.surface, b.surface)
    diff = float(np.abs(a.range_m - b.range_m).max()) * 1e3
    return f"same holes and valid pixels as the compiled CPU renderer: {same}, max |range diff| {diff:.4f} mm"


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--points", type=float, default=20e6, help="points of the synthetic scan")
    p.add_argument("--size", default="2048x1152")
    p.add_argument("--fov", type=float, default=120.0)
    p.add_argument("--runs", type=int, default=10)
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument("--device", choices=("auto", "cuda", "cpu"), default="auto")
    args = p.parse_args(argv)
    cuda = torch.cuda.is_available() if args.device == "auto" else args.device == "cuda"
    backend = "cuda" if cuda else "torch"
    w, h = (int(v) for v in args.size.split("x"))
    t0 = time.perf_counter()
    scan = room_scan(int(args.points), seed=0, label_wall=True, glass=True)
    t_scan = time.perf_counter() - t0
    t0 = time.perf_counter()
    index = build_index(scan)
    t_index = time.perf_counter() - t0
    n = len(scan.xyz)
    del scan
    ref = read_rig(RIG).camera("cam0").model
    assert isinstance(ref, DoubleSphere)
    T = index.T_world_scan.copy()
    T[:3, :3] = R_up_cam(0.0)
    views: list[tuple[CameraModel, np.ndarray]] = [
        (virtual_ds(ref, args.fov, w, h), partner_pose(T, "DOWN", b)) for b in (0.0, 0.1, 0.2, 0.3)
    ]
    for m, _ in views:
        pixel_geometry(m)
    params = RenderParams(backend=backend)  # type: ignore[arg-type]
    times = timed_views(lambda m, Tc: render_view([index], m, Tc, params), views, args.runs, args.warmup)
    gpu = torch.cuda.get_device_name() if cuda else f"CPU, {torch.get_num_threads()} torch threads"
    rend = render_view([index], views[0][0], views[0][1], params)
    ref_rend = render_view([index], views[0][0], views[0][1], replace(params, backend="numba"))
    print(f"\n{machine_line()}; torch {torch.__version__}, device: {gpu}")
    print(f"\nsynthetic scan {n / 1e6:.1f} M points (built in {t_scan:.1f} s, indexed in {t_index:.1f} s); "
          f"{w}x{h} fisheye, nominal FOV {args.fov} deg, backend {backend}\n")  # fmt: skip
    print("| measure | value |")
    print("|---|---|")
    med, st = 1e3 * statistics.median(times), rend.stats
    print(f"| per view, median of {args.runs} after {args.warmup} warm-up | {med:.1f} ms |")
    print(f"| per view, min / max | {1e3 * min(times):.1f} / {1e3 * max(times):.1f} ms |")
    touched, in_image = st["points_touched"] / 1e6, st["points_in_image"] / 1e6
    print(f"| points touched / in image | {touched:.2f} M / {in_image:.2f} M |")
    print(f"| valid / hole pixels | {st['valid_px']} / {st['hole_px']} |")
    print(f"\n{compare(ref_rend, rend)}")
    if "open3d" in sys.modules:
        raise SystemExit("open3d was imported on the GPU path")
    print("open3d imported: no")


if __name__ == "__main__":
    main()
