"""An in-process message bus and the runner of a node graph (drivers, cameras, emulators, recorder).

SensorBox runs its live nodes as objects in one process, each with its own
threads, instead of ROS processes: on a 2-core box a process per node would
spend its time copying images between processes. A node publishes
`(topic, msgtype, stamp_ns, raw)` (serialised ROS 2 bytes, header stamp in ns)
through the `Publish` callable it gets in its `NodeContext`; the bus hands the
message synchronously to every subscriber (the recorder's bounded queues), so
subscribers must not block.

Topic names resolve like ROS 2 names: `/abs` stays, `rel` becomes
`/<namespace>/rel`, `~/x` becomes `/<namespace>/<node>/x`; then the node's
remaps (`from` resolved the same way) are applied.

`run_graph` starts the nodes in `priority` order (0 = sinks such as the
recorder, 1 = emulated devices, 2 = sources), waits until it is told to stop
(SIGINT/SIGTERM via `stop_on_signals`, a duration, a node asking for shutdown or
failing), then stops them in reverse order so the recorder drains last.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import threading
import time
from collections.abc import Callable, Collection, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import Protocol

from sensorbox.errors import GraphError

log = logging.getLogger(__name__)

Publish = Callable[[str, str, int, bytes], None]
"""(topic, msgtype, stamp_ns, serialised bytes) -> None; the Livox driver's callback shape."""
Subscriber = Callable[[str, str, int, bytes], None]

PRIORITY_SINK, PRIORITY_DEVICE, PRIORITY_SOURCE = 0, 1, 2


# ---------------------------------------------------------------- names


def _join(*parts: str) -> str:
    out = "/".join(p.strip("/") for p in parts if p.strip("/"))
    return "/" + out


def resolve_name(name: str, namespace: str = "/", node: str = "") -> str:
    """A ROS 2 topic name made absolute: `/a` stays, `a` -> `/ns/a`, `~/a` -> `/ns/node/a`."""
    if not name or any(c.isspace() for c in name) or "//" in name or (name.endswith("/") and name != "/"):
        raise GraphError(f"invalid topic name {name!r}: expected e.g. '/livox/imu', 'imu' or '~/image'")
    if name.startswith("/"):
        return name
    if name == "~" or name.startswith("~/"):
        if not node:
            raise GraphError(f"topic {name!r} is private (~) but no node name is known")
        return _join(namespace, node, name[1:])
    return _join(namespace, name)


# ---------------------------------------------------------------- the bus


class Bus:
    """Synchronous fan-out from publishers to subscribers, counting what each topic published."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._subs: list[tuple[frozenset[str] | None, Subscriber]] = []
        self._counts: dict[str, int] = {}
        self._types: dict[str, str] = {}

    def subscribe(self, callback: Subscriber, topics: Collection[str] | None = None) -> None:
        """Call `callback` for every message on `topics` (None: every topic)."""
        with self._lock:
            self._subs.append((None if topics is None else frozenset(topics), callback))

    def publish(self, topic: str, msgtype: str, stamp_ns: int, raw: bytes) -> None:
        with self._lock:
            self._counts[topic] = self._counts.get(topic, 0) + 1
            self._types.setdefault(topic, msgtype)
            subs = self._subs
        for topics, callback in subs:
            if topics is None or topic in topics:
                callback(topic, msgtype, stamp_ns, raw)

    def publisher(
        self, namespace: str = "/", node: str = "", remaps: Sequence[tuple[str, str]] = ()
    ) -> Publish:
        """A `Publish` that resolves a node's topic names and applies its remaps before publishing."""
        rules = {resolve_name(a, namespace, node): resolve_name(b, namespace, node) for a, b in remaps}
        cache: dict[str, str] = {}

        def publish(topic: str, msgtype: str, stamp_ns: int, raw: bytes) -> None:
            full = cache.get(topic)
            if full is None:
                resolved = resolve_name(topic, namespace, node)
                full = cache[topic] = rules.get(resolved, resolved)
            self.publish(full, msgtype, stamp_ns, raw)

        return publish

    def counts(self) -> dict[str, int]:
        """Messages published per topic so far."""
        with self._lock:
            return dict(self._counts)

    def types(self) -> dict[str, str]:
        with self._lock:
            return dict(self._types)


