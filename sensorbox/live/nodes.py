"""SensorBox node types: what a launch file's `pkg`/`exec` start, and their parameters.

- `sensorbox/recorder` (`recorder.Recorder`): out (bags), name (capture_<time>),
  topics ([] = all), split_size_mb (0 = off), split_duration_s (0), duration_s
  (0 = until stopped), queue_size (4096 per topic), queue_mb (512 per topic),
  min_free_mb (1024), compress (true), flush_s (1.0).
- `sensorbox/livox_driver`, alias `livox_ros_driver2/livox_ros_driver2_node`
  (`LivoxDriverNode` over `livox.Mid360Driver`): host_ip and lidar_ips, or
  user_config_path (livox_ros_driver2's MID360 JSON: host IP, ports, lidar IPs,
  extrinsics); xfer_format (1 = CustomMsg, 0 = PointCloud2), multi_topic (1),
  publish_freq (10.0 Hz), frame_id (livox_frame), data_type (1), imu (true),
  port_base (56000: the Livox ports; else a block of nine from it), discovery_s
  (0 = skip discovery), process (true: the driver runs in its own process, which
  camera encoding and the recorder cannot starve; false: in the graph's process).
- `sensorbox/mid360_emulator` (`EmulatorNode`): ip (127.0.0.x), lidar (rig
  LiDAR name, lidar_top), port_base, loop_s (1.0; 0 = simulate live), time_type
  (1 = PTP), data_type (1), loss/reorder/duplicate/malformed (0), rate (1.0),
  range_noise_m (0.02), listen_broadcast (false), + sim.
- `sensorbox/camera`, alias `zed_wrapper/zed_wrapper` (`cameras.CameraNode`, one
  camera): source (zed | opencv | sim), topic (~/rgb/color/rect/image), frame_id,
  image (jpeg | raw), jpeg_quality (90), fps (30); zed: serial, resolution
  (HD1200); opencv: device, width, height, fourcc, stamps, realtime; sim: camera
  (upper | lower), buffer_frames (4) + sim.
- `sensorbox/stereo_camera` (a pair by stamp): as camera, with upper_/lower_
  topic, frame_id, serial or device; pair_tolerance_ms (half a period).
- `sensorbox/sim_camera`: stereo_camera with source sim.
- `sensorbox/talker` (`TalkerNode`, demo_nodes' talker): topic (chatter),
  rate_hz (10), count (0 = forever), payload_bytes (0).

"sim" parameters: scene (indoor), trajectory (static), seed (0), rig (reference
rig), scale (1.0), supersample (1); cameras also prerender (auto | always |
never), loop_frames (30), write_rig ("" = no; a path gets the rig at render
resolution, rig file + camchain, when the camera node starts).

Building a node (`build_node`) reads and checks its parameters and starts
nothing, writes nothing: `launch --dry-run` builds every node to refuse what
the run would.

The Livox driver publishes relative topics (`livox/lidar_<ip>`, as
livox_ros_driver2 does), so a node namespace applies; remap them to the rig's
topics when the lidar IPs differ (emulated lidars on 127.0.0.x).
"""

from __future__ import annotations

import importlib
import ipaddress
import itertools
import logging
import math
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from calibration.errors import SensorboxError
from ingest.train.sync import pair_tolerance_ns
from sensorbox.errors import GraphError
from sensorbox.live.bus import (
    PRIORITY_SOURCE,
    Bus,
    Node,
    NodeContext,
    NodeStatus,
    Publish,
    Shutdown,
    node_context,
)
from sensorbox.live.livox_node import LivoxDriverNode, read_livox_json

log = logging.getLogger(__name__)

MiB = 1 << 20
ZED_IMAGE_TOPIC = "~/rgb/color/rect/image"


# ---------------------------------------------------------------- parameters


