"""Geometry for SensorBox: camera models, Kalibr camchains and rig files.

Imports nothing from `ingest` or `sensorbox` (a test enforces it).
"""

from calibration.camera import CameraModel, FieldOfView, field_of_view
from calibration.distortion import Fov, RadTan
from calibration.errors import CalibrationError, SensorboxError
from calibration.fisheye import DoubleSphere, ExtendedUnified, KannalaBrandt, Unified
from calibration.kalibr import (
    CameraChain,
    KalibrCamera,
    read_kalibr_camchain,
    write_kalibr_camchain,
)
from calibration.pinhole import Omni, Pinhole
from calibration.rig import Camera, Imu, Lidar, Rig, read_livox_config, read_rig, write_rig

__all__ = [
    "CalibrationError",
    "Camera",
    "CameraChain",
    "CameraModel",
    "DoubleSphere",
    "ExtendedUnified",
    "FieldOfView",
    "Fov",
    "Imu",
    "KalibrCamera",
    "KannalaBrandt",
    "Lidar",
    "Omni",
    "Pinhole",
    "RadTan",
    "Rig",
    "SensorboxError",
    "Unified",
    "field_of_view",
    "read_kalibr_camchain",
    "read_livox_config",
    "read_rig",
    "write_kalibr_camchain",
    "write_rig",
]
