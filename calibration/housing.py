"""Each Livox Mid-360 carries its IMU in the LiDAR's housing: the IMU sits unturned at a fixed offset in
the LiDAR's frame (Livox's figure: (11.0, 23.29, -44.12) mm). A rig file whose LiDAR and IMU of one
housing disagree with that has one of the two poses wrong, and `calib refine`, which turns a housing
as a whole, would carry the error from one to the other."""

from __future__ import annotations

import numpy as np

from calibration.rig import Imu, Lidar, Rig
from calibration.types import F64

IMU_IN_LIDAR_M: F64 = np.array([0.011, 0.02329, -0.04412])
"""Where a Mid-360's IMU sits in its LiDAR's frame (m), unturned."""
HOUSING_DEG = 0.5
HOUSING_MM = 10.0
"""A rig's IMU further than this from where its LiDAR's housing puts it (rotation, position) is named:
an IMU-camera calibration of the real unit lands within a few tenths of a degree and a few millimetres."""


def housing_lidar(rig: Rig, imu: Imu) -> Lidar | None:
    """The LiDAR of the same Mid-360 as `imu`: the one whose address (or topic suffix) its topic ends
    with; None when no LiDAR's does."""
    for lidar in rig.lidars:
        key = lidar.ip.replace(".", "_") if lidar.ip else lidar.topic.rsplit("lidar", 1)[-1]
        if key and imu.topic.endswith(key):
            return lidar
    return None


def housing_warnings(rig: Rig) -> list[str]:
    """One line per IMU whose pose in the rig disagrees with its LiDAR's housing (`HOUSING_DEG`,
    `HOUSING_MM`)."""
    out = []
    for imu in rig.imus:
        lidar = housing_lidar(rig, imu)
        if lidar is None:
            continue
        T_lidar_imu = np.linalg.inv(lidar.T_cam0_lidar) @ imu.T_cam0_imu
        cos = np.clip((np.trace(T_lidar_imu[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
        angle_deg = float(np.degrees(np.arccos(cos)))
        off_mm = float(np.linalg.norm(T_lidar_imu[:3, 3] - IMU_IN_LIDAR_M) * 1e3)
        if angle_deg > HOUSING_DEG or off_mm > HOUSING_MM:
            where = rig.source or rig.name
            out.append(
                f"{where}: {imu.name} is {angle_deg:.2f} deg and {off_mm:.1f} mm from where {lidar.name}'s "
                "housing puts it (a Mid-360's IMU sits unturned at (11.0, 23.29, -44.12) mm in its LiDAR's "
                f"frame): one of the two poses is off; calib refine turns a housing as a whole, so check "
                f"{lidar.name}'s T_cam0_lidar and {imu.name}'s T_cam0_imu first"
            )
    return out
