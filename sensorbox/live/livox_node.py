"""The Livox Mid-360 driver as a graph node (`sensorbox/livox_driver` in launch files; see nodes.py)."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import Any

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
