"""`sensorbox inspect BAG...`: print what a recording holds and how well it is timed.

`inspect_cmd` is a plain typer command function; `sensorbox.cli` registers it.
It parses, calls `ingest.inspect.inspect_bags` and prints rich tables plus a
suggested rig topic mapping (YAML). Errors are `SensorboxError`s, left to the
main CLI to turn into one line and exit code 2.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape
from rich.table import Table

from ingest.bag_report import BagReport, LidarCoverage, StereoReport, TopicStats
from ingest.inspect import inspect_bags
from sensorbox.cli.common import console, path_param, print_error, print_warning, progress_bar


def _num(value: float | None, fmt: str = ".3f") -> str:
    return "-" if value is None else format(value, fmt)


def _short_type(msgtype: str) -> str:
    """`sensor_msgs/msg/Image` -> `Image` (the full name is in the rig check and the API)."""
    return msgtype.split("/")[-1]


def _gaps(t: TopicStats) -> str:
    return "0" if not t.gaps else f"{t.gaps}, {_num(t.largest_gap_ms, '.1f')}"


def _offsets(t: TopicStats) -> str:
    if t.log_offset_median_ms is None:
        return "-"
    med, lo, hi = t.log_offset_median_ms, t.log_offset_min_ms, t.log_offset_max_ms
    return f"{med:.2f} ({lo:.2f}..{hi:.2f})"


def _topics_table(report: BagReport) -> Table:
    table = Table(title="Topics: timing from header stamps (log = bag receive time)")
    lost = ["lost (corrupt chunks)"] if report.lost_chunks else []
    for col in (
        "topic", "type", "count", *lost, "rate [Hz]", "gaps, max [ms]", "dup/order",
        "log-stamp [ms] med (min..max)",
    ):  # fmt: skip
        table.add_column(
            escape(col), justify="left" if col in ("topic", "type") else "right", overflow="fold"
        )
    for t in report.topics:
        rate = _num(t.rate_hz, ".2f") if t.stamped else "no header"
        order = f"{t.duplicates}/{t.out_of_order}" if t.stamped else "-"
        gaps = _gaps(t) if t.stamped else "-"
        n_lost = [f"[red]{t.lost}[/red]" if t.lost else "0"] if lost else []
        table.add_row(t.topic, _short_type(t.msgtype), str(t.count), *n_lost, rate, gaps, order, _offsets(t))
        if t.error:
            what = f"{t.undecodable} unreadable: {t.error}" if t.undecodable else t.error
            table.add_row("", f"[red]{escape(what)}[/red]", *[""] * (5 + len(lost)))
    return table


def _stereo_table(s: StereoReport) -> Table:
    title = f"Stereo pairing by header stamp (topics from {s.source}; dt = lower - upper)"
    table = Table(title=title, show_header=False)
    table.add_column("", style="bold")
    table.add_column("", overflow="fold")
    rows = (
        ("upper", s.upper_topic),
        ("lower", s.lower_topic),
        ("pairs", f"{s.pairs} (nearest stamps within {s.tolerance_ms:.2f} ms)"),
        ("unpaired upper / lower", f"{s.unpaired_upper} / {s.unpaired_lower}"),
        (
            "dt median, |dt| median, |dt| max",
            f"{_num(s.median_dt_ms)} ms, {_num(s.median_abs_dt_ms)} ms, {_num(s.max_abs_dt_ms)} ms",
        ),
    )
    for key, value in rows:
        table.add_row(key, value)
    return table


def _lidar_table(lidars: tuple[LidarCoverage, ...]) -> Table:
    table = Table(title="LiDAR sweeps (sensor frame; medians over sweeps)")
    for col in (
        "topic", "sweeps", "points", "zero points", "duration [ms]", "1°x1° coverage of 360 x [-7, 52]°",
        "elevation [°]", "point time",
    ):  # fmt: skip
        # a topic is never folded: two LiDARs' topics differ in their last characters (..._12, ..._13)
        topic = col == "topic"
        table.add_column(escape(col), justify="left" if topic else "right", overflow="fold", no_wrap=topic)
    for li in lidars:
        zero = "-" if li.zero_fraction is None else f"{li.zero_fraction * 100:.1f} %"
        cover = "-" if li.coverage_median is None else f"{li.coverage_median * 100:.1f} %"
        el = (
            "-"
            if li.elevation_min_deg is None or li.elevation_max_deg is None
            else f"{li.elevation_min_deg:.1f} .. {li.elevation_max_deg:.1f}"
        )
        sweeps = str(li.sweeps) + (f" ({li.undecodable} unreadable)" if li.undecodable else "")
        table.add_row(
            li.topic,
            sweeps,
            _num(li.points_median, ".0f"),
            zero,
            _num(li.duration_ms_median, ".2f"),
            cover,
            el,
            escape(li.time_layout or "-"),
        )
    return table


def _print_rig(report: BagReport, rig_path: Path) -> None:
    problems = report.rig_problems
    if problems is None:
        return
    if not problems:
        line = f"Rig {rig_path}: every topic is in the bag with the expected type and has messages."
        console.print(line, highlight=False)
        return
    table = Table(title=f"Rig {rig_path} vs the bag")
    for col in ("sensor", "topic", "problem"):
        table.add_column(col, overflow="fold")
    for p in problems:
        table.add_row(p.sensor, p.topic or "-", f"[red]{escape(p.problem)}[/red]")
    console.print(table)
    have = ", ".join(f"{t.topic} ({_short_type(t.msgtype)})" for t in report.topics) or "none"
    console.print(f"The bag's topics: {have}", highlight=False)


def _print_report(report: BagReport, rig_path: Path | None) -> None:
    ros = f"ROS {report.ros_version}"
    head = f"{', '.join(map(str, report.paths))}: {ros}, {report.message_count} messages"
    console.print(f"[bold]{head}[/bold], {report.duration_s:.2f} s of log time", highlight=False)
    if report.salvaged:
        console.print(
            f"read record by record (--salvage): {', '.join(map(str, report.salvaged))}", highlight=False
        )
    for chunk in report.lost_chunks:
        console.print(f"[red]{escape(chunk.describe())}; skipped[/red]", highlight=False, soft_wrap=True)
    console.print(_topics_table(report))
    if report.stereo is not None:
        console.print(_stereo_table(report.stereo))
    if report.lidars:
        console.print(_lidar_table(report.lidars))
    for line in report.clock_problems():
        print_warning(line, console)
    if rig_path is not None:
        _print_rig(report, rig_path)
    console.print("[bold]Suggested rig topic mapping[/bold]")
    for note in report.mapping.notes:
        console.print(f"# note: {note}", markup=False, highlight=False)
    for sensor in report.mapping.sensors:
        if sensor.reason:
            console.print(f"# {sensor.name}: {sensor.reason}", markup=False, highlight=False)
    console.print(report.mapping.yaml().rstrip("\n"), markup=False, highlight=False, soft_wrap=True)


def inspect_cmd(
    bags: Annotated[
        list[Path],
        typer.Argument(
            help="ROS 1 .bag files, or ROS 2 .mcap/.db3 files or rosbag2 folders (one recording).",
            **path_param("BAGS", many=True),
        ),
    ],
    rig: Annotated[
        Path | None,
        typer.Option(
            "--rig",
            help="Rig file (or Kalibr camchain): check its topics and pair its cameras (exit code 2 when a "
            "sensor's topic is missing, of another type or empty).",
            **path_param("--rig"),
        ),
    ] = None,
    salvage: Annotated[
        bool,
        typer.Option(
            "--salvage",
            help="Read MCAP files record by record: keep what truncated or damaged files still hold; "
            "skip corrupt chunks (failed CRC or decompression, any format), counting their messages as "
            "lost (without it, a corrupt chunk is an error naming it).",
        ),
    ] = False,
) -> None:
    """Topics, types, counts, rates, gaps, stamp vs log-time offsets, stereo pairing, LiDAR coverage.

    Reads every message once (images are not decoded: only their header
    stamps) and ends with a suggested rig topic mapping in rig-file YAML.
    """
    from calibration.rig import read_rig

    rig_obj = read_rig(rig) if rig is not None else None
    with progress_bar("reading", "messages") as update:
        report = inspect_bags(bags, salvage=salvage, rig=rig_obj, progress=update)
    _print_report(report, rig)
    if report.rig_problems:  # the report stands; a script running inspect before ingest sees the failure
        n = len(report.rig_problems)
        verb = "does" if n == 1 else "do"
        print_error(f"{rig}: {n} of its sensors {verb} not match the bag (the table above)")
        raise typer.Exit(2)
