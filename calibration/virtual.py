"""Virtual cameras for the benchmark: DS fisheyes by the FOV laws, view poses, crops.

FOV laws (DESIGN.md section 3): from a reference Double Sphere calibration
(f, xi, alpha), a fisheye of nominal field of view FOV (degrees) has

    f(FOV)     = f * n * 180 / FOV
    xi(FOV)    = xi * (1 - m * FOV / 180)
    alpha(FOV) = alpha + m * (1 - alpha) * FOV / 180,     m = 0.2, n = 1.25

The laws do not hit the nominal FOV exactly (it is a family of lenses, not a
fit), so `virtual_fisheye` also reports the true FOV found by unprojecting the
image border (`calibration.camera.field_of_view`). Focal lengths are first
scaled from the reference image width to the virtual one, so the law means the
same lens at any resolution; the principal point is the image centre.

View poses: a "level" camera looks along a yaw angle in a z-up frame (a
levelled terrestrial scan: x forward, y left, z up); its optical axis is
tilted by the pitch (positive looks up). Stereo partners share the reference
camera's orientation and sit `baseline_m` along its +y (DOWN, the vertical
pair) or +x (RIGHT, the horizontal pair), so rectification is the identity.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from calibration.camera import CameraModel, FieldOfView, field_of_view
from calibration.errors import CalibrationError
from calibration.fisheye import DoubleSphere
from calibration.types import F32, F64, Bool

FOV_M = 0.2
"""m of the FOV laws (xi and alpha)."""
FOV_N = 1.25
"""n of the FOV laws (focal length)."""
PARTNERS = {"DOWN": np.array([0.0, 1.0, 0.0]), "RIGHT": np.array([1.0, 0.0, 0.0])}
"""Unit offset of each stereo partner from the reference camera, in the reference camera frame."""


def virtual_ds(reference: DoubleSphere, fov_deg: float, width: int, height: int) -> DoubleSphere:
    """The DS fisheye of nominal ``fov_deg`` degrees on a ``width`` x ``height`` image (FOV laws)."""
    if not (isinstance(fov_deg, int | float) and 0.0 < fov_deg < 360.0):
        raise CalibrationError(f"virtual_ds: FOV must be in (0, 360) degrees, got {fov_deg!r}")
    s = fov_deg / 180.0
    scale = (width / reference.width) * FOV_N / s
    # alpha stays in [alpha, alpha + 2 m (1 - alpha)) inside [0, 1) for every FOV below 360
    alpha = reference.alpha + FOV_M * (1.0 - reference.alpha) * s
    return DoubleSphere(
        fx=reference.fx * scale,
        fy=reference.fy * scale,
        cx=(width - 1) / 2.0,
        cy=(height - 1) / 2.0,
        xi=reference.xi * (1.0 - FOV_M * s),
        alpha=alpha,
        width=width,
        height=height,
    )


@dataclass(frozen=True)
class VirtualFisheye:
    """A virtual fisheye: its nominal FOV (degrees), DS model and true FOV (radians)."""

    nominal_fov_deg: float
    model: DoubleSphere
    fov: FieldOfView

    def report(self) -> dict[str, Any]:
        """Plain dict for scene files: nominal and true FOVs in degrees plus the DS parameters."""
        return {
            "nominal_fov_deg": self.nominal_fov_deg,
            "true_fov_deg": {
                "horizontal": round(math.degrees(self.fov.horizontal_rad), 4),
                "vertical": round(math.degrees(self.fov.vertical_rad), 4),
                "diagonal": round(math.degrees(self.fov.diagonal_rad), 4),
            },
            "model": "ds",
            **{k: float(v) if isinstance(v, float) else v for k, v in self.model.params().items()},
        }


def virtual_fisheye(reference: DoubleSphere, fov_deg: float, width: int, height: int) -> VirtualFisheye:
    """`virtual_ds` plus its true FOV measured by unprojecting the image border."""
    model = virtual_ds(reference, fov_deg, width, height)
    return VirtualFisheye(float(fov_deg), model, field_of_view(model))


def R_up_cam(yaw_rad: float, pitch_rad: float = 0.0) -> F64:
    """Rotation of a level camera (x right, y down, z forward) into a z-up frame (x fwd, y left, z up).

    Yaw turns the optical axis from +x towards +y (counter-clockwise seen from
    above); pitch > 0 tilts it up.
    """
    cy, sy, cp, sp = math.cos(yaw_rad), math.sin(yaw_rad), math.cos(pitch_rad), math.sin(pitch_rad)
    forward = np.array([cp * cy, cp * sy, sp])
    right = np.array([sy, -cy, 0.0])
    down = np.cross(forward, right)
    return np.column_stack([right, down, forward])


def partner_pose(T_world_ref: F64, partner: str, baseline_m: float) -> F64:
    """Pose of the stereo partner ``DOWN`` or ``RIGHT`` at ``baseline_m`` from the reference camera."""
    if partner not in PARTNERS:
        raise CalibrationError(f"partner_pose: partner must be one of {sorted(PARTNERS)}, got {partner!r}")
    T_ref_partner = np.eye(4)
    T_ref_partner[:3, 3] = PARTNERS[partner] * baseline_m
    out: F64 = np.asarray(T_world_ref, np.float64) @ T_ref_partner
    return out


@dataclass(frozen=True)
class CroppedModel(CameraModel):
    """A window of another camera model's image: pixel (i, j) here is (i + col_offset, j + row_offset) there.

    Used for crops of models that have no crop of their own (pinhole crops,
    a Cassini window around what a fisheye sees). Validity is the base model's.
    """

    base: CameraModel
    col_offset: int
    row_offset: int
    width: int
    height: int

    def __post_init__(self) -> None:
        b = self.base
        if not (
            self.col_offset >= 0
            and self.row_offset >= 0
            and self.width > 0
            and self.height > 0
            and self.col_offset + self.width <= b.width
            and self.row_offset + self.height <= b.height
        ):
            raise CalibrationError(
                f"CroppedModel: window cols {self.col_offset}..{self.col_offset + self.width}, rows "
                f"{self.row_offset}..{self.row_offset + self.height} does not fit in {b.width}x{b.height}"
            )

    def _project(self, x: F64, y: F64, z: F64) -> tuple[F64, F64, Bool]:
        u, v, ok = self.base._project(x, y, z)
        return u - self.col_offset, v - self.row_offset, ok

    def _unproject(self, u: F64, v: F64) -> tuple[F64, F64, F64, Bool]:
        return self.base._unproject(u + self.col_offset, v + self.row_offset)

    @property
    def max_off_axis_rad(self) -> float:
        """The base model's."""
        return self.base.max_off_axis_rad

    def _scaled_params(self, factor: float) -> dict[str, Any]:
        raise CalibrationError("CroppedModel: scale the base model and crop again instead")


