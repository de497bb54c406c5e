"""The simulator's nodes for launch files: Mid-360 emulators and the simulated stereo camera.

The live node registry (`sensorbox.live.nodes.NODE_TYPES`) names these
factories; their parameters are documented there.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from calibration.rig import REFERENCE_RIG, read_rig
from sensorbox.errors import GraphError
from sensorbox.live.bus import PRIORITY_DEVICE, Node, NodeContext, NodeStatus
from sensorbox.live.nodes import Params, stereo_camera_node
from sensorbox.sim.camera_source import SimCameras, SimCameraSource
from sensorbox.sim.config import MAX_DURATION_S, SimConfig
from sensorbox.sim.emulator_process import EmulatorProcess, EmulatorSpec
from sensorbox.sim.lidar import SWEEP_PERIOD_NS
from sensorbox.sim.mid360 import Mid360Emulator
from sensorbox.sim.run import setup_sim
from sensorbox.sim.scan_source import SimScan

MIN_LOOP_S = 2 * SWEEP_PERIOD_NS / 1e9
"""The shortest emulator loop (s) besides 0: two sweeps, so that it holds a whole one whatever its phase."""


def _sim_config(p: Params, **fixed: Any) -> Any:
    cfg = SimConfig(
        scene=p.text("scene", "indoor"), trajectory=p.text("trajectory", "static"), seed=p.integer("seed", 0),
        rig=p.path("rig", str(REFERENCE_RIG)), scale=p.number("scale", 1.0),
        supersample=p.integer("supersample", 1), **fixed,
    )  # fmt: skip
    cfg.validate()
    return cfg


class EmulatorNode:
    """One emulated Mid-360 (`sensorbox.sim.mid360.Mid360Emulator`) on loopback, in a child process of its
    own (`sensorbox.sim.emulator_process`: the graph's threads cannot stall it); priority: device."""

    priority = PRIORITY_DEVICE

    def __init__(self, name: str, sim_cfg: Any, lidar: str, ip: str, loop_s: float, options: dict[str, Any]):
        self.name = name
        self.process = EmulatorProcess(EmulatorSpec(name, sim_cfg, lidar, ip, loop_s, options))
        self.claims = (f"the Mid-360 address {ip}",)  # what the launch checks no other node opens

    def start(self) -> None:
        self.process.start()

    def stop(self) -> None:
        self.process.stop()

    def status(self) -> NodeStatus:
        return NodeStatus(dict(self.process.counters))


def mid360_emulator_node(ctx: NodeContext, p: Params) -> Node:
    from sensorbox.livox import Ports

    ip = p.text("ip", "")
    if not ip.startswith("127."):
        raise GraphError(f"{p.where}: ip {ip!r}: an emulated lidar needs a loopback address 127.0.0.x")
    base = p.port_base()
    options = {
        "ports": Ports.block(base) if base != 56000 else Ports(),
        "time_type": p.integer("time_type", 1), "data_type": p.integer("data_type", 1),
        "loss": p.number("loss", 0.0), "reorder": p.number("reorder", 0.0),
        "duplicate": p.number("duplicate", 0.0), "malformed": p.number("malformed", 0.0),
        "rate": p.number("rate", 1.0), "listen_broadcast": p.flag("listen_broadcast", False),
    }  # fmt: skip
    noise = p.number("range_noise_m", 0.02)
    sim = _sim_config(p, range_noise_m=noise)
    loop_s = p.number("loop_s", 1.0, (MAX_DURATION_S, "s (the longest simulated recording)"))
    if loop_s < 0:
        raise GraphError(f"{p.where}: loop_s must be >= 0 (0 = simulate live), got {loop_s}")
    if 0 < loop_s < MIN_LOOP_S:  # the loop's scan is a simulated recording of loop_s seconds
        raise GraphError(
            f"{p.where}: loop_s {loop_s:g}: expected 0 (simulate live) or at least {MIN_LOOP_S:g} s "
            "(two 10 Hz sweeps: a shorter loop may hold no whole sweep to replay)"
        )
    lidar = p.text("lidar", "lidar_top")
    names = [li.name for li in read_rig(sim.rig).lidars]  # the dry run reads it too: a missing file, a name
    if lidar not in names:
        have = ", ".join(names) or "no lidar"
        raise GraphError(f"{p.where}: lidar {lidar!r}: the rig {sim.rig} has {have}")
    return EmulatorNode(ctx.name, sim, lidar, ip, loop_s, options)


def sim_cameras(p: Params) -> tuple[SimCameras, Callable[[], None] | None]:
    """The simulated pair, and what its camera node does once open: write the rig at render
    resolution where `write_rig` names a path (at start, so that building the node writes nothing)."""
    sim = SimCameras(_sim_config(p, camera_rate_hz=p.number("fps", 30.0)))
    rig_out = p.text("write_rig", "")
    if not rig_out:
        return sim, None

    def write_rig() -> None:
        sim.write_rig(Path(rig_out))

    return sim, write_rig


def sim_camera_source(p: Params, sim: SimCameras, cam: int, name: str) -> SimCameraSource:
    """One of the simulated pair as a camera source (the `sim` source of the camera nodes)."""
    prerender = p.choice("prerender", ("auto", "always", "never"), "auto")
    loop, buffer = p.integer("loop_frames", 30), p.integer("buffer_frames", 4)
    return SimCameraSource(sim, cam, prerender=prerender, loop_frames=loop, buffer_frames=buffer, name=name)  # type: ignore[arg-type]


def sim_camera_node(ctx: NodeContext, p: Params) -> Node:
    return stereo_camera_node(ctx, p, source="sim")


def sim_emulators(
    cfg: SimConfig,
    ips: Sequence[str] | None = None,
    **options: Any,
) -> list[Mid360Emulator]:
    """One emulator per rig LiDAR of the simulated recording `cfg` (scene, trajectory, rig), not started.

    `ips` default to 127.0.0.<last octet of the rig's IP> (127.0.0.12 and
    127.0.0.13 for the reference rig); `options` go to every `Mid360Emulator`
    (ports, rate, time_type, impairments); serials end in the rig IP's last octet.
    """
    setup = setup_sim(cfg)
    out = []
    for k, lidar in enumerate(setup.rig.lidars):
        last = (lidar.ip or f"0.0.0.{10 + k}").rsplit(".", 1)[-1]
        ip = ips[k] if ips is not None else f"127.0.0.{last}"
        serial = f"47MDL9A00100{int(last):02d}"
        opts = {"seed": cfg.seed * 100 + k, **options}
        out.append(Mid360Emulator(ip, SimScan(setup, k), serial=serial, **opts))
    return out
