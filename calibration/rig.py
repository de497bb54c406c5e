"""The SensorBox rig file: a Kalibr camchain plus LiDARs, IMUs, topics and roles.

A rig file is YAML::

    sensorbox_rig: 1
    name: sensorbox-reference
    camchain: sensorbox-camchain.yaml      # relative to the rig file
    cameras:
      cam0: {role: upper, topic: /zed_upper/zed_node/rgb/color/rect/image}
      cam1: {role: lower}                  # topic defaults to the camchain's rostopic
    lidars:
      lidar_top:
        topic: /livox/lidar_192_168_1_12
        ip: 192.168.1.12                   # optional
        T_cam0_lidar: [[...4x4...]]        # p_cam0 = T_cam0_lidar @ p_lidar, metres
      lidar_bottom:
        topic: /livox/lidar_192_168_1_13
        livox_extrinsic: {roll: 180.0, pitch: 0.0, yaw: 0.0, x: 0, y: 0, z: -220}
        T_cam0_base: [[...]]               # optional, default identity
    imus:
      imu_top: {topic: /livox/imu_192_168_1_12, T_cam0_imu: [[...]], rate_hz: 200}

A LiDAR's pose is either ``T_cam0_lidar`` or the Livox driver's extrinsic
(``livox_extrinsic`` inline, or ``livox_config: FILE.json`` + ``ip``), which maps
the LiDAR into a base frame, placed in cam0 by ``T_cam0_base``.

Keys other than these are refused (a misspelt ``imu:`` would drop both IMUs),
as is a LiDAR or IMU more than `MAX_LEVER_ARM_M` from cam0.
"""

from __future__ import annotations

import importlib.resources
import json
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from calibration.camera import CameraModel
from calibration.errors import CalibrationError, SensorboxError, WriteError
from calibration.files import read_text, write_atomic_set
from calibration.kalibr import (
    CameraChain,
    KalibrCamera,
    camchain_text,
    load_yaml,
    matrix_to_list,
    parse_kalibr_camchain,
)
from calibration.rig_fields import (
    bag_topic,
    check_lever_arm,
    each_once,
    finite,
    is_ipv4,
    known_keys,
    require_mapping,
    require_str,
)
from calibration.transforms import as_transform, invert, livox_extrinsic_to_transform
from calibration.types import F64

REFERENCE_RIG = Path(str(importlib.resources.files("calibration") / "sensorbox.yaml"))
"""The reference SensorBox rig shipped with the package (DESIGN.md section 3), with its camchain beside it."""

RIG_VERSION = 1
ROLES = ("upper", "lower")
_LIVOX_KEYS = ("roll", "pitch", "yaw", "x", "y", "z")
_RIG_KEYS = ("sensorbox_rig", "name", "camchain", "cameras", "lidars", "imus")
_CAMERA_KEYS = ("role", "topic")
_LIDAR_KEYS = ("topic", "ip", "T_cam0_lidar", "livox_extrinsic", "livox_config", "T_cam0_base")
_IMU_KEYS = ("topic", "T_cam0_imu", "rate_hz")


@dataclass(frozen=True, eq=False)
class Camera:
    """A camera of the rig: its model, pose relative to cam0, role, topic and clock offset.

    ``timeshift_cam_imu`` (seconds, Kalibr's name and convention) maps the
    camera's header stamps onto the IMU's clock: t_imu = t_cam + shift. The
    rig's IMUs are the Mid-360s' own, stamped by their LiDAR's clock, so it is
    the camera's offset to the LiDAR clock; None when the camchain has none.
    """

    name: str
    model: CameraModel
    T_cam_cam0: F64
    role: str | None = None
    topic: str | None = None
    timeshift_cam_imu: float | None = None

    @property
    def timeshift_ns(self) -> int:
        """``timeshift_cam_imu`` in ns (0 when unknown): add it to a header stamp to get the exposure time."""
        return round((self.timeshift_cam_imu or 0.0) * 1e9)

    @property
    def T_cam0_cam(self) -> F64:
        """Pose of this camera in cam0."""
        return invert(self.T_cam_cam0)


@dataclass(frozen=True, eq=False)
class Lidar:
    """A LiDAR of the rig; points map into cam0 by ``T_cam0_lidar`` (metres)."""

    name: str
    topic: str
    T_cam0_lidar: F64
    ip: str | None = None


