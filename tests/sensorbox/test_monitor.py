"""The live monitor (`--monitor PORT`) against a real Foxglove WebSocket client on the emulated rig.

The client (tests/foxglove_client.py) does the WebSocket handshake itself,
subscribes to every channel the monitor advertises and decodes each channel's
messages by its own schema; the monitor's books must balance against what the
recorder wrote.
"""

from __future__ import annotations

import json
import re
import socket
import threading
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from calibration.rig import REFERENCE_RIG
from sensorbox.live.launch import parse_launch
from sensorbox.live.launch_run import run_launch
from sensorbox.live.monitor import REASONS, MonitorConfig
from tests.foxglove_client import FoxgloveClient
from tests.live import NO_DISK_GUARD
from tests.sensorbox.test_capture import (
    IMUS,
    LIDARS,
    LOWER,
    ROOT,
    SIM_LAUNCH,
    UPPER,
    fresh_port_base,
    run_cli,
)

CHANNELS = {
    "/monitor/upper/image", "/monitor/lower/image", "/monitor/lidar_top/points", "/monitor/lidar_bottom/points",
    "/monitor/imu_top", "/monitor/imu_bottom", "/monitor/status", "/monitor/coverage",
}  # fmt: skip


def free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class ClientThread(threading.Thread):
    """Connects while the graph starts, subscribes to every advertised channel, reads until told to stop."""

    def __init__(self, port: int) -> None:
        super().__init__(daemon=True)
        self.port, self.stop = port, threading.Event()
        self.client: FoxgloveClient | None = None
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            self.client = FoxgloveClient.connect("127.0.0.1", self.port, timeout_s=300)
            while not self.stop.is_set() and self.client.closed is None:
                self.client.poll(0.2)
                self.client.subscribe_all()  # the monitor advertises all its channels at start
        except BaseException as err:  # reported by the test
            if not self.stop.is_set():
                self.error = err


def check_image(msg: dict[str, Any], frame_id: str) -> np.ndarray:
    assert msg["format"] == b"jpeg" and msg["frame_id"] == frame_id.encode()
    image = cv2.imdecode(np.frombuffer(msg["data"], np.uint8), cv2.IMREAD_COLOR)
    assert image is not None and image.shape == (300, 480, 3)  # scale 0.25 frames: 480 x 300, not reduced
    return image


def check_cloud(msg: dict[str, Any]) -> np.ndarray:
    assert msg["frame_id"] == b"cam0" and msg["point_stride"] == 16
    names = [f["name"] for f in msg["fields"]]
    assert names == [b"x", b"y", b"z", b"intensity"]
    pts = np.frombuffer(msg["data"], np.float32).reshape(-1, 4)
    # how many points a message holds depends on when it was published (a sweep's first packets, or a
    # whole one): only that it has some, every one finite and within the simulated scene, is checked
    assert len(pts) > 0 and np.isfinite(pts).all()
    assert float(np.abs(pts[:, :3]).max()) < 200.0
    return pts


