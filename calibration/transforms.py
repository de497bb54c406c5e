"""Rigid transforms: validation, inversion and Euler-angle conventions.

`T_a_b` is a 4x4 float64 matrix mapping points in frame b to frame a:
``p_a = T_a_b @ p_b``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence

import numpy as np

from calibration.errors import CalibrationError
from calibration.types import F64

log = logging.getLogger(__name__)

# A rotation printed to 6 decimals (C++ streams' default precision, many tools' output) is off
# orthonormal by up to about 3e-6 and is used as written (1e-5 rad is 0.1 mm at 10 m). Published
# extrinsics with 5 or 4 decimals (KAIST's camchain: 2.1e-5) are off by up to about 3e-4: those are
# replaced by their nearest rotation, with a warning. Beyond 1e-3 the matrix is no printed rotation.
ORTHONORMAL_TOL = 1e-5
"""Largest |R^T R - I| entry of a rotation read from a file that is used as written."""
ROUNDED_TOL = 1e-3
"""Largest |R^T R - I| entry of a rotation read from a file that is taken as a rounded one (and
re-orthonormalised); beyond it the matrix is refused."""


def as_transform(value: object, what: str) -> F64:
    """Validate ``value`` as a 4x4 rigid transform and return it as float64.

    ``value`` is four rows of four numbers, or 16 numbers in row-major order
    (as OpenCV and several calibration tools write them). ``what`` names the
    source (file, camera, key) for the error message. Raises `CalibrationError`
    if the shape is neither, an entry is not a finite number, the bottom row is
    not [0, 0, 0, 1], or the rotation block is no rotation (determinant -1, or off
    orthonormal by more than `ROUNDED_TOL`). A rotation off by more than
    `ORTHONORMAL_TOL` (printed with 4 or 5 decimals) is replaced by its nearest
    rotation, with a logged warning naming `what`.
    """
    try:
        T = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise CalibrationError(f"{what}: expected a 4x4 list of numbers, got {value!r}") from err
    flat = T.shape == (16,)
    if flat:
        T = T.reshape(4, 4)
    if T.shape != (4, 4):
        raise CalibrationError(
            f"{what}: expected a 4x4 matrix (or 16 numbers, row-major), got shape {T.shape}"
        )
    if not np.all(np.isfinite(T)):
        raise CalibrationError(f"{what}: matrix has non-finite entries")
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-12, rtol=0.0):
        hint = ""
        if flat and np.allclose(T[:, 3], [0.0, 0.0, 0.0, 1.0], atol=1e-12, rtol=0.0):
            hint = " (these 16 numbers look column-major; expected row-major)"
        raise CalibrationError(f"{what}: bottom row must be [0, 0, 0, 1], got {T[3].tolist()}{hint}")
    R = T[:3, :3]
    ortho_err = float(np.max(np.abs(R.T @ R - np.eye(3))))
    if ortho_err > ROUNDED_TOL:
        raise CalibrationError(
            f"{what}: rotation is not orthonormal (max |R^T R - I| = {ortho_err:.2e}, "
            f"expected <= {ROUNDED_TOL:.0e})"
        )
    if np.linalg.det(R) < 0.0:
        raise CalibrationError(f"{what}: rotation has determinant -1 (a reflection)")
    if ortho_err > ORTHONORMAL_TOL:  # printed with few decimals: its nearest rotation
        U, _, Vt = np.linalg.svd(R)
        nearest = U @ Vt
        moved = float(np.max(np.abs(nearest - R)))
        log.warning(
            "%s: rotation off orthonormal by %.1e (printed with few decimals?); its nearest rotation is "
            "used (entries moved by up to %.1e)", what, ortho_err, moved,
        )  # fmt: skip
        T = T.copy()
        T[:3, :3] = nearest
    return T


def invert(T_a_b: F64) -> F64:
    """Return ``T_b_a`` for a rigid transform ``T_a_b``."""
    R = T_a_b[:3, :3]
    T_b_a = np.eye(4)
    T_b_a[:3, :3] = R.T
    T_b_a[:3, 3] = -R.T @ T_a_b[:3, 3]
    return T_b_a


def make_transform(R: F64 | Sequence[Sequence[float]], t: F64 | Sequence[float]) -> F64:
    """Assemble a 4x4 transform from a 3x3 rotation and a translation (metres)."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=np.float64)
    T[:3, 3] = np.asarray(t, dtype=np.float64)
    return T


def rot_x(angle_rad: float) -> F64:
    """Rotation about x by ``angle_rad`` (right-handed)."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(angle_rad: float) -> F64:
    """Rotation about y by ``angle_rad`` (right-handed)."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle_rad: float) -> F64:
    """Rotation about z by ``angle_rad`` (right-handed)."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rodrigues(rotvec: F64 | Sequence[float]) -> F64:
    """Rotation matrix of a rotation vector (axis * angle in radians)."""
    w = np.asarray(rotvec, dtype=np.float64)
    angle = float(np.linalg.norm(w))
    if angle < 1e-15:
        return np.eye(3)
    k = w / angle
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    R: F64 = np.eye(3) + math.sin(angle) * K + (1.0 - math.cos(angle)) * (K @ K)
    return R


def livox_extrinsic_to_transform(
    roll_deg: float, pitch_deg: float, yaw_deg: float, x_mm: float, y_mm: float, z_mm: float
) -> F64:
    """Transform of a livox_ros_driver2 ``extrinsic_parameter`` block.

    The driver applies ``p' = R p + t`` with ``R = Rz(yaw) Ry(pitch) Rx(roll)``,
    angles in degrees and ``t`` in millimetres; the result is returned in metres.
    """
    R = rot_z(math.radians(yaw_deg)) @ rot_y(math.radians(pitch_deg)) @ rot_x(math.radians(roll_deg))
    return make_transform(R, np.array([x_mm, y_mm, z_mm], dtype=np.float64) / 1000.0)
