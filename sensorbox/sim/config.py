"""Every knob of a simulated recording (`SimConfig`), checked before anything is simulated, with the
bounds it checks against and the Mid-360 IMU's datasheet noise (`with_mid360_imu_noise`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np

from calibration.errors import SensorboxError
from calibration.rig import REFERENCE_RIG
from sensorbox.live.bagwriter import FORMATS, BagFormat
from sensorbox.sim.lidar import MID360_BEAM_DIVERGENCE_DEG, NOISE_MODELS
from sensorbox.sim.scenes import SCENES
from sensorbox.sim.trajectory import TRAJECTORIES

MAX_CAMERA_OFFSET_NS = 1_000_000_000
"""Largest camera or LiDAR clock offset simulated (ns): a second."""
MAX_DURATION_S = 1e8
"""Longest simulated run (s), about three years: the live emulators run "forever" as 1e7 s, and a
run's nanoseconds must stay far inside int64 (1e300 s overflowed)."""
MAX_RANGE_NOISE_M = 10.0
"""Largest range noise simulated (1-sigma, m): the Mid-360 measures to 40 m with about 2 cm; noise
of metres already drowns every scene, and 1e300 turned every point into a point at 0."""
MID360_IMU_GYRO_NOISE_DENSITY = np.radians(4.5e-3)
"""The Mid-360's IMU (TDK ICM-40609-D) gyro noise density, rad/s/sqrt(Hz) (datasheet: 4.5 mdps/sqrt(Hz))."""
MID360_IMU_ACC_NOISE_DENSITY_G = 100e-6
"""Its accelerometer noise density, g/sqrt(Hz) (datasheet: 100 ug/sqrt(Hz))."""
MID360_IMU_GYRO_BIAS_RAD_S = np.radians(0.1)
"""1-sigma of a gyro's constant bias per axis: a factory-trimmed MEMS gyro's residual offset."""
MID360_IMU_ACC_BIAS_G = 0.01
"""1-sigma of an accelerometer's constant bias per axis (10 mg)."""


def with_mid360_imu_noise(cfg: SimConfig) -> SimConfig:
    """`cfg` with the Mid-360 IMU's datasheet noise at its IMU rate and typical constant biases."""
    root_hz = math.sqrt(cfg.imu_rate_hz)
    return replace(
        cfg,
        gyro_noise_rad_s=float(MID360_IMU_GYRO_NOISE_DENSITY * root_hz),
        acc_noise_g=MID360_IMU_ACC_NOISE_DENSITY_G * root_hz,
        gyro_bias_rad_s=float(MID360_IMU_GYRO_BIAS_RAD_S),
        acc_bias_g=MID360_IMU_ACC_BIAS_G,
    )