# ---------------------------------------------------------------- nodes


@dataclass(frozen=True)
class NodeStatus:
    """What a node reports: its counters, drops by stage, and (recorders) what it wrote."""

    counters: Mapping[str, float] = field(default_factory=dict)
    drops: Mapping[str, int] = field(default_factory=dict)  # stage -> messages/frames/packets lost there
    written: Mapping[str, int] = field(default_factory=dict)  # recorders: messages written per topic
    files: tuple[Path, ...] = ()  # recorders: bags written or being written
    rates_hz: Mapping[str, float] = field(default_factory=dict)  # recorders: mean rate written per topic
    error: str | None = None


class Node(Protocol):
    """A live node: `start()` returns once its threads run; `stop()` joins them.

    A node may also have `graph_started()` (called once every node has started)
    and a `done` property (sources: True once their stream ended).
    """

    name: str
    priority: int

    def start(self) -> None: ...

    def stop(self) -> None: ...

    def status(self) -> NodeStatus: ...


class Shutdown:
    """The graph's stop flag plus the first reason given for stopping."""

    def __init__(self, event: threading.Event | None = None) -> None:
        self.event = event or threading.Event()
        self.reason: str | None = None
        self.error: str | None = None
        self._lock = threading.Lock()

    def request(self, reason: str, error: bool = False) -> None:
        with self._lock:
            if self.reason is None:
                self.reason = reason
            if error and self.error is None:
                self.error = reason
        self.event.set()


@dataclass(frozen=True)
class NodeContext:
    """What a node factory gets besides its parameters."""

    name: str
    namespace: str
    bus: Bus
    publish: Publish
    shutdown: Shutdown
    remaps: tuple[tuple[str, str], ...] = ()

    def resolve(self, topic: str) -> str:
        """The absolute, remapped name `topic` has when this node publishes or subscribes to it."""
        full = resolve_name(topic, self.namespace, self.name)
        rules = {resolve_name(a, self.namespace, self.name): b for a, b in self.remaps}
        return resolve_name(rules[full], self.namespace, self.name) if full in rules else full


def node_context(
    bus: Bus, shutdown: Shutdown, name: str, namespace: str = "/", remaps: Sequence[tuple[str, str]] = ()
) -> NodeContext:
    return NodeContext(name, namespace, bus, bus.publisher(namespace, name, remaps), shutdown, tuple(remaps))


# ---------------------------------------------------------------- running a graph


@dataclass(frozen=True)
class GraphSnapshot:
    """The state of a running graph: what was published and written, drops, node counters."""

    elapsed_s: float
    published: dict[str, int]  # per topic, on the bus
    written: dict[str, int]  # per topic, summed over recorders
    rates_hz: dict[str, float]  # per topic, mean rate written (first recorder that has the topic)
    drops: dict[str, int]  # "node.stage" -> count
    nodes: dict[str, NodeStatus]
    declared: dict[str, str] = field(default_factory=dict)  # topic -> the node that says it publishes it
    expected: dict[str, str] = field(default_factory=dict)  # topic -> why a node expects it (`expects`)

    def silent_topics(self) -> dict[str, list[str]]:
        """Per node, the topics it says it publishes (`publishes`) on which nothing was published."""
        out: dict[str, list[str]] = {}
        for topic, node in sorted(self.declared.items()):
            if not self.published.get(topic, 0):
                out.setdefault(node, []).append(topic)
        return out

    def counter(self, key: str) -> float | None:
        """The first node counter called `key` (e.g. disk_free_bytes), or None."""
        for st in self.nodes.values():
            if key in st.counters:
                return st.counters[key]
        return None

    def total_drops(self) -> int:
        return sum(self.drops.values())


