"""`sensorbox simulate --out BAG`: a virtual SensorBox writes a bag plus its exact truth (<bag>.truth/)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.table import Table

from sensorbox.cli.common import LidarMsgOpt, console, human_bytes, path_param, progress_bar

if TYPE_CHECKING:
    from sensorbox.sim.run import SimSummary

OutOpt = Annotated[
    Path,
    typer.Option(
        "--out", help="Bag to write: a rosbag2 folder, or NAME.bag for --format bag.", **path_param("--out")
    ),
]
SceneOpt = Annotated[str, typer.Option(help="Procedural scene: indoor | outdoor.")]
TrajectoryOpt = Annotated[str, typer.Option(help="static | walk (1.2 m/s handheld) | custom (--tum).")]
TumOpt = Annotated[
    Path | None,
    typer.Option(help="TUM file of T_world_cam0 for --trajectory custom; time 0 is its first row, "
                 "and it must span --duration."),
]  # fmt: skip
DurationOpt = Annotated[float, typer.Option(help="Seconds to simulate.")]
SeedOpt = Annotated[int, typer.Option(help="Seed of the scene layout, texture, pattern phases and noise.")]
FormatOpt = Annotated[str, typer.Option("--format", help="mcap | db3 (ROS 2 sqlite3) | bag (ROS 1).")]
ImageOpt = Annotated[str, typer.Option(help="raw (Image bgra8) | jpeg (CompressedImage).")]
ScaleOpt = Annotated[float, typer.Option(help="Image resolution scale (0.25 -> 480x300).")]
RangeNoiseOpt = Annotated[float, typer.Option(help="LiDAR range noise, 1-sigma metres (0 = exact).")]
LidarOffsetOpt = Annotated[float, typer.Option(help="Clock offset of the second LiDAR (ms).")]
SupersampleOpt = Annotated[int, typer.Option(help="Rays per pixel per axis (anti-aliasing).")]
MoversOpt = Annotated[
    bool, typer.Option("--movers", help="Add people walking, a swinging door and (outdoor) a passing car.")
]


def summary_table(summary: SimSummary, duration_s: float) -> Table:
    """Messages and rate per topic of the written bag."""
    table = Table(title=f"{summary.bag} ({human_bytes(summary.size_bytes)}, {summary.seconds:.1f} s)")
    for col in ("topic", "messages", "rate [Hz]"):
        table.add_column(col, justify="left" if col == "topic" else "right")
    for topic, n in summary.counts.items():
        table.add_row(topic, str(n), f"{n / duration_s:.1f}")
    return table


def simulate_cmd(
    out: OutOpt, scene: SceneOpt = "indoor", trajectory: TrajectoryOpt = "static", tum: TumOpt = None,
    duration: DurationOpt = 1.0, seed: SeedOpt = 0, fmt: FormatOpt = "mcap",
    lidar_msg: LidarMsgOpt = "custom", image: ImageOpt = "raw", scale: ScaleOpt = 1.0,
    range_noise: RangeNoiseOpt = 0.02,
    lidar_offset_ms: LidarOffsetOpt = 0.0, supersample: SupersampleOpt = 1, movers: MoversOpt = False,
) -> None:  # fmt: skip
    """Simulate the SensorBox in a procedural scene: write a bag plus its exact truth (<bag>.truth/)."""
    from calibration.errors import SensorboxError
    from sensorbox.sim.run import SimConfig, simulate

    if not math.isfinite(lidar_offset_ms):
        raise SensorboxError(f"--lidar-offset-ms must be a finite number, got {lidar_offset_ms}")
    cfg = SimConfig(
        scene=scene, trajectory=trajectory, tum=tum, duration_s=duration, seed=seed, format=fmt,  # type: ignore[arg-type]
        lidar_msg=lidar_msg, image=image, scale=scale, range_noise_m=range_noise,  # type: ignore[arg-type]
        lidar_clock_offset_ns=round(lidar_offset_ms * 1e6), supersample=supersample, movers=movers,
    )  # fmt: skip
    total_ms = round(duration * 1000) if math.isfinite(duration) else 0  # simulate() refuses the rest
    with progress_bar("simulating", "ms simulated") as update:
        summary = simulate(cfg, out, progress=lambda done: update(round(done * 1000), total_ms))
    console.print(summary_table(summary, duration))
    stages = ", ".join(f"{k} {v:.1f} s" for k, v in summary.stage_seconds.items())
    console.print(f"Time per stage: {stages}")
    console.print(f"Truth (scene mesh, trajectory, rig, parameters): {summary.truth}")
