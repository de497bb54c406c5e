"""The runner of a parsed launch file (`sensorbox.live.launch.LaunchPlan`): its nodes built on one bus
and run in one process until shutdown (`run_launch`), or built and dropped to refuse what the run would
refuse before starting anything (`check_launch`, `launch --dry-run`)."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from sensorbox.errors import LaunchError
from sensorbox.live.bus import Bus, GraphResult, GraphSnapshot, Shutdown, run_graph
from sensorbox.live.launch import LaunchPlan

if TYPE_CHECKING:
    from sensorbox.live.monitor import MonitorConfig


def run_launch(
    plan: LaunchPlan,
    *,
    shutdown: Shutdown | None = None,
    on_tick: Callable[[GraphSnapshot], None] | None = None,
    tick_s: float = 0.5,
    monitor: MonitorConfig | None = None,
) -> GraphResult:
    """Build the plan's nodes in one process and run them until shutdown (see `bus.run_graph`); with
    `monitor`, a live monitor node beside them (`sensorbox.live.monitor`)."""
    bus = Bus()
    shutdown = shutdown or Shutdown()
    nodes = _build_nodes(plan, bus, shutdown)
    if monitor is not None:
        from sensorbox.live.monitor import Monitor

        node = Monitor(monitor, bus)
        nodes.append(node)
        on_tick = node.ticker(on_tick)
    return run_graph(nodes, bus, shutdown, on_tick=on_tick, tick_s=tick_s)


def check_launch(plan: LaunchPlan) -> None:
    """Refuse what `run_launch` would refuse before starting a node (a parameter value, an unused
    parameter, an unknown node type, no node), starting none: `launch --dry-run`.

    The nodes are built as the run builds them, then dropped; building a node
    starts nothing and writes nothing (devices open, processes start and
    files are written when the graph starts it). A simulated node sets up its
    scene, so this takes a few seconds.
    """
    _build_nodes(plan, Bus(), Shutdown())


def _build_nodes(plan: LaunchPlan, bus: Bus, shutdown: Shutdown) -> list[Any]:
    """Every node of the plan, built on `bus` (not started); LaunchError when the file starts none."""
    from sensorbox.live.nodes import build_node

    nodes = [build_node(spec, bus, shutdown) for spec in plan.nodes]
    if not nodes:
        raise LaunchError(f"{plan.file}: the launch file starts no node")
    first: dict[str, str] = {}  # the graph refuses two of one name; the dry run names where they are
    for spec, node in zip(plan.nodes, nodes, strict=True):
        if node.name in first:
            raise LaunchError(
                f"{spec.where}: a second node named {node.name!r} (the first at {first[node.name]}); "
                "give each node its own name"
            )
        first[node.name] = spec.where
    publisher: dict[str, str] = {}  # one publisher per topic: two would be recorded interleaved as one
    for spec, node in zip(plan.nodes, nodes, strict=True):
        for topic in getattr(node, "publishes", ()):
            if topic in publisher:
                raise LaunchError(
                    f"{spec.where}: node {node.name!r} publishes {topic}, as does {publisher[topic]}; their "
                    "messages would be recorded as one topic: give each its own (a remap or its topic "
                    "parameter)"
                )
            publisher[topic] = f"node {node.name!r} at {spec.where}"
    _one_source_per_device(plan, nodes)
    return nodes


def _one_source_per_device(plan: LaunchPlan, nodes: list[Any]) -> None:
    """LaunchError when two sources open one device (`claims`): a camera device or ZED serial given as
    both cameras, two emulators on one address."""
    opener: dict[str, tuple[str, str]] = {}
    for spec, node in zip(plan.nodes, nodes, strict=True):
        for device in getattr(node, "claims", ()):
            if device not in opener:
                opener[device] = (node.name, spec.where)
                continue
            name, where = opener[device]
            also = " for both its cameras" if name == node.name else f", as does node {name!r} at {where}"
            raise LaunchError(
                f"{spec.where}: node {node.name!r} opens {device}{also}; one device cannot be two sources: "
                "give each its own"
            )
