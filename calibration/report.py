"""A geometric summary of a rig: models, true FOVs, baselines and frames."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from calibration.camera import FieldOfView, field_of_view
from calibration.rig import Rig
from calibration.types import F64


@dataclass(frozen=True)
class FrameReport:
    """Where a sensor sits in cam0: position (m), rotation angle from cam0 (rad), axes."""

    name: str
    kind: str
    topic: str | None
    T_cam0_sensor: F64
    position_m: F64
    rotation_rad: float

    @property
    def z_axis_cam0(self) -> F64:
        """The sensor's z axis expressed in cam0 (optical axis for a camera, up for a LiDAR)."""
        return self.T_cam0_sensor[:3, 2].copy()


@dataclass(frozen=True)
class CameraReport:
    """One camera: model type, its parameters and the measured field of view."""

    name: str
    role: str | None
    model: str
    params: dict[str, Any]
    fov: FieldOfView
    frame: FrameReport


@dataclass(frozen=True)
class RigReport:
    """Everything `sensorbox calib check` prints."""

    name: str
    cameras: tuple[CameraReport, ...]
    frames: tuple[FrameReport, ...]
    baseline_m: float | None


def _frame(name: str, kind: str, topic: str | None, T: F64) -> FrameReport:
    cos = (np.trace(T[:3, :3]) - 1.0) / 2.0
    return FrameReport(name, kind, topic, T, T[:3, 3].copy(), math.acos(float(np.clip(cos, -1, 1))))


def describe_rig(rig: Rig) -> RigReport:
    """Measure the rig: FOV of each camera by unprojecting its border, baseline, frames."""
    cams = []
    for cam in rig.cameras:
        frame = _frame(cam.name, "camera", cam.topic, cam.T_cam0_cam)
        cams.append(
            CameraReport(
                cam.name,
                cam.role,
                type(cam.model).__name__,
                cam.model.params(),
                field_of_view(cam.model),
                frame,
            )
        )
    frames = [c.frame for c in cams]
    frames += [_frame(li.name, "lidar", li.topic, li.T_cam0_lidar) for li in rig.lidars]
    frames += [_frame(imu.name, "imu", imu.topic, imu.T_cam0_imu) for imu in rig.imus]
    roles = {c.role for c in rig.cameras}
    baseline = rig.baseline_m() if {"upper", "lower"} <= roles else None
    return RigReport(rig.name, tuple(cams), tuple(frames), baseline)