@dataclass(frozen=True, eq=False)
class Imu:
    """An IMU of the rig; ``T_cam0_imu`` maps IMU-frame vectors into cam0."""

    name: str
    topic: str
    T_cam0_imu: F64
    rate_hz: float | None = None


@dataclass(frozen=True, eq=False)
class Rig:
    """Cameras (from a Kalibr camchain), LiDARs and IMUs, all placed in cam0."""

    cameras: tuple[Camera, ...]
    lidars: tuple[Lidar, ...] = ()
    imus: tuple[Imu, ...] = ()
    name: str = "rig"
    source: Path | None = field(default=None)
    camchain: CameraChain | None = field(default=None)

    def camera(self, name_or_role: str) -> Camera:
        """The camera with this name (``cam0``) or role (``upper``/``lower``)."""
        for cam in self.cameras:
            if name_or_role in (cam.name, cam.role):
                return cam
        known = ", ".join(f"{c.name} ({c.role})" if c.role else c.name for c in self.cameras)
        raise CalibrationError(f"{self._where}: no camera named or role {name_or_role!r} (has: {known})")

    def lidar(self, name: str) -> Lidar:
        """The LiDAR with this name."""
        for lidar in self.lidars:
            if lidar.name == name:
                return lidar
        known = ", ".join(li.name for li in self.lidars) or "none"
        raise CalibrationError(f"{self._where}: no lidar named {name!r} (has: {known})")

    @property
    def upper(self) -> Camera:
        """The reference (upper) camera."""
        return self.camera("upper")

    @property
    def lower(self) -> Camera:
        """The lower camera of the vertical stereo pair."""
        return self.camera("lower")

    @property
    def _where(self) -> str:
        return str(self.source) if self.source is not None else f"rig {self.name!r}"

    def baseline_m(self, a: str = "upper", b: str = "lower") -> float:
        """Distance between two camera centres in metres."""
        ca = self.camera(a).T_cam0_cam[:3, 3]
        cb = self.camera(b).T_cam0_cam[:3, 3]
        return float(np.linalg.norm(cb - ca))


def read_livox_config(path: str | Path) -> dict[str, F64]:
    """Read a livox_ros_driver2 JSON config; return ``{ip: T_base_lidar}``.

    Each ``lidar_configs[i].extrinsic_parameter`` holds roll/pitch/yaw in
    degrees and x/y/z in millimetres (R = Rz(yaw) Ry(pitch) Rx(roll)).
    """
    p = Path(path)
    text = read_text(p, "Livox config", "JSON")  # a BOM, as some Windows editors save, is dropped
    try:
        data = json.loads(text)
    except RecursionError as err:  # json's decoder recurses once per [ or {
        raise CalibrationError(f"{p}: malformed JSON: nested too deeply for a Livox config") from err
    except json.JSONDecodeError as err:
        raise CalibrationError(f"{p}: line {err.lineno}: malformed JSON: {err.msg}") from err
    configs = data.get("lidar_configs") if isinstance(data, dict) else None
    if not isinstance(configs, list):
        raise CalibrationError(f"{p}: missing key 'lidar_configs' (a list)")
    out: dict[str, F64] = {}
    index: dict[str, int] = {}
    for i, cfg in enumerate(configs):
        where = f"{p}: lidar_configs[{i}]"
        cfg = require_mapping(cfg, where)
        ip = require_str(cfg, "ip", where)
        if ip in index:  # which extrinsic is meant cannot be told
            raise CalibrationError(f"{where}.ip: {ip} is also lidar_configs[{index[ip]}]'s")
        index[ip] = i
        ext = cfg.get("extrinsic_parameter")
        if ext is None:
            raise CalibrationError(f"{where}: missing key 'extrinsic_parameter'")
        out[ip] = _livox_block(ext, f"{where}.extrinsic_parameter")
    return out


def _livox_block(block: object, where: str) -> F64:
    block = require_mapping(block, where)
    values = []
    for key in _LIVOX_KEYS:
        if key not in block:
            raise CalibrationError(f"{where}: missing key '{key}' (degrees for roll/pitch/yaw, mm for x/y/z)")
        v = block[key]
        if not isinstance(v, int | float) or isinstance(v, bool) or not finite(v):
            raise CalibrationError(f"{where}.{key}: expected a number, got {v!r}")
        values.append(float(v))
    return livox_extrinsic_to_transform(*values)


