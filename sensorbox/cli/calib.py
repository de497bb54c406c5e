"""`sensorbox calib check RIG_OR_CAMCHAIN [--plot rig.png]`: a calibration in numbers and a drawing;
`sensorbox calib refine BAG... --rig RIG --out REFINED`: the clocks a recording reveals, as a refined rig."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.table import Table

from sensorbox.cli.common import (
    check_not_an_input,
    check_out_file,
    console,
    path_param,
    print_warning,
    progress_bar,
)

if TYPE_CHECKING:
    from calibration.report import RigReport
    from ingest.train.run.lidar_poses import LidarRefinement
    from ingest.train.run.refine import Refinement

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
    from calibration.housing import housing_warnings
    from calibration.rectify import MIN_BASELINE_M, rectify_rig, stereo_warnings
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
    for line in [*stereo_warnings(rig), *housing_warnings(rig)]:
        print_warning(line, console)
    if report.baseline_m is not None and report.baseline_m < MIN_BASELINE_M:
        rectify_rig(rig)  # refuses it as ingest does: the cameras are no stereo pair
    if plot is not None:
        from sensorbox.analysis.plots import plot_rig

        out = plot_rig(rig, report, plot)
        console.print(f"Rig drawing written to {out}")


BagsArg = Annotated[
    list[Path],
    typer.Argument(help="The recording: bag files or rosbag2 folders.", **path_param("BAGS", many=True)),
]
RigOpt = Annotated[
    Path,
    typer.Option(
        "--rig", help="The rig file to refine (sensorbox_rig YAML or camchain).", **path_param("--rig")
    ),
]
RefinedOpt = Annotated[
    Path,
    typer.Option(
        "--out", help="Refined rig file to write (its camchain is written beside it).", **path_param("--out")
    ),
]
WorkersOpt = Annotated[
    int,
    typer.Option(
        help="Local worker processes of the LiDAR alignment's sparse ingests (1 = in this process)."
    ),
]
ChartOpt = Annotated[
    Path | None,
    typer.Option(
        "--plot", help="Chart of the residual against the clock offset (PNG).", **path_param("--plot")
    ),
]


def refine_table(refinement: Refinement) -> Table:
    """Per camera: the rig's clock offset, the estimate with its evidence, and what the refined rig takes."""
    table = Table(
        title="Camera clock offsets to the LiDAR/IMU clock (timeshift_cam_imu: exposure = stamp + shift)"
    )
    for col in ("camera", "rig [ms]", "estimate [ms]", "1-sigma [ms]", "frame pairs", "rate change [deg/s]",
                "residual before -> after [deg]", "refined rig"):  # fmt: skip
        table.add_column(col, justify="left" if col in ("camera", "refined rig") else "right")
    for cam in refinement.cameras:
        e = cam.estimate
        table.add_row(
            cam.camera, f"{cam.rig_timeshift_ms:+.3f}",
            f"{e.timeshift_ms:+.3f}" if e.observable else "-", f"{e.sigma_ms:.3f}", str(e.pairs),
            f"{e.excitation_deg_s:.1f}", f"{e.residual_before_deg:.4f} -> {e.residual_after_deg:.4f}",
            "estimate" if cam.applied else "rig's value kept (see below)" if cam.rejected
            else "rig's value kept (not observable)",
        )  # fmt: skip
    return table


def imu_table(refinement: Refinement) -> Table:
    """Per IMU: its clock against cam0's exposures and its rotation correction (and its LiDAR's)."""
    table = Table(
        title="IMUs in cam0 (each Mid-360's IMU turns with its LiDAR): found from the gyro against cam0"
    )
    for col in ("imu", "lidar", "cam0 exposure on its clock [ms]", "rotation correction [deg]",
                "1-sigma [deg]", "residual before -> after [deg]", "refined rig"):  # fmt: skip
        table.add_column(col, justify="left" if col in ("imu", "lidar", "refined rig") else "right")
    moved = {lidar.lidar: lidar for lidar in refinement.lidars if lidar.applied}
    for imu in refinement.imus:
        t, r = imu.timeshift, imu.rotation
        outcome = "rotation refined" if r.observable else "rig's rotation kept (not observable)"
        if imu.lidar in moved:  # the housing turned as a whole by its LiDAR's pose correction
            outcome += f"; then turned with {imu.lidar} ({moved[imu.lidar].rotation_deg:.3f} deg)"
        table.add_row(
            imu.imu, imu.lidar or "-",
            f"{t.timeshift_ms:+.3f} ± {t.sigma_ms:.3f}" if t.observable else "not observable",
            f"{r.correction_deg:.3f}" if r.observable else "-", f"{r.sigma_deg:.3f}",
            f"{r.residual_before_deg:.4f} -> {r.residual_after_deg:.4f}", outcome,
        )  # fmt: skip
    return table


