"""`sensorbox launch FILE [name:=value ...]` and `sensorbox capture --rig RIG --out DIR`.

Both run a node graph (drivers, cameras, emulators, recorder) in this process
until Ctrl-C / SIGTERM, a duration, the recorder's disk guard or an error; a
live status line on stderr shows per-topic rates, drops and free disk space,
and a summary table follows. `sensorbox.cli` registers the command functions.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.live import Live
from rich.logging import RichHandler
from rich.markup import escape
from rich.table import Table
from rich.text import Text

from calibration.errors import SensorboxError
from sensorbox.cli.common import (
    LidarMsgOpt,
    check_out_folder,
    console,
    err_console,
    human_bytes,
    path_param,
    print_warning,
)
from sensorbox.live.bus import GraphResult, GraphSnapshot, Shutdown, stop_on_signals
from sensorbox.live.livox_node import silent_lidars

if TYPE_CHECKING:
    from sensorbox.live.launch import LaunchPlan
    from sensorbox.live.monitor import MonitorConfig

PLAIN_STATUS_EVERY_S = 10.0  # without a terminal, one status line this often


def topic_labels(topics: list[str]) -> dict[str, str]:
    """Short unique labels: `/zed_upper/.../image/compressed` -> zed_upper, `/livox/imu_1_2` -> imu_1_2."""
    out: dict[str, str] = {}
    for t in topics:
        parts = [p for p in t.strip("/").split("/") if p and p != "compressed"] or ["/"]
        out[t] = parts[-1] if parts[0] == "livox" else parts[0]
    counts: dict[str, int] = {}
    for label in out.values():
        counts[label] = counts.get(label, 0) + 1
    return {t: (label if counts[label] == 1 else t) for t, label in out.items()}


def status_line(prev: GraphSnapshot | None, now: GraphSnapshot) -> str:
    """One line: elapsed time, written messages/s per topic, drops by stage, bytes written, disk free."""
    topics = sorted(set(now.published) | set(now.written))
    labels = topic_labels(topics)
    dt = now.elapsed_s - prev.elapsed_s if prev is not None else now.elapsed_s
    rates = []
    for t in topics:
        before = prev.written.get(t, 0) if prev is not None else 0
        rate = (now.written.get(t, 0) - before) / dt if dt > 0 else 0.0
        rates.append(f"{labels[t]} {rate:.1f}")
    drops = {k: v for k, v in now.drops.items() if v}
    drop_text = ", ".join(f"{k.split('.', 1)[-1]} {v}" for k, v in sorted(drops.items())) or "0"
    written = now.counter("bytes_written")
    free = now.counter("disk_free_bytes")
    parts = [f"{now.elapsed_s:6.1f} s", " | ".join(rates) + " msg/s" if rates else "no messages yet",
             f"drops {drop_text}"]  # fmt: skip
    if written is not None:
        parts.append(f"{human_bytes(written)} written")
    if free is not None and free >= 0:
        parts.append(f"{human_bytes(free)} free")
    return "  ".join(parts)


def monitor_line(snap: GraphSnapshot) -> str | None:
    """`--monitor`'s books in one line (None without a monitor): sent, and skipped by reason."""
    st = snap.nodes.get("monitor")
    if st is None or "sent" not in st.counters:
        return None
    c = st.counters
    skipped = [
        f"{k.removeprefix('skipped_')} {c[k]:.0f}" for k in sorted(c) if k.startswith("skipped_") and c[k]
    ]
    return (
        f"Monitor: {c['sent']:.0f} messages sent to Foxglove; skipped: {', '.join(skipped) or 'none'} "
        "(the monitor's, not the recording's: the bags hold all the recorder wrote)"
    )


