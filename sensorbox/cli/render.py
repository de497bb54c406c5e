"""`sensorbox render-benchmark SCAN... --rig RIG --out DIR`: benchmark views from dense laser scans.

Parses the options into an `ingest.render.request.BenchmarkRequest`, calls
`ingest.render.benchmark.run_benchmark` with a progress bar and prints a
summary table. Errors are `SensorboxError`s, left to the main CLI.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.table import Table

from sensorbox.cli.common import check_out_folder, console, path_param, print_warning, progress_bar

if TYPE_CHECKING:
    from ingest.render.benchmark import BenchmarkSummary
    from ingest.render.plan import BenchmarkConfig

ScansArg = Annotated[
    list[Path],
    typer.Argument(
        help="Scans: site.yaml manifests, .e57 (with poses), .pcd (VIEWPOINT pose), .ply.",
        **path_param("SCANS", many=True),
    ),
]
RigOpt = Annotated[
    Path,
    typer.Option(
        help="Rig file; its cam0 is the reference Double Sphere calibration.", **path_param("--rig")
    ),
]
OutOpt = Annotated[
    Path,
    typer.Option(help="Output folder (WideDepth benchmark layout); reruns resume.", **path_param("--out")),
]
FovOpt = Annotated[
    list[float] | None,
    typer.Option("--fov", help="Fisheye FOVs in degrees (repeat; default 120 140 165 195)."),
]
BaselineOpt = Annotated[
    list[float] | None,
    typer.Option(
        "--baseline", help="Stereo baselines in mm, at most 2000 (repeat; default 20 65 120 200 300)."
    ),
]
YawOpt = Annotated[list[float] | None, typer.Option("--yaw", help="View yaw(s) in degrees (repeat).")]
HeightOpt = Annotated[
    list[float] | None,
    typer.Option("--height", help="View height(s) above the scan centre, m, within +-100 (repeat)."),
]
PitchOpt = Annotated[float, typer.Option(help="View pitch in degrees (up > 0).")]
CenterOpt = Annotated[
    list[str] | None, typer.Option("--center", help="Scan name(s) to put views at (default: every scan).")
]
SizeOpt = Annotated[str, typer.Option(help="Fisheye and pinhole image size WIDTHxHEIGHT.")]
BundleOpt = Annotated[int, typer.Option(help="Scans per view: the centre and its nearest neighbours.")]
WorkersOpt = Annotated[int, typer.Option(help="Local worker processes (views rendered in parallel).")]
ClipOpt = Annotated[
    float | None, typer.Option(help="Ranges beyond this (m) are invalid, e.g. outdoors through windows.")
]
ClipModeOpt = Annotated[
    str, typer.Option(help="invalid (0 in depth, colour kept) | drop (those points are not drawn).")
]
MaskOpt = Annotated[
    list[Path] | None,
    typer.Option("--mask", help="Mask cloud (world frame) of reflective/transparent surfaces (repeat)."),
]
MaskLabelOpt = Annotated[
    str, typer.Option(help="Per-point field marking masked points (non-zero); '' for none.")
]
PointsPerPxOpt = Annotated[float, typer.Option(help="Level of detail: points drawn per pixel.")]
BackendOpt = Annotated[
    str,
    typer.Option(help="Renderer: numba (compiled CPU kernels), numpy (reference), torch (PyTorch on the CPU) "
                 "or cuda (PyTorch on the GPU); the same images."),
]  # fmt: skip
HeightFullOpt = Annotated[
    int | None,
    typer.Option(
        help="Rows of the full-sphere equirect (default: each fisheye's centre "
        "resolution, the sphere at most 16x its pixels)."
    ),
]
PinholeOpt = Annotated[
    list[float] | None, typer.Option("--pinhole-in", help="FOV folders with pinhole images (default 120).")
]
SiteOpt = Annotated[int, typer.Option(help="Site number, the first part of the scene ids.")]
ExrOpt = Annotated[bool, typer.Option("--exr/--no-exr", help="Also write float32 EXR copies of the GT.")]
PngLevelOpt = Annotated[int, typer.Option(help="PNG deflate level 0-3 (speed vs size).")]


def _pct(part: float, whole: float) -> str:
    return "-" if whole <= 0 else f"{100.0 * part / whole:.2f} %"


def summary_table(summary: BenchmarkSummary, cfg: BenchmarkConfig, out: Path) -> Table:
    """Per scene and FOV: valid fisheye pixels, holes (CENTER, worst partner), masked, clipped."""
    from ingest.render.plan import fov_label

    title = (
        f"{out}: {len(summary.scenes)} scenes, {summary.renders} views in {summary.seconds:.1f} s "
        f"(LOD index {summary.index_seconds:.1f} s), {summary.files} files"
    )
    table = Table(title=title)
    columns = ("scene", "FOV", "fisheye valid", "holes CENTER", "holes DOWN/RIGHT (max)", "masked", "clipped")
    for col in columns:
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
    return table


def render_benchmark_cmd(
    scans: ScansArg, rig: RigOpt, out: OutOpt, fov: FovOpt = None, baseline: BaselineOpt = None,
    yaw: YawOpt = None, height: HeightOpt = None, pitch: PitchOpt = 0.0, center: CenterOpt = None,
    size: SizeOpt = "2048x1152", bundle: BundleOpt = 3, workers: WorkersOpt = 2, clip: ClipOpt = None,
    clip_mode: ClipModeOpt = "invalid", mask: MaskOpt = None, mask_label: MaskLabelOpt = "label",
    points_per_px: PointsPerPxOpt = 2.0, height_full: HeightFullOpt = None, pinhole_fov: PinholeOpt = None,
    site_id: SiteOpt = 0, exr: ExrOpt = True, png_level: PngLevelOpt = 1, backend: BackendOpt = "numba",
) -> None:  # fmt: skip
    """Render benchmark views (virtual fisheye, pano, Cassini and pinhole cameras, DOWN/RIGHT stereo
    partners) from dense laser scans into the WideDepth benchmark layout."""
    from ingest.render.benchmark import refuse_training_set, run_benchmark
    from ingest.render.request import BenchmarkRequest, prepare

    check_out_folder("--out", out, "the benchmark layout")
    refuse_training_set(out)  # before the scans are read
    request = BenchmarkRequest(
        scans, rig, out, fovs_deg=fov, baselines_mm=baseline, yaws_deg=yaw, heights_m=height, pitch_deg=pitch,
        centers=center, size=size, bundle=bundle, workers=workers, clip_m=clip, clip_mode=clip_mode,
        masks=mask,
        mask_label=mask_label, points_per_px=points_per_px, height_full=height_full, pinhole_fovs=pinhole_fov,
        site_id=site_id, exr=exr, png_level=png_level, backend=backend,
    )  # fmt: skip
    site, reference, cfg = prepare(request)
    points = sum(len(s.xyz) for s in site) / 1e6
    console.print(f"{len(site)} scans, {points:.1f} M points; reference camera {type(reference).__name__}")
    with progress_bar("rendering", "views") as update:
        summary = run_benchmark(
            site, reference, out, cfg,
            progress=lambda done, total: update(done, total, "rendering", "views"),
            passes=lambda what, done, total: update(done, total, f"rendering: {what}", "scans"),
        )  # fmt: skip
    console.print(summary_table(summary, cfg, out))
    for line in summary.warnings:
        console.print(f"[yellow]warning:[/] {line}", highlight=False)
    if summary.empty:
        n = sum(len(keys) for keys in summary.empty.values())
        scenes = len(summary.empty)
        console.print(f"Renders showing (almost) nothing: {n} in {scenes} scenes (scene.yaml: warnings)")
    if summary.skipped:
        console.print(f"Already done (scene.yaml present, skipped): {', '.join(summary.skipped)}")
    for line in summary.damaged:
        print_warning(f"damaged scene rendered again: {line}")
    if summary.stale_temporaries:
        console.print(f"Removed {summary.stale_temporaries} unfinished temporary files of a killed run")
    console.print(f"Benchmark: {out} (each <scene>/scene.yaml lists cameras, poses and counts)")
