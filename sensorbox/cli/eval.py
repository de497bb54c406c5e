"""`sensorbox eval` and `sensorbox stats`: score predictions, describe a dataset.

Plain typer command functions registered by `sensorbox.cli`. They parse, call
`ingest.eval.evaluate.evaluate` / `ingest.eval.stats.dataset_stats`, print markdown
tables and write JSON and PNG files. Errors are `SensorboxError`s, left to
the main CLI to turn into one line and exit code 2.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from sensorbox.cli.common import check_out_file, check_out_folder, path_param, print_warning, progress_bar

if TYPE_CHECKING:
    from ingest.eval.evaluate import EvalReport
    from ingest.eval.request import EvalRequest
    from ingest.eval.stats import DatasetStats

MISSING_LISTED = 20  # missing predictions printed by name; the JSON lists all


def _echo(text: str = "") -> None:
    typer.echo(text)


DatasetOpt = Annotated[
    Path,
    typer.Option(
        "--dataset",
        help="Dataset root: WideDepth train layout or benchmark layout.",
        **path_param("--dataset"),
    ),
]
PredOpt = Annotated[
    Path,
    typer.Option(
        "--pred",
        help="Predictions: the GT's relative path and stem, as .png (uint16), .exr or .npy.",
        **path_param("--pred"),
    ),
]
TaskOpt = Annotated[str, typer.Option("--task", help="stereo (disparity) | mono | completion (depth).")]
ByOpt = Annotated[
    list[str] | None, typer.Option("--by", help="Group by fov | baseline (repeat for both; benchmark).")
]
CompareOpt = Annotated[
    str | None,
    typer.Option("--compare", help="A,B: percentage change of A vs B, e.g. 195FOV,120FOV or 200mm,65mm."),
]
HeatmapOpt = Annotated[
    Path | None,
    typer.Option("--heatmap", help="Write a PNG of --metric over FOV x baseline.", **path_param("--heatmap")),
]
MetricOpt = Annotated[
    str | None, typer.Option(help="Metric of the heatmap (default epe_px for stereo, abs_rel for depth).")
]
RegionOpt = Annotated[str, typer.Option(help="Region of --compare and --heatmap: all | edges | a mask.")]
JsonOpt = Annotated[
    Path | None,
    typer.Option("--json", help="JSON report (default: <pred>/eval_<task>.json).", **path_param("--json")),
]
ImageTypeOpt = Annotated[
    str | None,
    typer.Option(help="Benchmark view to score only (fisheye, pano, pano_crop, ...); benchmark layout only."),
]
MaskOpt = Annotated[
    list[str] | None,
    typer.Option(help="Extra region NAME=DIR: PNG masks named like the GT, non-zero inside (repeatable)."),
]
EdgesOpt = Annotated[
    bool, typer.Option("--edges/--no-edges", help="Also score the band of 3 px around GT edges.")
]
AlignOpt = Annotated[
    str, typer.Option(help="Depth only: none | median (per-sample median scaling of relative depth).")
]


def _print_report(report: EvalReport, task: str, dataset: Path) -> None:
    """One markdown table per region, then the samples that had no prediction."""
    from ingest.eval.report import markdown_table

    n_gt = len(report.samples) + len(report.missing)
    _echo(f"# {task} on {dataset} ({report.layout} layout): {len(report.samples)} of {n_gt} samples scored")
    for r in report.regions:
        _echo(f"\n## region: {r}\n")
        _echo(markdown_table(report, r))
    if report.missing:
        _echo(f"\nMissing predictions: {len(report.missing)} of {n_gt} (not scored):")
        for rel in report.missing[:MISSING_LISTED]:
            _echo(f"  {rel}")
        if len(report.missing) > MISSING_LISTED:
            _echo(f"  ... and {len(report.missing) - MISSING_LISTED} more (all in the JSON)")


def _print_compare(report: EvalReport, req: EvalRequest) -> None:
    """The --compare table, when asked for."""
    from ingest.eval import report as rp

    if req.pair is not None:
        a, b = req.pair
        _echo(f"\n## {a} vs {b} (region {req.region}; change = (A - B) / |B|)\n")
        _echo(rp.markdown_compare(rp.compare(report, a, b, req.region), a, b))


def _heatmap(report: EvalReport, req: EvalRequest, heatmap: Path, name: str, task: str, pred: Path) -> bytes:
    """The --heatmap chart's file bytes: metric `name` over FOV x baseline."""
    from ingest.eval import report as rp
    from sensorbox.analysis.plots import draw_heatmap

    title = f"{task}: {name} ({req.region}), {pred.name}"
    return draw_heatmap(rp.heatmap(report, name, req.region), heatmap, title)