def _summary(result: GraphResult, title: str) -> None:
    snap = result.snapshot
    elapsed = max(snap.elapsed_s, 1e-9)
    by_error = result.error is not None and result.reason == result.error  # printed once, as `error:`
    stopped = " by the error below" if by_error else f": {result.reason}"
    table = Table(title=f"{title}: {snap.elapsed_s:.1f} s, stopped{escape(stopped)}")
    for col in ("topic", "published", "written", "lost", "rate [Hz]"):
        table.add_column(col, justify="left" if col == "topic" else "right", overflow="fold")
    for topic in sorted(set(snap.published) | set(snap.written)):
        pub, wr = snap.published.get(topic, 0), snap.written.get(topic, 0)
        rate = snap.rates_hz.get(topic, wr / elapsed)
        table.add_row(topic, str(pub), str(wr), str(pub - wr), f"{rate:.1f}")
    console.print(table)
    drops = Table(title="Drops by stage (node.stage)")
    drops.add_column("stage")
    drops.add_column("count", justify="right")
    for stage, n in sorted(snap.drops.items()):
        drops.add_row(stage, str(n))
    if snap.drops:
        console.print(drops)
    line = monitor_line(snap)
    if line is not None:
        console.print(line, highlight=False, soft_wrap=True)
    for path in result.files:
        size = (
            sum(f.stat().st_size for f in Path(path).rglob("*") if f.is_file()) if Path(path).exists() else 0
        )
        console.print(f"Bag: {path} ({human_bytes(size)})", highlight=False)
    for line in silent_lines(snap, bool(result.files)):
        print_warning(line)
    if not any(snap.published.values()):
        print_warning(
            f"no message was published in {snap.elapsed_s:.1f} s: no node of the run publishes a topic (a "
            "recorder alone records nothing), so no bag was written"
        )
    # node errors other than the run's own (that one is the `error:` line `_finish` ends with)
    errors = [
        f"{name}: {st.error}" for name, st in snap.nodes.items() if st.error and st.error != result.error
    ]
    for line in errors:
        err_console.print(f"[red]{escape(line)}[/red]")


def silent_lines(snap: GraphSnapshot, recorded: bool) -> list[str]:
    """One line per LiDAR that sent nothing (`silent_lidars`) and, when the run `recorded` a bag, per other
    node that published nothing on a topic it publishes (a camera stopped before its first frame)."""
    lines = silent_lidars(snap.nodes, snap.elapsed_s)
    for topic, why in sorted(snap.expected.items()):
        if recorded and not snap.published.get(topic, 0) and topic not in snap.declared:
            lines.append(
                f"{topic}: {why}, yet nothing was published on it in {snap.elapsed_s:.1f} s; the recording "
                "holds none of it (a driver that does not list that sensor's address, or a remap that sends "
                "it elsewhere)"
            )
    for name, topics in snap.silent_topics().items():
        if recorded and not any(line.startswith(f"{name}: ") for line in lines):
            lines.append(
                f"{name}: published nothing on {', '.join(topics)} in {snap.elapsed_s:.1f} s; the recording "
                "holds no message of it (a camera that had not started, or was unplugged)"
            )
    return lines


def _setup_logging(verbose: bool) -> None:
    """Library log records on stderr through rich: its level column, then the message alone.

    (`basicConfig` would give the handler logging's default "LEVEL:logger:message"
    format, so every line said its level twice.)
    """
    handler = RichHandler(console=err_console, show_path=False, show_time=False)
    handler.setFormatter(logging.Formatter("%(message)s"))
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, handlers=[handler], force=True)
    logging.getLogger("sensorbox.live.monitor").setLevel(logging.INFO)  # its one INFO line: where to connect


def _run_live(run: Callable[[Shutdown, Callable[[GraphSnapshot], None]], GraphResult]) -> GraphResult:
    """Run a graph with SIGINT/SIGTERM as a clean stop and a status line on stderr."""
    shutdown = Shutdown()
    state: dict[str, GraphSnapshot | float | None] = {"prev": None, "printed": 0.0}
    tty = err_console.is_terminal

    with stop_on_signals(shutdown):
        if tty:
            with Live(
                Text("starting nodes ..."), console=err_console, refresh_per_second=4, transient=True
            ) as live:

                def tick(snap: GraphSnapshot) -> None:
                    prev = state["prev"]
                    live.update(Text(status_line(prev if isinstance(prev, GraphSnapshot) else None, snap)))
                    state["prev"] = snap

                return run(shutdown, tick)

        def plain(snap: GraphSnapshot) -> None:
            printed = state["printed"]
            if isinstance(printed, float) and time.monotonic() - printed >= PLAIN_STATUS_EVERY_S:
                prev = state["prev"]
                err_console.print(
                    status_line(prev if isinstance(prev, GraphSnapshot) else None, snap), highlight=False
                )
                state["prev"], state["printed"] = snap, time.monotonic()

        return run(shutdown, plain)


def _finish(result: GraphResult, title: str) -> None:
    _summary(result, title)
    if result.error:
        raise SensorboxError(result.error)


