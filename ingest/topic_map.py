"""Which bag topics are which rig sensors: camera roles from topic words, Livox topics by IP and
mount (from their IMU's gravity), and a rig file checked against the bag's topics."""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence

from calibration.rig import Rig
from ingest.bag_report import (
    MappedSensor,
    RigProblem,
    TopicMapping,
    TopicStats,
)
from ingest.bags.rostypes import COMPRESSED_IMAGE_TYPE, IMAGE_TYPE, IMU_TYPE, LIVOX_PACKAGES, POINTCLOUD2_TYPE

IMAGE_TYPES = frozenset({IMAGE_TYPE, COMPRESSED_IMAGE_TYPE})


LIDAR_TYPES = frozenset({POINTCLOUD2_TYPE, *(f"{pkg}/msg/CustomMsg" for pkg in LIVOX_PACKAGES)})


IMU_TYPES = frozenset({IMU_TYPE})


UPRIGHT_COS = 0.7
"""|z| of the mean unit specific force above which a LiDAR counts as upright or upside down."""


_UPPER_WORDS = frozenset({"upper", "top", "up", "left"})


_LOWER_WORDS = frozenset({"lower", "bottom", "down", "low", "right"})


_NOT_COLOUR_WORDS = frozenset({"depth", "disparity", "confidence", "mask", "normals", "seg"})


_LIVOX_IP = re.compile(r"(?:^|/)(lidar|imu)_(\d{1,3})_(\d{1,3})_(\d{1,3})_(\d{1,3})$")


def _words(topic: str) -> set[str]:
    return set(re.split(r"[^a-z0-9]+", topic.lower())) - {""}


def _camera_role(topic: str) -> str | None:
    """'upper' / 'lower' from the words of a topic name, None when unclear."""
    words = _words(topic)
    up, low = bool(words & _UPPER_WORDS), bool(words & _LOWER_WORDS)
    return "upper" if up and not low else "lower" if low and not up else None


def _image_topics(stats: Iterable[TopicStats]) -> list[TopicStats]:
    """Colour image topics (not depth, disparity, ...), sorted by name."""
    return sorted(
        (t for t in stats if t.msgtype in IMAGE_TYPES and not _words(t.topic) & _NOT_COLOUR_WORDS),
        key=lambda t: t.topic,
    )


def _best(candidates: list[TopicStats]) -> TopicStats:
    """Most messages, then raw Image over CompressedImage, then the shortest name."""
    return min(candidates, key=lambda t: (-t.count, t.msgtype != IMAGE_TYPE, len(t.topic), t.topic))


def _guess_cameras(stats: Sequence[TopicStats]) -> tuple[list[MappedSensor], str | None]:
    """(cam0 upper, cam1 lower) from topic names, else the first two image topics; with a note."""
    images = _image_topics(stats)
    by_role = {r: [t for t in images if _camera_role(t.topic) == r] for r in ("upper", "lower")}
    if by_role["upper"] and by_role["lower"]:
        up, low = _best(by_role["upper"]), _best(by_role["lower"])
        why = "topic name says {}"
        return [
            MappedSensor(
                "camera", "cam0", up.topic, role="upper", rate_hz=up.rate_hz, reason=why.format("upper")
            ),
            MappedSensor(
                "camera", "cam1", low.topic, role="lower", rate_hz=low.rate_hz, reason=why.format("lower")
            ),
        ], None
    if len(images) >= 2:
        a, b = images[:2]
        note = f"camera roles guessed from topic order ({a.topic} upper, {b.topic} lower): check them"
        return [
            MappedSensor(
                "camera", "cam0", a.topic, role="upper", rate_hz=a.rate_hz, reason="first image topic"
            ),
            MappedSensor(
                "camera", "cam1", b.topic, role="lower", rate_hz=b.rate_hz, reason="second image topic"
            ),
        ], note
    if images:
        return [MappedSensor("camera", "cam0", images[0].topic, rate_hz=images[0].rate_hz)], (
            "only one image topic: no stereo pair"
        )
    return [], "no image topics"


