"""Decode the messages SensorBox ingests from their raw serialised bytes.

Input is what a bag stores: ROS 2 CDR bytes (`ros_version=2`) or ROS 1 bytes
(`ros_version=1`). Small headers go through rosbags' deserialisers (on a
`memoryview`, so nothing is copied); the payloads are viewed with numpy.

Public API:

- `decode(msgtype, raw, ros_version) -> Sweep | Frame | ImuSample`: dispatch on
  the type name (`DECODED_TYPES`; ROS 1 style `pkg/Type` is accepted too).
- `decode_pointcloud2(raw, ros_version) -> PointCloud`: a structured array laid
  out by the message's own fields, offsets, `point_step`, `row_step` and
  endianness.
- `decode_image(raw, ros_version) -> Frame` (`step` honoured; bgr8, rgb8,
  bgra8, rgba8, mono8, mono16, bayer_{rggb,bggr,gbrg,grbg}{8,16}).
- `decode_compressed_image(raw, ros_version) -> Frame` (anything `cv2.imdecode` reads).
- `decode_imu(raw, ros_version) -> ImuSample`.
- `sweep_from_custom_msg(msg)`, `sweep_from_pointcloud(cloud) -> Sweep`.

Conventions: times are int64 ns from the message header (never bag log time);
points in metres in the sensor frame; colour images come back BGR uint8
HxWx3 and mono images HxW (uint8, or uint16 for mono16). Arrays may be
read-only views of `raw` when no conversion was needed. Bytes that do not
match their type raise `MessageDecodeError`.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from functools import cached_property
from typing import Any, Literal

import cv2
import numpy as np

from ingest.bags.image_pixels import image_pixels, to_bgr
from ingest.bags.jpeg_warnings import jpeg_warnings
from ingest.bags.livox_msg import CustomMsg, decode_custom_msg
from ingest.bags.point_time import MAX_OFFSET_NS, point_times_ns
from ingest.bags.rostypes import (
    COMPRESSED_IMAGE_TYPE,
    IMAGE_TYPE,
    IMU_TYPE,
    LIVOX_PACKAGES,
    POINTCLOUD2_TYPE,
    typestore,
)
from ingest.errors import MessageDecodeError

RosVersion = Literal[1, 2]
Array = np.ndarray[Any, np.dtype[Any]]
Raw = bytes | memoryview

__all__ = [
    "DECODED_TYPES",
    "Frame",
    "ImuSample",
    "MessageDecodeError",
    "PointCloud",
    "RosVersion",
    "Sweep",
    "decode",
    "decode_compressed_image",
    "decode_image",
    "decode_imu",
    "decode_pointcloud2",
    "header_stamp_ns",
    "pointfield_dtype",
    "sweep_from_custom_msg",
    "sweep_from_pointcloud",
]


MIN_PRINT_POINTS = 100
"""Measured points a sweep needs for its `Sweep.points_print` to tell it from another's."""


@dataclass(frozen=True)
class Sweep:
    """One LiDAR message as points, each with its own absolute time.

    `xyz_m` is (N, 3) float32 or float64 in the sensor frame; `stamps_ns` is
    (N,) int64. `reflectivity` is the driver's per-point return strength as
    stored (uint8 for Livox CustomMsg, the `reflectivity` or else `intensity`
    field of a PointCloud2); `tag` and `line` are uint8 Livox fields. Each of
    those three is None when the message has no such field. `time_layout`
    says where the point times came from (e.g. "time float32 s from the
    header stamp (Velodyne)"; `NO_POINT_TIME` when the message has none).
    """

    stamp_ns: int
    frame_id: str
    xyz_m: Array
    stamps_ns: np.ndarray[Any, np.dtype[np.int64]]
    reflectivity: Array | None = None
    tag: Array | None = None
    line: Array | None = None
    time_layout: str = ""
    late: np.ndarray[Any, np.dtype[np.bool_]] | None = None  # points whose own time field lies beyond any
    # sweep (a Livox offset_time over `MAX_OFFSET_NS`: 0xFFFFFFFF is 4.3 s), whatever the clocks; None: none

    @cached_property
    def span_ns(self) -> tuple[int, int]:
        """(earliest, latest) point time; a driver need not write its points in time order."""
        if len(self.stamps_ns) == 0:
            return self.stamp_ns, self.stamp_ns
        return int(self.stamps_ns.min()), int(self.stamps_ns.max())

    @cached_property
    def points_print(self) -> int | None:
        """A hash of the sweep's measured points (finite and off the origin, a Livox "no return"), to the
        bit; None for fewer than `MIN_PRINT_POINTS` of them, which say nothing. Two sweeps measured apart
        never share it: every return carries its own range noise. Computed once a sweep: the plan pass
        asks it for the same sweep twice (`ingest.train.repeats`, `ingest.train.run.lidar_rate`)."""
        xyz = np.asarray(self.xyz_m)
        x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]  # per column: reductions along rows of 3 are slow
        real = np.isfinite(x) & np.isfinite(y) & np.isfinite(z) & ((x != 0) | (y != 0) | (z != 0))
        n_real = int(real.sum())
        if n_real < MIN_PRINT_POINTS:
            return None
        return hash(np.ascontiguousarray(xyz if n_real == len(xyz) else xyz[real]).tobytes())