FileArg = Annotated[
    Path,
    typer.Argument(
        help="Launch file (ROS 2 YAML launch syntax), e.g. launch/sim.launch.yaml.", **path_param("FILE")
    ),
]
ArgsArg = Annotated[
    list[str] | None, typer.Argument(help="Launch arguments NAME:=VALUE, e.g. out:=bags duration:=10.")
]
ShowArgsOpt = Annotated[bool, typer.Option("--show-args", "-s", help="List the file's arguments and exit.")]
DryRunOpt = Annotated[
    bool,
    typer.Option(
        "--dry-run",
        help="Check the nodes as the run does (starting none), print them with their parameters, and exit.",
    ),
]
VerboseOpt = Annotated[bool, typer.Option("--verbose", "-v", help="Log what each node does.")]
MonitorOpt = Annotated[
    int | None,
    typer.Option(
        "--monitor", metavar="PORT",
        help="Serve a live view on this TCP port for Foxglove (Open connection > Foxglove WebSocket, "
        "ws://HOST:PORT): both cameras, both LiDARs in cam0, the IMUs, status and a coverage preview; it "
        "never slows the recording (docs/monitor.md).",
    ),
]  # fmt: skip
MonitorHostOpt = Annotated[
    str, typer.Option("--monitor-host", help="Address the monitor listens on; 0.0.0.0 for other computers.")
]
MonitorRigOpt = Annotated[
    Path | None,
    typer.Option(
        help="--monitor: the rig file (camera models, LiDAR and IMU poses); default the one a node of the "
        "launch file names in its `rig` parameter.", **path_param("--monitor-rig"),
    ),
]  # fmt: skip


def _print_arguments(plan: LaunchPlan, file: Path) -> None:
    """Each declared argument with its value, default, choices and description."""
    console.print(f"Arguments of {file} (pass NAME:=VALUE):", highlight=False)
    for arg in plan.arguments:
        default = "required" if arg.default is None else f"default {arg.default!r}"
        choices = f", one of {', '.join(arg.choices)}" if arg.choices else ""
        value = plan.configurations.get(arg.name, "")
        console.print(f"  {arg.name}:={value!r} ({default}{choices})", highlight=False, soft_wrap=True)
        if arg.description:
            console.print(f"      {arg.description}", highlight=False, soft_wrap=True)


def _print_nodes(plan: LaunchPlan, file: Path) -> None:
    """Each node the file would start, with its parameters and remaps."""
    console.print(f"Nodes of {file}:", highlight=False)
    for n in plan.nodes:
        console.print(
            f"- {n.name or n.exec} ({n.pkg}/{n.exec}), namespace {n.namespace}, {n.where}", highlight=False
        )
        for key, value in n.params.items():
            console.print(f"    param {key} = {value!r}", highlight=False, soft_wrap=True)
        for a, b in n.remaps:
            console.print(f"    remap {a} -> {b}", highlight=False, soft_wrap=True)
    for message in plan.messages:
        console.print(message, highlight=False)


def _monitor_config(plan: LaunchPlan, file: Path, port: int, host: str, rig: Path | None) -> MonitorConfig:
    """`launch --monitor`'s settings: the port checked, the rig given or the launch file's."""
    from sensorbox.live.monitor import MonitorConfig, plan_rig

    if not 1 <= port <= 65535:
        raise SensorboxError(f"--monitor {port}: expected a TCP port 1..65535")
    rig = rig or plan_rig(plan.nodes)
    if rig is None:
        raise SensorboxError(
            f"--monitor: no node of {file} names a rig (a `rig` parameter); pass --monitor-rig RIG"
        )
    return MonitorConfig(port, rig, host)


def launch_cmd(
    file: FileArg, args: ArgsArg = None, show_args: ShowArgsOpt = False, dry_run: DryRunOpt = False,
    verbose: VerboseOpt = False, monitor: MonitorOpt = None, monitor_host: MonitorHostOpt = "127.0.0.1",
    monitor_rig: MonitorRigOpt = None,
) -> None:  # fmt: skip
    """Start the nodes a launch file names (drivers, cameras, emulators, recorder) until Ctrl-C."""
    from sensorbox.live.launch import parse_cli_args, parse_launch
    from sensorbox.live.launch_run import check_launch, run_launch

    _setup_logging(verbose)
    plan = parse_launch(file, parse_cli_args(args or []))
    if show_args:
        _print_arguments(plan, file)
        return
    mon = None if monitor is None else _monitor_config(plan, file, monitor, monitor_host, monitor_rig)
    if dry_run:
        check_launch(plan)  # what the run refuses before it starts, the dry run refuses
        _print_nodes(plan, file)
        return
    for message in plan.messages:
        err_console.print(message, highlight=False)
    result = _run_live(lambda sd, tick: run_launch(plan, shutdown=sd, on_tick=tick, monitor=mon))
    _finish(result, str(file))


