"""`sensorbox render-benchmark SCAN... --rig RIG --out DIR`: benchmark views from dense laser scans.

A plain typer command function registered by `sensorbox.cli`. It parses, reads
the scans (`ingest.render.scans.read_scans`) and the reference DS camera (cam0 of the
rig), calls `ingest.render.benchmark.run_benchmark` with a progress bar and prints a
summary table. Errors are `SensorboxError`s, left to the main CLI.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
from rich.table import Table

from calibration.errors import SensorboxError

console = Console(width=None if sys.stdout.isatty() else 140)
progress_console = Console(stderr=True)


def _size(text: str) -> tuple[int, int]:
    w, sep, h = text.lower().partition("x")
    if not sep or not w.isdigit() or not h.isdigit():
        raise SensorboxError(f"--size {text!r}: expected WIDTHxHEIGHT, e.g. 2048x1152")
    return int(w), int(h)


def _to_scan(pts_world: Any, T_world_scan: Any) -> Any:
    """World points into a scan's frame (float32)."""
    return ((pts_world - T_world_scan[:3, 3]) @ T_world_scan[:3, :3]).astype("float32")


def _pct(part: float, whole: float) -> str:
    return "-" if whole <= 0 else f"{100.0 * part / whole:.2f} %"


def render_benchmark_cmd(
    scans: Annotated[
        list[Path],
        typer.Argument(help="Scans: site.yaml manifests, .e57 (with poses), .pcd (VIEWPOINT pose), .ply."),
    ],
    rig: Annotated[Path, typer.Option(help="Rig file; its cam0 is the reference Double Sphere calibration.")],
    out: Annotated[Path, typer.Option(help="Output folder (WideDepth benchmark layout); reruns resume.")],
    fov: Annotated[
        list[float] | None,
        typer.Option("--fov", help="Fisheye FOVs in degrees (repeat; default 120 140 165 195)."),
    ] = None,
    baseline: Annotated[
        list[float] | None,
        typer.Option("--baseline", help="Stereo baselines in mm (repeat; default 20 65 120 200 300)."),
    ] = None,
    yaw: Annotated[list[float] | None, typer.Option("--yaw", help="View yaw(s) in degrees (repeat).")] = None,
    height: Annotated[
        list[float] | None, typer.Option("--height", help="View height(s) above the scan centre, m (repeat).")
    ] = None,
    pitch: Annotated[float, typer.Option(help="View pitch in degrees (up > 0).")] = 0.0,
    center: Annotated[
        list[str] | None, typer.Option("--center", help="Scan name(s) to put views at (default: every scan).")
    ] = None,
    size: Annotated[str, typer.Option(help="Fisheye and pinhole image size WIDTHxHEIGHT.")] = "2048x1152",
    bundle: Annotated[int, typer.Option(help="Scans per view: the centre and its nearest neighbours.")] = 3,
    workers: Annotated[int, typer.Option(help="Local worker processes (views rendered in parallel).")] = 2,
    clip: Annotated[
        float | None, typer.Option(help="Ranges beyond this (m) are invalid, e.g. outdoors through windows.")
    ] = None,
    clip_mode: Annotated[
        str, typer.Option(help="invalid (0 in depth, colour kept) | drop (those points are not drawn).")
    ] = "invalid",
    mask: Annotated[
        list[Path] | None,
        typer.Option("--mask", help="Mask cloud (world frame) of reflective/transparent surfaces (repeat)."),
    ] = None,
    mask_label: Annotated[
        str, typer.Option(help="Per-point field marking masked points (non-zero); '' for none.")
    ] = "label",
    points_per_px: Annotated[float, typer.Option(help="Level of detail: points drawn per pixel.")] = 2.0,
    height_full: Annotated[
        int | None, typer.Option(help="Rows of the full-sphere equirect (default: from each fisheye).")
    ] = None,
    pinhole_fov: Annotated[
        list[float] | None,
        typer.Option("--pinhole-in", help="FOV folders with pinhole images (default 120)."),
    ] = None,
    site_id: Annotated[int, typer.Option(help="Site number, the first part of the scene ids.")] = 0,
    exr: Annotated[
        bool, typer.Option("--exr/--no-exr", help="Also write float32 EXR copies of the GT.")
    ] = True,
    png_level: Annotated[int, typer.Option(help="PNG deflate level 0-3 (speed vs size).")] = 1,
) -> None:
    """Render benchmark views (virtual fisheye, pano, Cassini and pinhole cameras, DOWN/RIGHT stereo
    partners) from dense laser scans into the WideDepth benchmark layout."""
    from dataclasses import replace

    import numpy as np

    from calibration.rig import read_rig
    from ingest.render.benchmark import BASELINES_MM, FOVS_DEG, BenchmarkConfig, fov_label, run_benchmark
    from ingest.render.scans import read_cloud, read_scans
    from ingest.render.view import RenderParams

    if clip_mode not in ("invalid", "drop"):
        raise SensorboxError(f"--clip-mode {clip_mode!r}: expected invalid or drop")
    if not 0 <= png_level <= 3:
        raise SensorboxError(f"--png-level {png_level}: expected 0..3")
    if not points_per_px > 0:
        raise SensorboxError(f"--points-per-px {points_per_px}: must be > 0")
    width, height_px = _size(size)
    reference = read_rig(rig).camera("cam0").model
    site = read_scans(scans, mask_label or None)
    for m in mask or []:  # a world-frame mask cloud joins every scan, in that scan's frame
        world = read_cloud(m, np.eye(4), None).xyz.astype(np.float64)
        site = [
            replace(s, mask_xyz=np.concatenate([s.mask_xyz, _to_scan(world, s.T_world_scan)])) for s in site
        ]
    cfg = BenchmarkConfig(
        fovs_deg=tuple(fov or FOVS_DEG), baselines_mm=tuple(baseline or BASELINES_MM), width=width,
        height=height_px, yaws_deg=tuple(yaw or (0.0,)), heights_m=tuple(height or (0.0,)), pitch_deg=pitch,
        centers=tuple(center or ()), bundle=bundle, pinhole_fovs=tuple(pinhole_fov or (120.0,)),
        height_full=height_full, site_id=site_id, exr=exr, png_level=png_level, workers=workers,
        render=RenderParams(points_per_px=points_per_px, clip_m=clip, clip_mode=clip_mode),  # type: ignore[arg-type]
    )  # fmt: skip
    total = sum(len(s.xyz) for s in site)
    what = f"{len(site)} scans, {total / 1e6:.1f} M points; reference camera {type(reference).__name__}"
    console.print(what, highlight=False)
    columns = (TextColumn("rendering"), BarColumn(), MofNCompleteColumn(), TextColumn("views"))
    with Progress(*columns, TimeRemainingColumn(), console=progress_console, transient=True) as bar:
        task = bar.add_task("render", total=None)
        summary = run_benchmark(
            site, reference, out, cfg, progress=lambda done, n: bar.update(task, completed=done, total=n)
        )
    title = (
        f"{out}: {len(summary.scenes)} scenes, {summary.renders} views in {summary.seconds:.1f} s "
        f"(LOD index {summary.index_seconds:.1f} s), {summary.files} files"
    )
    table = Table(title=title)
    for col in (
        "scene",
        "FOV",
        "fisheye valid",
        "holes CENTER",
        "holes DOWN/RIGHT (max)",
        "masked",
        "clipped",
    ):
        table.add_column(col, justify="left" if col == "scene" else "right")
    for scene, st in summary.stats.items():
        for f in cfg.fovs_deg:
            lab = fov_label(f)
            c = st.get(f"{lab}/CENTER/fisheye", {})
            rays = c.get("pixels_with_ray", 0)
            partner = [v for k, v in st.items() if k.startswith(f"{lab}/") and k.endswith("/fisheye")
                       and "/CENTER/" not in k]  # fmt: skip
            worst = max((v["hole_px"] / max(v["pixels_with_ray"], 1) for v in partner), default=0.0)
            table.add_row(
                scene, lab, _pct(c.get("valid_px", 0), rays), _pct(c.get("hole_px", 0), rays),
                f"{100 * worst:.2f} %", _pct(c.get("masked_px", 0), rays), _pct(c.get("clipped_px", 0), rays),
            )  # fmt: skip
    console.print(table)
    if summary.skipped:
        console.print(
            f"Already done (scene.yaml present, skipped): {', '.join(summary.skipped)}", highlight=False
        )
    console.print(
        f"Benchmark: {out} (each <scene>/scene.yaml lists cameras, poses and counts)", highlight=False
    )