class Params:
    """A node's parameters, read with type checks; `check()` rejects the ones nobody read."""

    def __init__(self, values: Mapping[str, Any], where: str) -> None:
        self._values = dict(values)
        self._asked: set[str] = set()
        self.where = where

    def _err(self, key: str, value: Any, want: str) -> GraphError:
        return GraphError(f"{self.where}: parameter {key!r} = {value!r}: expected {want}")

    def has(self, key: str) -> bool:
        self._asked.add(key)
        return key in self._values

    def raw(self, key: str, default: Any) -> Any:
        self._asked.add(key)
        return self._values.get(key, default)

    def text(self, key: str, default: str) -> str:
        v = self.raw(key, default)
        if isinstance(v, bool) or not isinstance(v, str | int | float):
            raise self._err(key, v, "a string")
        return str(v)

    def path(self, key: str, default: str) -> Path:
        """A path; an empty one is refused: it would be the current folder (`out: ''` recorded there)."""
        v = self.text(key, default)
        if not v.strip():
            raise self._err(key, v, "a path (an empty one would be the current folder)")
        return Path(v)

    def number(
        self,
        key: str,
        default: float,
        at_most: tuple[float, str] | None = None,
        at_least: float | None = None,
    ) -> float:
        """A finite float; text that Python reads as one counts too: YAML 1.1 types '1e-9' (no dot) as a
        string, and a launch argument substituted into a parameter arrives as text. `at_most` is an upper
        bound and its unit: a value no run can use (a disk reserve of 1e300 MiB) is refused here, where
        the dry run sees it too, not when the run is under way."""
        given = self.raw(key, default)
        v = given
        if isinstance(v, str):
            try:
                v = float(v)
            except ValueError:
                raise self._err(key, given, "a finite number") from None
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise self._err(key, given, "a finite number")  # as given: 'nan' stays text
        if at_most is not None and v > at_most[0]:
            raise self._err(key, given, f"at most {at_most[0]:g} {at_most[1]}")
        if at_least is not None and v < at_least:
            raise self._err(key, given, f"at least {at_least:g}")
        return float(v)

    def integer(self, key: str, default: int) -> int:
        v = self.raw(key, default)
        if isinstance(v, bool) or not isinstance(v, int):
            raise self._err(key, v, "an integer")
        return v

    def port_base(self) -> int:
        """`port_base`: the first of nine consecutive UDP ports, so 1..65527 (56000 = Livox's own)."""
        v = self.integer("port_base", 56000)
        if not 1 <= v <= 65535 - 8:
            raise self._err("port_base", v, "1..65527 (the first of nine UDP ports, each <= 65535)")
        return v

    def flag(self, key: str, default: bool) -> bool:
        v = self.raw(key, default)
        if isinstance(v, bool):
            return v
        if isinstance(v, int) and v in (0, 1):
            return bool(v)
        raise self._err(key, v, "true/false (or 1/0)")

    def texts(self, key: str, default: Sequence[str]) -> list[str]:
        v = self.raw(key, list(default))
        if isinstance(v, str):
            v = [s for s in v.replace(",", " ").split() if s]
        if not isinstance(v, list) or not all(isinstance(s, str | int | float) for s in v):
            raise self._err(key, v, "a list of strings")
        return [str(s) for s in v]

    def choice(self, key: str, choices: Sequence[str], default: str) -> str:
        v = self.text(key, default)
        if v not in choices:
            raise self._err(key, v, f"one of {', '.join(choices)}")
        return v

    def check(self) -> None:
        unused = sorted(set(self._values) - self._asked)
        if unused:
            raise GraphError(
                f"{self.where}: parameter(s) {', '.join(unused)} not used by this node (with these"
                f" settings); it reads: {', '.join(sorted(self._asked))}"
            )


# ---------------------------------------------------------------- Livox driver