RigOpt = Annotated[
    Path, typer.Option(help="Rig file: lidar IPs and topics, camera topics.", **path_param("--rig"))
]
OutOpt = Annotated[
    Path, typer.Option(help="Folder the bags go to (NAME_000, NAME_001, ...).", **path_param("--out"))
]
CameraOpt = Annotated[str, typer.Option(help="zed (ZED SDK) | opencv (V4L2).")]
UpperOpt = Annotated[str, typer.Option(help="Upper camera: ZED serial or V4L2 device.")]
LowerOpt = Annotated[str, typer.Option(help="Lower camera: ZED serial or V4L2 device.")]
HostIpOpt = Annotated[str, typer.Option(help="This computer's address on the lidar network.")]
ImageOpt = Annotated[str, typer.Option(help="jpeg (CompressedImage) | raw (Image bgra8).")]
JpegQualityOpt = Annotated[int, typer.Option(help="JPEG quality 1-100.")]
DurationOpt = Annotated[float, typer.Option(help="Seconds to record (0 = until Ctrl-C).")]
SplitSizeOpt = Annotated[float, typer.Option(help="Start a new bag at this size, MiB (0 = never).")]
MinFreeOpt = Annotated[float, typer.Option(help="Stop before the disk has less than this free, MiB.")]
NameOpt = Annotated[str, typer.Option(help="Bag name prefix (default capture_<time>).")]
EmulateOpt = Annotated[
    bool, typer.Option("--emulate", help="No hardware: emulated Mid-360s on loopback, simulated cameras.")
]
PortBaseOpt = Annotated[int, typer.Option(help="First of the nine Livox UDP ports.")]
ScaleOpt = Annotated[float, typer.Option(help="--emulate: camera resolution scale.")]


def _check_choice(flag: str, value: str, known: tuple[str, ...]) -> None:
    if value not in known:
        raise SensorboxError(f"{flag} {value!r}: expected one of {', '.join(known)}")


def capture_cmd(
    rig: RigOpt, out: OutOpt, camera: CameraOpt = "zed", upper: UpperOpt = "", lower: LowerOpt = "",
    host_ip: HostIpOpt = "192.168.1.5", image: ImageOpt = "jpeg", jpeg_quality: JpegQualityOpt = 90,
    lidar_msg: LidarMsgOpt = "custom", duration: DurationOpt = 0.0, split_size: SplitSizeOpt = 4096.0,
    min_free: MinFreeOpt = 2048.0, name: NameOpt = "", emulate: EmulateOpt = False,
    port_base: PortBaseOpt = 56000, scale: ScaleOpt = 1.0, verbose: VerboseOpt = False,
    monitor: MonitorOpt = None, monitor_host: MonitorHostOpt = "127.0.0.1",
) -> None:  # fmt: skip
    """Record the rig (both Mid-360s, both cameras) into mcap bags; the rig file's form of
    launch/sensorbox.launch.yaml."""
    from sensorbox.live.capture import CaptureConfig, capture, check_config

    _check_choice("--camera", camera, ("zed", "opencv"))
    _check_choice("--image", image, ("jpeg", "raw"))
    _check_choice("--lidar-msg", lidar_msg, ("custom", "pointcloud2"))
    cfg = CaptureConfig(
        rig=rig, out=out, name=name, host_ip=host_ip, camera=camera, upper=upper, lower=lower,  # type: ignore[arg-type]
        image=image, jpeg_quality=jpeg_quality, xfer_format=1 if lidar_msg == "custom" else 0,  # type: ignore[arg-type]
        duration_s=duration, split_size_mb=split_size, min_free_mb=min_free, emulate=emulate,
        port_base=port_base, scale=scale, monitor_port=monitor, monitor_host=monitor_host,
    )  # fmt: skip
    check_out_folder("--out", out, "the bags")
    check_config(cfg)  # before the logging set-up, as the choices above: a refused option changes nothing
    _setup_logging(verbose)
    result = _run_live(lambda sd, tick: capture(cfg, shutdown=sd, on_tick=tick))
    _finish(result, f"capture {out}")