def _parse_lidar(name: str, block: object, where: str, base_dir: Path) -> Lidar:
    block = require_mapping(block, where)
    known_keys(block, _LIDAR_KEYS, where)
    topic = bag_topic(require_str(block, "topic", where))
    ip = block.get("ip")
    if ip is not None and not is_ipv4(ip):
        raise CalibrationError(f"{where}.ip: expected a dotted IPv4 address such as 192.168.1.12, got {ip!r}")
    given = [k for k in ("T_cam0_lidar", "livox_extrinsic", "livox_config") if k in block]
    if len(given) != 1:
        raise CalibrationError(
            f"{where}: expected exactly one of 'T_cam0_lidar', 'livox_extrinsic', 'livox_config', "
            f"got {given or 'none'}"
        )
    if given[0] == "T_cam0_lidar":
        if "T_cam0_base" in block:
            raise CalibrationError(
                f"{where}.T_cam0_base: places a livox_extrinsic or livox_config in cam0; with T_cam0_lidar "
                "it would be ignored (give T_cam0_lidar = T_cam0_base @ T_base_lidar alone)"
            )
        T = as_transform(block["T_cam0_lidar"], f"{where}.T_cam0_lidar")
        check_lever_arm(T, f"{where}.T_cam0_lidar", "millimetres written as metres?")
    else:
        if given[0] == "livox_extrinsic":
            inline = require_mapping(block["livox_extrinsic"], f"{where}.livox_extrinsic")
            known_keys(inline, _LIVOX_KEYS, f"{where}.livox_extrinsic")  # the driver's JSON may hold more
            T_base_lidar = _livox_block(inline, f"{where}.livox_extrinsic")
        else:
            cfg_path = base_dir / str(block["livox_config"])
            if ip is None:
                raise CalibrationError(f"{where}: missing key 'ip' (which LiDAR of the livox_config it is)")
            try:
                table = read_livox_config(cfg_path)
            except CalibrationError as err:
                raise CalibrationError(f"{where}.livox_config: {err}") from err
            if ip not in table:
                raise CalibrationError(
                    f"{where}.ip: {ip!r} not found in {cfg_path} (has: {', '.join(table) or 'none'})"
                )
            T_base_lidar = table[ip]
        T_cam0_base = (
            as_transform(block["T_cam0_base"], f"{where}.T_cam0_base")
            if "T_cam0_base" in block
            else np.eye(4)
        )
        T = T_cam0_base @ T_base_lidar
        placed = " @ T_cam0_base" if "T_cam0_base" in block else ""
        units = "the Livox x, y, z are millimetres, T_cam0_base metres"
        check_lever_arm(T, f"{where}.{given[0]}{placed}", units)
    return Lidar(name=name, topic=topic, T_cam0_lidar=T, ip=ip)


def _parse_imu(name: str, block: object, where: str) -> Imu:
    block = require_mapping(block, where)
    known_keys(block, _IMU_KEYS, where)
    topic = bag_topic(require_str(block, "topic", where))
    if "T_cam0_imu" not in block:
        raise CalibrationError(f"{where}: missing key 'T_cam0_imu'")
    rate = block.get("rate_hz")
    if rate is not None and (
        not isinstance(rate, int | float) or isinstance(rate, bool) or not (rate > 0 and finite(rate))
    ):
        raise CalibrationError(f"{where}.rate_hz: expected a positive number, got {rate!r}")
    T_cam0_imu = as_transform(block["T_cam0_imu"], f"{where}.T_cam0_imu")
    check_lever_arm(T_cam0_imu, f"{where}.T_cam0_imu", "millimetres written as metres?")
    return Imu(
        name=name,
        topic=topic,
        T_cam0_imu=T_cam0_imu,
        rate_hz=None if rate is None else float(rate),
    )


def rig_from_camchain(chain: CameraChain, name: str = "camchain") -> Rig:
    """A rig made of a bare camchain: cam0 is the upper camera, cam1 the lower one."""
    cams = tuple(
        Camera(
            name=c.name,
            model=c.model,
            T_cam_cam0=c.T_cam_cam0,
            role=ROLES[i] if i < len(ROLES) else None,
            topic=c.rostopic,
            timeshift_cam_imu=c.timeshift_cam_imu,
        )
        for i, c in enumerate(chain.cameras)
    )
    return Rig(cameras=cams, name=name, source=chain.source, camchain=chain)