def livox_driver_node(ctx: NodeContext, p: Params) -> Node:
    from sensorbox.livox import DriverConfig, LidarEndpoint, Ports
    from sensorbox.livox.config import imu_topic, lidar_topic

    fmt = {0: "pointcloud2", 1: "custom"}.get(p.integer("xfer_format", 1))
    if fmt is None:
        raise GraphError(f"{p.where}: xfer_format: 0 (PointCloud2) or 1 (CustomMsg); 2 is ROS 1 only")
    frame_id = p.text("frame_id", "livox_frame")
    if frame_id != "livox_frame":
        raise GraphError(f"{p.where}: frame_id {frame_id!r}: the driver publishes 'livox_frame' only")
    freq = p.number("publish_freq", 10.0)
    freq = min(100.0, max(0.5, freq))  # livox_ros_driver2 clamps it the same way
    base = p.port_base()
    ports = Ports.block(base) if base != 56000 else Ports()
    data_type = p.integer("data_type", 1)
    host_ip = p.text("host_ip", "")
    lidars: list[Any] = [LidarEndpoint(ip) for ip in p.texts("lidar_ips", [])]
    config_path = p.text("user_config_path", "")
    if config_path:
        cfg = read_livox_json(Path(config_path))
        host_ip = host_ip or cfg["host_ip"]
        if not lidars:
            lidars = [LidarEndpoint(ip, ext) for ip, ext in cfg["lidars"]]
        if base == 56000:
            ports = Ports(**{**ports.__dict__, **cfg["ports"]})
        if not p.has("data_type"):
            data_type = cfg["data_type"]
    if not host_ip or not lidars:
        raise GraphError(
            f"{p.where}: give host_ip and lidar_ips, or user_config_path (livox_ros_driver2 JSON)"
        )
    for key, ip in (("host_ip", host_ip), *(("lidar_ips", lidar.ip) for lidar in lidars)):
        try:  # the dry run builds this node too: a mistyped address is said before any socket opens
            ipaddress.IPv4Address(ip)
        except ValueError:
            raise p._err(key, ip, "a dotted IPv4 address such as 192.168.1.5") from None
    config = DriverConfig(
        host_ip=host_ip, lidars=tuple(lidars), msg_format=fmt,  # type: ignore[arg-type]
        publish_interval_ns=round(1e9 / freq), multi_topic=p.flag("multi_topic", True),
        imu=p.flag("imu", True), data_type=data_type, ports=ports,
    )  # fmt: skip
    config.validate()
    node = LivoxDriverNode(
        ctx.name, config, ctx.publish, p.number("discovery_s", 0.0), p.flag("process", True)
    )
    topics = []
    for lidar in config.lidars:
        ip = lidar.topic_ip or lidar.ip
        topics += [
            lidar_topic(ip, config.multi_topic),
            *([imu_topic(ip, config.multi_topic)] if config.imu else []),
        ]
    node.publishes = tuple(ctx.resolve(t.lstrip("/")) for t in topics)  # published as relative names
    return node


# ---------------------------------------------------------------- cameras


def _source(p: Params, kind: str, which: str, sim: Any, cam: int, name: str) -> Any:
    from sensorbox.live.sources import OpenCVSource, ZedSource

    pre = f"{which}_" if which else ""
    if kind == "zed":
        serial = p.integer(pre + "serial", 0)
        if serial < 0:
            raise p._err(pre + "serial", serial, "a ZED serial number (0: the first camera found)")
        return ZedSource(serial or None, p.text("resolution", "HD1200"), int(p.number("fps", 30.0)), name)
    if kind == "opencv":
        device = p.text(pre + "device", str(cam))
        stamps = p.choice("stamps", ("auto", "host", "file"), "auto")
        return OpenCVSource(
            device, width=p.integer("width", 0), height=p.integer("height", 0), fps=p.number("fps", 0.0),
            fourcc=p.text("fourcc", "MJPG"), stamps=None if stamps == "auto" else stamps,  # type: ignore[arg-type]
            realtime=p.flag("realtime", False), name=name,
        )  # fmt: skip
    return _sim("sim_camera_source")(p, sim, cam, name)


def _image_opts(p: Params) -> dict[str, Any]:
    return {
        "image": p.choice("image", ("jpeg", "raw"), "jpeg"),
        "jpeg_quality": p.integer("jpeg_quality", 90),
    }


def camera_node(ctx: NodeContext, p: Params) -> Node:
    from sensorbox.live.cameras import CameraNode, CameraOutput

    kind = p.choice("source", ("zed", "opencv", "sim"), "zed")
    sim, on_open = None, None
    cam = 0
    if kind == "sim":
        sim, on_open = _sim("sim_cameras")(p)
        cam = {"upper": 0, "lower": 1, "0": 0, "1": 1}.get(p.text("camera", "upper"), -1)
        if cam < 0:
            raise GraphError(f"{p.where}: camera: expected upper or lower")
    source = _source(p, kind, "", sim, cam, ctx.name)
    default_topic = sim.topic(cam) if sim is not None else ZED_IMAGE_TOPIC
    out = CameraOutput(
        ctx.resolve(p.text("topic", default_topic)), p.text("frame_id", f"{ctx.name}_optical_frame")
    )
    node = CameraNode(
        ctx.name, [source], [out], ctx.bus.publish, ctx.shutdown, on_open=on_open, **_image_opts(p)
    )
    node.claims = _claims(p, kind, [""], [cam])
    return node


