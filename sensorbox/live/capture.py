"""`sensorbox capture`: the real rig's launch file (launch/sensorbox.launch.yaml) built from a rig file.

Recipe: the rig names the lidars (IP, topic), their IMUs and the two cameras'
topics; from it come the Livox driver node (remapping the driver's
`/livox/lidar_<ip>` names to the rig's topics where they differ), the stereo
camera node (ZED X One pair by serial, or two V4L2 devices), and the recorder.
`emulate=True` swaps the hardware for the simulator: one Mid-360 emulator per
rig lidar on 127.0.0.<last octet of its IP> and the simulated camera pair, as
launch/sim.launch.yaml does, so the whole path runs without a rig.
"""

from __future__ import annotations

import ipaddress
import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from calibration.errors import SensorboxError
from calibration.rig import Rig, read_rig
from sensorbox.live.bus import GraphResult, GraphSnapshot, Shutdown
from sensorbox.live.launch import LaunchPlan, NodeSpec
from sensorbox.live.launch_run import run_launch


@dataclass(frozen=True)
class CaptureConfig:
    """What `sensorbox capture` records (sizes in MiB, times in s)."""

    rig: Path
    out: Path
    name: str = ""  # bag prefix; "" = capture_<local time>
    host_ip: str = "192.168.1.5"
    camera: Literal["zed", "opencv", "sim"] = "zed"
    upper: str = ""  # ZED serial or V4L2 device of the upper camera ("" = the SDK's first / /dev/video0)
    lower: str = ""
    image: Literal["jpeg", "raw"] = "jpeg"
    jpeg_quality: int = 90
    xfer_format: int = 1  # 1 CustomMsg, 0 PointCloud2
    duration_s: float = 0.0  # 0 = until interrupted
    split_size_mb: float = 4096.0
    min_free_mb: float = 2048.0
    emulate: bool = False  # emulated Mid-360s on loopback + simulated cameras
    port_base: int = 56000
    scene: str = "indoor"  # emulate: the simulated scene
    scale: float = 1.0  # emulate: camera resolution scale
    monitor_port: int | None = None  # serve the live monitor on this TCP port (None = no monitor)
    monitor_host: str = "127.0.0.1"


def check_config(cfg: CaptureConfig) -> None:
    """Refuse settings the nodes would refuse, before anything is created or copied into `out`.

    The fields are `sensorbox capture`'s options, so each message names the
    option and the value as given (`--split-size -5`, not the recorder's
    `split_bytes` in bytes, nor the rig file the plan is built from).
    """
    from sensorbox.live.recorder_config import MAX_MIB, MAX_S, NAME_PATTERN

    if not 1 <= cfg.jpeg_quality <= 100:
        raise SensorboxError(f"--jpeg-quality {cfg.jpeg_quality}: expected 1..100")
    for flag, value, what, (most, most_unit) in (
        ("--duration", cfg.duration_s, "seconds (0 = until Ctrl-C)", MAX_S),
        ("--split-size", cfg.split_size_mb, "MiB (0 = never split)", MAX_MIB),
        ("--min-free", cfg.min_free_mb, "MiB", MAX_MIB),
    ):
        if not (math.isfinite(value) and value >= 0):
            raise SensorboxError(f"{flag} {value:g}: expected a finite number >= 0, in {what}")
        if value > most:
            raise SensorboxError(f"{flag} {value:g}: expected at most {most:g} {most_unit}")
    if cfg.name and not re.fullmatch(NAME_PATTERN, cfg.name):
        raise SensorboxError(f"--name {cfg.name!r}: use letters, digits and _ . + - only (a folder name)")
    if cfg.emulate and not (math.isfinite(cfg.scale) and cfg.scale > 0):
        raise SensorboxError(f"--scale {cfg.scale:g}: expected a number > 0 (0.25 -> 480x300)")
    if cfg.monitor_port is not None and not 1 <= cfg.monitor_port <= 65535:
        raise SensorboxError(f"--monitor {cfg.monitor_port}: expected a TCP port 1..65535")
    if not 1 <= cfg.port_base <= 65535 - 8:
        raise SensorboxError(f"--port-base {cfg.port_base}: expected 1..65527 (the first of nine UDP ports)")
    try:  # --emulate listens on loopback instead, but a mistyped address is still one
        ipaddress.IPv4Address(cfg.host_ip)
    except ValueError:
        raise SensorboxError(
            f"--host-ip {cfg.host_ip!r}: expected a dotted IPv4 address such as 192.168.1.5"
        ) from None


def _where(cfg: CaptureConfig) -> str:
    return f"{cfg.rig} (capture)"