@pytest.mark.realtime
def test_monitor_serves_every_channel_to_a_foxglove_client_and_its_books_balance(tmp_path):
    port = free_tcp_port()
    args = {"out": str(tmp_path / "bags"), "duration": "4", "scale": "0.25", "name": "mon",
            "port_base": str(fresh_port_base()), "min_free_mb": str(NO_DISK_GUARD), "trajectory": "walk"}  # fmt: skip
    reader = ClientThread(port)
    reader.start()
    result = run_launch(
        parse_launch(SIM_LAUNCH, args), tick_s=0.1, monitor=MonitorConfig(port, REFERENCE_RIG)
    )
    reader.stop.set()
    reader.join(30)
    assert reader.error is None, reader.error
    assert result.error is None and result.reason == "recorder: recorded 4 s"
    client = reader.client
    assert client is not None and client.subprotocol == "foxglove.sdk.v1"
    # the server closed the connection when the monitor stopped (no status code, or 1000: normal)
    assert client.closed in (None, b"") or client.closed[:2] == b"\x03\xe8", client.closed
    advertised = {c.topic for c in client.channels.values()}
    assert advertised == CHANNELS

    # every channel's messages decode: images, point clouds, IMU, status, coverage
    got = client.messages
    assert set(got) == CHANNELS, sorted(CHANNELS - set(got))
    for msg in got["/monitor/upper/image"]:
        check_image(msg, "cam0")
    for msg in got["/monitor/lower/image"]:
        check_image(msg, "cam1")
    for topic in ("/monitor/lidar_top/points", "/monitor/lidar_bottom/points"):
        for msg in got[topic]:
            pts = check_cloud(msg)
            assert np.median(np.linalg.norm(pts[:, :3], axis=1)) < 20  # indoor: metres, not millimetres
    for msg in got["/monitor/imu_top"]:
        assert set(msg) == {"stamp_ns", "gyro_rad_s", "acc"} and abs(msg["acc"]["z"]) > 0.5  # about 1 g
    cover = [check_image(m, "cam0") for m in got["/monitor/coverage"]]
    assert cover
    status = got["/monitor/status"][-1]
    fraction = status["coverage_fraction"]
    assert fraction is not None and 0.05 < fraction < 1.0
    rows = {row["topic"]: row for row in status["topics"]}
    assert set(rows) >= {UPPER, LOWER, *LIDARS, *IMUS}
    on_disk = sum(f.stat().st_size for f in (tmp_path / "bags" / "mon_000").iterdir())
    assert status["disk_free_bytes"] > 0 and 0 < status["bag_bytes"] <= on_disk
    assert status["written_bytes"] > 0

    # the books: every message on a monitored topic was sent or skipped for one reason, and the
    # monitor saw every message the recorder wrote
    snap = result.snapshot
    c = snap.nodes["monitor"].counters
    rec_drops = sum(v for k, v in snap.drops.items() if k.startswith("recorder."))
    assert rec_drops == 0 and snap.nodes["monitor"].error is None
    for topic in (UPPER, LOWER, *LIDARS, *IMUS):
        received = c[f"{topic}.received"]
        skipped = {r: c.get(f"{topic}.skipped_{r}", 0) for r in REASONS}
        assert received == snap.published[topic] == snap.written[topic], topic
        assert received == c[f"{topic}.sent"] + sum(skipped.values()), (topic, c[f"{topic}.sent"], skipped)
        assert skipped["decode"] == skipped["error"] == 0, topic
    # what the client read was sent; the monitor sent sweeps and frames once it had a subscriber
    for topic, channel in ((LIDARS[0], "/monitor/lidar_top/points"), (UPPER, "/monitor/upper/image")):
        assert 0 < len(got[channel]) <= c[f"{topic}.sent"]
    assert c.get(f"{LIDARS[0]}.skipped_rate", 0) == 0  # sweeps are never thinned by rate
    assert c["sent"] == sum(c[f"{t}.sent"] for t in (UPPER, LOWER, *LIDARS, *IMUS))
    assert sorted(Path(tmp_path / "bags").glob("mon_*")) == [tmp_path / "bags" / "mon_000"]


TALKER_LAUNCH = """launch:
- node: {pkg: sensorbox, exec: talker, name: talker, param: [{name: count, value: 3}]}
"""


def test_monitor_options_are_checked_before_anything_starts(tmp_path):
    launch = tmp_path / "talker.launch.yaml"
    launch.write_text(TALKER_LAUNCH)
    res = run_cli("launch", str(SIM_LAUNCH), "--monitor", "0")
    assert (res.returncode, res.stderr) == (2, "error: --monitor 0: expected a TCP port 1..65535\n")
    res = run_cli("launch", str(launch), "--monitor", "8765", "--dry-run")  # the dry run refuses it too
    assert res.returncode == 2
    assert res.stderr == (
        f"error: --monitor: no node of {launch} names a rig (a `rig` parameter); pass --monitor-rig RIG\n"
    )
    res = run_cli("capture", "--rig", str(REFERENCE_RIG), "--out", str(tmp_path / "o"), "--monitor", "70000")
    assert (res.returncode, res.stderr) == (2, "error: --monitor 70000: expected a TCP port 1..65535\n")
    assert not (tmp_path / "o").exists()


