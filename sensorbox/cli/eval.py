"""`sensorbox eval` and `sensorbox stats`: score predictions, describe a dataset.

Plain typer command functions registered by `sensorbox.cli`. They parse, call
`ingest.eval.evaluate.evaluate` / `ingest.eval.stats.dataset_stats`, print markdown
tables and write JSON and PNG files. Errors are `SensorboxError`s, left to
the main CLI to turn into one line and exit code 2.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from calibration.errors import SensorboxError

progress_console = Console(stderr=True)
MISSING_LISTED = 20  # missing predictions printed by name; the JSON lists all


def _echo(text: str = "") -> None:
    typer.echo(text)


def _progress(what: str) -> Progress:
    columns = (TextColumn(what), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
    return Progress(*columns, console=progress_console, transient=True, disable=not sys.stderr.isatty())


def _parse_masks(items: list[str]) -> tuple[tuple[str, Path], ...]:
    out = []
    for item in items:
        name, sep, folder = item.partition("=")
        if not sep or not name or not folder:
            raise SensorboxError(f"--mask {item!r}: expected NAME=DIR (e.g. stable=out/stability)")
        out.append((name, Path(folder)))
    return tuple(out)


def eval_cmd(
    dataset: Annotated[
        Path, typer.Option("--dataset", help="Dataset root: WideDepth train layout or benchmark layout.")
    ],
    pred: Annotated[
        Path,
        typer.Option(
            "--pred", help="Predictions: the GT's relative path and stem, as .png (uint16), .exr or .npy."
        ),
    ],
    task: Annotated[str, typer.Option("--task", help="stereo (disparity) | mono | completion (depth).")],
    by: Annotated[
        list[str] | None, typer.Option("--by", help="Group by fov | baseline (repeat for both; benchmark).")
    ] = None,
    compare: Annotated[
        str | None,
        typer.Option("--compare", help="A,B: percentage change of A vs B, e.g. 195FOV,120FOV or 200mm,65mm."),
    ] = None,
    heatmap: Annotated[
        Path | None, typer.Option("--heatmap", help="Write a PNG of --metric over FOV x baseline.")
    ] = None,
    metric: Annotated[
        str | None, typer.Option(help="Metric of the heatmap (default epe_px for stereo, abs_rel for depth).")
    ] = None,
    region: Annotated[
        str, typer.Option(help="Region of --compare and --heatmap: all | edges | a mask.")
    ] = "all",
    json_out: Annotated[
        Path | None, typer.Option("--json", help="JSON report (default: <pred>/eval_<task>.json).")
    ] = None,
    image_type: Annotated[
        str | None, typer.Option(help="Benchmark view to score only (fisheye, pano, pano_crop, ...).")
    ] = None,
    mask: Annotated[
        list[str] | None,
        typer.Option(
            help="Extra region NAME=DIR: PNG masks named like the GT, non-zero inside (repeatable)."
        ),
    ] = None,
    edges: Annotated[
        bool, typer.Option("--edges/--no-edges", help="Also score the band of 3 px around GT edges.")
    ] = True,
    align: Annotated[
        str, typer.Option(help="Depth only: none | median (per-sample median scaling of relative depth).")
    ] = "none",
) -> None:
    """Score depth or disparity predictions against a dataset's GT: markdown tables, JSON, heatmap.

    Metrics are over valid GT only (coverage = share of it with a prediction);
    stereo: EPE, median, p95, bad-1/2/3 (px); depth: AbsRel, MAE, RMSE,
    delta < 1.25^k. Totals pool every pixel.
    """
    from ingest.eval import evaluate as ev

    if task not in ev.TASKS:
        raise SensorboxError(f"--task {task!r}: expected one of {', '.join(ev.TASKS)}")
    keys = list(dict.fromkeys(by or []))
    pair: tuple[str, str] | None = None
    if compare is not None:
        a, sep, b = compare.partition(",")
        if not sep:
            raise SensorboxError(f"--compare {compare!r}: expected A,B (e.g. 195FOV,120FOV)")
        pair = (a.strip(), b.strip())
        key = ev.parse_config_label(pair[0])[0]
        if key not in keys:
            keys.append(key)
    if heatmap is not None:
        keys += [k for k in ev.GROUP_KEYS if k not in keys]
    masks = _parse_masks(mask or [])
    regions = ("all", *(["edges"] if edges else []), *(name for name, _ in masks))
    if region not in regions:
        raise SensorboxError(f"--region {region!r}: expected one of {', '.join(regions)}")
    opts = ev.EvalOptions(
        task=task,
        by=tuple(keys),
        image_type=image_type,
        edges=edges,
        masks=masks,
        align=align,  # type: ignore[arg-type]
    )
    with _progress("scoring") as bar:
        job = bar.add_task("eval", total=None)
        report = ev.evaluate(dataset, pred, opts, progress=lambda d, t: bar.update(job, completed=d, total=t))
    n_gt = len(report.samples) + len(report.missing)
    _echo(f"# {task} on {dataset} ({report.layout} layout): {len(report.samples)} of {n_gt} samples scored")
    for r in report.regions:
        _echo()
        _echo(f"## region: {r}")
        _echo()
        _echo(ev.markdown_table(report, r))
    if report.missing:
        _echo()
        _echo(f"Missing predictions: {len(report.missing)} of {n_gt} (not scored):")
        for rel in report.missing[:MISSING_LISTED]:
            _echo(f"  {rel}")
        if len(report.missing) > MISSING_LISTED:
            _echo(f"  ... and {len(report.missing) - MISSING_LISTED} more (all in the JSON)")
    if pair is not None:
        rows = ev.compare(report, pair[0], pair[1], region)
        _echo()
        _echo(f"## {pair[0]} vs {pair[1]} (region {region}; change = (A - B) / |B|)")
        _echo()
        _echo(ev.markdown_compare(rows, pair[0], pair[1]))
    if heatmap is not None:
        from sensorbox.analysis.plots import plot_heatmap

        name = metric or report.columns[0]
        grid = ev.heatmap(report, name, region)
        title = f"{task}: {name} ({region}), {pred.name}"
        _echo()
        _echo(f"Heatmap of {name} over FOV x baseline: {plot_heatmap(grid, heatmap, title)}")
    out = ev.write_report_json(report, json_out or pred / f"eval_{task}.json")
    _echo(f"JSON report: {out}")


def stats_cmd(
    dataset: Annotated[
        Path, typer.Argument(help="Dataset root: WideDepth train layout or benchmark layout.")
    ],
    out: Annotated[
        Path | None, typer.Option("--out", help="Folder for stats.json and stats.png (default: DATASET).")
    ] = None,
    image_type: Annotated[
        str | None, typer.Option(help="Benchmark view to describe only (fisheye, pano, pano_crop, ...).")
    ] = None,
) -> None:
    """Depth distribution (0-1, 1-2, 2-5, 5-10, 10+ m), GT density and mean 11x11 local entropy.

    Uses each sample's depth GT and its image (train: depth_fisheye + left_fisheye;
    benchmark: CENTER/depth/<view> + CENTER/<view>). Writes stats.json and the
    histograms as stats.png.
    """
    from ingest.dataset.layout import write_atomic
    from ingest.eval.stats import dataset_stats
    from sensorbox.analysis.plots import plot_stats

    with _progress("describing") as bar:
        job = bar.add_task("stats", total=None)
        stats = dataset_stats(
            dataset, image_type, progress=lambda d, t: bar.update(job, completed=d, total=t)
        )
    folder = out or dataset
    folder.mkdir(parents=True, exist_ok=True)
    _echo(f"# {dataset} ({stats.layout} layout): {len(stats.samples)} depth maps")
    _echo()
    _echo("| depth | " + " | ".join(stats.bins) + " |")
    _echo("|---|" + "---|" * len(stats.bins))
    _echo("| valid GT pixels | " + " | ".join(str(c) for c in stats.depth_counts) + " |")
    shares = ("-" if math.isnan(s) else f"{100.0 * s:.2f}" for s in stats.depth_shares)
    _echo("| share [%] | " + " | ".join(shares) + " |")
    _echo()
    entropy = "-" if math.isnan(stats.entropy_mean_bits) else f"{stats.entropy_mean_bits:.3f}"
    _echo("| GT density [%] (mean of samples) | mean local entropy 11x11 [bits] |")
    _echo("|---|---|")
    _echo(f"| {100.0 * stats.density_mean:.3f} | {entropy} |")
    if stats.missing_images:
        _echo()
        listed = ", ".join(stats.missing_images[:MISSING_LISTED])
        _echo(f"No image for {len(stats.missing_images)} depth map(s), entropy left out: {listed}")
    doc = json.dumps(stats.to_json(), indent=1) + "\n"
    write_atomic(folder / "stats.json", doc.encode())
    png = plot_stats(stats, folder / "stats.png")
    _echo()
    _echo(f"Numbers: {folder / 'stats.json'}; histograms: {png}")
