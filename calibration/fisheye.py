"""Wide-angle camera models: Double Sphere, (Extended) Unified and Kannala-Brandt.

Formulas follow the Double Sphere paper (Usenko et al., 3DV 2018) and
basalt-headers; projection validity matches Kalibr's (see notes/cameras.md).
Unprojection is valid only where the ray it gives is one `project` accepts, so
every valid pixel projects back onto itself (Kalibr's DS/EUCM unprojection
bound alone, the alpha circle, lets rays past the projection limit through).
All are closed form except Kannala-Brandt unprojection, which solves the
polynomial by Newton's method to `KB_TOL` radians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from calibration.camera import FocalModel
from calibration.errors import CalibrationError
from calibration.types import F64, Bool

KB_TOL = 1e-13
KB_FIT_TOL = 1e-9
"""|theta_d(theta) - r_d| an unprojected ray must reach (a nanoradian: far below a pixel)."""
"""Kannala-Brandt unprojection tolerance on theta, radians."""
KB_MAX_ITER = 100  # bisection halves a 3.14 rad bracket to 1e-13 in 45; Newton ends far sooner


def _alpha_w1(alpha: float) -> float:
    """w1 of the DS/EUCM validity test: alpha/(1-alpha) if alpha <= 0.5 else (1-alpha)/alpha."""
    return alpha / (1.0 - alpha) if alpha <= 0.5 else (1.0 - alpha) / alpha


@dataclass(frozen=True)
class DoubleSphere(FocalModel):
    """Double Sphere model: fx, fy, cx, cy in pixels; xi and alpha unitless.

    Projection is valid where z > -w2 * |p|; unprojection where r^2 <= 1/(2 alpha - 1)
    when alpha > 0.5 and the ray it gives satisfies the projection test. With
    xi != 0 the second condition is the tighter one near the image circle.
    The FOV may exceed 180 degrees but never 2 acos(-w2).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    xi: float
    alpha: float
    width: int
    height: int

    FINITE = ("xi", "alpha")

    def _check_params(self) -> None:
        self._require_unit_interval("alpha")
        # The second sphere's centre lies within the first's radius; at xi = -1 it sits on the
        # optical axis' point of the first sphere, so the principal ray itself has no image.
        if not -1.0 < self.xi <= 1.0:
            raise CalibrationError(
                f"DoubleSphere: xi must be in (-1, 1], got {self.xi!r} (at -1 the optical axis has no "
                "image, beyond 1 the valid image circle shrinks to a few pixels; a fitted fisheye's xi is "
                "about -0.3..0.3)"
            )

    @cached_property
    def w2(self) -> float:
        """Projection validity constant: valid iff z > -w2 * |p|."""
        w1 = _alpha_w1(self.alpha)
        return (w1 + self.xi) / math.sqrt(2.0 * w1 * self.xi + self.xi * self.xi + 1.0)

    @property
    def max_off_axis_rad(self) -> float:
        """acos(-w2): the angle from the axis where projection stops being valid."""
        return math.acos(min(1.0, max(-1.0, -self.w2)))

    def _project_fused(self, flat: F64) -> tuple[F64, Bool]:
        from calibration.kernels import project_double_sphere

        p = np.ascontiguousarray(flat)
        return project_double_sphere(p, self.fx, self.fy, self.cx, self.cy, self.xi, self.alpha, self.w2)

    def _unproject_fused(self, flat: F64) -> tuple[F64, Bool]:
        from calibration.kernels import unproject_double_sphere

        uv = np.ascontiguousarray(flat)
        return unproject_double_sphere(uv, self.fx, self.fy, self.cx, self.cy, self.xi, self.alpha, self.w2)

    def _project_normalised(self, x: F64, y: F64, z: F64) -> tuple[F64, F64, Bool]:
        # in place where possible: fresh temporaries of a million points cost more than the arithmetic
        r2 = x * x
        r2 += y * y
        d1 = z * z
        d1 += r2
        np.sqrt(d1, out=d1)
        k = d1 * self.xi
        k += z
        n = k * k
        n += r2
        np.sqrt(n, out=n)
        n *= self.alpha
        k *= 1.0 - self.alpha
        n += k
        d1 *= -self.w2
        valid = z > d1
        valid &= n > 0.0
        np.divide(1.0, n, out=n)
        return x * n, y * n, valid

    def _unproject_normalised(self, mx: F64, my: F64) -> tuple[F64, F64, F64, Bool]:
        a, xi = self.alpha, self.xi
        r2 = mx * mx + my * my
        valid = np.ones_like(r2, dtype=bool) if a <= 0.5 else r2 <= 1.0 / (2.0 * a - 1.0)
        mz = (1.0 - a * a * r2) / (a * np.sqrt(1.0 - (2.0 * a - 1.0) * r2) + 1.0 - a)
        s = (mz * xi + np.sqrt(mz * mz + (1.0 - xi * xi) * r2)) / (mz * mz + r2)
        x, y, z = s * mx, s * my, s * mz - xi
        # The image circle above is where the formula is defined; the pixel is valid only if its
        # ray is inside the projection's domain too. With xi != 0 the projection of the limit
        # ray z = -w2 |p| lies inside that circle, and the ring between them unprojects to rays
        # beyond the limit (the fold) that `project` refuses.
        valid &= z > -self.w2 * np.sqrt(x * x + y * y + z * z)
        return x, y, z, valid