@pytest.mark.realtime
def test_a_taken_port_is_one_error_line_and_no_bag(tmp_path):
    launch = tmp_path / "talker.launch.yaml"
    launch.write_text(TALKER_LAUNCH)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        res = run_cli("launch", str(launch), "--monitor", str(port), "--monitor-rig", str(REFERENCE_RIG))
    assert res.returncode == 2
    assert res.stderr.startswith(f"error: monitor: cannot serve on 127.0.0.1:{port}: ")
    assert res.stderr.endswith("; choose another --monitor port\n") and res.stderr.count("\n") == 1


@pytest.mark.realtime
def test_a_host_that_resolves_nowhere_is_named_not_the_port(tmp_path):
    """Sweep 5: `--monitor-host not.a.host.invalid` ended with "choose another --monitor port"."""
    launch = tmp_path / "talker.launch.yaml"
    launch.write_text(TALKER_LAUNCH)
    res = run_cli(
        "launch", str(launch), "--monitor", "8765", "--monitor-host", "not.a.host.invalid",
        "--monitor-rig", str(REFERENCE_RIG),
    )  # fmt: skip
    assert res.returncode == 2 and res.stderr.count("\n") == 1
    assert res.stderr.startswith(
        "error: monitor: --monitor-host 'not.a.host.invalid' is no address of this computer ("
    )
    assert res.stderr.endswith("); expected one of its addresses or names (0.0.0.0: every one)\n")


def test_the_shipped_foxglove_layout_is_the_monitors_and_shows_its_channels():
    from calibration.rig import read_rig
    from sensorbox.live.monitor_layout import LAYOUT_FILE, layout_text

    assert LAYOUT_FILE == ROOT / "sensorbox" / "share" / "foxglove" / "monitor_layout.json"
    assert LAYOUT_FILE.read_text() == layout_text(read_rig(REFERENCE_RIG))
    text = LAYOUT_FILE.read_text()
    layout = json.loads(text)
    assert layout["version"] == 1 and layout["content"]["type"] == "split"
    images = re.findall(r'"imageTopic": "([^"]+)"', text)
    assert images == ["/monitor/upper/image", "/monitor/lower/image", "/monitor/coverage"]
    panels = re.findall(r'"panelType": "([^"]+)"', text)
    assert panels == ["Image", "Image", "Image", "ThreeDee", "Plot", "Plot", "RawMessages"]
    shown = set(images) | set(re.findall(r'"(/monitor/[a-z_]+/points)"', text))
    shown |= {m.split(".")[0] for m in re.findall(r'"value": "(/monitor/[^"]+)"', text)}
    assert shown == CHANNELS


class Subscribed:
    """Channels stand-in: every channel has a subscriber (the books, not the server, are under test)."""

    COVERAGE = "/monitor/coverage"

    def subscribed(self, channel: str) -> bool:
        return True


def test_offer_parks_without_waiting_for_the_worker_and_every_message_is_counted_once():
    """With no worker taking anything (a stalled one), the publisher's calls still return at once: one
    frame per camera parked (the rest above image_hz by their stamps), IMU samples above 50 Hz skipped,
    sweeps and IMU samples queued up to the bound then counted as backlog; at stop, what is parked
    counts as stopped."""
    from calibration.rig import read_rig
    from sensorbox.live.bus import Bus
    from sensorbox.live.monitor import Monitor

    bus = Bus()
    mon = Monitor(MonitorConfig(0, REFERENCE_RIG, image_hz=1e-3, queue_msgs=5), bus, read_rig(REFERENCE_RIG))
    mon._channels = Subscribed()  # type: ignore[assignment]  # started, as far as offer is concerned
    mon._running = True
    for k in range(3):  # no worker runs: each publish returns only because offer never waits
        bus.publish(UPPER, "sensor_msgs/msg/CompressedImage", k, b"jpeg")  # 1 parked, 2 above the rate
    for k in range(4):  # 8 offered, 5 queued, 3 backlog
        bus.publish(LIDARS[0], "livox_ros_driver2/msg/CustomMsg", k, b"sweep")
        bus.publish(IMUS[0], "sensor_msgs/msg/Imu", k * 20_000_000, b"imu")  # 50 Hz: each one taken
    bus.publish(IMUS[0], "sensor_msgs/msg/Imu", 65_000_000, b"imu")  # 5 ms after the last: above 50 Hz
    bus.publish("/chatter", "std_msgs/msg/String", 0, b"x")  # not a rig topic: not the monitor's
    mon.stop()
    counts = mon.counts()
    assert set(counts) == {UPPER, LIDARS[0], IMUS[0]}
    assert (counts[UPPER].received, counts[UPPER].sent, counts[UPPER].skipped) == (
        3,
        0,
        {"rate": 2, "stopped": 1},
    )
    sweeps, imu = counts[LIDARS[0]], counts[IMUS[0]]
    assert (sweeps.received, imu.received) == (4, 5)
    assert sweeps.skipped == {"stopped": 3, "backlog": 1}
    assert imu.skipped == {"stopped": 2, "backlog": 2, "rate": 1}
    # after the stop, arrivals are counted as stopped, never parked
    bus.publish(UPPER, "sensor_msgs/msg/CompressedImage", 9, b"jpeg")
    assert mon.counts()[UPPER].skipped == {"rate": 2, "stopped": 2}
    c = mon.status().counters
    assert (c["sent"], c["skipped_stopped"], c["skipped_backlog"], c["skipped_rate"]) == (0, 7, 3, 3)


