"""ROS message types SensorBox reads and writes, as rosbags typestores.

The Livox driver messages are not in any stock typestore, so they are registered
here from their `.msg` text (livox_ros_driver2 v1.2.6, identical layout in the
older livox_ros_driver). The ROS 1 MD5 of the generated `CustomMsg` definition
is `e4d6829bdfe657cb6c21a746c86b21a6`, the same the real driver publishes with;
a test pins it so a rosbags upgrade cannot silently change it.
"""

from __future__ import annotations

from functools import cache
from typing import Literal

from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

CUSTOM_POINT_MSG = """\
uint32 offset_time
float32 x
float32 y
float32 z
uint8 reflectivity
uint8 tag
uint8 line
"""

CUSTOM_MSG = """\
std_msgs/Header header
uint64 timebase
uint32 point_num
uint8 lidar_id
uint8[3] rsvd
CustomPoint[] points
"""

LIVOX_PACKAGES = ("livox_ros_driver2", "livox_ros_driver")
"""Packages whose `CustomMsg`/`CustomPoint` share the layout above."""

CUSTOM_MSG_TYPE = "livox_ros_driver2/msg/CustomMsg"
IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE_TYPE = "sensor_msgs/msg/CompressedImage"
POINTCLOUD2_TYPE = "sensor_msgs/msg/PointCloud2"
IMU_TYPE = "sensor_msgs/msg/Imu"

ROS1_CUSTOM_MSG_MD5 = "e4d6829bdfe657cb6c21a746c86b21a6"


def livox_types() -> dict[str, object]:
    """Message definitions of both Livox packages, ready for `Typestore.register`."""
    types: dict[str, object] = {}
    for pkg in LIVOX_PACKAGES:
        types.update(get_types_from_msg(CUSTOM_POINT_MSG, f"{pkg}/msg/CustomPoint"))
        msg = CUSTOM_MSG.replace("CustomPoint[]", f"{pkg}/CustomPoint[]")
        types.update(get_types_from_msg(msg, f"{pkg}/msg/CustomMsg"))
    return types


@cache
def typestore(ros_version: Literal[1, 2] = 2) -> Typestore:
    """Stock sensor_msgs (ROS 2 Humble or ROS 1 Noetic) plus the Livox messages.

    Cached: typestores are read-only after registration.
    """
    store = get_typestore(Stores.ROS2_HUMBLE if ros_version == 2 else Stores.ROS1_NOETIC)
    store.register(livox_types())  # type: ignore[arg-type]
    return store
