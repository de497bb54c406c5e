"""Benchmark views from dense scans: speed on a 20M-point scan, and accuracy against the simulator's truth.

Speed (the acceptance of `sensorbox render-benchmark`): a simulated static
terrestrial scan of the indoor scene with about 20 M points (cached as PLY
under out/bench/), loaded, sorted into its level-of-detail index, then one
2048x1152 fisheye (RGB + range) rendered per view by the numpy reference
recipe and by the compiled kernels (`RenderParams.backend`), and by the naive
render that projects every point of the scan (no culling, no level of
detail): the three taken in turn, median of 3 runs each, wall and CPU
seconds, and whether both backends give the same holes and ranges. Also:
views per second over a set of views with 1 and 2 forked workers, each
backend, and the peak resident memory after each phase. Run it on an idle
machine: it uses the 2 cores it is given (the compiled kernels run on numba
threads, one per core; forked workers share the cores).

Accuracy (test scale, 256x160): rendered range vs the mesh's exact range per
pixel (median off depth edges), background leaking through foreground, holes
with the central scan alone and with the bundle of three, with and without
1.5 mm scanner noise; and the disparity GT against OpenCV's SGBM (bad-3).

Writes out/bench/bench_render.png (or --out).
"""

from __future__ import annotations

import argparse
import multiprocessing
import resource
import statistics
import sys
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from functools import partial
from pathlib import Path
from typing import Any

import cv2
import numba
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import OUT_DIR, machine_line

from calibration import DoubleSphere, read_rig
from calibration.stereo import rotate_for_stereo, unrotate_from_stereo
from calibration.virtual import R_up_cam, partner_pose, virtual_ds
from ingest.dataset.layout import DISP_SCALE, read_png_u16
from ingest.eval.metrics import score_range
from ingest.raster.lod import ScanIndex, build_index
from ingest.raster.params import RenderParams
from ingest.raster.scan import Scan
from ingest.raster.view import Rendering, pixel_geometry, render_view
from ingest.render.benchmark import run_benchmark
from ingest.render.plan import BenchmarkConfig
from ingest.render.scans import read_scans
from ingest.runtime.executor import share_cores
from sensorbox.sim.appearance import Texture
from sensorbox.sim.scenes import build_scene
from sensorbox.sim.tls import TlsParams, bundle_poses, pose_at, simulate_scan, true_range, write_site

RIG = Path(__file__).resolve().parents[1] / "calibration" / "sensorbox.yaml"
CENTRE = [-2.0, 0.0, 1.4]
_VIEWS: list[tuple[Any, np.ndarray]] = []
_INDEX: list[ScanIndex] = []
_PARAMS: list[RenderParams] = [RenderParams()]
NUMPY = RenderParams(backend="numpy")
COMPILED = RenderParams(backend="numba")


def reference() -> DoubleSphere:
    ref = read_rig(RIG).camera("cam0").model
    assert isinstance(ref, DoubleSphere)
    return ref