def _eucm_project(x: F64, y: F64, z: F64, alpha: float, beta: float) -> tuple[F64, F64, Bool]:
    d = x * x  # in place where possible (see DoubleSphere)
    d += y * y
    d *= beta
    d += z * z
    np.sqrt(d, out=d)
    n = z * (1.0 - alpha)
    n += alpha * d
    d *= -_alpha_w1(alpha)
    valid = z > d
    valid &= n > 0.0
    np.divide(1.0, n, out=n)
    return x * n, y * n, valid


def _eucm_fused(model: ExtendedUnified | Unified, flat: F64, beta: float) -> tuple[F64, Bool]:
    """EUCM/UCM `project` in one compiled pass (`calibration.kernels`)."""
    from calibration.kernels import project_extended_unified

    p = np.ascontiguousarray(flat)
    m = model
    return project_extended_unified(p, m.fx, m.fy, m.cx, m.cy, m.alpha, beta, _alpha_w1(m.alpha))


def _eucm_max_off_axis(alpha: float, beta: float) -> float:
    """Angle from the axis where z = -w1 d with d = sqrt(beta (x^2 + y^2) + z^2), radians.

    On a unit ray at angle theta: cos(theta) = -w1 sqrt(beta sin^2 + cos^2), solved for theta.
    """
    w1 = _alpha_w1(alpha)
    if w1 == 0.0:
        return math.pi / 2.0
    # cos^2 = w1^2 (beta (1 - cos^2) + cos^2)  ->  cos^2 = w1^2 beta / (1 - w1^2 + w1^2 beta)
    cos2 = w1 * w1 * beta / (1.0 - w1 * w1 + w1 * w1 * beta)
    return math.acos(-math.sqrt(min(1.0, cos2)))


def _eucm_unproject(mx: F64, my: F64, alpha: float, beta: float) -> tuple[F64, F64, F64, Bool]:
    r2 = mx * mx + my * my
    # alpha <= 0.5: every pixel unprojects; else the image circle r^2 <= 1/(beta (2 alpha - 1)).
    bound = np.inf if alpha <= 0.5 else 1.0 / (beta * (2.0 * alpha - 1.0))
    valid = r2 <= bound
    mz = (1.0 - beta * alpha * alpha * r2) / (
        alpha * np.sqrt(1.0 - (2.0 * alpha - 1.0) * beta * r2) + 1.0 - alpha
    )
    # Pixels on the circle itself unproject to the limit ray, which `_eucm_project` refuses.
    valid &= mz > -_alpha_w1(alpha) * np.sqrt(beta * r2 + mz * mz)
    return mx, my, mz, valid


@dataclass(frozen=True)
class ExtendedUnified(FocalModel):
    """Extended Unified Camera Model (EUCM): alpha in [0, 1], beta > 0."""

    fx: float
    fy: float
    cx: float
    cy: float
    alpha: float
    beta: float
    width: int
    height: int

    FINITE = ("alpha",)
    POSITIVE = ("beta",)

    def _check_params(self) -> None:
        self._require_unit_interval("alpha")

    @property
    def max_off_axis_rad(self) -> float:
        """The angle from the axis where projection stops being valid."""
        return _eucm_max_off_axis(self.alpha, self.beta)

    def _project_fused(self, flat: F64) -> tuple[F64, Bool]:
        return _eucm_fused(self, flat, self.beta)

    def _project_normalised(self, x: F64, y: F64, z: F64) -> tuple[F64, F64, Bool]:
        return _eucm_project(x, y, z, self.alpha, self.beta)

    def _unproject_normalised(self, mx: F64, my: F64) -> tuple[F64, F64, F64, Bool]:
        return _eucm_unproject(mx, my, self.alpha, self.beta)