def _livox_ip(topic: str, kind: str) -> str | None:
    """The dotted IP of a livox_ros_driver2 multi_topic name (`.../lidar_192_168_1_12`)."""
    m = _LIVOX_IP.search(topic)
    if m is None or m.group(1) != kind or any(int(g) > 255 for g in m.groups()[1:]):
        return None
    return ".".join(m.groups()[1:])


def _mount(up_z: float | None) -> str | None:
    """'top' (upright: gravity reaction along +z), 'bottom' (upside down) or None."""
    if up_z is None:
        return None
    return "top" if up_z > UPRIGHT_COS else "bottom" if up_z < -UPRIGHT_COS else None


def _guess_lidars(
    stats: Sequence[TopicStats], up_z: dict[str, float]
) -> tuple[list[MappedSensor], list[MappedSensor], list[str]]:
    """LiDAR and IMU entries, paired by Livox IP and named top/bottom by gravity where possible."""
    lidars = [t for t in stats if t.msgtype in LIDAR_TYPES]
    imu_topics = [t for t in stats if t.msgtype in IMU_TYPES]
    imu_by_ip = {ip: t for t in imu_topics if (ip := _livox_ip(t.topic, "imu")) is not None}
    notes: list[str] = []
    plan = []  # (lidar stats, ip, matching imu stats, mount)
    for t in lidars:
        ip = _livox_ip(t.topic, "lidar")
        imu = imu_by_ip.get(ip) if ip else None
        plan.append((t, ip, imu, _mount(up_z.get(imu.topic)) if imu else None))
    mounts = [m for *_, m in plan]
    use_mount = all(mounts) and len(set(mounts)) == len(mounts)
    if lidars and not use_mount:
        notes.append("LiDAR mounting (top/bottom) not clear from IMU gravity: named by IP or order")
    out_l: list[MappedSensor] = []
    out_i: list[MappedSensor] = []
    paired: set[str] = set()
    for k, (t, ip, imu, mount) in enumerate(plan):
        suffix = mount if use_mount else (ip.split(".")[-1] if ip else str(k))
        why = f"{t.msgtype}"
        if use_mount and imu is not None:
            side = "up" if mount == "top" else "down"
            why += f"; its IMU's z axis points {side} (mean unit specific force z {up_z[imu.topic]:+.2f})"
        out_l.append(MappedSensor("lidar", f"lidar_{suffix}", t.topic, ip=ip, rate_hz=t.rate_hz, reason=why))
        if imu is not None:
            paired.add(imu.topic)
            reason = f"same Livox IP as {t.topic}"
            out_i.append(MappedSensor("imu", f"imu_{suffix}", imu.topic, rate_hz=imu.rate_hz, reason=reason))
    others = [t for t in imu_topics if t.topic not in paired]
    for k, t in enumerate(others):
        name = f"imu{k}" if len(others) > 1 else "imu"
        out_i.append(MappedSensor("imu", name, t.topic, rate_hz=t.rate_hz, reason="no LiDAR with its IP"))
    return out_l, out_i, notes


def suggest_mapping(stats: Sequence[TopicStats], up_z: dict[str, float] | None = None) -> TopicMapping:
    """A rig topic mapping from topic names, types and (optionally) IMU gravity directions.

    `up_z` maps an IMU topic to the z component of its mean unit specific
    force (sensor frame): about +1 upright, -1 upside down.
    """
    cams, cam_note = _guess_cameras(stats)
    lidars, imus, notes = _guess_lidars(stats, up_z or {})
    all_notes = ([cam_note] if cam_note else []) + notes
    return TopicMapping((*cams, *lidars, *imus), tuple(all_notes))


def _resolve_image_topic(topic: str | None, names: dict[str, str]) -> str | None:
    """`topic` if in the bag, else its image_transport `/compressed` variant if that is."""
    if topic is None:
        return None
    if topic in names:
        return topic
    compressed = topic.rstrip("/") + "/compressed"
    return compressed if compressed in names else None


