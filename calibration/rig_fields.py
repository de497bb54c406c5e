"""The checks a rig file's fields go through: mappings holding only known keys, non-empty strings,
finite numbers, topics as a bag stores them, IPv4 addresses, values no two sensors share, and a
sensor's lever arm from cam0 that a handheld rig can have."""

from __future__ import annotations

import difflib
import ipaddress
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from calibration.errors import CalibrationError
from calibration.types import F64

MAX_LEVER_ARM_M = 2.0
"""Farthest a LiDAR or IMU may sit from cam0 (m). The rig is handheld: the
reference rig's sensors are 0.02-0.21 m from cam0, and 2 m leaves room for any
pole or backpack mount, while a lever arm written in millimetres (87 mm as 87)
is 40 times over it. It is the bound the camera baseline is held to
(`calibration.rectify.MAX_PLAUSIBLE_BASELINE_M`). A LiDAR pose is the ground
truth's frame: a wrong one moves every GT point, so it is refused, not warned about."""


def require_mapping(value: object, where: str) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise CalibrationError(f"{where}: expected a mapping, got {value!r}")
    return value


def known_keys(block: Mapping[Any, Any], known: tuple[str, ...], where: str) -> None:
    """Refuse a key not in `known`: a misspelt one (``imu`` for ``imus``) would drop its sensors silently.

    The rig file is SensorBox's own, versioned format (unlike a camchain,
    which other tools extend), so an unknown key is a mistake, never data to skip.
    """
    for key in block:
        if key not in known:
            near = difflib.get_close_matches(str(key), known, n=1)
            hint = f" (did you mean '{near[0]}'?)" if near else ""
            raise CalibrationError(f"{where}: unknown key {key!r}{hint}; known keys: {', '.join(known)}")


def check_lever_arm(T: F64, where: str, hint: str) -> None:
    """Refuse a sensor pose whose translation puts it over `MAX_LEVER_ARM_M` from cam0."""
    distance_m = float(np.linalg.norm(T[:3, 3]))
    if not distance_m <= MAX_LEVER_ARM_M:
        raise CalibrationError(
            f"{where}: translation {distance_m:.4g} m from cam0: expected <= {MAX_LEVER_ARM_M:g} m "
            f"on a handheld rig ({hint})"
        )


def require_str(block: Mapping[str, Any], key: str, where: str) -> str:
    if key not in block:
        raise CalibrationError(f"{where}: missing key '{key}'")
    value = block[key]
    if not isinstance(value, str) or not value:
        raise CalibrationError(f"{where}.{key}: expected a non-empty string, got {value!r}")
    return value


def finite(v: float) -> bool:
    """`math.isfinite`, False (not OverflowError) for an integer beyond float's range."""
    try:
        return math.isfinite(v)
    except OverflowError:
        return False


def bag_topic(name: str) -> str:
    """A rig topic as a bag stores it: fully qualified, no trailing slash.

    Recorders write absolute names (`/livox/lidar_192_168_1_12`); a relative
    one in a rig file means the same topic in the root namespace.
    """
    return "/" + name.strip("/")


def is_ipv4(value: object) -> bool:
    if not isinstance(value, str):
        return False
    try:
        ipaddress.IPv4Address(value)
    except ValueError:
        return False
    return True


def each_once(values: list[tuple[str, str, str | None]], why: str) -> None:
    """Refuse a value (a topic, an IP) that two sensors share, naming both files and keys; None is unset.

    Each of `values` is (file, key, value), the key with its field
    ("lidars.lidar_top.topic", "cam1.rostopic"). A topic belongs to one
    sensor: messages on a shared one cannot be told apart (two Mid-360s on
    livox_ros_driver2's multi_topic 0 share /livox/lidar, and their
    CustomMsg.lidar_id is the first octet of the IP, the same for both).
    """
    owner: dict[str, tuple[str, str]] = {}
    for file, key, value in values:
        if value is None:
            continue
        if value in owner:
            first_file, first = owner[value]
            both_lidars = all(k.startswith("lidars.") and k.endswith(".topic") for k in (first, key))
            hint = " (for Livox LiDARs, livox_ros_driver2's multi_topic: 1)" if both_lidars else ""
            second = key if file == first_file else f"{file}: {key}"
            raise CalibrationError(f"{first_file}: {first} and {second} are both {value}: {why}{hint}")
        owner[value] = (file, key)