def eval_cmd(
    dataset: DatasetOpt, pred: PredOpt, task: TaskOpt, by: ByOpt = None, compare: CompareOpt = None,
    heatmap: HeatmapOpt = None, metric: MetricOpt = None, region: RegionOpt = "all", json_out: JsonOpt = None,
    image_type: ImageTypeOpt = None, mask: MaskOpt = None, edges: EdgesOpt = True, align: AlignOpt = "none",
) -> None:  # fmt: skip
    """Score depth or disparity predictions against a dataset's GT: markdown tables, JSON, heatmap.

    Metrics are over valid GT only (coverage = share of it with a prediction);
    stereo: EPE, median, p95, bad-1/2/3 (px); depth: AbsRel, MAE, RMSE,
    delta < 1.25^k. Totals pool every pixel.
    """
    from ingest.dataset.layout import write_atomic_set
    from ingest.errors import EvalError
    from ingest.eval.evaluate import PRED_EXTS, evaluate, report_json
    from ingest.eval.request import eval_request

    req = eval_request(
        task, by or [], compare, heatmap is not None, mask or [], region, image_type, edges, align
    )
    for flag, path in (("--json", json_out), ("--heatmap", heatmap)):
        if path is not None:
            check_out_file(flag, path)
            _not_an_input(flag, path, dataset, pred, [Path(m.partition("=")[2]) for m in mask or []])
    with progress_bar("scoring", "samples") as update:
        report = evaluate(dataset, pred, req.options, progress=update)
    if not report.samples and report.missing:
        raise EvalError(
            f"{pred}: no prediction for any of the {len(report.missing)} GT samples of {dataset}; "
            f"expected files such as {pred / report.missing[0]}{{{','.join(PRED_EXTS)}}} "
            "(the prediction folder mirrors the dataset's)"
        )
    _print_report(report, task, dataset)
    _print_compare(report, req)
    out = json_out or pred / f"eval_{task}.json"
    name = metric or report.columns[0]
    files = [(out, report_json(report))]
    if heatmap is not None:  # the JSON and the chart are written as one set: both, or neither
        files.append((heatmap, _heatmap(report, req, heatmap, name, task, pred)))
    write_atomic_set(files)
    if heatmap is not None:
        _echo(f"\nHeatmap of {name} over FOV x baseline: {heatmap}")
    _echo(f"JSON report: {out}")


def _not_an_input(flag: str, path: Path, dataset: Path, pred: Path, masks: list[Path]) -> None:
    """Refuse a report path among the files eval reads: anywhere in the dataset, in the prediction
    folder below its top level (the predictions mirror the dataset there), or in a mask folder."""
    from calibration.files import resolved
    from ingest.errors import DatasetError

    where = resolved(path, DatasetError)
    for folder, what in [(dataset, "the dataset"), *((m, "a --mask folder") for m in masks)]:
        if where.is_relative_to(resolved(folder, DatasetError)):
            raise DatasetError(
                f"{flag} {path}: inside {what} ({folder}), whose files eval reads; give a path outside it"
            )
    top = resolved(pred, DatasetError)
    if where.is_relative_to(top) and where.parent != top:
        raise DatasetError(
            f"{flag} {path}: among the predictions ({pred}), whose files eval reads; give a path outside "
            f"{pred} or at its top level"
        )


def _print_stats(stats: DatasetStats, dataset: Path) -> None:
    """The depth histogram, GT density and entropy as markdown tables."""
    _echo(f"# {dataset} ({stats.layout} layout): {len(stats.samples)} depth maps\n")
    _echo("| depth | " + " | ".join(stats.bins) + " |")
    _echo("|---|" + "---|" * len(stats.bins))
    _echo("| valid GT pixels | " + " | ".join(str(c) for c in stats.depth_counts) + " |")
    shares = ("-" if math.isnan(s) else f"{100.0 * s:.2f}" for s in stats.depth_shares)
    _echo("| share [%] | " + " | ".join(shares) + " |\n")
    entropy = "-" if math.isnan(stats.entropy_mean_bits) else f"{stats.entropy_mean_bits:.3f}"
    _echo("| GT density [%] (mean of samples) | mean local entropy 11x11 [bits] |")
    _echo("|---|---|")
    _echo(f"| {100.0 * stats.density_mean:.3f} | {entropy} |")
    if stats.missing_images:
        listed = ", ".join(map(_printable, stats.missing_images[:MISSING_LISTED]))
        _echo(f"\nNo image for {len(stats.missing_images)} depth map(s), entropy left out: {listed}")
    if stats.missing_gt:
        listed = ", ".join(map(_printable, stats.missing_gt[:MISSING_LISTED]))
        print_warning(
            f"{dataset}: {len(stats.missing_gt)} finished sample(s) (meta/<id>.json) have no depth map "
            f"(depth_fisheye/<id>.png), left out of these statistics: {listed}"
        )


def _printable(name: str) -> str:
    """A file name as listed in one line: quoted with escapes when it holds a newline or another control
    character (a name with a newline split the warning into two lines)."""
    return name if name.isprintable() else repr(name)


def stats_cmd(
    dataset: Annotated[
        Path,
        typer.Argument(
            help="Dataset root: WideDepth train layout or benchmark layout.", **path_param("DATASET")
        ),
    ],
    out: Annotated[
        Path | None,
        typer.Option(
            "--out", help="Folder for stats.json and stats.png (default: DATASET).", **path_param("--out")
        ),
    ] = None,
    image_type: Annotated[
        str | None,
        typer.Option(
            help="Benchmark view to describe only (fisheye, pano, pano_crop, ...); benchmark layout only."
        ),
    ] = None,
) -> None:
    """Depth distribution (0-1, 1-2, 2-5, 5-10, 10+ m), GT density and mean 11x11 local entropy.

    Uses each sample's depth GT and its image (train: depth_fisheye + left_fisheye;
    benchmark: CENTER/depth/<view> + CENTER/<view>). Writes stats.json and the
    histograms as stats.png.
    """
    from ingest.eval.stats import dataset_stats
    from sensorbox.analysis.plots import write_stats

    folder = out or dataset
    if out is not None:
        check_out_folder("--out", folder, "stats.json and stats.png")
    with progress_bar("describing", "samples") as update:
        stats = dataset_stats(dataset, image_type, progress=update)
    _print_stats(stats, dataset)
    numbers, png = write_stats(stats, folder)
    _echo()
    _echo(f"Numbers: {numbers}; histograms: {png}")