@dataclass(frozen=True)
class Frame:
    """One camera image: BGR uint8 HxWx3 for colour (BGRA HxWx4 for a bgra8 one decoded with
    `keep_bgra`), HxW uint8/uint16 for mono."""

    stamp_ns: int
    frame_id: str
    image: Array


@dataclass(frozen=True)
class ImuSample:
    """One IMU reading: angular rate in rad/s and acceleration as stored.

    `acc` keeps the publisher's unit: m/s^2 by the sensor_msgs contract, but
    the Livox driver publishes g (multiply by 9.80665 for m/s^2).
    """

    stamp_ns: int
    frame_id: str
    gyro_rad_s: np.ndarray[Any, np.dtype[np.float64]]
    acc: np.ndarray[Any, np.dtype[np.float64]]


@dataclass(frozen=True)
class PointCloud:
    """A PointCloud2 as a structured array with the message's own field names.

    `points` is 1-D with `height * width` entries, row-major; reshape with
    `(height, width)` for organised clouds. `is_dense` False means invalid
    points (NaN) may be present.
    """

    stamp_ns: int
    frame_id: str
    points: np.ndarray[Any, np.dtype[np.void]]
    height: int
    width: int
    is_dense: bool


# ---------------------------------------------------------------- helpers


def _deserialize(raw: Raw, msgtype: str, ros_version: RosVersion) -> Any:
    """Deserialise with our typestore; any failure becomes `MessageDecodeError`."""
    store = typestore(ros_version)
    try:
        if ros_version == 1:
            return store.deserialize_ros1(memoryview(raw), msgtype)
        return store.deserialize_cdr(memoryview(raw), msgtype)
    except Exception as err:  # rosbags raises several types on malformed bytes
        raise MessageDecodeError(
            f"{len(raw)} bytes are not a valid ROS {ros_version} {msgtype}: {err}{_compressed_hint(raw)}"
        ) from err


COMPRESSED_MAGIC = {b"\x28\xb5\x2f\xfd": "zstd", b"\x04\x22\x4d\x18": "lz4", b"BZh": "bz2"}
"""How a compressed block begins: a message that does begins so is compressed, not damaged."""


def _compressed_hint(raw: Raw) -> str:
    """A hint when undecodable bytes begin with a compressor's magic number: a rosbag2 whose metadata.yaml
    says its messages are not compressed (message mode) while they are."""
    head = bytes(memoryview(raw)[:4])
    for magic, name in COMPRESSED_MAGIC.items():
        if head.startswith(magic):
            return (
                f" (they begin with {name}'s magic number: the message is {name}-compressed, which the bag's "
                "metadata does not say: check its compression_format and compression_mode)"
            )
    return ""


