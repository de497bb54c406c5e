"""The PyTorch renderer on a GPU (or the CPU): per-view milliseconds on a synthetic 20 M-point scan.

The scan is `ingest.raster.synthetic.room_scan` (numpy only: a box room with
a box in it, analytic ranges), sorted into its level-of-detail index, then
2048x1152 fisheye views (the reference rig's Double Sphere at 120 degrees,
as bench_render.py) rendered with `RenderParams.backend` "cuda" when torch
sees a GPU, else "torch" on the CPU: median of --runs after --warmup views
(the first copies the scan to the device). The compiled CPU renderer draws
the same view once for comparison (same holes, largest range difference).

`--check` renders instead a matrix of views with both backends and compares
them (masks, valid pixels, colours, counts, ranges within 0.1 mm): scans of
0.1 and 1 M points, sparse enough at the larger sizes that many pixels take
the raw fallback; Double Sphere fisheyes of 120 and 195 degrees at two
sizes, a panorama, a panorama crop and a pinhole, with and without a pixel
mask. It exits 1 if any view differs: what to run first on a new GPU.

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
from _common import machine_line, markdown_table

from calibration import CameraModel, DoubleSphere, read_rig
from calibration.spherical import Equirectangular, pinhole_for_fov
from calibration.virtual import R_up_cam, partner_pose, virtual_ds
from ingest.raster.lod import build_index
from ingest.raster.params import RenderParams
from ingest.raster.synthetic import room_scan
from ingest.raster.view import Rendering, pixel_geometry, render_view

RIG = Path(__file__).resolve().parents[1] / "calibration" / "sensorbox.yaml"


def device_line(cuda: bool) -> str:
    """torch's version and the device it renders on."""
    gpu = torch.cuda.get_device_name() if cuda else f"CPU, {torch.get_num_threads()} torch threads"
    return f"torch {torch.__version__}, device: {gpu}"


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


def same_rendering(a: Rendering, b: Rendering) -> tuple[bool, float]:
    """Whether two renderings agree (rays, surface, masks, clipping, valid pixels, colours, counts) and
    their largest range difference in mm; they agree only with that at most 0.1 mm."""
    diff_mm = float(np.abs(a.range_m - b.range_m).max()) * 1e3
    same = (
        all(np.array_equal(getattr(a, k), getattr(b, k)) for k in ("rays", "surface", "masked", "clipped"))
        and np.array_equal(a.range_m > 0, b.range_m > 0)
        and np.array_equal(a.bgr, b.bgr)
        and a.stats == b.stats
    )
    return same and diff_mm <= 0.1, diff_mm


def check_views(ref: DoubleSphere) -> list[tuple[str, CameraModel, np.ndarray | None]]:
    """(label, model, pixel mask or None) of `--check`'s views."""
    views: list[tuple[str, CameraModel, np.ndarray | None]] = []
    models: list[tuple[str, CameraModel]] = [
        *((f"DS {fov:.0f} deg {w}x{h}", virtual_ds(ref, fov, w, h))
          for fov in (120.0, 195.0) for w, h in ((1024, 576), (2048, 1152))),
        ("panorama 1024", Equirectangular(1024)),
        ("panorama crop", Equirectangular(2048).crop(300, 900, 200, 1800)),
        ("pinhole 60 deg 1920x1080", pinhole_for_fov(np.radians(60.0), 1920, 1080)),
    ]  # fmt: skip
    for label, model in models:
        mask = np.zeros((model.height, model.width), bool)
        mask[model.height // 4 : 3 * model.height // 4, model.width // 5 : 4 * model.width // 5] = True
        views += [(label, model, None), (f"{label}, pixel mask", model, mask)]
    return views


def check(backend: str, ref: DoubleSphere) -> int:
    """`--check`: every view with `backend` and the compiled renderer; the number that differ."""
    params = RenderParams(backend=backend)  # type: ignore[arg-type]
    rows, differ = [], 0
    for points in (1e5, 1e6):
        index = build_index(room_scan(int(points), seed=4, label_wall=True, glass=True))
        T = index.T_world_scan.copy()
        T[:3, :3] = R_up_cam(0.0)
        T_cam = partner_pose(T, "DOWN", 0.2)
        for label, model, mask in check_views(ref):
            a = render_view([index], model, T_cam, replace(params, backend="numba"), pixel_mask=mask)
            b = render_view([index], model, T_cam, params, pixel_mask=mask)
            ok, diff_mm = same_rendering(a, b)
            differ += not ok
            rows.append([f"{points / 1e6:.1f} M", label, str(a.stats["raw_px"]), str(a.stats["valid_px"]),
                         f"{diff_mm:.4f}", "yes" if ok else "NO"])  # fmt: skip
    markdown_table(["scan", "view", "raw-fallback px", "valid px", "max range diff mm", "same"], rows)
    return differ


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--points", type=float, default=20e6, help="points of the synthetic scan")
    p.add_argument("--size", default="2048x1152")
    p.add_argument("--fov", type=float, default=120.0)
    p.add_argument("--runs", type=int, default=10)
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument("--device", choices=("auto", "cuda", "cpu"), default="auto")
    p.add_argument("--check", action="store_true", help="compare both backends on a matrix of views instead")
    args = p.parse_args(argv)
    cuda = torch.cuda.is_available() if args.device == "auto" else args.device == "cuda"
    backend = "cuda" if cuda else "torch"
    ref = read_rig(RIG).camera("cam0").model
    assert isinstance(ref, DoubleSphere)
    if args.check:
        print(f"{machine_line()}; {device_line(cuda)}; backend {backend} against numba\n")
        differ = check(backend, ref)
        print(f"\n{differ} view(s) differ")
        raise SystemExit(1 if differ else 0)
    w, h = (int(v) for v in args.size.split("x"))
    t0 = time.perf_counter()
    scan = room_scan(int(args.points), seed=0, label_wall=True, glass=True)
    t_scan = time.perf_counter() - t0
    t0 = time.perf_counter()
    index = build_index(scan)
    t_index = time.perf_counter() - t0
    n = len(scan.xyz)
    del scan
    T = index.T_world_scan.copy()
    T[:3, :3] = R_up_cam(0.0)
    views: list[tuple[CameraModel, np.ndarray]] = [
        (virtual_ds(ref, args.fov, w, h), partner_pose(T, "DOWN", b)) for b in (0.0, 0.1, 0.2, 0.3)
    ]
    for m, _ in views:
        pixel_geometry(m)
    params = RenderParams(backend=backend)  # type: ignore[arg-type]
    times = timed_views(lambda m, Tc: render_view([index], m, Tc, params), views, args.runs, args.warmup)
    rend = render_view([index], views[0][0], views[0][1], params)
    ref_rend = render_view([index], views[0][0], views[0][1], replace(params, backend="numba"))
    print(f"\n{machine_line()}; {device_line(cuda)}")
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
    same, diff_mm = same_rendering(ref_rend, rend)
    print(f"\nthe compiled CPU renderer's image (masks, colours, counts, ranges): {same}, "
          f"max |range diff| {diff_mm:.4f} mm")  # fmt: skip
    if "open3d" in sys.modules:
        raise SystemExit("open3d was imported on the GPU path")
    print("open3d imported: no")


if __name__ == "__main__":
    main()
