"""`sensorbox calib check RIG_OR_CAMCHAIN [--plot rig.png]`: a calibration in numbers and a drawing."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.table import Table

from sensorbox.cli.common import check_out_file, console, path_param, print_warning

if TYPE_CHECKING:
    from calibration.report import RigReport

PathArg = Annotated[
    Path, typer.Argument(help="Rig file (sensorbox_rig YAML) or Kalibr camchain.", **path_param("RIG"))
]
PlotOpt = Annotated[
    Path | None,
    typer.Option("--plot", help="Write a top/side drawing of the rig (PNG).", **path_param("--plot")),
]


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


def cameras_table(report: RigReport, path: Path) -> Table:
    """Each camera's role, model, size, true horizontal, vertical and diagonal FOV and the model's limit."""
    cams = Table(title=f"Cameras of '{report.name}' ({path})")
    for col in ("camera", "role", "model", "size", "HFOV", "VFOV", "DFOV", "model limit"):
        cams.add_column(col)
    for c in report.cameras:
        fov = c.fov
        cams.add_row(
            c.name,
            c.role or "-",
            c.model,
            f"{c.params['width']}x{c.params['height']}",
            *(
                f"{math.degrees(a):.1f}°"
                for a in (fov.horizontal_rad, fov.vertical_rad, fov.diagonal_rad, fov.limit_rad)
            ),
        )
    return cams


def frames_table(report: RigReport) -> Table:
    """Every sensor frame's position and z axis in cam0, and its topic."""
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
    return frames


def calib_check(path: PathArg, plot: PlotOpt = None) -> None:
    """Print each camera's model, parameters and true FOV, the baseline and the rig's frames."""
    from calibration.rectify import stereo_warnings
    from calibration.report import describe_rig
    from calibration.rig import read_rig

    if plot is not None:
        check_out_file("--plot", plot)
    rig = read_rig(path)
    report = describe_rig(rig)
    console.print(cameras_table(report, path))
    for c in report.cameras:
        params = ", ".join(f"{k}={_fmt(v)}" for k, v in c.params.items() if k not in ("width", "height"))
        console.print(f"  {c.name}: {params}")
    console.print(frames_table(report))
    if report.baseline_m is not None:
        console.print(f"Stereo baseline upper->lower: [bold]{report.baseline_m * 1000:.2f} mm[/bold]")
    for line in stereo_warnings(rig):
        print_warning(line, console)
    if plot is not None:
        from sensorbox.analysis.plots import plot_rig

        out = plot_rig(rig, report, plot)
        console.print(f"Rig drawing written to {out}")