def _claims(p: Params, kind: str, which: list[str], cams: list[int]) -> tuple[str, ...]:
    """The devices a camera node's sources open: OpenCV devices, ZED serials (0, the first camera found,
    claims none): the launch refuses two sources on one."""
    if kind == "opencv":
        return tuple(
            f"the camera device {p.text(f'{w}_device' if w else 'device', str(c))}"
            for w, c in zip(which, cams, strict=True)
        )
    if kind == "zed":
        serials = [p.integer(f"{w}_serial" if w else "serial", 0) for w in which]
        return tuple(f"the ZED camera serial {s}" for s in serials if s > 0)
    return ()


def stereo_camera_node(ctx: NodeContext, p: Params, source: str | None = None) -> Node:
    from calibration.rig import REFERENCE_RIG, read_rig
    from sensorbox.live.cameras import CameraNode, CameraOutput

    kind = source or p.choice("source", ("zed", "opencv", "sim"), "zed")
    sim, on_open = _sim("sim_cameras")(p) if kind == "sim" else (None, None)
    if sim is not None:
        defaults = [sim.topic(0), sim.topic(1)]
    else:
        rig = read_rig(REFERENCE_RIG)
        defaults = [rig.upper.topic or "/zed_upper/image", rig.lower.topic or "/zed_lower/image"]
    sources, outputs = [], []
    for cam, which in enumerate(("upper", "lower")):
        sources.append(_source(p, kind, which, sim, cam, which))
        topic = ctx.resolve(p.text(f"{which}_topic", defaults[cam]))
        outputs.append(CameraOutput(topic, p.text(f"{which}_frame_id", f"cam{cam}_optical_frame")))
    fps = p.number("fps", 30.0)
    tol_ms = p.number("pair_tolerance_ms", pair_tolerance_ns(1e9 / fps) / 1e6)
    node = CameraNode(
        ctx.name, sources, outputs, ctx.bus.publish, ctx.shutdown, pair_tolerance_ns=round(tol_ms * 1e6),
        on_open=on_open, **_image_opts(p),
    )  # fmt: skip
    node.claims = _claims(p, kind, ["upper", "lower"], [0, 1])
    if sim is not None and on_open is not None:  # it writes the rig: the recording should hold its sensors
        rig, path = sim.setup.rig, p.text("write_rig", "")
        sensors = [*((li.topic, li.name) for li in rig.lidars), *((imu.topic, imu.name) for imu in rig.imus)]
        node.expects = {topic: f"{path} names it for {name}" for topic, name in sensors if topic}
    return node


# ---------------------------------------------------------------- recorder and talker


def recorder_node(ctx: NodeContext, p: Params) -> Node:
    from sensorbox.live.recorder import Recorder
    from sensorbox.live.recorder_config import MAX_MIB, MAX_S, RecorderConfig

    topics = tuple(ctx.resolve(t) for t in p.texts("topics", []))
    cfg = RecorderConfig(
        out=p.path("out", "bags"), name=p.text("name", ""), topics=topics,
        split_bytes=round(p.number("split_size_mb", 0.0, MAX_MIB, 0.0) * MiB),
        split_s=p.number("split_duration_s", 0.0, MAX_S, 0.0),
        duration_s=p.number("duration_s", 0.0, MAX_S, 0.0),
        queue_msgs=p.integer("queue_size", 4096),
        queue_bytes=round(p.number("queue_mb", 512.0, MAX_MIB, 0.0) * MiB),
        min_free_bytes=round(p.number("min_free_mb", 1024.0, MAX_MIB, 0.0) * MiB),
        compress=p.flag("compress", True), flush_s=p.number("flush_s", 1.0, MAX_S, 0.0),
    )  # fmt: skip
    rec = Recorder(cfg, ctx.name, ctx.shutdown, in_graph=True)
    rec.subscribe_to(ctx.bus, topics or None)
    return rec


