"""`sensorbox simulate --out BAG`: a virtual SensorBox writes a bag plus its exact truth (<bag>.truth/)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.table import Table

from sensorbox.cli.common import LidarMsgOpt, console, human_bytes, path_param, progress_bar, refuse_link_loop

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
DurationOpt = Annotated[float, typer.Option(help="Seconds to simulate (at least one camera frame, 1/30 s).")]
SeedOpt = Annotated[int, typer.Option(help="Seed of the scene layout, texture, pattern phases and noise.")]
FormatOpt = Annotated[str, typer.Option("--format", help="mcap | db3 (ROS 2 sqlite3) | bag (ROS 1).")]
ImageOpt = Annotated[str, typer.Option(help="raw (Image bgra8) | jpeg (CompressedImage).")]
ScaleOpt = Annotated[float, typer.Option(help="Image resolution scale (0.25 -> 480x300).")]
RangeNoiseOpt = Annotated[
    float, typer.Option(help="LiDAR range noise, 1-sigma metres (0 = exact; at most 10).")
]
LidarOffsetOpt = Annotated[float, typer.Option(help="Clock offset of the second LiDAR (ms).")]
SupersampleOpt = Annotated[int, typer.Option(help="Rays per pixel per axis (anti-aliasing).")]
CameraOffsetOpt = Annotated[
    str,
    typer.Option(help="Camera clock offset (ms): each image's header stamp is this much later than its true "
                 "mid-exposure on the LiDAR clock; X for both cameras or X,Y for upper,lower."),
]  # fmt: skip
ImuNoiseOpt = Annotated[
    bool, typer.Option("--imu-noise", help="IMU noise and bias at the Mid-360 IMU's datasheet figures.")
]  # fmt: skip
RangeNoiseModelOpt = Annotated[
    str, typer.Option(help="constant | mid360 (sigma grows with range, falls with reflectivity; "
                      "--range-noise is its value at 10 m).")
]  # fmt: skip
MixedReturnsOpt = Annotated[
    bool, typer.Option("--mixed-returns", help="A 0.2 deg beam: mixed ranges at depth edges.")
]  # fmt: skip
MoversOpt = Annotated[
    bool, typer.Option("--movers", help="Add people walking, a swinging door and (outdoor) a passing car.")
]


def camera_offsets_ns(text: str) -> tuple[int, int]:
    """`--camera-offset-ms` ("X" or "X,Y", ms) as (upper, lower) ns; one line naming the value otherwise."""
    from calibration.errors import SensorboxError

    parts = text.split(",")
    try:
        ms = [float(p) for p in parts]
    except ValueError:
        ms = []
    if len(ms) not in (1, 2) or not all(math.isfinite(v) for v in ms):
        raise SensorboxError(f"--camera-offset-ms {text!r}: expected X or X,Y in milliseconds (upper,lower)")
    upper, lower = (ms[0], ms[0]) if len(ms) == 1 else (ms[0], ms[1])
    return round(upper * 1e6), round(lower * 1e6)


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
    camera_offset_ms: CameraOffsetOpt = "0", imu_noise: ImuNoiseOpt = False,
    range_noise_model: RangeNoiseModelOpt = "constant", mixed_returns: MixedReturnsOpt = False,
) -> None:  # fmt: skip
    """Simulate the SensorBox in a procedural scene: write a bag plus its exact truth (<bag>.truth/)."""
    from calibration.errors import SensorboxError
    from sensorbox.sim.config import SimConfig, with_mid360_imu_noise
    from sensorbox.sim.run import simulate

    refuse_link_loop("--out", out, "a bag path")
    if not math.isfinite(lidar_offset_ms) or abs(lidar_offset_ms) > 1000:
        raise SensorboxError(
            f"--lidar-offset-ms must be a finite number within +-1000 ms, got {lidar_offset_ms}"
        )
    cfg = SimConfig(
        scene=scene, trajectory=trajectory, tum=tum, duration_s=duration, seed=seed, format=fmt,  # type: ignore[arg-type]
        lidar_msg=lidar_msg, image=image, scale=scale, range_noise_m=range_noise,  # type: ignore[arg-type]
        lidar_clock_offset_ns=round(lidar_offset_ms * 1e6), supersample=supersample, movers=movers,
        camera_offset_ns=camera_offsets_ns(camera_offset_ms), range_noise_model=range_noise_model,
        mixed_returns=mixed_returns,
    )  # fmt: skip
    if imu_noise:
        cfg = with_mid360_imu_noise(cfg)
    total_ms = round(duration * 1000) if math.isfinite(duration) else 0  # simulate() refuses the rest
    with progress_bar("simulating", "ms simulated") as update:
        summary = simulate(cfg, out, progress=lambda done: update(round(done * 1000), total_ms))
    console.print(summary_table(summary, duration))
    stages = ", ".join(f"{k} {v:.1f} s" for k, v in summary.stage_seconds.items())
    console.print(f"Time per stage: {stages}")
    console.print(f"Truth (scene mesh, trajectory, rig, parameters): {summary.truth}")