@dataclass(frozen=True)
class SimConfig:
    """Every knob of a simulated recording (times in ns unless named otherwise)."""

    scene: str = "indoor"
    trajectory: str = "static"
    tum: Path | None = None
    duration_s: float = 1.0
    seed: int = 0
    format: BagFormat = "mcap"
    lidar_msg: Literal["custom", "pointcloud2"] = "custom"
    image: Literal["raw", "jpeg"] = "raw"
    jpeg_quality: int = 90
    scale: float = 1.0
    supersample: int = 1
    range_noise_m: float = 0.02
    dust_fraction: float = 0.01
    lidar_clock_offset_ns: int = 0  # the second LiDAR's stamps run ahead of the first by this
    camera_rate_hz: float = 30.0
    camera_jitter_ns: int = 500_000  # uniform +-, on each camera's mid-exposure time
    stereo_offset_ns: int = 100_000  # lower camera's nominal exposure after the upper's
    imu_rate_hz: float = 200.0
    gyro_noise_rad_s: float = 0.0  # white noise, 1-sigma per reading
    acc_noise_g: float = 0.0
    gyro_bias_rad_s: float = 0.0  # 1-sigma of each IMU's constant per-axis bias
    acc_bias_g: float = 0.0
    camera_offset_ns: tuple[int, int] = (0, 0)  # per camera (upper, lower): header stamp - true exposure
    range_noise_model: str = "constant"  # or "mid360": sigma grows with range, falls with reflectivity
    mixed_returns: bool = False  # a beam of MID360_BEAM_DIVERGENCE_DEG: mixed ranges at depth edges
    start_ns: int = 1_700_000_000_000_000_000
    compress: bool = True
    movers: bool = False  # people, a door and (outdoor) a car moving through the scene
    rig: Path = field(default=REFERENCE_RIG)

    def validate(self) -> None:
        if self.scene not in SCENES:
            raise SensorboxError(f"--scene {self.scene!r}: expected one of {', '.join(SCENES)}")
        if self.trajectory not in TRAJECTORIES:
            raise SensorboxError(
                f"--trajectory {self.trajectory!r}: expected one of {', '.join(TRAJECTORIES)}"
            )
        if self.trajectory == "custom" and self.tum is None:
            raise SensorboxError(
                "--trajectory custom needs --tum FILE (t tx ty tz qx qy qz qw, T_world_cam0)"
            )
        for flag, choice, known in (
            ("--format", self.format, FORMATS),
            ("--lidar-msg", self.lidar_msg, ("custom", "pointcloud2")),
            ("--image", self.image, ("raw", "jpeg")),
        ):
            if choice not in known:
                raise SensorboxError(f"{flag} {choice!r}: expected one of {', '.join(known)}")
        if self.tum is not None and self.trajectory != "custom":
            raise SensorboxError(
                f"--tum is read only with --trajectory custom (got --trajectory {self.trajectory})"
            )
        for name, value, lo in (("duration", self.duration_s, 0.0), ("scale", self.scale, 0.0)):
            if not (value > lo and math.isfinite(value)):
                raise SensorboxError(f"--{name} must be a finite number > {lo}, got {value}")
        period_s = 1.0 / self.camera_rate_hz  # the first frame lies at a random phase within one period
        if self.duration_s < period_s:  # 1e-9 s wrote a bag without an image or an IMU reading, exit 0
            raise SensorboxError(
                f"--duration {self.duration_s:g}: shorter than one camera frame period "
                f"({period_s * 1e3:.1f} ms at {self.camera_rate_hz:g} Hz), so the bag may hold no image; "
                f"expected at least {period_s:.4g} s"
            )
        if self.duration_s > MAX_DURATION_S:  # int nanoseconds overflowed at 1e300
            raise SensorboxError(f"--duration {self.duration_s:g}: expected at most {MAX_DURATION_S:g} s")
        if abs(self.lidar_clock_offset_ns) > MAX_CAMERA_OFFSET_NS:
            raise SensorboxError(
                f"--lidar-offset-ms {self.lidar_clock_offset_ns / 1e6:g}: expected within "
                f"+-{MAX_CAMERA_OFFSET_NS / 1e6:g} ms"
            )
        if not (self.range_noise_m >= 0 and math.isfinite(self.range_noise_m)):
            raise SensorboxError(f"--range-noise must be a finite number >= 0 m, got {self.range_noise_m}")
        if self.range_noise_m > MAX_RANGE_NOISE_M:
            raise SensorboxError(
                f"--range-noise {self.range_noise_m:g}: expected at most {MAX_RANGE_NOISE_M:g} m (1-sigma)"
            )
        if self.supersample < 1:
            raise SensorboxError(f"--supersample must be >= 1, got {self.supersample}")
        if self.seed < 0:  # numpy's generators take non-negative seeds only
            raise SensorboxError(f"--seed must be an integer >= 0, got {self.seed}")
        if self.range_noise_model not in NOISE_MODELS:
            raise SensorboxError(
                f"--range-noise-model {self.range_noise_model!r}: expected one of {', '.join(NOISE_MODELS)}"
            )
        for ns in self.camera_offset_ns:
            if abs(ns) > MAX_CAMERA_OFFSET_NS:
                raise SensorboxError(
                    f"--camera-offset-ms {ns / 1e6:.9g}: expected within +-{MAX_CAMERA_OFFSET_NS / 1e6:g} ms"
                )

    @property
    def realism(self) -> dict[str, Any]:
        """The real-world error sources switched on (sim.yaml records them only when on)."""
        out: dict[str, Any] = {}
        if any(self.camera_offset_ns):
            out["camera_offset_ns"] = list(self.camera_offset_ns)
        if self.range_noise_model != "constant":
            out["range_noise_model"] = self.range_noise_model
        if self.mixed_returns:
            out["mixed_returns"] = True
            out["beam_divergence_deg"] = MID360_BEAM_DIVERGENCE_DEG
        return out
