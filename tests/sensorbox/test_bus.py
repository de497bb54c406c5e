"""The in-process bus and graph runner: ROS 2 name resolution, remaps, start/stop order, shutdown."""

from __future__ import annotations

import os
import signal
import threading

import pytest

from sensorbox.errors import GraphError
from sensorbox.live.bus import (
    PRIORITY_DEVICE,
    PRIORITY_SINK,
    PRIORITY_SOURCE,
    Bus,
    NodeStatus,
    Shutdown,
    node_context,
    resolve_name,
    run_graph,
    stop_on_signals,
)
from tests.live import HANG_S

pytestmark = pytest.mark.realtime  # threads on a clock, signals: run serially (make test)


@pytest.mark.parametrize(
    ("name", "ns", "node", "full"),
    [
        ("/livox/imu", "/rig", "drv", "/livox/imu"),
        ("livox/imu", "/", "drv", "/livox/imu"),
        ("imu", "/rig/left", "drv", "/rig/left/imu"),
        ("~/rgb/color/rect/image", "/zed_upper", "zed_node", "/zed_upper/zed_node/rgb/color/rect/image"),
        ("~", "/a", "n", "/a/n"),
    ],
)
def test_resolve_name(name, ns, node, full):
    assert resolve_name(name, ns, node) == full


@pytest.mark.parametrize("bad", ["", "a b", "a//b", "imu/"])
def test_resolve_name_rejects_bad_names(bad):
    with pytest.raises(GraphError, match="invalid topic name"):
        resolve_name(bad, "/", "n")


def test_publisher_resolves_and_remaps_and_subscribers_filter():
    bus = Bus()
    got_all, got_one = [], []
    bus.subscribe(lambda *m: got_all.append(m))
    bus.subscribe(lambda *m: got_one.append(m), topics=["/x/imu"])
    pub = bus.publisher("/rig", "cam", remaps=[("imu", "/x/imu"), ("/abs/a", "b")])
    pub("imu", "T", 1, b"1")  # relative -> /rig/imu -> remapped to /x/imu
    pub("/abs/a", "T", 2, b"2")  # -> /rig/b (the remap target resolves in the node's namespace)
    pub("~/image", "T", 3, b"3")  # private
    pub("other", "T", 4, b"4")
    assert [m[0] for m in got_all] == ["/x/imu", "/rig/b", "/rig/cam/image", "/rig/other"]
    assert got_one == [("/x/imu", "T", 1, b"1")]
    assert bus.counts() == {"/x/imu": 1, "/rig/b": 1, "/rig/cam/image": 1, "/rig/other": 1}


def test_context_resolve_matches_publisher():
    bus = Bus()
    ctx = node_context(bus, Shutdown(), "rec", "/ns", [("chatter", "/talk")])
    assert ctx.resolve("chatter") == "/talk"
    assert ctx.resolve("x") == "/ns/x"


class FakeNode:
    def __init__(self, name, priority, log, fail_start=False, done=None):
        self.name, self.priority, self.log, self.fail_start = name, priority, log, fail_start
        if done is not None:
            self.done = done

    def start(self):
        if self.fail_start:
            raise GraphError(f"{self.name} cannot start")
        self.log.append(("start", self.name))

    def stop(self):
        self.log.append(("stop", self.name))

    def status(self):
        return NodeStatus({"x": 1.0}, {"queue": 2}, {"/t": 3})


def test_graph_starts_by_priority_stops_in_reverse_and_reports():
    log: list[tuple[str, str]] = []
    nodes = [
        FakeNode("cam", PRIORITY_SOURCE, log),
        FakeNode("rec", PRIORITY_SINK, log),
        FakeNode("emu", PRIORITY_DEVICE, log),
    ]
    bus = Bus()
    res = run_graph(nodes, bus, Shutdown(), duration_s=0.05, tick_s=0.01)
    assert log == [
        ("start", "rec"),
        ("start", "emu"),
        ("start", "cam"),
        ("stop", "cam"),
        ("stop", "emu"),
        ("stop", "rec"),
    ]
    assert res.reason == "duration 0.05 s reached" and res.error is None
    assert res.snapshot.drops == {"cam.queue": 2, "rec.queue": 2, "emu.queue": 2}
    assert res.snapshot.written == {"/t": 9}


def test_failed_start_stops_started_nodes_and_raises():
    log: list[tuple[str, str]] = []
    nodes = [FakeNode("rec", PRIORITY_SINK, log), FakeNode("drv", PRIORITY_SOURCE, log, fail_start=True)]
    with pytest.raises(GraphError, match="drv cannot start"):
        run_graph(nodes, Bus(), Shutdown(), tick_s=0.01)
    assert log == [("start", "rec"), ("stop", "rec")]


def test_shutdown_request_from_a_node_thread_and_sources_done():
    sd = Shutdown()
    threading.Timer(0.05, lambda: sd.request("disk full", error=True)).start()
    res = run_graph([FakeNode("a", PRIORITY_SOURCE, [])], Bus(), sd, tick_s=0.01)
    assert (res.reason, res.error) == ("disk full", "disk full")
    res = run_graph([FakeNode("a", PRIORITY_SOURCE, [], done=True)], Bus(), Shutdown(), tick_s=0.01)
    assert res.reason == "every source finished"


def test_duplicate_node_names_are_an_error():
    with pytest.raises(GraphError, match="share the name"):
        run_graph([FakeNode("a", 0, []), FakeNode("a", 2, [])], Bus(), Shutdown())


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_signals_request_a_clean_shutdown(sig):
    sd = Shutdown()
    before = signal.getsignal(sig)
    with stop_on_signals(sd):
        os.kill(os.getpid(), sig)
        assert sd.event.wait(HANG_S)
    assert sd.reason == f"{signal.Signals(sig).name} received"
    assert signal.getsignal(sig) is before
