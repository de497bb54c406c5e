"""Perspective-type models: pinhole and Mei/omni, each with optional distortion."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from calibration.camera import FocalModel
from calibration.distortion import Distortion, Fov, RadTan
from calibration.errors import CalibrationError
from calibration.types import F64, Bool


@dataclass(frozen=True)
class Pinhole(FocalModel):
    """Pinhole camera, optionally with radtan or fov distortion. Valid for z > 0."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: Distortion | None = None

    def _check_params(self) -> None:
        if self.distortion is not None and not isinstance(self.distortion, RadTan | Fov):
            raise CalibrationError(f"Pinhole: unsupported distortion {self.distortion!r}")

    @property
    def max_off_axis_rad(self) -> float:
        """pi/2: only points in front of the image plane project."""
        return math.pi / 2.0

    @property
    def K(self) -> F64:
        """3x3 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def _project_fused(self, flat: F64) -> tuple[F64, Bool] | None:
        if self.distortion is not None:
            return None
        from calibration.kernels import project_pinhole

        return project_pinhole(np.ascontiguousarray(flat), self.fx, self.fy, self.cx, self.cy)

    def _project_normalised(self, x: F64, y: F64, z: F64) -> tuple[F64, F64, Bool]:
        mx, my = x / z, y / z
        if self.distortion is not None:
            mx, my = self.distortion.distort(mx, my)
        return mx, my, z > 0.0

    def _unproject_normalised(self, mx: F64, my: F64) -> tuple[F64, F64, F64, Bool]:
        valid = np.ones_like(mx, dtype=bool)
        if self.distortion is not None:
            mx, my, valid = self.distortion.undistort(mx, my)
        return mx, my, np.ones_like(mx), valid


@dataclass(frozen=True)
class Omni(FocalModel):
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

    FINITE = ("xi",)

    def _check_params(self) -> None:
        if self.xi < 0.0:
            raise CalibrationError(f"Omni: xi must be >= 0, got {self.xi!r}")
        if self.distortion is not None and not isinstance(self.distortion, RadTan):
            raise CalibrationError(f"Omni: only radtan distortion is supported, got {self.distortion!r}")

    @property
    def _w(self) -> float:
        return self.xi if self.xi <= 1.0 else 1.0 / self.xi

    @property
    def max_off_axis_rad(self) -> float:
        """acos(-w): the angle from the axis where projection stops being valid."""
        return math.acos(-self._w)

    def _project_normalised(self, x: F64, y: F64, z: F64) -> tuple[F64, F64, Bool]:
        d = np.sqrt(x * x + y * y + z * z)
        den = z + self.xi * d
        mx, my = x / den, y / den
        if self.distortion is not None:
            mx, my = self.distortion.distort(mx, my)
        valid = (z > -self._w * d) & (den > 0.0)
        return mx, my, valid

    def _unproject_normalised(self, mx: F64, my: F64) -> tuple[F64, F64, F64, Bool]:
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