def _type_problem(msgtype: str, allowed: frozenset[str], what: str) -> str:
    """'has type T; expected ...', with a hint when T is a ROS 1 name (pkg/Type) in a ROS 2 bag."""
    expected = " or ".join(sorted(allowed))
    ros1 = msgtype.count("/") == 1 and f"{msgtype.split('/')[0]}/msg/{msgtype.split('/')[1]}" in allowed
    hint = (
        f" (its schema names it the ROS 1 way: a ROS 2 bag names it {msgtype.replace('/', '/msg/')})"
        if ros1
        else ""
    )
    return f"has type {msgtype}; expected {what} type ({expected}){hint}"


def check_rig(
    rig: Rig, types: dict[str, str], counts: dict[str, int] | None = None
) -> tuple[RigProblem, ...]:
    """Rig topics missing from the bags (`types`: topic -> msgtype), of the wrong type or, with `counts`
    (topic -> messages), declared but empty.

    A camera topic is there when its image_transport `/compressed` variant is,
    as ingest reads either. A topic a bag declares without a message (a
    sensor that never published) is as useless to ingest as a missing one,
    which refuses it.
    """
    problems: list[RigProblem] = []
    wanted: list[tuple[str, str | None, frozenset[str], str]] = [
        (f"camera {c.name}" + (f" ({c.role})" if c.role else ""), c.topic, IMAGE_TYPES, "an image")
        for c in rig.cameras
    ]
    wanted += [(f"lidar {li.name}", li.topic, LIDAR_TYPES, "a LiDAR") for li in rig.lidars]
    wanted += [(f"imu {i.name}", i.topic, IMU_TYPES, "an IMU") for i in rig.imus]
    for sensor, topic, allowed, what in wanted:
        if topic is None:
            problems.append(RigProblem(sensor, None, "has no topic in the rig file"))
        elif topic not in types:
            alt = _resolve_image_topic(topic, types) if allowed is IMAGE_TYPES else None
            if alt is None:
                problems.append(RigProblem(sensor, topic, "not in the bag"))
            elif types[alt] not in allowed:  # the compressed variant is there, of another type
                problems.append(RigProblem(sensor, alt, _type_problem(types[alt], allowed, what)))
            elif counts is not None and counts.get(alt, 0) == 0:  # ingest reads the compressed variant
                problems.append(RigProblem(sensor, alt, "in the bag but empty: 0 messages"))
        elif types[topic] not in allowed:
            problems.append(RigProblem(sensor, topic, _type_problem(types[topic], allowed, what)))
        elif counts is not None and counts.get(topic, 0) == 0:
            problems.append(RigProblem(sensor, topic, "in the bag but empty: 0 messages"))
    return tuple(problems)


def stereo_topics(
    rig: Rig | None, mapping: TopicMapping, types: dict[str, str]
) -> tuple[str, str, str] | None:
    """(upper, lower, source) image topics to pair, from the rig, else the suggested mapping."""
    if rig is not None:
        roles = {c.role: _resolve_image_topic(c.topic, types) for c in rig.cameras if c.role}
        up, low = roles.get("upper"), roles.get("lower")
        if up and low and types[up] in IMAGE_TYPES and types[low] in IMAGE_TYPES:
            return up, low, "rig"
    cams = mapping.of_kind("camera")
    if len(cams) >= 2:
        return (
            cams[0].topic,
            cams[1].topic,
            "names" if cams[0].reason.startswith("topic name") else "first two",
        )
    return None


def missing_topic(where: str, wanted: str | None, what: str, topics: Iterable[str]) -> str:
    """The line for a rig sensor's topic the bag does not have: the bag's topics listed (quoted where a
    name holds whitespace or unprintable characters, which a plain listing hides), and a bag topic that
    differs from `wanted` only by surrounding whitespace named as such."""
    names = sorted(topics)
    listing = ", ".join(n if n.isprintable() and n == n.strip() and " " not in n else repr(n) for n in names)
    near = [n for n in names if wanted is not None and n != wanted and n.strip() == wanted.strip()]
    hint = f" ({near[0]!r} differs from it only by whitespace)" if near else ""
    return f"{where}: no topic {wanted!r} for {what} (from the rig){hint}; the bag has: {listing}"