def _check_crossed_topics(cams: list[Camera], chain: CameraChain, where: str) -> None:
    """Refuse a rig topic that the camchain names for another of its cameras.

    A rig file may give a camera another topic than the camchain's
    `rostopic` (the calibration bag was recorded under other names), but a
    topic the camchain gives to another camera says that the intrinsics and
    extrinsics were calibrated on the other camera's images: cam0's model
    would be applied to cam1's frames (the two swapped), every GT pixel
    wrong, without a word.
    """
    owners: dict[str, list[str]] = {}
    for kc in chain.cameras:
        if kc.rostopic is not None:
            owners.setdefault(bag_topic(kc.rostopic), []).append(kc.name)
    for cam in cams:
        names = owners.get(cam.topic, []) if cam.topic is not None else []
        other = names[0] if names and cam.name not in names else None  # a topic twice is refused apart
        if other is not None:
            raise CalibrationError(
                f"{where}.{cam.name}.topic: {cam.topic} is {other}'s rostopic in the camchain "
                f"({chain.source}): {other}'s calibration was made on that topic's images; expected "
                f"{cam.name}'s own topic (camchain: {_chain_topic(chain, cam.name)}), or the cameras named "
                "to match the camchain"
            )


def _chain_topic(chain: CameraChain, name: str) -> str:
    topic = next((kc.rostopic for kc in chain.cameras if kc.name == name), None)
    return "none given" if topic is None else topic


def _parse_cameras(block: object, chain: CameraChain, where: str) -> tuple[Camera, ...]:
    block = require_mapping(block, where)
    cams: list[Camera] = []
    for kc in chain.cameras:
        entry = require_mapping(block.get(kc.name, {}), f"{where}.{kc.name}")
        known_keys(entry, _CAMERA_KEYS, f"{where}.{kc.name}")
        role = entry.get("role")
        if role is not None and role not in ROLES:
            raise CalibrationError(f"{where}.{kc.name}.role: expected one of {ROLES}, got {role!r}")
        topic = entry.get("topic", kc.rostopic)
        if topic is not None and not isinstance(topic, str):
            raise CalibrationError(f"{where}.{kc.name}.topic: expected a string, got {topic!r}")
        topic = None if topic is None else bag_topic(topic)
        cams.append(Camera(kc.name, kc.model, kc.T_cam_cam0, role, topic, kc.timeshift_cam_imu))
    _check_crossed_topics(cams, chain, where)
    unknown = set(block) - {c.name for c in chain.cameras}
    if unknown:
        raise CalibrationError(
            f"{where}: cameras {sorted(unknown)} are not in the camchain "
            f"(has: {', '.join(c.name for c in chain.cameras)})"
        )
    roles = [c.role for c in cams if c.role is not None]
    if len(roles) != len(set(roles)):
        raise CalibrationError(f"{where}: each role may be given to one camera only, got {roles}")
    return tuple(cams)


def read_rig(path: str | Path) -> Rig:
    """Read a rig file, or a bare Kalibr camchain (then cam0 = upper, cam1 = lower)."""
    p = Path(path)
    data = load_yaml(p, "rig")
    if isinstance(data, Mapping) and "cam0" in data and "sensorbox_rig" not in data:
        chain = parse_kalibr_camchain(data, str(p))
        topics = [(str(p), f"{c.name}.rostopic", c.rostopic) for c in chain.cameras]
        each_once(topics, "each sensor needs its own topic")
        return rig_from_camchain(CameraChain(chain.cameras, source=p), name=p.stem)
    where = str(p)
    data = require_mapping(data, where)
    version = data.get("sensorbox_rig")
    if isinstance(version, bool) or version != RIG_VERSION:  # YAML's true equals 1 in Python
        raise CalibrationError(
            f"{where}: sensorbox_rig: expected version {RIG_VERSION} "
            f"(or a Kalibr camchain with cam0, cam1, ...), got {version!r}"
        )
    known_keys(data, _RIG_KEYS, where)
    chain_name = require_str(data, "camchain", where)
    chain_path = p.parent / chain_name
    chain_data = load_yaml(chain_path, f"Kalibr camchain (referenced by {p.name})")
    chain = CameraChain(parse_kalibr_camchain(chain_data, str(chain_path)).cameras, source=chain_path)
    cameras = _parse_cameras(data.get("cameras", {}), chain, f"{where}: cameras")
    lidars = tuple(
        _parse_lidar(str(n), b, f"{where}: lidars.{n}", p.parent)
        for n, b in require_mapping(data.get("lidars", {}), f"{where}: lidars").items()
    )
    imus = tuple(
        _parse_imu(str(n), b, f"{where}: imus.{n}")
        for n, b in require_mapping(data.get("imus", {}), f"{where}: imus").items()
    )
    given = require_mapping(data.get("cameras", {}), where)
    topics = [
        (where, f"cameras.{c.name}.topic", c.topic)
        if "topic" in given.get(c.name, {})
        else (str(chain_path), f"{c.name}.rostopic", c.topic)  # the camchain's, the rig giving none
        for c in cameras
    ]
    topics += [
        (where, f"{kind}.{s.name}.topic", s.topic)
        for kind, group in (("lidars", lidars), ("imus", imus))
        for s in group
    ]
    each_once(topics, "each sensor needs its own topic")
    each_once([(where, f"lidars.{li.name}.ip", li.ip) for li in lidars], "each LiDAR has its own address")
    name = data.get("name", p.stem)
    if not isinstance(name, str) or isinstance(name, bool):  # !!binary, a date: printed as b'...' or a date
        raise CalibrationError(f"{where}: name: expected a string, got {name!r}")
    return Rig(cameras, lidars, imus, name=name, source=p, camchain=chain)


