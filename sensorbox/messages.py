"""Serialise the messages the SensorBox drivers publish (ROS 2 CDR or ROS 1 bytes).

Topics and layouts follow the real drivers: ZED `sensor_msgs/Image` bgra8 (or
image_transport's `CompressedImage` jpeg on `<topic>/compressed`), Livox
`CustomMsg` (livox_ros_driver2, xfer_format 1) or its `PointCloud2`
(xfer_format 0: 26-byte packed PointXYZRTLT with an absolute float64 ns
timestamp), and `/livox/imu_*` `Imu` (acceleration in g, no orientation).
"""

from __future__ import annotations

from typing import Any, Literal

import cv2
import numpy as np

from calibration.errors import SensorboxError
from calibration.types import F64, U8
from ingest.bags.livox_msg import Points, encode_custom_msg
from ingest.bags.rostypes import (
    COMPRESSED_IMAGE_TYPE,
    CUSTOM_MSG_TYPE,
    IMAGE_TYPE,
    IMU_TYPE,
    POINTCLOUD2_TYPE,
    typestore,
)

RosVersion = Literal[1, 2]
LIVOX_FRAME = "livox_frame"
PC2_FIELDS = (
    ("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 12, 7),
    ("tag", 16, 2), ("line", 17, 2), ("timestamp", 18, 8),
)  # fmt: skip
"""(name, offset, PointField datatype): 7 = FLOAT32, 2 = UINT8, 8 = FLOAT64."""
PC2_DTYPE = np.dtype(
    {"names": ["x", "y", "z", "intensity", "tag", "line", "timestamp"],
     "formats": ["<f4", "<f4", "<f4", "<f4", "u1", "u1", "<f8"],
     "offsets": [0, 4, 8, 12, 16, 17, 18], "itemsize": 26}
)  # fmt: skip


def _header(ros: RosVersion, stamp_ns: int, frame_id: str, seq: int = 0) -> Any:
    ts = typestore(ros)
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    stamp = ts.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
    header = ts.types["std_msgs/msg/Header"]
    return (
        header(seq=seq, stamp=stamp, frame_id=frame_id)
        if ros == 1
        else header(stamp=stamp, frame_id=frame_id)
    )


def _serialise(ros: RosVersion, msg: Any, msgtype: str) -> bytes:
    ts = typestore(ros)
    return bytes(ts.serialize_ros1(msg, msgtype) if ros == 1 else ts.serialize_cdr(msg, msgtype))


def image_msg(stamp_ns: int, frame_id: str, bgr: U8, ros: RosVersion = 2) -> bytes:
    """`sensor_msgs/Image` bgra8 (alpha 255), as the ZED wrapper publishes colour images."""
    if bgr.ndim != 3 or bgr.shape[2] != 3 or bgr.dtype != np.uint8:
        raise SensorboxError(f"image_msg expects an HxWx3 uint8 BGR image, got {bgr.shape} {bgr.dtype}")
    bgra = cv2.cvtColor(bgr, cv2.COLOR_BGR2BGRA)
    h, w = bgr.shape[:2]
    msg = typestore(ros).types[IMAGE_TYPE](
        header=_header(ros, stamp_ns, frame_id), height=h, width=w, encoding="bgra8",
        is_bigendian=0, step=4 * w, data=bgra.reshape(-1),
    )  # fmt: skip
    return _serialise(ros, msg, IMAGE_TYPE)


def compressed_image_msg(
    stamp_ns: int,
    frame_id: str,
    bgr: U8,
    quality: int = 90,
    ros: RosVersion = 2,
) -> bytes:
    """`sensor_msgs/CompressedImage` jpeg, format string as image_transport writes it."""
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise SensorboxError(f"JPEG encoding failed for an image of shape {bgr.shape}")
    msg = typestore(ros).types[COMPRESSED_IMAGE_TYPE](
        header=_header(ros, stamp_ns, frame_id), format="bgra8; jpeg compressed bgr8", data=buf.reshape(-1)
    )
    return _serialise(ros, msg, COMPRESSED_IMAGE_TYPE)


def imu_msg(stamp_ns: int, gyro_rad_s: F64, acc_g: F64, ros: RosVersion = 2) -> bytes:
    """`sensor_msgs/Imu` as livox_ros_driver2 fills it: rates rad/s, acceleration in g, no orientation."""
    ts = typestore(ros)
    vec = ts.types["geometry_msgs/msg/Vector3"]
    msg = ts.types[IMU_TYPE](
        header=_header(ros, stamp_ns, LIVOX_FRAME),
        orientation=ts.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=0.0),
        orientation_covariance=np.zeros(9),
        angular_velocity=vec(x=float(gyro_rad_s[0]), y=float(gyro_rad_s[1]), z=float(gyro_rad_s[2])),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=vec(x=float(acc_g[0]), y=float(acc_g[1]), z=float(acc_g[2])),
        linear_acceleration_covariance=np.zeros(9),
    )
    return _serialise(ros, msg, IMU_TYPE)


def custom_msg(timebase_ns: int, points: Points, ros: RosVersion = 2, lidar_id: int = 192) -> bytes:
    """livox_ros_driver2 `CustomMsg`: header.stamp = timebase = the first point's time."""
    return encode_custom_msg(
        timebase_ns, LIVOX_FRAME, timebase_ns, points, lidar_id=lidar_id, ros_version=ros
    )


def pointcloud2_msg(timebase_ns: int, points: Points, ros: RosVersion = 2) -> bytes:
    """livox_ros_driver2 `PointCloud2` (xfer_format 0), every point including zero returns."""
    ts = typestore(ros)
    cloud = np.zeros(len(points), PC2_DTYPE)
    for name in ("x", "y", "z", "tag", "line"):
        cloud[name] = points[name]
    cloud["intensity"] = points["reflectivity"]
    cloud["timestamp"] = (np.int64(timebase_ns) + points["offset_time"].astype(np.int64)).astype(np.float64)
    field = ts.types["sensor_msgs/msg/PointField"]
    msg = ts.types[POINTCLOUD2_TYPE](
        header=_header(ros, timebase_ns, LIVOX_FRAME), height=1, width=len(points),
        fields=[field(name=n, offset=o, datatype=d, count=1) for n, o, d in PC2_FIELDS],
        is_bigendian=False, point_step=26, row_step=26 * len(points),
        data=np.frombuffer(cloud.tobytes(), np.uint8), is_dense=True,
    )  # fmt: skip
    return _serialise(ros, msg, POINTCLOUD2_TYPE)


LIDAR_MSG_TYPES = {"custom": CUSTOM_MSG_TYPE, "pointcloud2": POINTCLOUD2_TYPE}
IMAGE_MSG_TYPES = {"raw": IMAGE_TYPE, "jpeg": COMPRESSED_IMAGE_TYPE}