class TalkerNode:
    """demo_nodes' talker: `std_msgs/String` "Hello World: N" at `rate_hz` (tests, examples)."""

    priority = PRIORITY_SOURCE

    def __init__(self, name: str, publish: Publish, topic: str, rate_hz: float, count: int, payload: int):
        if rate_hz <= 0:
            raise GraphError(f"talker {name}: rate_hz must be > 0, got {rate_hz}")
        self.name, self._publish, self.topic = name, publish, topic
        self.rate_hz, self.count, self.payload = rate_hz, count, payload
        self.sent = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        from ingest.bags.rostypes import typestore

        ts = typestore(2)
        t0 = time.monotonic()
        for k in itertools.count():
            if self.count and k >= self.count:
                return
            if self._stop.wait(max(0.0, t0 + k / self.rate_hz - time.monotonic())):
                return
            text = f"Hello World: {k}" + "." * self.payload
            raw = bytes(ts.serialize_cdr(ts.types["std_msgs/msg/String"](data=text), "std_msgs/msg/String"))
            self._publish(self.topic, "std_msgs/msg/String", time.time_ns(), raw)
            self.sent += 1

    @property
    def done(self) -> bool:
        return bool(self.count) and self.sent >= self.count

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()

    def status(self) -> NodeStatus:
        return NodeStatus({"sent": float(self.sent)})


def talker_node(ctx: NodeContext, p: Params) -> Node:
    return TalkerNode(
        ctx.name, ctx.publish, p.text("topic", "chatter"), p.number("rate_hz", 10.0), p.integer("count", 0),
        p.integer("payload_bytes", 0),
    )  # fmt: skip


# ---------------------------------------------------------------- the registry


SIM_NODES = "sensorbox.sim.nodes"
"""Where the simulator's node factories live: live code reaches the simulator only by this name."""


def _sim(attr: str) -> Any:
    """A factory of the simulator's nodes, imported on first use."""
    return getattr(importlib.import_module(SIM_NODES), attr)


Factory = Callable[[NodeContext, "Params"], Node]


@dataclass(frozen=True)
class NodeType:
    """A launch file's `pkg`/`exec`: its factory, or the name of one in the simulator's nodes."""

    pkg: str
    exec: str
    factory: Factory | str
    summary: str
    defaults: Mapping[str, Any] = field(default_factory=dict)

    def make(self, ctx: NodeContext, params: Params) -> Node:
        factory = _sim(self.factory) if isinstance(self.factory, str) else self.factory
        node: Node = factory(ctx, params)
        return node


NODE_TYPES: tuple[NodeType, ...] = (
    NodeType("sensorbox", "recorder", recorder_node, "bounded queues into ROS 2 mcap bags"),
    NodeType("sensorbox", "livox_driver", livox_driver_node, "Livox Mid-360 UDP driver (no SDK)"),
    NodeType("livox_ros_driver2", "livox_ros_driver2_node", livox_driver_node, "= sensorbox/livox_driver"),
    NodeType("sensorbox", "mid360_emulator", "mid360_emulator_node", "emulated Mid-360 on loopback"),
    NodeType("sensorbox", "camera", camera_node, "one camera: ZED X One, OpenCV/V4L2 or simulated"),
    NodeType("zed_wrapper", "zed_wrapper", camera_node, "alias of sensorbox/camera (ZED)"),
    NodeType("sensorbox", "stereo_camera", stereo_camera_node, "upper+lower cameras paired by stamp"),
    NodeType("sensorbox", "sim_camera", "sim_camera_node", "the simulator's stereo pair at 30 Hz"),
    NodeType("sensorbox", "talker", talker_node, "std_msgs/String at a rate (demo_nodes' talker)"),
)  # fmt: skip


def node_type(pkg: str, exe: str) -> NodeType | None:
    return next((t for t in NODE_TYPES if t.pkg == pkg and t.exec == exe), None)


def known_node_types() -> list[str]:
    return [f"{t.pkg}/{t.exec}" for t in NODE_TYPES]


def build_node(spec: Any, bus: Bus, shutdown: Shutdown) -> Node:
    """The node a `launch.NodeSpec` describes, constructed (not started)."""
    t = node_type(spec.pkg, spec.exec)
    if t is None:
        raise GraphError(
            f"{spec.where}: unknown node type {spec.pkg}/{spec.exec}; known: {', '.join(known_node_types())}"
        )
    name = spec.name or spec.exec
    ctx = node_context(bus, shutdown, name, spec.namespace, spec.remaps)
    params = Params({**t.defaults, **spec.params}, spec.label)
    try:
        node = t.make(ctx, params)
    except GraphError:
        raise
    except SensorboxError as err:  # e.g. a RecorderError or DriverError about a parameter value
        raise GraphError(f"{spec.label}: {err}") from err
    params.check()
    return node