def gray(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    assert img is not None, path
    return np.asarray(img)


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far (MB; Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def site_for(points: float, out: Path) -> Path:
    """A cached single-scan site of about ``points`` points (simulated once)."""
    n_el_per_deg = 150.0  # elevation -60..90
    step = float(np.sqrt(360.0 * n_el_per_deg / points))
    folder = out / f"tls_{points / 1e6:.0f}M"
    manifest = folder / "site.yaml"
    if not manifest.exists():
        scene = build_scene("indoor", 0)
        t0 = time.perf_counter()
        scan = simulate_scan(scene, Texture(0), pose_at(CENTRE), TlsParams(step_deg=step), "scan_000")
        write_site(folder, scene, [scan], "ply", TlsParams(step_deg=step))
        print(f"simulated {len(scan.xyz_scan) / 1e6:.1f} M points (step {step:.4f} deg) in "
              f"{time.perf_counter() - t0:.1f} s -> {folder}")  # fmt: skip
    return manifest


def _render_one(k: int) -> int:
    model, T = _VIEWS[k]
    return render_view(_INDEX, model, T, _PARAMS[0]).stats["valid_px"]


def throughput(workers: int, params: RenderParams) -> float:
    """Views per second over `_VIEWS` with ``workers`` forked processes (1 = in this process).

    Workers split the cores between them as render-benchmark's do (`share_cores`).
    """
    _PARAMS[:] = [params]
    t0 = time.perf_counter()
    if workers == 1:
        for k in range(len(_VIEWS)):
            _render_one(k)
    else:
        ctx = multiprocessing.get_context("fork")
        init = partial(share_cores, workers)
        with ProcessPoolExecutor(workers, mp_context=ctx, initializer=init) as pool:
            list(pool.map(_render_one, range(len(_VIEWS))))
    return len(_VIEWS) / (time.perf_counter() - t0)


def interleaved(fns: dict[str, Callable[[], Any]], runs: int) -> dict[str, tuple[float, float, Any]]:
    """Per name: median wall and CPU seconds of ``runs`` calls, taken in turn (A B A B ...), last result."""
    wall: dict[str, list[float]] = {k: [] for k in fns}
    cpu: dict[str, list[float]] = {k: [] for k in fns}
    last: dict[str, Any] = {}
    for _ in range(runs):
        for name, fn in fns.items():
            t0, c0 = time.perf_counter(), time.process_time()
            last[name] = fn()
            wall[name].append(time.perf_counter() - t0)
            cpu[name].append(time.process_time() - c0)
    return {k: (statistics.median(wall[k]), statistics.median(cpu[k]), last[k]) for k in fns}


def speed(args: argparse.Namespace) -> list[tuple[str, float, str]]:
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("fork")) as pool:
        manifest = pool.submit(site_for, args.points, args.out).result()  # keeps its memory out of ours
    w, h = (int(v) for v in args.size.split("x"))
    t0 = time.perf_counter()
    (scan,) = read_scans([manifest])
    t_load, rss_load = time.perf_counter() - t0, peak_rss_mb()
    t0 = time.perf_counter()
    index = build_index(scan)
    t_index, rss_index = time.perf_counter() - t0, peak_rss_mb()
    n = len(scan.xyz)
    del scan
    ref = reference()
    model = virtual_ds(ref, args.fov, w, h)
    T = index.T_world_scan.copy()
    T[:3, :3] = R_up_cam(0.0)
    t0 = time.perf_counter()
    pixel_geometry(model)
    t_setup = time.perf_counter() - t0
    t0 = time.perf_counter()
    render_view([index], model, T, COMPILED)  # kernels compiled (or loaded from numba's cache) once
    t_first = time.perf_counter() - t0
    naive = RenderParams(points_per_px=None, frustum_culling=False)
    res = interleaved({"numpy": lambda: render_view([index], model, T, NUMPY),
                       "numba": lambda: render_view([index], model, T, COMPILED),
                       "naive": lambda: render_view([index], model, T, naive)}, args.runs)  # fmt: skip
    rss_view = peak_rss_mb()
    (t_ref, c_ref, r_ref), (t_c, c_c, r_c), (t_naive, _, r_naive) = res["numpy"], res["numba"], res["naive"]
    same_valid = np.array_equal(r_ref.range_m > 0, r_c.range_m > 0)
    same_holes = same_valid and np.array_equal(r_ref.surface, r_c.surface)
    diff_mm = float(np.abs(r_ref.range_m - r_c.range_m).max()) * 1e3
    bits = int((r_ref.range_m != r_c.range_m).sum())
    _INDEX[:] = [index]
    _VIEWS[:] = [
        (virtual_ds(ref, f, w, h), partner_pose(T, "DOWN", b))
        for f in (120, 140, 165, 195)
        for b in (0.0, 0.3)
    ]
    for m, _ in _VIEWS:
        pixel_geometry(m)  # per-model setup before forking, as render-benchmark does
    vps = {(b, k): throughput(k, p) for b, p in (("numpy", NUMPY), ("numba", COMPILED)) for k in (1, 2)}
    st, sn = r_c.stats, r_naive.stats
    layer = numba.threading_layer()  # type: ignore[attr-defined]
    print(f"\n{machine_line()}; numba {numba.__version__}, {numba.get_num_threads()} threads ({layer} layer)")
    print(f"\n{n / 1e6:.1f} M-point scan, {w}x{h} fisheye (nominal FOV {args.fov} deg): per view the median "
          f"of {args.runs} runs, numpy / numba / naive taken in turn; cv2 threads {cv2.getNumThreads()}"
          "\n")  # fmt: skip
    rows = [
        ("load (PLY, Open3D tensor IO)", t_load, f"peak RSS {rss_load:.0f} MB"),
        ("LOD build (voxel buckets, one argsort)", t_index, f"peak RSS {rss_index:.0f} MB"),
        ("camera setup (once per model, cached)", t_setup, ""),
        ("first compiled view (kernels compiled or loaded from cache)", t_first, ""),
        ("render one view, numpy reference (backend numpy)", t_ref, f"CPU {c_ref:.2f} s"),
        ("render one view, compiled (backend numba)", t_c,
         f"CPU {c_c:.2f} s; {st['points_touched'] / 1e6:.2f} M points touched, "
         f"{st['points_in_image'] / 1e6:.2f} M in image; peak RSS {rss_view:.0f} MB"),
        ("numpy / numba", t_ref / t_c, f"ratio; same holes and valid pixels: {same_holes}, max |range diff| "
         f"{diff_mm:.4f} mm, {bits} pixels not bit-identical"),
        ("render one view, naive (all points, numba)", t_naive,
         f"{sn['points_touched'] / 1e6:.2f} M points touched, {sn['points_in_image'] / 1e6:.2f} M in image"),
        ("naive / LOD", t_naive / t_c, "ratio"),
    ]  # fmt: skip
    for b in ("numpy", "numba"):
        rows += [
            (f"views/s, {b}, 1 process (8 views: 4 FOVs x CENTER, DOWN 300 mm)", vps[(b, 1)], ""),
            (f"views/s, {b}, 2 forked workers", vps[(b, 2)], f"x{vps[(b, 2)] / vps[(b, 1)]:.2f}"),
        ]
    rows.append(("views/s numba / numpy, 2 workers", vps[("numba", 2)] / vps[("numpy", 2)], "ratio"))
    print("| stage | seconds | notes |")
    print("|---|---|---|")
    for name, v, note in rows:
        unit = f"{v:.2f}" if ("views/s" in name or "/" in name) else f"{v:.3f}"
        print(f"| {name} | {unit} | {note} |")
    print(f"\nvalid pixels: LOD {st['valid_px']}, naive {sn['valid_px']}; holes {st['hole_px']} / "
          f"{sn['hole_px']}; peak RSS of the whole run {peak_rss_mb():.0f} MB")  # fmt: skip
    return rows


def _score(rend: Rendering, exact: np.ndarray) -> dict[str, float]:
    score = score_range(rend.range_m, exact)
    return {
        "median_mm": score.median_mm,
        "p90_mm": score.p90_mm,
        "leak_pct": 100.0 * score.leak,
        "leak_off_sil_pct": 100.0 * score.leak_off_silhouette,
        "holes": float(rend.holes.sum()),
        "holes_pct": 100.0 * float(rend.holes.sum() / rend.rays.sum()),
    }


def _bad3(gt: np.ndarray, est: np.ndarray) -> float:
    ok = (gt > 0) & (est > 0)
    return 100.0 * float((np.abs(gt - est)[ok] > 3.0).mean())


def accuracy(args: argparse.Namespace) -> list[tuple[str, dict[str, float]]]:
    scene = build_scene("indoor", 0)
    ref = reference()
    rows = []
    for noise in (0.0, 0.0015):
        sims = [simulate_scan(scene, Texture(0), T, TlsParams(step_deg=0.25, range_noise_m=noise), f"s{k}")
                for k, T in enumerate(bundle_poses(CENTRE))]  # fmt: skip
        idx = [
            build_index(Scan(s.name, s.T_world_scan, s.xyz_scan, s.rgb, mask_xyz=s.mask_xyz_scan))
            for s in sims
        ]
        T = sims[0].T_world_scan.copy()
        T[:3, :3] = R_up_cam(0.0)
        for fov in (120, 195):
            m = virtual_ds(ref, fov, 256, 160)
            for cam, Tc in (("CENTER", T), ("DOWN 300", partner_pose(T, "DOWN", 0.3)),
                            ("RIGHT 300", partner_pose(T, "RIGHT", 0.3))):  # fmt: skip
                exact, _ = true_range(scene, m, Tc)
                for bundle in (1, 3):
                    n_scans = f"{bundle} scan{'s' if bundle > 1 else ''}"
                    name = f"noise {noise * 1e3:.1f} mm, {fov} deg, {cam}, {n_scans}"
                    rows.append((name, _score(render_view(idx[:bundle], m, Tc), exact)))
    print(
        "\nAccuracy vs the mesh (256x160 fisheye, 0.87 M points per scan; median/p90 off 3 px depth edges; "
        "leak = farther than truth by > max(5 cm, 3 %) over valid pixels; off-sil: beyond 1 px of an edge)\n"
    )
    print("| case | median [mm] | p90 [mm] | leak [%] | leak off-sil [%] | holes [px] | holes [%] |")
    print("|---|---|---|---|---|---|---|")
    for name, s in rows:
        print(f"| {name} | {s['median_mm']:.3f} | {s['p90_mm']:.2f} | {s['leak_pct']:.3f} | "
              f"{s['leak_off_sil_pct']:.3f} | {s['holes']:.0f} | {s['holes_pct']:.2f} |")  # fmt: skip
    # disparity GT vs SGBM on the written benchmark
    out = args.out / "bench_render_layout"
    import shutil

    shutil.rmtree(out, ignore_errors=True)
    sims = [
        simulate_scan(scene, Texture(0), T, TlsParams(step_deg=0.25), f"s{k}")
        for k, T in enumerate(bundle_poses(CENTRE))
    ]
    scans = [Scan(s.name, s.T_world_scan, s.xyz_scan, s.rgb, mask_xyz=s.mask_xyz_scan) for s in sims]
    cfg = BenchmarkConfig(fovs_deg=(120.0,), baselines_mm=(120.0, 300.0), width=320, height=200,
                          height_full=640, centers=("s0",))  # fmt: skip
    run_benchmark(scans, ref, out, cfg)
    print(
        "\nDisparity GT vs cv2.StereoSGBM (320x200 fisheye; pano_crop of a 640-row sphere; "
        "bad-3 = |GT - SGBM| > 3 px)\n"
    )
    print("| pair | baseline | bad-3 [%] |")
    print("|---|---|---|")
    for b in (120, 300):
        base = out / "000_000_000" / "120FOV" / f"{b}mm"
        g = read_png_u16(base / "CENTER" / "disparity" / "pano_crop.png", DISP_SCALE)
        up, down = (gray(base / c / "pano_crop.png") for c in ("CENTER", "DOWN"))
        nd = 64 if b == 120 else 128
        sgbm = cv2.StereoSGBM.create(
            0, nd, 5, P1=8 * 25, P2=32 * 25, uniquenessRatio=10, mode=cv2.STEREO_SGBM_MODE_HH
        )
        est = unrotate_from_stereo(
            sgbm.compute(rotate_for_stereo(up), rotate_for_stereo(down)).astype(np.float32) / 16
        )
        print(f"| vertical, rotated pano_crop | {b} mm | {_bad3(g, est):.2f} |")
        g = read_png_u16(base / "CENTER" / "disparity" / "pinhole.png", DISP_SCALE)
        left, right = (gray(base / c / "pinhole.png") for c in ("CENTER", "RIGHT"))
        nd = 96 if b == 120 else 224
        sgbm = cv2.StereoSGBM.create(
            0, nd, 5, P1=8 * 25, P2=32 * 25, uniquenessRatio=10, mode=cv2.STEREO_SGBM_MODE_HH
        )
        est = sgbm.compute(left, right).astype(np.float32) / 16
        print(f"| horizontal, pinhole | {b} mm | {_bad3(g, est):.2f} |")
    return rows


def chart(
    speed_rows: list[tuple[str, float, str]], acc: list[tuple[str, dict[str, float]]], path: Path
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(13, 4.5))
    if speed_rows:
        keep = [r for r in speed_rows if "/" not in r[0] and "views/s" not in r[0]]
        a.barh([r[0] for r in keep][::-1], [r[1] for r in keep][::-1], color="tab:blue")
        a.axvline(0.5, color="tab:red", ls="--", lw=1, label="target 0.5 s per view")
        a.set_xlabel("seconds")
        a.set_title("20 M-point scan -> 2048x1152 fisheye RGB + range")
        a.legend(loc="lower right")
    if acc:
        names = [n.replace("noise ", "").replace(" deg", "") for n, _ in acc]
        x = np.arange(len(acc))
        b.bar(
            x,
            [s["holes_pct"] for _, s in acc],
            color=["tab:orange" if "1 scan" in n else "tab:green" for n in names],
        )
        b.set_xticks(x, names, rotation=90, fontsize=6)
        b.set_ylabel("holes [% of pixels]")
        b.set_title("holes: 1 scan (orange) vs bundle of 3 (green)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    print(f"\nchart: {path}")


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--points", type=float, default=20e6, help="points of the simulated scan")
    p.add_argument("--size", default="2048x1152")
    p.add_argument("--fov", type=float, default=120.0)
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--out", type=Path, default=OUT_DIR)
    p.add_argument("--skip-speed", action="store_true")
    p.add_argument("--skip-accuracy", action="store_true")
    args = p.parse_args(argv)
    cv2.setNumThreads(2)
    speed_rows = [] if args.skip_speed else speed(args)
    acc = [] if args.skip_accuracy else accuracy(args)
    chart(speed_rows, acc, args.out / "bench_render.png")


if __name__ == "__main__":
    main()