def _ips(rig: Rig, cfg: CaptureConfig) -> list[tuple[str, str]]:
    """(rig IP, IP the driver talks to) per rig lidar."""
    out = []
    for lidar in rig.lidars:
        if not lidar.ip:
            raise SensorboxError(f"{cfg.rig}: lidars.{lidar.name}: no 'ip'; the driver needs each lidar's IP")
        last = lidar.ip.rsplit(".", 1)[-1]
        out.append((lidar.ip, f"127.0.0.{last}" if cfg.emulate else lidar.ip))
    return out


def capture_plan(cfg: CaptureConfig) -> LaunchPlan:
    """The nodes `sensorbox capture` starts, as a launch plan (what the launch file would give)."""
    from sensorbox.livox.config import imu_topic, lidar_topic, topic_suffix

    rig = read_rig(cfg.rig)
    if not rig.lidars:
        raise SensorboxError(f"{cfg.rig}: the rig has no lidars to capture")
    where = _where(cfg)
    ips = _ips(rig, cfg)
    nodes: list[NodeSpec] = []
    if cfg.emulate:
        for lidar, (_, ip) in zip(rig.lidars, ips, strict=True):
            params = {"ip": ip, "lidar": lidar.name, "rig": str(cfg.rig), "scene": cfg.scene,
                      "port_base": cfg.port_base}  # fmt: skip
            nodes.append(
                NodeSpec("sensorbox", "mid360_emulator", f"{lidar.name}_emulator", "/", params, (), where)
            )
    remaps: list[tuple[str, str]] = []
    for lidar, (rig_ip, ip) in zip(rig.lidars, ips, strict=True):
        if lidar_topic(ip, True) != lidar.topic:
            remaps.append((lidar_topic(ip, True), lidar.topic))
        imu = next((i for i in rig.imus if i.topic.endswith(topic_suffix(rig_ip))), None)
        if imu is not None and imu_topic(ip, True) != imu.topic:
            remaps.append((imu_topic(ip, True), imu.topic))
    driver: dict[str, Any] = {
        "xfer_format": cfg.xfer_format, "multi_topic": 1, "publish_freq": 10.0, "frame_id": "livox_frame",
        "host_ip": "127.0.0.1" if cfg.emulate else cfg.host_ip, "lidar_ips": [ip for _, ip in ips],
    }  # fmt: skip
    if cfg.port_base != 56000:
        driver["port_base"] = cfg.port_base
    nodes.append(
        NodeSpec("livox_ros_driver2", "livox_ros_driver2_node", "livox_lidar_publisher", "/", driver,
                 tuple(remaps), where)
    )  # fmt: skip
    camera: dict[str, Any] = {"image": cfg.image, "jpeg_quality": cfg.jpeg_quality,
                              "upper_topic": rig.upper.topic, "lower_topic": rig.lower.topic}  # fmt: skip
    source = "sim" if cfg.emulate else cfg.camera
    camera["source"] = source
    if source == "zed":
        camera.update(upper_serial=int(cfg.upper or 0), lower_serial=int(cfg.lower or 0))
    elif source == "opencv":
        camera.update(upper_device=cfg.upper or "/dev/video0", lower_device=cfg.lower or "/dev/video1")
        camera.update(width=rig.upper.model.width, height=rig.upper.model.height)
    else:
        camera.update(rig=str(cfg.rig), scene=cfg.scene, scale=cfg.scale, write_rig=str(cfg.out / "rig.yaml"))
    nodes.append(NodeSpec("sensorbox", "stereo_camera", f"{source}_stereo", "/", camera, (), where))
    recorder = {"out": str(cfg.out), "name": cfg.name, "duration_s": cfg.duration_s,
                "split_size_mb": cfg.split_size_mb, "min_free_mb": cfg.min_free_mb}  # fmt: skip
    nodes.append(NodeSpec("sensorbox", "recorder", "recorder", "/", recorder, (), where))
    return LaunchPlan(Path(cfg.rig), nodes)


def capture(
    cfg: CaptureConfig,
    *,
    shutdown: Shutdown | None = None,
    on_tick: Callable[[GraphSnapshot], None] | None = None,
) -> GraphResult:
    """Record the rig until interrupted, `duration_s`, the disk guard or an error; the result.

    The settings are checked (`check_config`) before any node starts: a node
    writes into `out` as it starts (the simulated cameras copy the rig there).
    `monitor_port` adds the live monitor (`sensorbox.live.monitor`) on the rig file.
    """
    check_config(cfg)
    monitor = None
    if cfg.monitor_port is not None:
        from sensorbox.live.monitor import MonitorConfig

        monitor = MonitorConfig(cfg.monitor_port, cfg.rig, cfg.monitor_host)
    return run_launch(capture_plan(cfg), shutdown=shutdown, on_tick=on_tick, monitor=monitor)
