"""Perspective-type models: pinhole and Mei/omni, each with optional distortion."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from calibration.camera import CameraModel, check_focal, focal_scaled_params, require_finite
from calibration.distortion import Distortion, Fov, RadTan
from calibration.errors import CalibrationError
from calibration.types import F64, Bool


@dataclass(frozen=True)
class Pinhole(CameraModel):
    """Pinhole camera, optionally with radtan or fov distortion. Valid for z > 0."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: Distortion | None = None

    def __post_init__(self) -> None:
        check_focal(self, "Pinhole")
        if self.distortion is not None and not isinstance(self.distortion, RadTan | Fov):
            raise CalibrationError(f"Pinhole: unsupported distortion {self.distortion!r}")

    @property
    def K(self) -> F64:
        """3x3 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def _project(self, x: F64, y: F64, z: F64) -> tuple[F64, F64, Bool]:
        mx, my = x / z, y / z
        if self.distortion is not None:
            mx, my = self.distortion.distort(mx, my)
        return self.fx * mx + self.cx, self.fy * my + self.cy, z > 0.0

    def _unproject(self, u: F64, v: F64) -> tuple[F64, F64, F64, Bool]:
        mx = (u - self.cx) / self.fx
        my = (v - self.cy) / self.fy
        valid = np.ones_like(mx, dtype=bool)
        if self.distortion is not None:
            mx, my, valid = self.distortion.undistort(mx, my)
        return mx, my, np.ones_like(mx), valid

    def _scaled_params(self, factor: float) -> dict[str, Any]:
        return focal_scaled_params(self, factor)


@dataclass(frozen=True)
class Omni(CameraModel):
    """Mei unified omnidirectional model (Kalibr ``omni``, cv2.omnidir), optional radtan.

    u = fx * distort(x / (z + xi |p|)) + cx. Projection valid where
    z > -w |p| with w = xi if xi <= 1 else 1/xi.
    """

    xi: float
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: RadTan | None = None

    def __post_init__(self) -> None:
        check_focal(self, "Omni")
        require_finite("xi", self.xi, "Omni")
        if self.xi < 0.0:
            raise CalibrationError(f"Omni: xi must be >= 0, got {self.xi!r}")
        if self.distortion is not None and not isinstance(self.distortion, RadTan):
            raise CalibrationError(f"Omni: only radtan distortion is supported, got {self.distortion!r}")

    @property
    def _w(self) -> float:
        return self.xi if self.xi <= 1.0 else 1.0 / self.xi

    def _project(self, x: F64, y: F64, z: F64) -> tuple[F64, F64, Bool]:
        d = np.sqrt(x * x + y * y + z * z)
        den = z + self.xi * d
        mx, my = x / den, y / den
        if self.distortion is not None:
            mx, my = self.distortion.distort(mx, my)
        valid = (z > -self._w * d) & (den > 0.0)
        return self.fx * mx + self.cx, self.fy * my + self.cy, valid

    def _unproject(self, u: F64, v: F64) -> tuple[F64, F64, F64, Bool]:
        mx = (u - self.cx) / self.fx
        my = (v - self.cy) / self.fy
        valid = np.ones_like(mx, dtype=bool)
        if self.distortion is not None:
            mx, my, valid = self.distortion.undistort(mx, my)
        r2 = mx * mx + my * my
        disc = 1.0 + (1.0 - self.xi * self.xi) * r2
        valid &= disc >= 0.0
        f = (self.xi + np.sqrt(disc)) / (r2 + 1.0)
        x, y, z = f * mx, f * my, f - self.xi
        valid &= z > -self._w * np.sqrt(x * x + y * y + z * z)
        return x, y, z, valid

    def _scaled_params(self, factor: float) -> dict[str, Any]:
        return focal_scaled_params(self, factor)