@dataclass(frozen=True)
class Unified(FocalModel):
    """Unified Camera Model (UCM) in the alpha form: u = fx x / (alpha |p| + (1-alpha) z) + cx.

    Equal to Mei/omni with xi = alpha/(1-alpha) and gamma = f/(1-alpha).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    alpha: float
    width: int
    height: int

    FINITE = ("alpha",)

    def _check_params(self) -> None:
        self._require_unit_interval("alpha")

    @property
    def max_off_axis_rad(self) -> float:
        """As for EUCM: projection stops at z = -w1 |p|."""
        return _eucm_max_off_axis(self.alpha, 1.0)

    def _project_fused(self, flat: F64) -> tuple[F64, Bool]:
        return _eucm_fused(self, flat, 1.0)

    def _project_normalised(self, x: F64, y: F64, z: F64) -> tuple[F64, F64, Bool]:
        return _eucm_project(x, y, z, self.alpha, 1.0)

    def _unproject_normalised(self, mx: F64, my: F64) -> tuple[F64, F64, F64, Bool]:
        return _eucm_unproject(mx, my, self.alpha, 1.0)


@dataclass(frozen=True)
class KannalaBrandt(FocalModel):
    """Kannala-Brandt / equidistant fisheye with four coefficients (OpenCV fisheye).

    theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8) with
    theta the angle from the optical axis. Valid up to `theta_max`, the first
    angle where theta_d stops increasing (or pi), so rays beyond 90 degrees work.
    Kalibr stores this model as ``pinhole`` + ``equidistant``.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    k1: float
    k2: float
    k3: float
    k4: float
    width: int
    height: int

    FINITE = ("k1", "k2", "k3", "k4")

    def _poly(self, theta: F64) -> F64:
        t2 = theta * theta
        return theta * (1.0 + t2 * (self.k1 + t2 * (self.k2 + t2 * (self.k3 + t2 * self.k4))))

    def _dpoly(self, theta: F64) -> F64:
        t2 = theta * theta
        return 1.0 + t2 * (3.0 * self.k1 + t2 * (5.0 * self.k2 + t2 * (7.0 * self.k3 + t2 * 9.0 * self.k4)))

    @cached_property
    def theta_max(self) -> float:
        """Largest valid angle from the axis (radians): where d theta_d/d theta first hits 0."""
        theta = np.linspace(0.0, math.pi, 20001)
        bad = np.nonzero(self._dpoly(theta) <= 0.0)[0]
        if bad.size == 0:
            return math.pi
        lo, hi = float(theta[bad[0] - 1]), float(theta[bad[0]])
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            if self._dpoly(np.array([mid]))[0] > 0.0:
                lo = mid
            else:
                hi = mid
        return lo

    @property
    def max_off_axis_rad(self) -> float:
        """`theta_max`."""
        return self.theta_max

    def _project_normalised(self, x: F64, y: F64, z: F64) -> tuple[F64, F64, Bool]:
        r = np.hypot(x, y)
        theta = np.arctan2(r, z)
        rd = self._poly(theta)
        scale = np.where(r > 0.0, rd / r, 0.0)
        valid = (theta < self.theta_max) & ((r > 0.0) | (z > 0.0))
        return x * scale, y * scale, valid

    def _unproject_normalised(self, mx: F64, my: F64) -> tuple[F64, F64, F64, Bool]:
        rd = np.hypot(mx, my)
        rd_max = float(self._poly(np.array([self.theta_max]))[0])
        valid = rd < rd_max
        # theta_d rises monotonically on [0, theta_max]: Newton's step kept inside a bracket that shrinks
        # every iteration, else the bracket's middle. Plain Newton overshot where the slope nears 0
        # towards theta_max and left rays that `project` accepts invalid (a PADRL camchain: 48-63 deg).
        lo, hi = np.zeros_like(rd), np.full_like(rd, self.theta_max)
        theta = np.minimum(rd, self.theta_max)
        for _ in range(KB_MAX_ITER):
            f = self._poly(theta) - rd
            lo, hi = np.where(f < 0.0, theta, lo), np.where(f > 0.0, theta, hi)
            slope = self._dpoly(theta)
            newton = theta - f / np.where(slope > 0.0, slope, np.inf)
            inside = (newton > lo) & (newton < hi)
            step = np.where(inside, newton, 0.5 * (lo + hi)) - theta
            theta = theta + step
            if np.all(np.abs(step[valid]) < KB_TOL):
                break
        valid &= np.abs(self._poly(theta) - rd) < KB_FIT_TOL * np.maximum(1.0, rd)  # a root, not a stall
        s = np.where(rd > 0.0, np.sin(theta) / rd, 0.0)
        return mx * s, my * s, np.cos(theta), valid
