"""A launch file's YAML read with its line numbers (`LineMap`: every mapping knows its line, a key given
twice is an error), and ROS 2 parameter files (`param_file`), for `sensorbox.live.launch`."""

from __future__ import annotations

import re
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import yaml

from calibration.files import read_text
from calibration.opencv_yaml import BoundedSafeLoader, yaml_error_line
from sensorbox.errors import LaunchError


class LineMap(dict[str, Any]):
    """A YAML mapping that remembers its line (1-based)."""

    line = 0


class LineLoader(BoundedSafeLoader):
    """A SafeLoader (no arbitrary objects) whose mappings remember their line; nesting is bounded."""


def _construct_map(loader: LineLoader, node: yaml.MappingNode) -> LineMap:
    out = LineMap()
    out.line = node.start_mark.line + 1
    loader.flatten_mapping(node)
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=True)
        if not isinstance(key, str):
            raise LaunchError(f"line {key_node.start_mark.line + 1}: keys must be strings, got {key!r}")
        if key in out:
            raise LaunchError(f"line {key_node.start_mark.line + 1}: key {key!r} given twice")
        out[key] = loader.construct_object(value_node, deep=True)
    return out


LineLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_map)


def load_launch_yaml(path: Path) -> Any:
    text = read_text(path, "launch", error=LaunchError)  # a regular file of at most 4 MiB, UTF-8
    try:
        return yaml.load(text, Loader=LineLoader)
    except LaunchError as err:
        raise LaunchError(f"{path}:{err}") from err
    except yaml.YAMLError as err:
        raise LaunchError(yaml_error_line(path, err)) from err


ROS_NAME_PART = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
"""One part of a ROS name between slashes: letters, digits and underscores, not starting with a digit."""


def ros_namespace(ns: str, where: str) -> str:
    """`ns` when every part of it is a ROS name part (`ROS_NAME_PART`), else a `LaunchError`: a topic under
    it would be no ROS name, and the launch file's absolute remaps would not reach it."""
    bad = [part for part in ns.split("/") if part and not ROS_NAME_PART.fullmatch(part)]
    if bad:
        raise LaunchError(
            f"{where}: namespace {ns!r}: {bad[0]!r} is not a ROS name (letters, digits and _, not starting "
            "with a digit; parts joined by /)"
        )
    return ns


def join_ns(base: str, ns: str) -> str:
    parts = [p for p in (base + "/" + ns).split("/") if p]
    return "/" + "/".join(parts)


def param_file(path: Path, node: str, ns: str, where: str) -> dict[str, Any]:
    """`ros__parameters` for `node` (or `/**`) in a ROS 2 parameter file, nested keys dotted."""
    try:
        text = read_text(path, "parameter", error=LaunchError)
    except LaunchError as err:
        raise LaunchError(f"{where}: {err}") from err
    try:
        doc = yaml.load(text, Loader=BoundedSafeLoader)
    except yaml.YAMLError as err:
        raise LaunchError(f"{where}: parameter file {yaml_error_line(path, err)}") from err
    if not isinstance(doc, dict):
        raise LaunchError(f"{where}: parameter file {path}: expected a mapping of node names")
    fqn = join_ns(ns, node)
    out: dict[str, Any] = {}
    for key in ("/**", node, fqn, fqn.lstrip("/")):
        block = doc.get(key)
        if isinstance(block, dict):
            params = block.get("ros__parameters")
            if not isinstance(params, dict):
                raise LaunchError(f"{where}: parameter file {path}: {key!r} has no `ros__parameters` mapping")
            out.update(_flatten(params))
    return out


def _flatten(d: Mapping[str, Any], prefix: str = "") -> Iterator[tuple[str, Any]]:
    for k, v in d.items():
        if isinstance(v, dict):
            yield from _flatten(v, f"{prefix}{k}.")
        else:
            yield f"{prefix}{k}", v