@dataclass(frozen=True)
class GraphResult:
    snapshot: GraphSnapshot
    reason: str  # why it stopped
    error: str | None  # a node's failure, if that is why
    files: tuple[Path, ...]


def snapshot(nodes: Sequence[Node], bus: Bus, elapsed_s: float) -> GraphSnapshot:
    statuses: dict[str, NodeStatus] = {}
    for node in nodes:
        try:
            statuses[node.name] = node.status()
        except Exception as err:  # a status bug must not stop a recording
            statuses[node.name] = NodeStatus(error=f"status() failed: {err}")
    written: dict[str, int] = {}
    rates: dict[str, float] = {}
    drops: dict[str, int] = {}
    for name, st in statuses.items():
        for topic, n in st.written.items():
            written[topic] = written.get(topic, 0) + n
        for topic, hz in st.rates_hz.items():
            rates.setdefault(topic, hz)
        for stage, n in st.drops.items():
            drops[f"{name}.{stage}"] = n
    declared = {topic: node.name for node in nodes for topic in getattr(node, "publishes", ())}
    expected = {topic: why for node in nodes for topic, why in getattr(node, "expects", {}).items()}
    return GraphSnapshot(elapsed_s, bus.counts(), written, rates, drops, statuses, declared, expected)


def run_graph(
    nodes: Sequence[Node],
    bus: Bus,
    shutdown: Shutdown,
    *,
    duration_s: float | None = None,
    on_tick: Callable[[GraphSnapshot], None] | None = None,
    tick_s: float = 0.5,
) -> GraphResult:
    """Start `nodes`, run until `shutdown` is requested or `duration_s` passed, stop them; the result.

    A node that fails to start stops the nodes already started (so the
    recorder closes its bag) and re-raises. Node errors while running end the
    run; they are in `GraphResult.error`.
    """
    names = [n.name for n in nodes]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise GraphError(f"two nodes share the name(s) {', '.join(dup)}; give each node its own name")
    order = sorted(nodes, key=lambda n: n.priority)
    started: list[Node] = []
    t0 = time.monotonic()
    try:
        for node in order:
            log.info("starting node %s", node.name)
            node.start()
            started.append(node)
        for node in order:
            hook = getattr(node, "graph_started", None)
            if hook is not None:
                hook()
        t0 = time.monotonic()
        while not shutdown.event.wait(tick_s):
            elapsed = time.monotonic() - t0
            if on_tick is not None:
                on_tick(snapshot(nodes, bus, elapsed))
            if duration_s is not None and duration_s > 0 and elapsed >= duration_s:
                shutdown.request(f"duration {duration_s:g} s reached")
            sources = [n for n in nodes if n.priority == PRIORITY_SOURCE]
            if sources and all(getattr(n, "done", False) for n in sources):
                shutdown.request("every source finished")
    finally:
        if shutdown.reason is None:
            shutdown.request("start failed")
        errors = _stop_all(started)
    if errors:
        shutdown.error = shutdown.error or "; ".join(errors)
    snap = snapshot(nodes, bus, time.monotonic() - t0)
    files = tuple(f for st in snap.nodes.values() for f in st.files)
    assert shutdown.reason is not None
    return GraphResult(snap, shutdown.reason, shutdown.error, files)


def _stop_all(started: Sequence[Node]) -> list[str]:
    errors = []
    for node in reversed(started):
        log.info("stopping node %s", node.name)
        try:
            node.stop()
        except Exception as err:
            log.exception("node %s failed to stop", node.name)
            errors.append(f"node {node.name!r} failed to stop: {err}")
    return errors


@contextlib.contextmanager
def stop_on_signals(shutdown: Shutdown) -> Iterator[None]:
    """SIGINT and SIGTERM request a clean shutdown while inside (main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, _frame: FrameType | None) -> None:
        shutdown.request(f"{signal.Signals(signum).name} received")

    previous = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
