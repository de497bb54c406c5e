"""`sensorbox ingest BAG... --rig RIG --out DIR`: recorded bags -> the WideDepth training set.

Parses the options into an `ingest.train.pipeline.IngestConfig`, runs `ingest`
with a progress bar, prints the summary and draws a preview of the middle sample.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.table import Table

from sensorbox.cli.common import console, progress_bar

if TYPE_CHECKING:
    from ingest.train.pipeline import IngestSummary

BagsArg = Annotated[
    list[Path], typer.Argument(help="Bags: ROS 1 .bag, ROS 2 .mcap/.db3 files or rosbag2 folders.")
]
RigOpt = Annotated[Path, typer.Option(help="Rig file (cameras, LiDARs, IMUs and their topics).")]
OutOpt = Annotated[Path, typer.Option(help="Output folder (WideDepth train layout); reruns resume.")]
WorkersOpt = Annotated[int, typer.Option(help="Local worker processes (1 = in this process).")]
DaskOpt = Annotated[
    str | None, typer.Option(help="dask.distributed scheduler address, e.g. tcp://host:8786.")
]
EveryOpt = Annotated[int, typer.Option(help="Keep every N-th eligible frame.")]
WindowOpt = Annotated[float, typer.Option(help="LiDAR points within +- this of the frame time (ms).")]
ExrOpt = Annotated[bool, typer.Option("--exr", help="Also write float32 EXR copies of the GT.")]
PngLevelOpt = Annotated[int, typer.Option(help="PNG deflate level 0-3 (ISA-L; 0 fastest, 3 smallest).")]
HeightFullOpt = Annotated[
    int | None, typer.Option(help="Rows of the full-sphere equirect (default from cam0).")
]
MinRangeOpt = Annotated[float, typer.Option(help="Drop LiDAR returns nearer than this (m): rig self-hits.")]
MotionOpt = Annotated[
    str, typer.Option(help="Motion compensation: full (IMU rotation + velocity), rotation, off.")
]
SalvageOpt = Annotated[bool, typer.Option("--salvage", help="Read every complete chunk of a truncated mcap.")]


def summary_table(summary: IngestSummary, out: Path) -> Table:
    """Frames, pairs, samples written/resumed/skipped, GT density, skew, motion and time per stage."""
    import numpy as np

    table = Table(title=f"{out}: {summary.written} samples written in {summary.seconds:.1f} s")
    table.add_column("item")
    table.add_column("value", justify="right")
    rows = [
        (
            "upper frames / stereo pairs / planned samples",
            f"{summary.frames} / {summary.pairs} / {summary.planned}",
        ),
        ("written / already done (resumed)", f"{summary.written} / {summary.resumed}"),
        *((f"skipped: {reason}", str(n)) for reason, n in summary.skipped.items()),
    ]
    if summary.density:
        rows += [
            ("GT density (fisheye, median)", f"{np.median(summary.density) * 100:.2f} %"),
            (
                "LiDAR skew |t_point - t_frame| max (median of samples)",
                f"{np.median(summary.skew_ms):.1f} ms",
            ),
            ("motion compensation applied", f"{summary.motion_applied} / {summary.written}"),
            *((f"time: {k}", f"{np.mean(v):.0f} ms/sample") for k, v in summary.stage_ms.items()),
            *(
                (f"time: {k} (helper thread, beside clouds + GT)", f"{np.mean(v):.0f} ms/sample")
                for k, v in summary.overlapped_ms.items()
            ),
        ]
    for item, value in rows:
        table.add_row(item, value)
    return table


def ingest_cmd(
    bags: BagsArg, rig: RigOpt, out: OutOpt, workers: WorkersOpt = 2, dask: DaskOpt = None,
    every: EveryOpt = 1, window_ms: WindowOpt = 50.0, exr: ExrOpt = False, png_level: PngLevelOpt = 1,
    height_full: HeightFullOpt = None, min_range: MinRangeOpt = 0.3, motion: MotionOpt = "full",
    salvage: SalvageOpt = False,
) -> None:  # fmt: skip
    """Turn recorded bags into the WideDepth training set (rectified equirect pairs + sparse GT)."""
    from ingest.train.pipeline import IngestConfig, ingest
    from ingest.train.sample import SampleParams
    from sensorbox.analysis.plots import plot_sample

    sample = SampleParams(min_range_m=min_range, exr=exr, png_level=png_level, motion=motion)  # type: ignore[arg-type]
    cfg = IngestConfig(
        rig=rig, out=out, workers=workers, every=every, lidar_window_ns=round(window_ms * 1e6),
        height_full=height_full, salvage=salvage, dask=dask, sample=sample,
    )  # fmt: skip
    with progress_bar("ingesting", "samples") as update:
        summary = ingest(bags, cfg, progress=update)
    console.print(summary_table(summary, out))
    metas = sorted((out / "meta").glob("*.json"))
    if metas:
        sid = metas[len(metas) // 2].stem
        console.print(f"Preview of sample {sid}: {plot_sample(out, sid, out / 'preview.png')}")
    console.print(f"Dataset: {out} (dataset.yaml describes it)")