def crop_bounds(mask: Bool, margin_px: int = 1) -> tuple[int, int, int, int]:
    """(col_offset, row_offset, width, height) of the bounding box of ``mask`` plus a margin."""
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        raise CalibrationError("crop_bounds: the mask is empty")
    r0, r1 = max(0, int(rows[0]) - margin_px), min(mask.shape[0], int(rows[-1]) + 1 + margin_px)
    c0, c1 = max(0, int(cols[0]) - margin_px), min(mask.shape[1], int(cols[-1]) + 1 + margin_px)
    return c0, r0, c1 - c0, r1 - r0


def project_f32(model: CameraModel, x: F32, y: F32, z: F32) -> tuple[F32, F32, Bool]:
    """Project flat float32 coordinates with ``model``'s formulas in float32 (renderer hot path).

    `CameraModel.project` works in float64 with NaN filling; a renderer that
    projects millions of points per view needs neither (float32 keeps 1e-4 px
    at 4000 px). Invalid entries carry arbitrary values: use the mask.
    """
    with np.errstate(all="ignore"):
        # the models' formulas are dtype-generic numpy: float32 in, float32 out
        u, v, ok = model._project(x, y, z)  # type: ignore[arg-type]
        ok = ok & np.isfinite(u) & np.isfinite(v)
    return np.asarray(u, np.float32), np.asarray(v, np.float32), ok
