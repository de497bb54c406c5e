"""Stereo rectification for spherical and pinhole pairs.

Vertical stereo (DESIGN.md section 3): the rectified frame's y axis points
along the baseline from cam0 (upper) to cam1 (lower), its z axis is the mean
optical axis made orthogonal to y, and x = y cross z. In that frame an
`Equirectangular` image has its pole on -y ("up", away from the lower
camera) and columns are epipolar lines.

Horizontal stereo (the benchmark's RIGHT camera): x along the baseline from
the left (reference) to the right camera, z the orthogonalised mean optical
axis, y = z cross x; rows of a pinhole or `Cassini` image are epipolar lines.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.errors import CalibrationError
from calibration.rig import Rig
from calibration.transforms import invert
from calibration.types import F64


@dataclass(frozen=True, eq=False)
class StereoRectification:
    """Rotations from the shared rectified frame into each camera, and the baseline.

    ``R_cam0_rect`` maps rectified vectors into cam0 (reference), ``R_cam1_rect``
    into cam1. ``baseline_m`` is the distance between the camera centres; in
    the rectified frame cam1 sits at ``baseline_m`` along +y (vertical) or +x
    (horizontal) from cam0.
    """

    R_cam0_rect: F64
    R_cam1_rect: F64
    baseline_m: float
    orientation: str


def _unit(v: F64, what: str) -> F64:
    n = float(np.linalg.norm(v))
    if n < 1e-12:
        raise CalibrationError(f"rectification: {what} is degenerate (zero length)")
    out: F64 = v / n
    return out


def rectify_stereo(T_cam1_cam0: F64, orientation: str = "vertical") -> StereoRectification:
    """Rectify a pair given ``T_cam1_cam0`` (p_cam1 = T p_cam0).

    ``orientation`` is ``"vertical"`` (baseline becomes +y) or ``"horizontal"``
    (baseline becomes +x).
    """
    T_cam0_cam1 = invert(T_cam1_cam0)
    R_cam0_cam1 = T_cam0_cam1[:3, :3]
    b = T_cam0_cam1[:3, 3]  # cam1's centre in cam0
    axis = _unit(b, "baseline")
    z_mean = _unit(np.array([0.0, 0.0, 1.0]) + R_cam0_cam1[:, 2], "mean optical axis")
    z = _unit(z_mean - (z_mean @ axis) * axis, "optical axis orthogonal to the baseline")
    if orientation == "vertical":
        y = axis
        x = np.cross(y, z)
    elif orientation == "horizontal":
        x = axis
        y = np.cross(z, x)
    else:
        raise CalibrationError(
            f"rectification: orientation must be 'vertical' or 'horizontal', got {orientation!r}"
        )
    R_cam0_rect = np.column_stack([x, y, z])
    R_cam1_rect = R_cam0_cam1.T @ R_cam0_rect
    return StereoRectification(R_cam0_rect, R_cam1_rect, float(np.linalg.norm(b)), orientation)


MIN_BASELINE_M = 1e-3
MAX_PLAUSIBLE_BASELINE_M = 2.0  # a handheld rig; more is a camchain in millimetres, most likely
MAX_BASELINE_TILT_DEG = 45.0
"""The SensorBox's cameras are stacked: a lower camera whose centre lies further than this from the upper
camera's down axis (y) sits beside it, which is a camchain of another rig or a transposed T_cn_cnm1."""


def _lower_in_upper(rig: Rig) -> tuple[F64, str, str]:
    """The lower camera's centre in the upper camera's frame (m), and both names."""
    ref, oth = rig.upper, rig.lower
    return (ref.T_cam_cam0 @ oth.T_cam0_cam)[:3, 3], ref.name, oth.name


def rectify_rig(rig: Rig, reference: str = "upper", other: str = "lower") -> StereoRectification:
    """Vertical-stereo rectification of a rig's upper/lower pair (upper = reference)."""
    ref, oth = rig.camera(reference), rig.camera(other)
    T_oth_ref = oth.T_cam_cam0 @ ref.T_cam0_cam
    b = invert(T_oth_ref)[:3, 3]
    if (apart_mm := float(np.linalg.norm(b)) * 1e3) < MIN_BASELINE_M * 1e3:
        raise CalibrationError(
            f"{rig.source or rig.name}: cameras {ref.name} and {oth.name} are {apart_mm:.3f} mm apart; "
            f"a stereo pair needs a baseline of at least {MIN_BASELINE_M * 1e3:g} mm: check {oth.name}'s "
            "T_cn_cnm1 in the camchain"
        )
    return rectify_stereo(T_oth_ref, "vertical")


def stereo_warnings(rig: Rig) -> list[str]:
    """What looks wrong in the upper/lower pair's layout, one line each (nothing for a rig without both, or
    whose cameras are no stereo pair: `rectify_rig` refuses that).

    The rectified images point their "up" from the lower camera to the upper:
    a lower camera above the upper one in the upper's frame (y down) turns the
    dataset upside down (roles swapped?); one beside it (`MAX_BASELINE_TILT_DEG`) is
    a camchain of another rig. A baseline over 2 m is most likely
    a camchain in millimetres (Kalibr writes metres).
    """
    try:
        b, up, low = _lower_in_upper(rig)
    except CalibrationError:  # no upper or lower role
        return []
    where = f"{rig.source or rig.name}"
    if float(np.linalg.norm(b)) < MIN_BASELINE_M:  # no pair at all: `rectify_rig` refuses it
        return []
    out = []
    centre = f"its centre at [{b[0]:.4f}, {b[1]:.4f}, {b[2]:.4f}] m in {up}"
    tilt_deg = float(np.degrees(np.arccos(np.clip(b[1] / np.linalg.norm(b), -1.0, 1.0))))
    if MAX_BASELINE_TILT_DEG < tilt_deg < 180.0 - MAX_BASELINE_TILT_DEG:
        out.append(
            f"{where}: the lower camera {low} is beside the upper camera {up}, not below it ({centre}, "
            f"{tilt_deg:.0f} deg from {up}'s y axis, which points down): the SensorBox's cameras are "
            f"stacked; check {low}'s T_cn_cnm1 in the camchain"
        )
    elif b[1] <= 0.0:
        out.append(
            f"{where}: the lower camera {low} is not below the upper camera {up} ({centre}, whose y points "
            "down): rectified images and GT will be upside down unless both cameras are mounted upside "
            "down; are the roles swapped?"
        )
    if np.linalg.norm(b) > MAX_PLAUSIBLE_BASELINE_M:
        out.append(
            f"{where}: stereo baseline {np.linalg.norm(b):.3f} m; is the camchain in millimetres? "
            "(Kalibr writes metres)"
        )
    return out
