"""The Livox Mid-360 driver as a graph node (`sensorbox/livox_driver` in launch files; see nodes.py) and
the livox_ros_driver2 user config it reads (`read_livox_json`)."""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from calibration.files import read_text
from sensorbox.errors import GraphError
from sensorbox.live.bus import PRIORITY_SOURCE, NodeStatus, Publish

log = logging.getLogger(__name__)

LIDAR_COUNTERS = ("sweeps", "points", "packets", "duplicates", "imu_packets", "counter_jumps", "time_jumps")


def silent_lidars(nodes: Mapping[str, NodeStatus], elapsed_s: float) -> list[str]:
    """One line per LiDAR a driver node received no point or no IMU packet from in the whole run.

    A recording of such a run holds no LiDAR (or IMU) message of it, yet
    every drop counter is 0; an emulator that never sent (`loop_s:=0` once
    listed 1e8 sweep windows before its first) looks like a quiet success.
    """
    lines = []
    for name, status in nodes.items():
        for key, packets in status.counters.items():
            if not key.endswith(".packets"):
                continue
            ip = key.removesuffix(".packets")
            imu = status.counters.get(f"{ip}.imu_packets")
            none = [what for what, n in (("point", packets), ("IMU", imu)) if n == 0]
            if none:
                lines.append(
                    f"{name}: lidar {ip} sent no {' and no '.join(none)} packet in {elapsed_s:.1f} s; the "
                    f"recording holds no {' or '.join('LiDAR' if w == 'point' else w for w in none)} message "
                    "from it"
                )
    return lines


class LivoxDriverNode:
    """`sensorbox.livox.Mid360Driver` as a node (priority: source); with `process` (the default) the
    driver runs in a child process (`sensorbox.livox.process.DriverProcess`) that the graph's cameras
    and recorder cannot starve."""

    priority = PRIORITY_SOURCE

    def __init__(
        self, name: str, config: Any, publish: Publish, discovery_s: float = 0.0, process: bool = True
    ) -> None:
        from sensorbox.livox import Mid360Driver
        from sensorbox.livox.process import DriverProcess

        self.name = name
        self.config = config
        self.discovery_s = discovery_s
        self.publishes: tuple[str, ...] = ()  # absolute topic names, set by the graph's factory
        self.discovered: list[Any] = []

        def relative(topic: str, msgtype: str, stamp_ns: int, raw: bytes) -> None:
            publish(topic.lstrip("/"), msgtype, stamp_ns, raw)  # livox_ros_driver2's names are relative

        self.driver: Any = (DriverProcess if process else Mid360Driver)(config, relative)

    def start(self) -> None:
        if self.discovery_s > 0:
            self.discovered = self.driver.discover(self.discovery_s)
            found = {d.ip for d in self.discovered}
            missing = [li.ip for li in self.config.lidars if li.ip not in found]
            if missing:
                log.warning("%s: lidar(s) %s did not answer discovery", self.name, ", ".join(missing))
        self.driver.start()

    def stop(self) -> None:
        self.driver.stop()

    def status(self) -> NodeStatus:
        st = self.driver.stats()
        counters: dict[str, float] = {"foreign": float(st.foreign), "rcvbuf_bytes": float(st.rcvbuf_bytes),
                                      "kernel_drops": float(st.kernel_drops)}  # fmt: skip  # part of udp_lost
        if getattr(self.driver, "granted_nice", None) is not None:  # the driver's own process
            counters["process_nice"] = float(self.driver.granted_nice)
        drops = {"udp_lost": 0, "udp_late": 0, "udp_malformed": 0, "imu_lost": 0}
        for ip, s in st.lidars.items():
            for key in (
                "sweeps",
                "points",
                "packets",
                "duplicates",
                "imu_packets",
                "counter_jumps",
                "time_jumps",
            ):
                counters[f"{ip}.{key}"] = float(getattr(s, key))
            drops["udp_lost"] += s.lost
            drops["udp_late"] += s.late
            drops["udp_malformed"] += s.malformed
            drops["imu_lost"] += s.imu_lost
        return NodeStatus(counters, drops, error=getattr(self.driver, "error", None))


def read_livox_json(path: Path) -> dict[str, Any]:
    """host_ip, ports (dict of Ports fields), lidars [(ip, extrinsic | None)] and data_type from a
    livox_ros_driver2 user config (MID360_config.json)."""
    text = read_text(Path(path), "Livox user config", "JSON", error=GraphError)  # a regular file, <= 4 MiB
    try:
        doc = json.loads(text)
    except RecursionError as err:  # json's decoder recurses once per [ or {
        raise GraphError(f"{path}: malformed JSON: nested too deeply for a Livox user config") from err
    except json.JSONDecodeError as err:
        raise GraphError(f"{path}: line {err.lineno}: malformed JSON: {err.msg}") from err
    try:
        mid = doc["MID360"]
        host, dev = mid["host_net_info"], mid["lidar_net_info"]
        ips = {host[k] for k in ("cmd_data_ip", "push_msg_ip", "point_data_ip", "imu_data_ip")}
        if len(ips) != 1:
            raise GraphError(f"{path}: MID360.host_net_info: SensorBox needs one host IP, got {sorted(ips)}")
        ports = {
            "lidar_cmd": dev["cmd_data_port"], "lidar_push": dev["push_msg_port"],
            "lidar_point": dev["point_data_port"], "lidar_imu": dev["imu_data_port"],
            "host_cmd": host["cmd_data_port"], "host_push": host["push_msg_port"],
            "host_point": host["point_data_port"], "host_imu": host["imu_data_port"],
        }  # fmt: skip
        lidars = []
        types = set()
        for k, cfg in enumerate(doc["lidar_configs"]):
            ext = cfg.get("extrinsic_parameter")
            extrinsic = (
                None
                if ext is None
                else tuple(float(ext[key]) for key in ("roll", "pitch", "yaw", "x", "y", "z"))
            )
            if extrinsic is not None and not any(extrinsic):
                extrinsic = None  # identity: nothing to apply
            lidars.append((str(cfg["ip"]), extrinsic))
            types.add(int(cfg.get("pcl_data_type", 1)))
            if int(cfg.get("pattern_mode", 0)) != 0:
                raise GraphError(
                    f"{path}: lidar_configs[{k}].pattern_mode: only 0 (non-repetitive) is supported"
                )
    except (KeyError, TypeError, ValueError) as err:
        raise GraphError(f"{path}: not a livox_ros_driver2 MID360 config: missing or bad {err}") from err
    if len(types) != 1:
        raise GraphError(f"{path}: lidar_configs use different pcl_data_type values {sorted(types)}")
    return {"host_ip": next(iter(ips)), "ports": ports, "lidars": lidars, "data_type": types.pop()}
