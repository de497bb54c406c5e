"""`sensorbox ingest BAG... --rig RIG --out DIR`: recorded bags -> the WideDepth training set.

Parses the options into an `ingest.train.run.settings.IngestConfig`, runs `ingest`
with a progress bar, prints the summary and then draws a preview of the middle
sample (after the run and its summary: not part of the run's time; a few seconds
of matplotlib at full resolution, `--no-preview` skips it).
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.table import Table

from sensorbox.cli.common import (
    check_out_folder,
    console,
    err_console,
    path_param,
    print_warning,
    progress_bar,
)

if TYPE_CHECKING:
    from ingest.errors import SettingError
    from ingest.train.run.summary import IngestSummary
    from ingest.train.trajectory.segments import SegmentParams

BagsArg = Annotated[
    list[Path],
    typer.Argument(
        help="Bags: ROS 1 .bag, ROS 2 .mcap/.db3 files or rosbag2 folders.", **path_param("BAGS", many=True)
    ),
]
RigOpt = Annotated[
    Path, typer.Option(help="Rig file (cameras, LiDARs, IMUs and their topics).", **path_param("--rig"))
]
OutOpt = Annotated[
    Path, typer.Option(help="Output folder (WideDepth train layout); reruns resume.", **path_param("--out"))
]
WorkersOpt = Annotated[
    int,
    typer.Option(
        help="Local worker processes (1 = in this process). With more, a recording over 10 s runs its "
        "trajectory pass as joined segments on them too."
    ),
]
DaskOpt = Annotated[
    str | None,
    typer.Option(
        help="dask.distributed scheduler address, e.g. tcp://host:8786; checked before anything is written. "
        "The workers read the bags for the trajectory pass's segments at the paths given here."
    ),
]
EveryOpt = Annotated[int, typer.Option(help="Keep every N-th eligible frame.")]
WindowOpt = Annotated[
    float, typer.Option(help="Sparse GT: LiDAR points within +- this of the frame time (ms).")
]
GtOpt = Annotated[
    str,
    typer.Option(
        help="Ground truth: auto (dense when the trajectory is sound, else sparse; the decision goes to "
        "dataset.yaml and every meta file), dense (every sweep of --gt-window-ms placed by the "
        "recording's LiDAR-inertial trajectory, movers removed) or sparse (the frame's own sweeps: no "
        "trajectory pass, the fastest)."
    ),
]
GtWindowOpt = Annotated[
    float | None,
    typer.Option(
        help="Dense GT: sweeps within +- this of the frame time (ms). Default 500; --gt auto widens the "
        "default to 1000 for a rig that stood still."
    ),
]
BackendOpt = Annotated[
    str,
    typer.Option(
        help="Dense GT renderer: numba (compiled CPU kernels), numpy (reference), torch (PyTorch on the "
        "CPU) or cuda (PyTorch on the GPU); the same GT."
    ),
]
ExrOpt = Annotated[bool, typer.Option("--exr", help="Also write float32 EXR copies of the GT.")]
PngLevelOpt = Annotated[int, typer.Option(help="PNG deflate level 0-3 (ISA-L; 0 fastest, 3 smallest).")]
HeightFullOpt = Annotated[
    int | None,
    typer.Option(
        help="Rows of the full-sphere equirect (default from cam0's centre resolution, "
        "the sphere at most 16x its pixels)."
    ),
]
MinRangeOpt = Annotated[float, typer.Option(help="Drop LiDAR returns nearer than this (m): rig self-hits.")]
MotionOpt = Annotated[
    str, typer.Option(help="Motion compensation: full (IMU rotation + velocity), rotation, off.")
]
MaxBadOpt = Annotated[
    int,
    typer.Option(
        help="Skip and count up to N undecodable messages (a warning names each one's bag, topic and time); "
        "one more stops the run (exit code 2). The count goes to the summary and dataset.yaml."
    ),
]
RefineOpt = Annotated[
    bool,
    typer.Option(
        "--refine",
        help="First estimate each camera's clock offset and each LiDAR's rotation from the bags "
        "(`sensorbox calib refine`) and ingest with the refined rig; what the recording cannot reveal "
        "(a rig that stood still) keeps the rig's value, with a warning.",
    ),
]
SegmentOpt = Annotated[
    float,
    typer.Option(
        "--segment-s",
        help="--gt dense or auto with --workers 2 or more, or --dask: the trajectory pass runs as segments "
        "of at most this many seconds, overlapping by 3 s, each a job of the workers, joined into one "
        "trajectory; at least 8.5. A recording no longer than this, or 'inf', runs it as one pass.",
    ),
]
PreviewOpt = Annotated[
    bool, typer.Option(help="After the summary, draw preview.png of the middle sample (matplotlib).")
]
SalvageOpt = Annotated[
    bool,
    typer.Option(
        "--salvage",
        help="Read mcap files record by record: keep what a truncated or damaged file still holds; skip "
        "corrupt chunks (failed CRC or decompression, any format) and count their messages as lost, "
        "planning no sample whose LiDAR/IMU window overlaps them. Without it a corrupt chunk stops the "
        "run, naming it, before anything is written.",
    ),
]

MAX_WINDOW_MS = 3_600_000.0
"""Largest LiDAR window (+- ms) an option may ask for: an hour."""


Rows = list[tuple[str, str]]


def _when(shown: object, item: str, value: str) -> Rows:
    """[(item, value)] when `shown` is truthy: a row the table holds only when it has something to say."""
    return [(item, value)] if shown else []


def _count_rows(s: IngestSummary) -> Rows:
    """What the passes found and the samples came to: frames, pairs, written, resumed, skipped, dropped."""
    gaps = s.imu_gaps_ms
    return [
        ("upper frames / stereo pairs / planned samples", f"{s.frames} / {s.pairs} / {s.planned}"),
        *_when(s.uncovered, "stereo pairs without LiDAR points in their window (not planned)",
               str(s.uncovered)),
        *_when(gaps, "IMU gaps over 5 periods (longest)", f"{len(gaps)} ({max(gaps, default=0):.0f} ms)"),
        ("written / already done (resumed)", f"{s.written} / {s.resumed}"),
        *_when(s.without_gt, "written without any GT pixel", str(s.without_gt)),
        *_when(s.held_elsewhere, "already done: frames another sample holds (not written twice)",
               str(s.held_elsewhere)),
        *_when(s.damaged, "finished samples found damaged, written again", str(len(s.damaged))),
        ("ground truth", f"{s.method} ({s.decision})"),
        *((f"skipped: {reason}", str(n)) for reason, n in s.skipped.items()),
        *((f"written, flagged in meta: {what}", str(n)) for what, n in s.flagged.items()),
        *((f"undecodable messages skipped: {topic}", str(n)) for topic, n in s.undecodable.items()),
        *((f"dropped, {why}: {topic}", f"{n:,}")
          for topic, counts in s.dropped.items() for why, n in counts.items()),
        *((f"lost in corrupt chunks: {topic}", str(n)) for topic, n in s.lost.items()),
        *((f"messages repeating a stamp, first read: {topic}", str(n)) for topic, n in s.duplicates.items()),
        *_when(s.stale_temporaries, "unfinished temporary files of a killed run, removed",
               str(s.stale_temporaries)),
    ]  # fmt: skip


def _pass_rows(s: IngestSummary) -> Rows:
    """The trajectory pass and the one-off start-up costs (compiling, dense GT's warm-up and blocks)."""
    rows: Rows = []
    if s.trajectory is not None:
        t = s.trajectory
        residual = f"{t.residual_median_mm:.2f} / {t.residual_p95_mm:.2f} mm"
        took = f"{t.seconds:.1f} s" + (", the earlier run's pass reused" if t.reused else "")
        rows.append(("trajectory (knots, residual median / p95, time)", f"{t.knots}, {residual}, {took}"))
        if t.split is not None:
            mm, deg = t.split.worst()
            rows.append((
                "trajectory segments on the workers (segments, jobs, joins' largest RMS residual)",
                f"{t.split.segments}, {t.split.jobs}, {mm:.1f} mm / {deg:.3f} deg",
            ))  # fmt: skip
            rows += [("trajectory segments run again as one job", line) for line in t.split.run_again]
        rows += _when(
            t.gaps, "trajectory gaps: knots carried by prediction (too few LiDAR points)", str(t.gaps)
        )
        rows.append(("trajectory file (TUM, T_world_cam0)", t.file))
    # the first run of a checkout compiles the kernels: the stage times include it
    rows += _when(s.compile_s >= 0.5, "numba kernels compiled (once: cached on disk for later runs)",
                  f"{s.compile_s:.1f} s")  # fmt: skip
    if s.dense_warm_up_s is not None:
        rows.append(("dense GT start-up: kernels and pixel rays, once", f"{s.dense_warm_up_s:.1f} s"))
    if s.dense_planes is not None:  # fitted and tested as tasks of the workers (the workers' seconds)
        blocks, seconds = s.dense_planes
        rows.append(("dense GT blocks: planes and free space once, time", f"{blocks}, {seconds:.1f} s"))
    return rows


OPTIONS: dict[str, tuple[str, float | None]] = {
    "gt": ("--gt", None),
    "lidar_window_ns": ("--window-ms", 1e-6),
    "sample.dense.window_ns": ("--gt-window-ms", 1e-6),
    "sample.motion": ("--motion", None),
    "sample.png_level": ("--png-level", None),
    "sample.min_range_m": ("--min-range", None),
    "sample.dense.render.backend": ("--backend", None),
    "max_bad": ("--max-bad", None),
    "workers": ("--workers", None),
    "every": ("--every", None),
    "height_full": ("--height-full", None),
    "dask": ("--dask", None),
    "trajectory_segments.length_ns": ("--segment-s", 1e-9),
}
"""The option that sets each `IngestConfig` setting (a dotted field) and the factor from the field's unit
to the option's (ns -> ms), so that an error names what the user typed."""


def option_line(err: SettingError) -> str:
    """`err`'s line with every setting named by its option and the value in the option's unit."""
    from ingest.errors import shown

    _, factor = OPTIONS.get(err.setting, (err.setting, None))
    value = err.value
    if factor is not None and isinstance(value, int | float):
        value = value * factor
    return err.line(lambda field: OPTIONS.get(field, (field, None))[0], shown(value))


def _sample_rows(s: IngestSummary) -> Rows:
    """Medians over the written samples: GT density, LiDAR skew, stereo offset, motion, time per stage."""
    import numpy as np

    if not s.density:
        return []
    by_method = s.density_by_method if len(s.density_by_method) > 1 else {}
    dt = s.stereo_dt_ms
    return [
        ("GT density (fisheye, median)", f"{np.median(s.density) * 100:.2f} %"),
        *((f"GT density of the {method} GT samples (median, samples)",
           f"{np.median(d) * 100:.2f} %, {len(d)}") for method, d in by_method.items()),
        ("LiDAR skew |t_point - t_frame| max (median of samples)", f"{np.median(s.skew_ms):.1f} ms"),
        # hardware-synced cameras: 0; a constant offset means unsynced exposures
        ("stereo stamp offset lower - upper (median, max |.|)",
         f"{np.median(dt):.2f} ms, {np.max(np.abs(dt)):.2f} ms"),
        ("motion compensation applied", f"{s.motion_applied} / {s.written}"),
        *_alignment_rows(s),
        *((f"dense GT points (all samples): {k}", f"{n:,}") for k, n in s.dense_points.items()),
        *(
            [("sparse GT points removed: the window's other slices saw through them", f"{s.seen_through:,}")]
            if s.seen_through
            else []
        ),
        *((f"time: {k}", f"{np.mean(v):.0f} ms/sample") for k, v in s.stage_ms.items()),
        *((f"time: {k} (helper thread, beside clouds + GT)", f"{np.mean(v):.0f} ms/sample")
          for k, v in s.overlapped_ms.items()),
    ]  # fmt: skip


def _alignment_rows(s: IngestSummary) -> Rows:
    """Per LiDAR: how far its points sit from where cam0's images show them (median over the samples),
    and the upper camera's clock offset they imply (`ingest.train.gt.align.CalibrationCheck`)."""
    check = s.calibration
    if check is None:
        return []
    rows = [(f"{name} points on cam0's images: misalignment (median)", f"{deg:.3f} deg")
            for name, deg in check.median_shift_deg.items()]  # fmt: skip
    ms = check.combined.clock_offset_ms
    if ms is not None:
        rows.append(
            (
                "upper camera clock vs LiDAR points (1-sigma)",
                f"{ms:+.2f} ms ({check.combined.sigma_clock_ms:.2f})",
            )
        )
    return rows


def summary_table(summary: IngestSummary, out: Path) -> Table:
    """Frames, pairs, samples written/resumed/skipped, GT density, skew, motion and time per stage."""
    table = Table(title=f"{out}: {summary.written} samples written in {summary.seconds:.1f} s")
    table.add_column("item")
    table.add_column("value", justify="right")
    for item, value in (*_count_rows(summary), *_pass_rows(summary), *_sample_rows(summary)):
        table.add_row(item, value)
    return table


def _segments(segment_s: float) -> SegmentParams:
    """The trajectory pass's segments of `--segment-s` (s; inf: one pass), the overlap the default's."""
    from ingest.errors import DatasetError
    from ingest.train.trajectory.segments import ONE_PASS_NS, SegmentParams, min_length_ns

    overlap_ns = SegmentParams().overlap_ns
    shortest_s = min_length_ns(overlap_ns) / 1e9
    if math.isnan(segment_s) or segment_s < shortest_s:
        raise DatasetError(
            f"--segment-s {segment_s:g}: expected at least {shortest_s:g} s (three times the segments' "
            f"{overlap_ns / 1e9:g} s overlap less half a second: consecutive joins apart), "
            "or inf for one pass"
        )
    length_ns = ONE_PASS_NS if segment_s * 1e9 >= ONE_PASS_NS else round(segment_s * 1e9)
    return SegmentParams(length_ns=length_ns, overlap_ns=overlap_ns)


def ingest_cmd(
    bags: BagsArg, rig: RigOpt, out: OutOpt, workers: WorkersOpt = 2, dask: DaskOpt = None,
    every: EveryOpt = 1, window_ms: WindowOpt = 50.0, exr: ExrOpt = False, png_level: PngLevelOpt = 1,
    height_full: HeightFullOpt = None, min_range: MinRangeOpt = 0.3, motion: MotionOpt = "full",
    salvage: SalvageOpt = False, gt: GtOpt = "auto", gt_window_ms: GtWindowOpt = None,
    max_bad: MaxBadOpt = 0, preview: PreviewOpt = True, backend: BackendOpt = "numba",
    refine: RefineOpt = False, segment_s: SegmentOpt = 10.0,
) -> None:  # fmt: skip
    """Turn recorded bags into the WideDepth training set (rectified equirect pairs + depth/disparity GT)."""
    from ingest.errors import DatasetError, SettingError
    from ingest.train.gt.dense import DenseParams
    from ingest.train.run.pipeline import (
        PASS_READ,
        PASS_REFINE,
        PASS_TRAJECTORY,
        PASS_TRAJECTORY_JOBS,
        ingest,
    )
    from ingest.train.run.sample_job import SampleParams
    from ingest.train.run.settings import IngestConfig

    check_out_folder("--out", out, "the dataset")
    if gt_window_ms is not None and gt == "sparse":
        raise DatasetError(
            "--gt-window-ms sets the window of dense GT (--gt dense or auto); sparse GT's is --window-ms"
        )
    given = DenseParams().window_ns / 1e6 if gt_window_ms is None else gt_window_ms
    for name, value in (("--window-ms", window_ms), ("--gt-window-ms", given)):  # before round()
        if not math.isfinite(value):
            raise DatasetError(f"{name} must be a finite number, got {value:g}")
        if abs(value) > MAX_WINDOW_MS:  # int nanoseconds overflowed at 1e300; 1e12 asked for all memory
            raise DatasetError(f"{name} {value:g}: expected at most {MAX_WINDOW_MS:g} ms (an hour)")
        if 0 < value < 0.5e-6:  # rounds to 0 ns, which the check after round() would call 0
            raise DatasetError(f"{name} {value:g}: under 1 ns, the resolution of the stamps; expected > 0")
    dense = DenseParams(window_ns=round(given * 1e6))
    dense = replace(dense, render=replace(dense.render, backend=backend))  # type: ignore[arg-type]  # validated
    sample = SampleParams(min_range_m=min_range, exr=exr, png_level=png_level, motion=motion, dense=dense)  # type: ignore[arg-type]
    cfg = IngestConfig(
        rig=rig, out=out, workers=workers, every=every, lidar_window_ns=round(window_ms * 1e6),
        height_full=height_full, salvage=salvage, dask=dask, gt=gt, max_bad=max_bad, sample=sample,
        widen_static=gt_window_ms is None, refine=refine, trajectory_segments=_segments(segment_s),
    )  # fmt: skip
    units = {PASS_REFINE: "messages", PASS_READ: "messages", PASS_TRAJECTORY: "LiDAR sweeps"}
    units[PASS_TRAJECTORY_JOBS] = "segment jobs"
    try:
        cfg.validate()  # before the progress bar: a bad value is one line
        with progress_bar("ingesting", "samples") as update:
            summary = ingest(
                bags, cfg, warn=print_warning,
                progress=lambda done, total: update(done, total, "ingesting", "samples"),
                passes=lambda what, done, total: update(done, total, f"ingesting: {what}", units[what]),
            )  # fmt: skip
    except SettingError as err:  # named as the library knows it: name the option instead
        raise DatasetError(option_line(err)) from None
    except KeyboardInterrupt:  # Ctrl-C: every file written is whole (written atomically), a rerun resumes
        held = len(list((out / "meta").glob("*.json"))) if (out / "meta").is_dir() else 0
        samples = f"{held} sample{'' if held == 1 else 's'}"
        line = f"interrupted: {out} holds {samples}; the same command resumes"
        err_console.print(line, markup=False, highlight=False, soft_wrap=True)
        raise typer.Exit(130) from None
    for line in summary.lost_chunks:
        console.print(f"skipped {line}", markup=False, highlight=False, soft_wrap=True)
    if summary.refinement is not None:
        from sensorbox.cli.calib import imu_table, refine_table, stereo_line

        console.print(refine_table(summary.refinement))
        console.print(imu_table(summary.refinement))
        console.print(stereo_line(summary.refinement))
    console.print(summary_table(summary, out))
    for line in summary.warnings:
        print_warning(line)
    for line in summary.damaged:
        print_warning(f"damaged sample written again: {line}")
    metas = sorted((out / "meta").glob("*.json")) if preview else []
    if metas:
        from sensorbox.analysis.plots import plot_sample

        sid = metas[len(metas) // 2].stem
        console.print(f"Preview of sample {sid}: {plot_sample(out, sid, out / 'preview.png')}")
    console.print(f"Dataset: {out} (dataset.yaml describes it)")
