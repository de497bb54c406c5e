"""The camera-model contract shared by every projection.

A camera model maps 3D points in its own frame (x right, y down, z forward,
metres) to continuous pixel coordinates (the centre of pixel (col i, row j) is
(i, j)) and back to unit rays. Every call returns a validity mask next to the
values; entries that are not valid are NaN, so an invalid entry can never pass
for a real pixel or ray. Model validity (the maths is defined and invertible
there) is separate from image bounds (`CameraModel.in_image`).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, fields, replace
from typing import Any, ClassVar, Self

import numpy as np

from calibration.errors import CalibrationError
from calibration.types import F64, ArrayLike, Bool


def _check_shape(arr: F64, last: int, what: str) -> None:
    if arr.ndim == 0 or arr.shape[-1] != last:
        raise ValueError(f"{what}: expected an array of shape (..., {last}), got {arr.shape}")


class CameraModel(ABC):
    """Abstract camera model; concrete models are frozen dataclasses.

    Subclasses implement `_project` and `_unproject` on flat float64 arrays;
    this base handles shapes, NaN-filling of invalid entries and ray
    normalisation. Being frozen dataclasses, models are hashable by value and
    serve as cache keys (e.g. for warp maps).
    """

    width: int
    height: int

    # -- subclass hooks -------------------------------------------------
    @abstractmethod
    def _project(self, x: F64, y: F64, z: F64) -> tuple[F64, F64, Bool]:
        """Project flat coordinate arrays; return (u, v, valid)."""

    @abstractmethod
    def _unproject(self, u: F64, v: F64) -> tuple[F64, F64, F64, Bool]:
        """Unproject flat pixel arrays; return (x, y, z, valid), not necessarily unit."""

    @abstractmethod
    def _scaled_params(self, factor: float) -> dict[str, Any]:
        """Parameters that change when the image is resized by ``factor``.

        ``width``/``height`` may be included; otherwise they are the rounded scaled size.
        """

    # -- public contract -------------------------------------------------
    def project(self, points: ArrayLike) -> tuple[F64, Bool]:
        """Project points of shape (..., 3) in metres to pixels (..., 2).

        Returns ``(uv, valid)``; ``valid`` is the model's validity (not image
        bounds) and invalid ``uv`` entries are NaN.
        """
        P = np.asarray(points, dtype=np.float64)
        _check_shape(P, 3, f"{type(self).__name__}.project")
        from calibration.kernels import finish_projection  # numba: loaded with the first projection

        flat = P.reshape(-1, 3)
        fused = self._project_fused(flat)
        if fused is not None:
            uv, valid = fused
        else:
            x, y, z = flat[:, 0], flat[:, 1], flat[:, 2]
            with np.errstate(all="ignore"):
                u, v, valid = self._project(x, y, z)
            uv, valid = finish_projection(u, v, valid, x, y, z)
        return uv.reshape(*P.shape[:-1], 2), valid.reshape(P.shape[:-1])

    def _project_fused(self, flat: F64) -> tuple[F64, Bool] | None:
        """`project` of (N, 3) points as one compiled pass, where the model has one (else None).

        The closed-form models have one: it computes the same formula as
        `_project` point by point, without the numpy temporaries.
        """
        return None

    def unproject(self, pixels: ArrayLike) -> tuple[F64, Bool]:
        """Unproject pixels of shape (..., 2) to unit rays (..., 3).

        Returns ``(rays, valid)``; invalid rays are NaN. A ray times the range
        gives the 3D point (range, not z depth).
        """
        uv = np.asarray(pixels, dtype=np.float64)
        _check_shape(uv, 2, f"{type(self).__name__}.unproject")
        flat = uv.reshape(-1, 2)
        fused = self._unproject_fused(flat)
        if fused is not None:
            rays, valid = fused
        else:
            rays, valid = self._unproject_numpy(flat)
        return rays.reshape(*uv.shape[:-1], 3), valid.reshape(uv.shape[:-1])

    def _unproject_numpy(self, flat: F64) -> tuple[F64, Bool]:
        """`unproject` of (N, 2) pixels with the model's numpy formula (`_unproject`)."""
        with np.errstate(all="ignore"):
            x, y, z, valid = self._unproject(flat[:, 0], flat[:, 1])
            norm = np.sqrt(x * x + y * y + z * z)
            rays = np.stack([x / norm, y / norm, z / norm], axis=-1)
            valid = valid & np.all(np.isfinite(rays), axis=1) & (norm > 0.0)
        rays[~valid] = np.nan
        return rays, valid

    def _unproject_fused(self, flat: F64) -> tuple[F64, Bool] | None:
        """`unproject` of (N, 2) pixels as one compiled pass, where the model has one (else None)."""
        return None

    def in_image(self, pixels: ArrayLike) -> Bool:
        """Mask of pixels inside the image: u in [-0.5, W - 0.5), v in [-0.5, H - 0.5)."""
        uv = np.asarray(pixels, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            return (
                (uv[..., 0] >= -0.5)
                & (uv[..., 0] < self.width - 0.5)
                & (uv[..., 1] >= -0.5)
                & (uv[..., 1] < self.height - 0.5)
            )

    def scaled(self, factor: float) -> Self:
        """The same lens on an image resized by ``factor`` (e.g. 0.5 for half size).

        Focal lengths scale by ``factor``; the principal point follows the
        pixel-centre convention, ``c' = (c + 0.5) * factor - 0.5``; the size is
        rounded to whole pixels.
        """
        if not (math.isfinite(factor) and factor > 0.0):
            raise ValueError(f"scale factor must be a positive number, got {factor!r}")
        params = self._scaled_params(factor)
        # Models whose size follows from other parameters (spherical images) set it themselves.
        params.setdefault("width", max(1, round(self.width * factor)))
        params.setdefault("height", max(1, round(self.height * factor)))
        return replace(self, **params)  # type: ignore[type-var]

    def pixel_grid(self, row0: int = 0, row1: int | None = None) -> F64:
        """Pixel centres of rows [row0, row1) (default: the whole image), shape (rows, W, 2) as (u, v)."""
        rows = np.arange(row0, self.height if row1 is None else min(row1, self.height), dtype=np.float64)
        u, v = np.meshgrid(np.arange(self.width, dtype=np.float64), rows)
        return np.stack([u, v], axis=-1)

    @property
    def max_off_axis_rad(self) -> float:
        """Largest angle from the optical axis (+z) the model can project, radians.

        Rays at or beyond it are refused by `project`, so no true field of view
        can exceed twice this angle. pi for models without such a limit.
        """
        return math.pi

    def params(self) -> dict[str, Any]:
        """All parameters as a plain dict (for reports and serialisation)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}  # type: ignore[arg-type]


@dataclass(frozen=True)
class FieldOfView:
    """True field of view found by unprojecting the image border (radians).

    Each value is the sum of the largest off-axis angles on the two sides of
    the principal point along the central row (horizontal), central column
    (vertical) and the image diagonals (diagonal), so it exceeds pi for lenses
    that see behind the image plane. ``limit_rad`` is the model's own bound,
    twice `CameraModel.max_off_axis_rad`; none of the three exceeds it.
    """

    horizontal_rad: float
    vertical_rad: float
    diagonal_rad: float
    limit_rad: float


def _off_axis(rays: F64) -> F64:
    return np.arctan2(np.hypot(rays[..., 0], rays[..., 1]), rays[..., 2])


ROUND_TRIP_TOL_PX = 1e-3
"""How far project(unproject(uv)) may land from uv for a pixel to count as seeing its ray."""


def round_trip_rays(model: CameraModel, pixels: ArrayLike) -> tuple[F64, Bool]:
    """Unproject ``pixels`` (..., 2) and keep only rays that project back onto their pixel.

    The models' own validity already guarantees this; the FOV report checks it
    again so that it can never count a ray the model would refuse to project.
    """
    uv = np.asarray(pixels, dtype=np.float64)
    rays, valid = model.unproject(uv)
    back, back_ok = model.project(np.where(valid[..., None], rays, 0.0))
    miss_px = np.hypot(back[..., 0] - uv[..., 0], back[..., 1] - uv[..., 1])
    with np.errstate(invalid="ignore"):
        valid &= back_ok & (miss_px < ROUND_TRIP_TOL_PX)
    return rays, valid


def _max_angle_along(model: CameraModel, start: F64, end: F64, samples: int) -> float:
    """Largest off-axis angle of valid rays on the segment start->end.

    Where validity ends inside the segment (an image circle smaller than the
    sensor), the boundary is refined by bisection: the angle grows steeply
    there, so a sampled value would understate the FOV by a degree or more.
    """
    t = np.linspace(0.0, 1.0, samples)
    rays, valid = round_trip_rays(model, start[None, :] * (1.0 - t[:, None]) + end[None, :] * t[:, None])
    if not np.any(valid):
        return 0.0
    best = float(np.max(_off_axis(rays[valid])))
    last = int(np.nonzero(valid)[0][-1])
    if last + 1 < samples and not valid[last + 1]:
        lo, hi = float(t[last]), float(t[last + 1])
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            ray, ok = round_trip_rays(model, start * (1.0 - mid) + end * mid)
            if ok:
                lo = mid
                best = max(best, float(_off_axis(ray)))
            else:
                hi = mid
    return best


def field_of_view(model: CameraModel, samples: int = 4001) -> FieldOfView:
    """Measure the true FOV of ``model`` by unprojecting its image border.

    Lines run from the principal point (``cx``, ``cy``; the image centre for
    models without one) to the outer edge of the image (-0.5 and W - 0.5);
    where the model stops being valid before the border, the last valid ray
    along the line counts.
    """
    cx = float(getattr(model, "cx", (model.width - 1) / 2.0))
    cy = float(getattr(model, "cy", (model.height - 1) / 2.0))
    c = np.array([cx, cy])
    left, right = np.array([-0.5, cy]), np.array([model.width - 0.5, cy])
    top, bottom = np.array([cx, -0.5]), np.array([cx, model.height - 0.5])
    corners = [
        np.array([-0.5, -0.5]),
        np.array([model.width - 0.5, model.height - 0.5]),
        np.array([model.width - 0.5, -0.5]),
        np.array([-0.5, model.height - 0.5]),
    ]

    def side(end: F64) -> float:
        return _max_angle_along(model, c, end, samples)

    diag = max(side(corners[0]) + side(corners[1]), side(corners[2]) + side(corners[3]))
    return FieldOfView(side(left) + side(right), side(top) + side(bottom), diag, 2.0 * model.max_off_axis_rad)


def require_positive(name: str, value: float, model: str) -> None:
    """Raise `CalibrationError` unless ``value`` is a finite number > 0."""
    if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
        raise CalibrationError(f"{model}: {name} must be a finite number > 0, got {value!r}")


def require_finite(name: str, value: float, model: str) -> None:
    """Raise `CalibrationError` unless ``value`` is a finite number."""
    if not (isinstance(value, int | float) and math.isfinite(value)):
        raise CalibrationError(f"{model}: {name} must be a finite number, got {value!r}")


FOCAL_PER_SIDE_RANGE = (1e-3, 1e3)
"""Bounds on a focal length in pixels over the image side it spans (fx / width, fy / height).

A pinhole with f = 1e3 sides sees 2 atan(1 / 2e3) = 0.03 deg across the image, a telescope
rather than a lens; one with f = 1e-3 sides sees 179.9 deg, and a fisheye's f is about 0.3
sides. Beyond these a camera covers no useful field of view: fu = 1e300 passed as an HFOV of
0.0 deg and ingest then failed sizing an occlusion grid."""


def require_focal(name: str, value: float, side_px: int, model: str) -> None:
    """Raise `CalibrationError` unless ``value`` (pixels) is a finite focal length within
    `FOCAL_PER_SIDE_RANGE` times ``side_px``, the image side it spans."""
    require_positive(name, value, model)
    low, high = (k * side_px for k in FOCAL_PER_SIDE_RANGE)
    if not low <= value <= high:
        raise CalibrationError(
            f"{model}: {name} must be within {low:g}..{high:g} px ({FOCAL_PER_SIDE_RANGE[0]:g}.."
            f"{FOCAL_PER_SIDE_RANGE[1]:g} times the image's {side_px} px) for a useful field of view, "
            f"got {value!r}"
        )


PIXEL_ASPECT_RANGE = (0.5, 2.0)
"""Bounds on fx / fy, a pixel's height over its width. A camera's pixels are square within a few per cent
(a fitted fisheye: 500.23 / 500.07); 2 is a sensor read out with 2x1 binning. fy = 10 fx passed as a camera
with a VFOV of 11 deg, whose GT landed 0.7 deg off the images."""


def require_pixel_aspect(fx: float, fy: float, model: str) -> None:
    """Raise `CalibrationError` unless fx / fy lies within `PIXEL_ASPECT_RANGE`."""
    low, high = PIXEL_ASPECT_RANGE
    if not low <= fx / fy <= high:
        raise CalibrationError(
            f"{model}: fx / fy = {fx / fy:.3g} (fx {fx!r}, fy {fy!r}): expected {low:g}..{high:g}, as a "
            "camera's pixels are square within a few per cent (fx or fy mistyped?)"
        )


def require_size(width: int, height: int, model: str) -> None:
    """Raise `CalibrationError` unless width and height are positive integers."""
    for name, value in (("width", width), ("height", height)):
        if isinstance(value, bool) or not isinstance(value, int | np.integer) or value <= 0:
            raise CalibrationError(f"{model}: {name} must be a positive integer, got {value!r}")


class FocalModel(CameraModel):
    """A model whose pixels are an affine map of normalised coordinates.

    ``u = fx * mx + cx``, ``v = fy * my + cy``: subclasses implement the lens
    part (`_project_normalised`, `_unproject_normalised`) and list the
    parameters that must be finite (`FINITE`) or positive (`POSITIVE`);
    `_check_params` adds any range a model needs beyond that.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    FINITE: ClassVar[tuple[str, ...]] = ()
    POSITIVE: ClassVar[tuple[str, ...]] = ()

    def __post_init__(self) -> None:
        name = type(self).__name__
        require_size(self.width, self.height, name)
        require_focal("fx", self.fx, self.width, name)
        require_focal("fy", self.fy, self.height, name)
        require_pixel_aspect(self.fx, self.fy, name)
        for key in ("cx", "cy"):
            require_finite(key, getattr(self, key), name)
        for key in self.FINITE:
            require_finite(key, getattr(self, key), name)
        for key in self.POSITIVE:
            require_positive(key, getattr(self, key), name)
        self._check_params()

    def _check_params(self) -> None:
        """Model-specific parameter ranges; raise `CalibrationError`."""

    def _require_unit_interval(self, key: str) -> None:
        value = getattr(self, key)
        if not 0.0 <= value < 1.0:
            raise CalibrationError(f"{type(self).__name__}: {key} must be in [0, 1), got {value!r}")

    @abstractmethod
    def _project_normalised(self, x: F64, y: F64, z: F64) -> tuple[F64, F64, Bool]:
        """Points to normalised image coordinates (mx, my) and validity."""

    @abstractmethod
    def _unproject_normalised(self, mx: F64, my: F64) -> tuple[F64, F64, F64, Bool]:
        """Normalised image coordinates to (x, y, z) rays, not necessarily unit, and validity."""

    def _project(self, x: F64, y: F64, z: F64) -> tuple[F64, F64, Bool]:
        mx, my, valid = self._project_normalised(x, y, z)
        u = mx * self.fx  # the model's own fresh arrays: scaled and shifted in place, one temporary each
        u += self.cx
        v = my * self.fy
        v += self.cy
        return u, v, valid

    def _unproject(self, u: F64, v: F64) -> tuple[F64, F64, F64, Bool]:
        return self._unproject_normalised((u - self.cx) / self.fx, (v - self.cy) / self.fy)

    def _scaled_params(self, factor: float) -> dict[str, Any]:
        """fx, fy, cx, cy on an image resized by ``factor`` (pixel-centre convention)."""
        return {
            "fx": self.fx * factor,
            "fy": self.fy * factor,
            "cx": (self.cx + 0.5) * factor - 0.5,
            "cy": (self.cy + 0.5) * factor - 0.5,
        }