def lidar_table(refinement: Refinement) -> Table:
    """Per LiDAR: the correction of its pose from its points on cam0's images, and the misalignment
    before and after."""
    table = Table(title="LiDAR poses in cam0 (points laid onto cam0's images)", title_justify="left")
    for col in ("lidar", "correction [deg, mm]", "1-sigma [deg, mm]",
                "median misalignment before -> after [deg]", "samples", "refined rig"):  # fmt: skip
        table.add_column(col, justify="left" if col in ("lidar", "refined rig") else "right")
    for lidar in refinement.lidars:
        table.add_row(
            lidar.lidar, f"{lidar.rotation_deg:.3f}, {lidar.translation_mm:.1f}",
            f"{lidar.sigma_rotation_deg:.3f}, {lidar.sigma_translation_mm:.1f}",
            f"{lidar.shift_before_deg:.3f} -> {lidar.shift_after_deg:.3f}", str(lidar.samples),
            _lidar_outcome(lidar),
        )  # fmt: skip
    return table


def _lidar_outcome(lidar: LidarRefinement) -> str:
    """The lidar table's last column: what refine wrote for this LiDAR."""
    from ingest.train.run.lidar_poses import MAX_TRANSLATION_SIGMA_MM

    if lidar.applied and lidar.translation_held:
        return f"rotation refined; position kept (1-sigma over {MAX_TRANSLATION_SIGMA_MM:.0f} mm)"
    if lidar.applied:
        return "pose refined"
    if lidar.mismatch:
        return "rig's pose kept (see the line below)"
    return "rig's pose kept (uncertain and insignificant)"


def stereo_line(refinement: Refinement) -> str:
    """One line: the stereo rotation the cameras' own motion implies against the camchain's."""
    s = refinement.stereo
    if not s.observable:
        return f"Stereo rotation check: not observable from this recording ({s.pairs} frame pairs)."
    return (
        f"Stereo rotation check: the cameras' motion puts cam1 {s.angle_deg:.3f} deg from the camchain's "
        f"stereo rotation (1-sigma {s.sigma_deg:.3f} deg, {s.pairs} frame pairs; not changed by refine)."
    )


def calib_refine(
    bags: BagsArg, rig: RigOpt, out: RefinedOpt, plot: ChartOpt = None, workers: WorkersOpt = 2
) -> None:
    """Estimate the cameras' clock offsets and each LiDAR's pose in cam0 from a recording; write the refined
    rig.

    Needs a recording in which the rig turned for the clocks; what it cannot reveal keeps the rig's value
    (docs/refine.md).
    """
    import tempfile

    from calibration.housing import housing_warnings
    from calibration.rig import read_rig, write_rig
    from ingest.dataset.layout import write_atomic_set
    from ingest.train.run.pipeline import refine_rig

    check_out_file("--out", out)
    if plot is not None:
        check_out_file("--plot", plot)
    given = read_rig(rig)
    for line in housing_warnings(given):
        print_warning(line, console)
    read = [rig, *([Path(given.camchain.source)] if given.camchain and given.camchain.source else []), *bags]
    written = [("--out", out), ("--out", out.with_name(f"{out.stem}-camchain.yaml")), ("--plot", plot)]
    for flag, target in written:
        if target is not None:
            check_not_an_input(flag, target, read, "which refine reads (the rig, its camchain or a bag)")
    with progress_bar("reading frames and gyro", "messages") as update:
        refinement = refine_rig(
            bags, given, workers, progress=update,
            aligning=lambda done, total: update(done, total, "aligning LiDAR points to cam0", "samples"),
        )  # fmt: skip
    console.print(refine_table(refinement))
    console.print(imu_table(refinement))
    if refinement.lidars:
        console.print(lidar_table(refinement))
    console.print(stereo_line(refinement))
    frames = ", ".join(f"{n} {k}" for k, n in refinement.frames.items())
    readings = ", ".join(f"{n} {k}" for k, n in refinement.imu_readings.items())
    console.print(f"Read {frames} frames and {readings} gyro readings.")
    if refinement.stereo_alignment is not None:
        a = refinement.stereo_alignment
        console.print(
            f"Stereo pose check (LiDAR points on both images, {a.lidar}): the camchain's T_cam1_cam0 is "
            f"{a.rotation_deg:.3f} deg and {a.translation_mm:.1f} mm from what they say (1-sigma "
            f"{a.sigma_rotation_deg:.3f} deg, {a.sigma_translation_mm:.1f} mm; not changed by refine)."
        )
    if refinement.image_clock_ms is not None:
        ms, sigma = refinement.image_clock_ms
        console.print(
            f"Check: the LiDAR points on cam0's images put its refined clock {ms:+.3f} ms "
            f"(1-sigma {sigma:.3f}) off."
        )
    for line in refinement.unobserved_lines():
        print_warning(line, console)
    with tempfile.TemporaryDirectory() as tmp:  # the rig and its camchain written as one set, or neither
        chain = write_rig(refinement.rig, Path(tmp) / out.name)
        write_atomic_set(
            [(out, (Path(tmp) / out.name).read_bytes()), (out.parent / chain.name, chain.read_bytes())]
        )
    console.print(f"Refined rig written to {out}")
    if plot is not None:
        from sensorbox.analysis.plots import plot_timeshift

        console.print(f"Chart written to {plot_timeshift(refinement, plot)}")
