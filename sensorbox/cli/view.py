"""`sensorbox view`: a dataset as a Rerun recording, opened in the Rerun viewer or saved as .rrd.

A plain typer command function registered by `sensorbox.cli`: it parses,
calls `sensorbox.analysis.view.view_dataset` under a progress bar and
prints one summary line. Errors are `SensorboxError`s, left to the main CLI
to turn into one line and exit code 2 (3 for a refused write).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from sensorbox.cli.common import check_not_an_input, check_out_file, human_bytes, path_param, progress_bar

if TYPE_CHECKING:
    from sensorbox.analysis.view_files import ViewSummary


def summary_line(summary: ViewSummary, dataset: Path, save: Path | None) -> str:
    """The command's closing line: what the recording holds and where it went."""
    unit = "samples" if summary.layout == "train" else "scenes"
    parts = [
        f"{dataset} ({summary.layout} layout): {summary.samples} {unit}",
        f"{summary.images} images",
        f"{summary.depth_images} depth images",
        f"{len(summary.series)} series ({summary.scalars} values)",
    ]
    if summary.layout == "train":
        parts.append(f"{summary.poses} on the trajectory")
    parts.append(f"{summary.frames} rig frames")
    if summary.missing_files:
        parts.append(f"missing files: {len(summary.missing_files)} (first: {summary.missing_files[0]})")
    where = f"saved {save} ({human_bytes(save.stat().st_size)})" if save else "sent to the Rerun viewer"
    return "; ".join(parts) + f"; {where}"


def view_cmd(
    dataset: Annotated[
        Path,
        typer.Argument(
            help="Dataset root: WideDepth train layout (ingest) or benchmark layout (render-benchmark).",
            **path_param("DATASET"),
        ),
    ],
    save: Annotated[
        Path | None,
        typer.Option(
            "--save",
            help="Write the recording to this .rrd file, not to a viewer ('rerun FILE' opens it).",
            **path_param("--save"),
        ),
    ] = None,
    full_res: Annotated[
        bool,
        typer.Option("--full-res", help="Images at full resolution (default: longest side at most 960 px)."),
    ] = False,
) -> None:
    """Browse a dataset in Rerun: images, GT depth and disparity, rig frames, trajectory and every number
    of meta/*.json as time series, on one timeline.

    Train layout: one step per sample at its exposure time (timeline 'time',
    also 'sample' by id). Benchmark layout: one step per scene (timeline
    'scene'). Without --save the Rerun viewer is spawned.
    """
    from ingest.eval.evaluate import detect_layout
    from sensorbox.analysis.view import view_dataset
    from sensorbox.analysis.view_files import MAX_SIDE_PX

    unit = "samples" if detect_layout(dataset) == "train" else "scenes"
    if save is not None:
        check_out_file("--save", save)
        if save.suffix != ".rrd":  # a recording inside the dataset is fine; one over its files is not
            check_not_an_input("--save", save, [dataset], "the dataset the viewer reads")
    with progress_bar("viewing", unit) as update:
        summary = view_dataset(dataset, save, None if full_res else MAX_SIDE_PX, progress=update)
    typer.echo(summary_line(summary, dataset, save))
