"""The ``sensorbox`` command line: one module per command, each parses, calls one library function, prints.

Every `SensorboxError` becomes one readable line on stderr and exit code 2.
"""

from __future__ import annotations

import sys

import typer

from calibration.errors import SensorboxError
from sensorbox.cli.bench import bench_cmd
from sensorbox.cli.calib import calib_check
from sensorbox.cli.capture import capture_cmd, launch_cmd
from sensorbox.cli.common import err_console
from sensorbox.cli.eval import eval_cmd, stats_cmd
from sensorbox.cli.ingest import ingest_cmd
from sensorbox.cli.inspect import inspect_cmd
from sensorbox.cli.render import render_benchmark_cmd
from sensorbox.cli.simulate import simulate_cmd

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
calib_app.command("check")(calib_check)
for name, command in (
    ("simulate", simulate_cmd), ("inspect", inspect_cmd), ("ingest", ingest_cmd), ("eval", eval_cmd),
    ("stats", stats_cmd), ("bench", bench_cmd), ("launch", launch_cmd), ("capture", capture_cmd),
    ("render-benchmark", render_benchmark_cmd),
):  # fmt: skip
    app.command(name)(command)


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
