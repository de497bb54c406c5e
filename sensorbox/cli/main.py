"""The ``sensorbox`` command line: parse, call one library function, print.

Every `SensorboxError` becomes one readable line on stderr and exit code 2.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

from calibration.errors import SensorboxError

app = typer.Typer(
    name="sensorbox",
    help="SensorBox: fisheye stereo + Livox LiDAR rig tools (WideDepth pipeline).",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)
calib_app = typer.Typer(
    help="Inspect and check calibrations (Kalibr camchains, rig files).", no_args_is_help=True
)
app.add_typer(calib_app, name="calib")

# Piped output (CI logs, `make demo | tee`) gets a readable width instead of rich's 80 columns.
console = Console(width=None if sys.stdout.isatty() else 140)
err_console = Console(stderr=True, width=None if sys.stderr.isatty() else 200)


def _fmt(value: object) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    if value is None:
        return "-"
    if hasattr(value, "coeffs"):
        return f"{type(value).__name__}{[round(c, 6) for c in value.coeffs()]}"
    return str(value)


_DIRECTIONS = {
    (0, 1): "right",
    (0, -1): "left",
    (1, 1): "down",
    (1, -1): "up",
    (2, 1): "forward",
    (2, -1): "backward",
}


def _direction(v: object) -> str:
    """Name the cam0 direction a unit vector mostly points to, e.g. 'up (99.9%)'."""
    import numpy as np

    a = np.asarray(v, dtype=float)
    i = int(np.argmax(np.abs(a)))
    return f"{_DIRECTIONS[(i, 1 if a[i] > 0 else -1)]} ({abs(a[i]) * 100:.1f}%)"


@calib_app.command("check")
def calib_check(
    path: Annotated[Path, typer.Argument(help="Rig file (sensorbox_rig YAML) or Kalibr camchain.")],
    plot: Annotated[
        Path | None, typer.Option("--plot", help="Write a top/side drawing of the rig (PNG).")
    ] = None,
) -> None:
    """Print each camera's model, parameters and true FOV, the baseline and the rig's frames."""
    from calibration.report import describe_rig
    from calibration.rig import read_rig

    rig = read_rig(path)
    report = describe_rig(rig)

    cams = Table(title=f"Cameras of '{report.name}' ({path})")
    for col in ("camera", "role", "model", "size", "HFOV", "VFOV", "DFOV"):
        cams.add_column(col)
    for c in report.cameras:
        fov = c.fov
        cams.add_row(
            c.name,
            c.role or "-",
            c.model,
            f"{c.params['width']}x{c.params['height']}",
            *(f"{math.degrees(a):.1f}°" for a in (fov.horizontal_rad, fov.vertical_rad, fov.diagonal_rad)),
        )
    console.print(cams)
    for c in report.cameras:
        params = ", ".join(f"{k}={_fmt(v)}" for k, v in c.params.items() if k not in ("width", "height"))
        console.print(f"  {c.name}: {params}", highlight=False)

    frames = Table(title="Frames in cam0 (x right, y down, z forward)")
    for col in ("frame", "kind", "x [m]", "y [m]", "z [m]", "its z axis", "topic"):
        frames.add_column(col, overflow="fold")
    for f in report.frames:
        frames.add_row(
            f.name,
            f.kind,
            *(f"{v:+.4f}" for v in f.position_m),
            _direction(f.z_axis_cam0),
            f.topic or "-",
        )
    console.print(frames)
    if report.baseline_m is not None:
        console.print(f"Stereo baseline upper->lower: [bold]{report.baseline_m * 1000:.2f} mm[/bold]")
    if plot is not None:
        from sensorbox.analysis.plots import plot_rig

        out = plot_rig(rig, report, plot)
        console.print(f"Rig drawing written to {out}")


def _human_bytes(n: int) -> str:
    for unit in ("B", "KB", "MB", "GB"):
        if n < 1024 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024  # type: ignore[assignment]
    return f"{n} B"


@app.command("simulate")
def simulate_cmd(
    out: Annotated[
        Path, typer.Option("--out", help="Bag to write: a rosbag2 folder, or NAME.bag for --format bag.")
    ],
    scene: Annotated[str, typer.Option(help="Procedural scene: indoor | outdoor.")] = "indoor",
    trajectory: Annotated[
        str, typer.Option(help="static | walk (1.2 m/s handheld) | custom (--tum).")
    ] = "static",
    tum: Annotated[
        Path | None, typer.Option(help="TUM file of T_world_cam0 for --trajectory custom.")
    ] = None,
    duration: Annotated[float, typer.Option(help="Seconds to simulate.")] = 1.0,
    seed: Annotated[
        int, typer.Option(help="Seed of the scene layout, texture, pattern phases and noise.")
    ] = 0,
    fmt: Annotated[str, typer.Option("--format", help="mcap | db3 (ROS 2 sqlite3) | bag (ROS 1).")] = "mcap",
    lidar_msg: Annotated[str, typer.Option(help="custom (livox CustomMsg) | pointcloud2.")] = "custom",
    image: Annotated[str, typer.Option(help="raw (Image bgra8) | jpeg (CompressedImage).")] = "raw",
    scale: Annotated[float, typer.Option(help="Image resolution scale (0.25 -> 480x300).")] = 1.0,
    range_noise: Annotated[float, typer.Option(help="LiDAR range noise, 1-sigma metres (0 = exact).")] = 0.02,
    lidar_offset_ms: Annotated[float, typer.Option(help="Clock offset of the second LiDAR (ms).")] = 0.0,
    supersample: Annotated[int, typer.Option(help="Rays per pixel per axis (anti-aliasing).")] = 1,
) -> None:
    """Simulate the SensorBox in a procedural scene: write a bag plus its exact truth (<bag>.truth/)."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    from sensorbox.sim.run import SimConfig, simulate

    cfg = SimConfig(
        scene=scene, trajectory=trajectory, tum=tum, duration_s=duration, seed=seed, format=fmt,  # type: ignore[arg-type]
        lidar_msg=lidar_msg, image=image, scale=scale, range_noise_m=range_noise,  # type: ignore[arg-type]
        lidar_clock_offset_ns=round(lidar_offset_ms * 1e6), supersample=supersample,
    )  # fmt: skip
    columns = (TextColumn("simulating"), BarColumn(), TextColumn("{task.completed:.1f}/{task.total:.1f} s"))
    with Progress(*columns, TimeRemainingColumn(), console=err_console, transient=True) as bar:
        task = bar.add_task("sim", total=duration)
        summary = simulate(cfg, out, progress=lambda done: bar.update(task, completed=done))
    table = Table(title=f"{summary.bag} ({_human_bytes(summary.size_bytes)}, {summary.seconds:.1f} s)")
    for col in ("topic", "messages", "rate [Hz]"):
        table.add_column(col, justify="left" if col == "topic" else "right")
    for topic, n in summary.counts.items():
        table.add_row(topic, str(n), f"{n / duration:.1f}")
    console.print(table)
    stages = ", ".join(f"{k} {v:.1f} s" for k, v in summary.stage_seconds.items())
    console.print(f"Time per stage: {stages}", highlight=False)
    console.print(f"Truth (scene mesh, trajectory, rig, parameters): {summary.truth}", highlight=False)