def with_timeshifts(rig: Rig, timeshift_cam_imu_s: Mapping[str, float]) -> Rig:
    """The rig with these cameras' ``timeshift_cam_imu`` (seconds, by camera name) replaced, in its
    cameras and its camchain alike (so `write_rig` writes them)."""
    unknown = set(timeshift_cam_imu_s) - {c.name for c in rig.cameras}
    if unknown:
        raise CalibrationError(f"{rig._where}: no cameras {sorted(unknown)} to set a time shift on")
    shifts = {name: float(s) for name, s in timeshift_cam_imu_s.items()}
    cams = tuple(replace(c, timeshift_cam_imu=shifts[c.name]) if c.name in shifts else c for c in rig.cameras)
    chain = None
    if rig.camchain is not None:
        chain = replace(
            rig.camchain,
            cameras=tuple(
                replace(k, timeshift_cam_imu=shifts[k.name]) if k.name in shifts else k
                for k in rig.camchain.cameras
            ),
        )
    return replace(rig, cameras=cams, camchain=chain)


def write_rig(
    rig: Rig, path: str | Path, camchain_name: str | None = None, error: type[SensorboxError] = WriteError
) -> Path:
    """Write ``rig`` as a rig file plus its camchain beside it; returns the camchain path.

    LiDAR poses are written as ``T_cam0_lidar`` (the resolved form). Both
    files are written as one set (`calibration.files.write_atomic_set`): both
    or neither, a refused write or a path that is a device or FIFO is `error`
    naming the file, and no empty or cut file is left.
    """
    p = Path(path)
    camchain_name = camchain_name or f"{p.stem}-camchain.yaml"
    chain = rig.camchain or CameraChain(
        tuple(
            KalibrCamera(c.name, c.model, c.T_cam_cam0, None, None, c.timeshift_cam_imu, c.topic)
            for c in rig.cameras
        )
    )  # fmt: skip
    chain_path = p.parent / camchain_name
    doc: dict[str, Any] = {
        "sensorbox_rig": RIG_VERSION,
        "name": rig.name,
        "camchain": camchain_name,
        "cameras": {
            c.name: {k: v for k, v in (("role", c.role), ("topic", c.topic)) if v is not None}
            for c in rig.cameras
        },
        "lidars": {
            li.name: {
                "topic": li.topic,
                **({"ip": li.ip} if li.ip else {}),
                "T_cam0_lidar": matrix_to_list(li.T_cam0_lidar),
            }
            for li in rig.lidars
        },
        "imus": {
            imu.name: {
                "topic": imu.topic,
                "T_cam0_imu": matrix_to_list(imu.T_cam0_imu),
                **({"rate_hz": imu.rate_hz} if imu.rate_hz is not None else {}),
            }
            for imu in rig.imus
        },
    }
    rig_text = yaml.safe_dump(doc, default_flow_style=None, sort_keys=False)
    write_atomic_set([(chain_path, camchain_text(chain).encode()), (p, rig_text.encode())], error)
    return chain_path
