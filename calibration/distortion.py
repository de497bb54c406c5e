"""Lens distortions applied on normalised image coordinates (Kalibr's pinhole/omni).

``distort`` maps undistorted normalised coordinates (mx, my) to distorted
ones; ``undistort`` inverts it. Radial-tangential has no closed-form inverse:
it is solved by Newton's method with the analytic 2x2 Jacobian, stopping when
the residual is below `UNDISTORT_TOL` (normalised units, about 5e-10 px for a
500 px focal length) or after `UNDISTORT_MAX_ITER` steps; entries that do not
converge are reported invalid.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from calibration.camera import require_finite
from calibration.errors import CalibrationError
from calibration.types import F64, Bool

UNDISTORT_TOL = 1e-12
UNDISTORT_MAX_ITER = 30


@dataclass(frozen=True)
class RadTan:
    """Radial-tangential (Brown-Conrady, OpenCV's first four) coefficients k1, k2, p1, p2."""

    k1: float
    k2: float
    p1: float
    p2: float

    kalibr_name = "radtan"

    def __post_init__(self) -> None:
        for name in ("k1", "k2", "p1", "p2"):
            require_finite(name, getattr(self, name), "radtan distortion")

    def coeffs(self) -> list[float]:
        """Kalibr's ``distortion_coeffs`` order: [k1, k2, p1, p2]."""
        return [self.k1, self.k2, self.p1, self.p2]

    def distort(self, mx: F64, my: F64) -> tuple[F64, F64]:
        """Apply the distortion to normalised coordinates."""
        r2 = mx * mx + my * my
        radial = 1.0 + self.k1 * r2 + self.k2 * r2 * r2
        xd = mx * radial + 2.0 * self.p1 * mx * my + self.p2 * (r2 + 2.0 * mx * mx)
        yd = my * radial + self.p1 * (r2 + 2.0 * my * my) + 2.0 * self.p2 * mx * my
        return xd, yd

    def _jacobian(self, mx: F64, my: F64) -> tuple[F64, F64, F64, F64]:
        r2 = mx * mx + my * my
        radial = 1.0 + self.k1 * r2 + self.k2 * r2 * r2
        dradial = 2.0 * self.k1 + 4.0 * self.k2 * r2  # d radial / d(r2) * 2
        j00 = radial + mx * dradial * mx + 2.0 * self.p1 * my + 6.0 * self.p2 * mx
        j01 = mx * dradial * my + 2.0 * self.p1 * mx + 2.0 * self.p2 * my
        j10 = my * dradial * mx + 2.0 * self.p1 * mx + 2.0 * self.p2 * my
        j11 = radial + my * dradial * my + 6.0 * self.p1 * my + 2.0 * self.p2 * mx
        return j00, j01, j10, j11

    def undistort(self, xd: F64, yd: F64) -> tuple[F64, F64, Bool]:
        """Invert `distort` by Newton's method; returns (mx, my, converged)."""
        mx, my = xd.copy(), yd.copy()
        tol = UNDISTORT_TOL * np.maximum(1.0, np.hypot(xd, yd))
        for _ in range(UNDISTORT_MAX_ITER):
            fx, fy = self.distort(mx, my)
            ex, ey = fx - xd, fy - yd
            converged = np.hypot(ex, ey) < tol
            if converged.all():
                break
            j00, j01, j10, j11 = self._jacobian(mx, my)
            det = j00 * j11 - j01 * j10
            mx = mx - (j11 * ex - j01 * ey) / det
            my = my - (-j10 * ex + j00 * ey) / det
        else:
            fx, fy = self.distort(mx, my)
            converged = np.hypot(fx - xd, fy - yd) < tol
        # The Jacobian must stay positive definite-ish: past the fold the inverse is not unique.
        j00, j01, j10, j11 = self._jacobian(mx, my)
        converged &= (j00 * j11 - j01 * j10) > 0.0
        return mx, my, converged


@dataclass(frozen=True)
class Fov:
    """Devernay-Faugeras field-of-view distortion with parameter w (radians)."""

    w: float

    kalibr_name = "fov"

    def __post_init__(self) -> None:
        require_finite("w", self.w, "fov distortion")
        if not 0.0 < self.w < math.pi:
            raise CalibrationError(f"fov distortion: w must be in (0, pi), got {self.w!r}")

    def coeffs(self) -> list[float]:
        """Kalibr's ``distortion_coeffs``: [w]."""
        return [self.w]

    def _factor(self, r: F64) -> F64:
        t = 2.0 * math.tan(self.w / 2.0)
        with np.errstate(all="ignore"):
            return np.where(r > 1e-12, np.arctan(r * t) / (self.w * r), t / self.w)

    def distort(self, mx: F64, my: F64) -> tuple[F64, F64]:
        """rd = atan(2 r tan(w/2)) / w."""
        f = self._factor(np.hypot(mx, my))
        return mx * f, my * f

    def undistort(self, xd: F64, yd: F64) -> tuple[F64, F64, Bool]:
        """r = tan(rd w) / (2 tan(w/2)), valid while rd w < pi/2."""
        rd = np.hypot(xd, yd)
        valid = rd * self.w < math.pi / 2.0
        t = 2.0 * math.tan(self.w / 2.0)
        with np.errstate(all="ignore"):
            f = np.where(rd > 1e-12, np.tan(rd * self.w) / (t * rd), self.w / t)
        return xd * f, yd * f, valid


Distortion = RadTan | Fov
