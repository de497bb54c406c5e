"""`sensorbox bench`: speed vs accuracy of the ingest alternatives, and equirect vs cubemap stereo.

Parses, runs `sensorbox.analysis.bench.run_bench` (which documents what is
written) with a progress line, prints its markdown report.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Annotated

import typer

from sensorbox.cli.common import check_out_folder, path_param, progress_bar

OutOpt = Annotated[Path, typer.Option(help="Folder for the CSVs and charts.", **path_param("--out"))]
BagOpt = Annotated[
    list[Path] | None,
    typer.Option(
        help="Simulator bag(s) with BAG.truth/ (repeatable; default: simulate two).",
        **path_param("--bag", many=True),
    ),
]
QuickOpt = Annotated[
    bool, typer.Option("--quick", help="A small run: five alternatives, every 3rd frame, 0.25 scale.")
]
ScaleOpt = Annotated[float | None, typer.Option(help="Image scale of simulated bags (default 0.5).")]
DurationOpt = Annotated[float, typer.Option(help="Seconds per simulated bag.")]
EveryOpt = Annotated[int | None, typer.Option(help="Keep every N-th frame (default 1, quick 3).")]
OnlyOpt = Annotated[
    list[str] | None, typer.Option(help="Run only these alternatives (repeatable; see the CSV names).")
]
ProjectionOpt = Annotated[
    bool, typer.Option("--projection/--no-projection", help="Also compare equirect vs cubemap SGBM.")
]
DenseOpt = Annotated[
    bool,
    typer.Option(
        "--dense",
        help="Instead: dense vs sparse GT at full resolution (density x accuracy x window, movers, noise; "
        "bench/bench_dense.py); about 30 minutes on 2 cores.",
    ),
]
RepeatsOpt = Annotated[
    int, typer.Option(help="Timing rounds (each sample's time is the median; accuracy from the first).")
]


def bench_cmd(
    out: OutOpt = Path("out/bench"), bag: BagOpt = None, quick: QuickOpt = False, scale: ScaleOpt = None,
    duration: DurationOpt = 0.5, every: EveryOpt = None, only: OnlyOpt = None,
    projection: ProjectionOpt = True, repeats: RepeatsOpt = 1, dense: DenseOpt = False,
) -> None:  # fmt: skip
    """Speed vs accuracy of the ingest pipeline's alternatives on simulated bags with exact truth.

    Alternatives: occlusion filter off / window sizes / z-buffer order
    flipped, motion compensation off / rotation only, equirect resolution,
    image interpolation, PNG level, and the default run again (an A/A control:
    how far timing noise alone moves a point). Prints markdown tables and
    writes bench_tradeoff.csv/.png (Pareto front) and bench_projection.csv/.png.
    """
    from sensorbox.analysis.bench import bench_bags, bench_report, bench_settings, default_sims, run_bench

    if dense:
        return dense_study(out)
    check_out_folder("--out", out, "the CSVs and charts")
    alternatives, step = bench_settings(only or [], quick, every, repeats, duration)
    with (
        tempfile.TemporaryDirectory(prefix="sensorbox-bench-") as tmp,
        progress_bar("bench", "steps") as update,
    ):
        steps = {"done": 0, "total": 0}

        def on_step(what: str) -> None:  # called as each step starts: the ones before it are done
            update(steps["done"], steps["total"], note=what[:60])
            steps["done"] += 1

        sim_scale = (0.25 if quick else 0.5) if scale is None else scale  # 0 is refused, not the default
        steps["total"] = 0 if bag else len(default_sims(sim_scale, duration))  # simulated when none given
        bags = bench_bags(bag or [], Path(tmp), sim_scale, duration, on_step)
        steps["done"], steps["total"] = 0, len(alternatives) * len(bags) * repeats + int(projection)
        result = run_bench(bags, out, alternatives, Path(tmp) / "work", step, projection, repeats, on_step)
    typer.echo(bench_report(result, bags))


def dense_study(out: Path) -> None:
    """`sensorbox bench --dense`: the dense-GT study's table as it is measured, the trajectory, the chart."""
    from sensorbox.analysis.dense_study import dense_chart, format_row, run_dense_study, table_header

    check_out_folder("--out", out, "dense.png")
    typer.echo(table_header())
    with tempfile.TemporaryDirectory(prefix="sensorbox-dense-") as tmp:
        result = run_dense_study(Path(tmp), on_row=lambda *row: typer.echo(format_row(*row)))
    typer.echo(result.trajectory_line())
    out.mkdir(parents=True, exist_ok=True)
    dense_chart(result.rows, out / "dense.png")
    typer.echo(f"chart: {out / 'dense.png'}")