def _stamp_ns(header: Any) -> int:
    """Header stamp (sec, nanosec) as int ns."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _check_version(ros_version: int) -> None:
    if ros_version not in (1, 2):
        raise ValueError(f"ros_version must be 1 or 2, got {ros_version!r}")


# ---------------------------------------------------------------- PointCloud2

POINTFIELD_DTYPES: dict[int, str] = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
"""sensor_msgs/PointField datatype codes -> numpy base type (byte order added per message)."""


def pointfield_dtype(
    fields: list[tuple[str, int, int, int]], point_step: int, is_bigendian: bool
) -> np.dtype[np.void]:
    """Structured dtype of one point from `(name, offset_bytes, datatype, count)` fields.

    The itemsize is always `point_step`, so padding between and after fields is
    skipped. Fields with `count` 0 are ignored; `count` > 1 becomes a subarray.
    """
    order = ">" if is_bigendian else "<"
    names: list[str] = []
    formats: list[Any] = []
    offsets: list[int] = []
    for name, offset, datatype, count in fields:
        if count == 0:
            continue
        if datatype not in POINTFIELD_DTYPES:
            raise MessageDecodeError(
                f"PointCloud2 field {name!r} has datatype {datatype}; expected one of 1..8 (INT8..FLOAT64)"
            )
        if not name or name in names:
            raise MessageDecodeError(f"PointCloud2 field name {name!r} is empty or repeated")
        base = np.dtype(order + POINTFIELD_DTYPES[datatype])
        if offset < 0 or offset + base.itemsize * count > point_step:
            raise MessageDecodeError(
                f"PointCloud2 field {name!r} at offset {offset} ({count} x {base.itemsize} bytes)"
                f" does not fit in point_step {point_step}"
            )
        names.append(name)
        formats.append(base if count == 1 else (base, (count,)))
        offsets.append(offset)
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step})


def decode_pointcloud2(raw: Raw, ros_version: RosVersion = 2) -> PointCloud:
    """Decode a `sensor_msgs/PointCloud2` by its own field layout.

    Honours `point_step` (padding), `row_step` (padded rows; 0 is read as
    `width * point_step`, as some drivers send) and `is_bigendian`. Points are
    a zero-copy view of `raw` unless rows are padded.
    """
    _check_version(ros_version)
    msg = _deserialize(raw, POINTCLOUD2_TYPE, ros_version)
    height, width = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    fields = [(f.name, int(f.offset), int(f.datatype), int(f.count)) for f in msg.fields]
    count = height * width
    if count and point_step <= 0:
        raise MessageDecodeError(f"PointCloud2 with {count} points has point_step {point_step}")
    dtype = pointfield_dtype(fields, max(point_step, 0), bool(msg.is_bigendian))
    row_bytes = width * point_step
    if row_step == 0:
        row_step = row_bytes
    if row_step < row_bytes:
        raise MessageDecodeError(f"PointCloud2 row_step {row_step} < width {width} x point_step {point_step}")
    data = msg.data
    need = (height - 1) * row_step + row_bytes if count else 0
    if data.size < need:
        raise MessageDecodeError(
            f"PointCloud2 {height}x{width} (point_step {point_step}, row_step {row_step})"
            f" needs {need} data bytes, has {data.size}"
        )
    points: np.ndarray[Any, np.dtype[np.void]]
    if count == 0:
        points = np.zeros(0, dtype)
    elif height == 1 or row_step == row_bytes:
        points = np.frombuffer(data, dtype, count=count)
    else:
        grid = np.ndarray((height, width), dtype, buffer=data, strides=(row_step, point_step))
        points = grid.reshape(-1)  # padded rows: one copy
    return PointCloud(
        _stamp_ns(msg.header), str(msg.header.frame_id), points, height, width, bool(msg.is_dense)
    )


def _field(points: np.ndarray[Any, np.dtype[np.void]], name: str) -> Array | None:
    """A contiguous native-endian copy of one field, or None when absent."""
    if points.dtype.names is None or name not in points.dtype.names:
        return None
    column = points[name]
    return np.ascontiguousarray(column, dtype=column.dtype.newbyteorder("="))


NO_POINT_TIME = "none: every point at the header stamp"
CUSTOM_MSG_TIME = "timebase + offset_time uint32 ns (Livox CustomMsg)"


def sweep_from_pointcloud(cloud: PointCloud) -> Sweep:
    """Points of a PointCloud2 as a `Sweep`.

    Needs x, y, z fields (float32 stay float32, anything else becomes float64).
    Point times come from the driver's time field, its unit and base read off
    the values against the header stamp (`ingest.bags.point_time`: Livox,
    Velodyne, Ouster, Hesai, RoboSense); without one every point gets the
    header stamp. A time field that fits no layout raises `MessageDecodeError`.
    """
    pts = cloud.points
    names = pts.dtype.names or ()
    fields: Mapping[str, tuple[Any, ...]] = pts.dtype.fields or {}
    missing = [n for n in ("x", "y", "z") if n not in names]
    if missing:
        raise MessageDecodeError(f"PointCloud2 has no {'/'.join(missing)} field; fields are {list(names)}")
    if any(fields[n][0].shape for n in "xyz"):
        raise MessageDecodeError("PointCloud2 x/y/z fields must have count 1")
    all_f4 = all(fields[n][0].kind == "f" and fields[n][0].itemsize == 4 for n in "xyz")
    xyz = np.empty((len(pts), 3), np.float32 if all_f4 else np.float64)
    for i, n in enumerate("xyz"):
        xyz[:, i] = pts[n]
    stamps, layout = point_times_ns(pts, cloud.stamp_ns)
    reflectivity = _field(pts, "reflectivity")
    if reflectivity is None:
        reflectivity = _field(pts, "intensity")
    return Sweep(
        cloud.stamp_ns,
        cloud.frame_id,
        xyz,
        stamps,
        reflectivity,
        _field(pts, "tag"),
        _field(pts, "line"),
        str(layout) if layout is not None else NO_POINT_TIME,
    )


def sweep_from_custom_msg(msg: CustomMsg) -> Sweep:
    """A Livox `CustomMsg` as a `Sweep`: xyz float32, point time = timebase + offset_time."""
    pts = msg.points
    xyz = np.empty((len(pts), 3), np.float32)
    for i, n in enumerate("xyz"):
        xyz[:, i] = pts[n]
    late = pts["offset_time"] > MAX_OFFSET_NS
    return Sweep(
        msg.stamp_ns,
        msg.frame_id,
        xyz,
        msg.point_stamps_ns,
        np.ascontiguousarray(pts["reflectivity"]),
        np.ascontiguousarray(pts["tag"]),
        np.ascontiguousarray(pts["line"]),
        CUSTOM_MSG_TIME,
        late if late.any() else None,
    )


# ---------------------------------------------------------------- images


def decode_image(raw: Raw, ros_version: RosVersion = 2, keep_bgra: bool = False) -> Frame:
    """Decode a `sensor_msgs/Image` (see `image_pixels.IMAGE_ENCODINGS`), honouring `step` padding.

    With `keep_bgra` a bgra8 image comes back as its recorded BGRA pixels
    (H, W, 4), a view of `raw` when its rows are not padded: the ingest's
    equirect warp and PNG writer take four channels faster than a conversion
    to BGR and three (bench/bench_ingest.py); its PNGs drop the alpha.
    """
    _check_version(ros_version)
    msg = _deserialize(raw, IMAGE_TYPE, ros_version)
    encoding = str(msg.encoding)
    pixels = image_pixels(msg)
    image = np.ascontiguousarray(pixels) if keep_bgra and encoding == "bgra8" else to_bgr(pixels, encoding)
    return Frame(_stamp_ns(msg.header), str(msg.header.frame_id), image)


def decode_compressed_image(raw: Raw, ros_version: RosVersion = 2) -> Frame:
    """Decode a `sensor_msgs/CompressedImage` (jpeg, png, ...) with `cv2.imdecode`.

    Colour comes back BGR uint8 HxWx3, greyscale HxW uint8. A JPEG whose data
    libjpeg finds corrupt (`ingest.bags.jpeg_warnings`) raises
    `MessageDecodeError` with libjpeg's words, though OpenCV decodes it.
    """
    _check_version(ros_version)
    msg = _deserialize(raw, COMPRESSED_IMAGE_TYPE, ros_version)
    data = np.asarray(msg.data, np.uint8)
    image = None
    with jpeg_warnings() as corrupt:
        if data.size:
            try:
                # the pixels as the sensor gave them: the camchain describes them, not an EXIF rotation
                image = cv2.imdecode(data, cv2.IMREAD_ANYCOLOR | cv2.IMREAD_IGNORE_ORIENTATION)
            except cv2.error:
                image = None
    what = f"CompressedImage (format {str(msg.format)!r}, {data.size} bytes)"
    if image is None:
        raise MessageDecodeError(f"{what} could not be decoded")
    if corrupt:  # decoded, with blocks of grey or smeared pixels where the data was damaged
        raise MessageDecodeError(f"{what}: {'; '.join(corrupt)}")
    return Frame(_stamp_ns(msg.header), str(msg.header.frame_id), image)


# ---------------------------------------------------------------- IMU


def decode_imu(raw: Raw, ros_version: RosVersion = 2) -> ImuSample:
    """Decode a `sensor_msgs/Imu`: header stamp, gyro (rad/s), acceleration as stored."""
    _check_version(ros_version)
    msg = _deserialize(raw, IMU_TYPE, ros_version)
    w, a = msg.angular_velocity, msg.linear_acceleration
    return ImuSample(
        _stamp_ns(msg.header),
        str(msg.header.frame_id),
        np.array([w.x, w.y, w.z], np.float64),
        np.array([a.x, a.y, a.z], np.float64),
    )


# ---------------------------------------------------------------- dispatch


def _custom(raw: Raw, ros_version: RosVersion) -> Sweep:
    return sweep_from_custom_msg(decode_custom_msg(raw, ros_version))


def _cloud(raw: Raw, ros_version: RosVersion) -> Sweep:
    return sweep_from_pointcloud(decode_pointcloud2(raw, ros_version))


_DECODERS: dict[str, Callable[[Raw, RosVersion], Sweep | Frame | ImuSample]] = {
    POINTCLOUD2_TYPE: _cloud,
    IMAGE_TYPE: decode_image,
    COMPRESSED_IMAGE_TYPE: decode_compressed_image,
    IMU_TYPE: decode_imu,
    **{f"{pkg}/msg/CustomMsg": _custom for pkg in LIVOX_PACKAGES},
}

DECODED_TYPES: frozenset[str] = frozenset(_DECODERS)
"""Message types `decode` understands (rosbags' normalised `pkg/msg/Type` names)."""


def _normalize(msgtype: str) -> str:
    """`pkg/Type` (ROS 1 style) -> `pkg/msg/Type`; other names unchanged."""
    parts = msgtype.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else msgtype


def decode(
    msgtype: str, raw: Raw, ros_version: RosVersion = 2, keep_bgra: bool = False
) -> Sweep | Frame | ImuSample:
    """Decode one message by type: LiDAR -> `Sweep`, images -> `Frame`, IMU -> `ImuSample`.

    `keep_bgra`: a raw bgra8 image stays BGRA (`decode_image`).
    """
    _check_version(ros_version)
    kind = _normalize(msgtype)
    if keep_bgra and kind == _normalize(IMAGE_TYPE):
        return decode_image(raw, ros_version, keep_bgra=True)
    decoder = _DECODERS.get(kind)
    if decoder is None:
        raise MessageDecodeError(
            f"no decoder for message type {msgtype!r}; expected one of {sorted(_DECODERS)}"
        )
    return decoder(raw, ros_version)


def header_stamp_ns(raw: bytes | memoryview, ros_version: RosVersion) -> int:
    """Header stamp (ns) of a serialised message that starts with `std_msgs/Header`.

    Reads 12 bytes only. ROS 2 CDR honours the encapsulation's byte order
    (byte 1: 0 big, 1 little endian). Raises `MessageDecodeError` when the
    buffer is too short or the nanoseconds are out of range.
    """
    if len(raw) < 12:
        raise MessageDecodeError(f"{len(raw)} bytes are too few for a ROS {ros_version} message header")
    if ros_version == 1:
        sec, nsec = struct.unpack_from("<II", raw, 4)
    else:
        order = "<" if raw[1] & 1 else ">"
        sec, nsec = struct.unpack_from(order + "iI", raw, 4)
    if nsec >= 1_000_000_000:
        raise MessageDecodeError(f"header stamp nanoseconds {nsec} >= 1e9: not a std_msgs/Header")
    return int(sec) * 1_000_000_000 + int(nsec)