class Failing(Subscribed):
    """Channels stand-in whose send fails: a bug in the monitor's sending path."""

    STATUS = "/monitor/status"

    def send(self, stream: object, item: object) -> str | None:
        raise RuntimeError("send broke")


@pytest.mark.realtime
def test_a_failing_monitor_counts_its_messages_as_error_and_says_so_once():
    from calibration.rig import read_rig
    from sensorbox.live.bus import Bus
    from sensorbox.live.monitor import Monitor
    from sensorbox.messages import imu_msg
    from tests.live import wait_for

    bus = Bus()
    mon = Monitor(MonitorConfig(0, REFERENCE_RIG), bus, read_rig(REFERENCE_RIG))
    mon.start()
    try:
        mon._channels = Failing()  # type: ignore[assignment]  # the server runs; sending breaks
        for k in range(3):
            stamp_ns = 1_000_000_000 + k * 100_000_000
            bus.publish(IMUS[0], "sensor_msgs/msg/Imu", stamp_ns, imu_msg(stamp_ns, np.zeros(3), np.ones(3)))

            def taken(n: int = k + 1) -> bool:
                return sum(mon.counts()[IMUS[0]].skipped.values()) == n

            wait_for(taken, "the worker took the sample")
    finally:
        mon.stop()
    assert mon.counts()[IMUS[0]].skipped == {"error": 3}
    assert mon.error == "monitor: RuntimeError: send broke"
    assert mon.status().error == mon.error


def test_the_run_summary_gives_the_monitors_books_in_one_line():
    from sensorbox.cli.capture import monitor_line
    from sensorbox.live.bus import GraphSnapshot, NodeStatus

    def snap(nodes: dict[str, NodeStatus]) -> GraphSnapshot:
        return GraphSnapshot(1.0, {}, {}, {}, {}, nodes)

    counters = {"sent": 8533.0, "skipped_rate": 21710.0, "skipped_superseded": 131.0, "skipped_backlog": 0.0}
    assert monitor_line(snap({"monitor": NodeStatus(counters)})) == (
        "Monitor: 8533 messages sent to Foxglove; skipped: rate 21710, superseded 131 "
        "(the monitor's, not the recording's: the bags hold all the recorder wrote)"
    )
    assert monitor_line(snap({"recorder": NodeStatus({"bytes_written": 5.0})})) is None


@pytest.mark.realtime
def test_the_cli_says_where_to_connect_once_the_server_listens(tmp_path):
    launch = tmp_path / "talker.launch.yaml"
    launch.write_text(TALKER_LAUNCH)
    port = free_tcp_port()
    res = run_cli("launch", str(launch), "--monitor", str(port), "--monitor-rig", str(REFERENCE_RIG))
    assert res.returncode == 0, res.stderr
    assert (
        f"monitor: in Foxglove, Open connection > Foxglove WebSocket > ws://127.0.0.1:{port} (layout: "
        "sensorbox/share/foxglove/monitor_layout.json)" in " ".join(res.stderr.split())
    )
    assert "Monitor: 0 messages sent to Foxglove; skipped: none" in res.stdout  # talker topics: not the rig's