def _register_ingest() -> None:
    from sensorbox.cli.ingest import ingest_cmd

    app.command("ingest")(ingest_cmd)


_register_ingest()


def _register_inspect() -> None:
    from sensorbox.cli.inspect import inspect_cmd

    app.command("inspect")(inspect_cmd)


_register_inspect()


def _register_eval() -> None:
    from sensorbox.cli.eval import eval_cmd, stats_cmd

    app.command("eval")(eval_cmd)
    app.command("stats")(stats_cmd)


_register_eval()


def _register_bench() -> None:
    from sensorbox.cli.bench import bench_cmd

    app.command("bench")(bench_cmd)


_register_bench()


def _register_capture() -> None:
    from sensorbox.cli.capture import capture_cmd, launch_cmd

    app.command("launch")(launch_cmd)
    app.command("capture")(capture_cmd)


_register_capture()


def _register_render() -> None:
    from sensorbox.cli.render import render_benchmark_cmd

    app.command("render-benchmark")(render_benchmark_cmd)


_register_render()


@app.callback()
def _root() -> None:
    """SensorBox command line."""


def main() -> None:
    """Console-script entry point: run the app, mapping SensorboxError to exit code 2."""
    try:
        app()
    except SensorboxError as err:
        err_console.print(f"[bold red]error:[/bold red] {err}", highlight=False, soft_wrap=True)
        sys.exit(2)


if __name__ == "__main__":
    main()
