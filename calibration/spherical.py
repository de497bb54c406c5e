"""Spherical target projections with the camera-model contract.

- `Equirectangular`: latitude/longitude image of the full sphere (H_full x
  2 H_full, pixel pitch pi/H_full) or a crop of it that keeps the full-sphere
  pitch. Row j is at latitude theta = (j + 0.5) pi / H_full measured from the
  pole (-y, "up"), column i at longitude phi = (i + 0.5) pi / H_full - pi
  measured from +z towards +x, so a ray is
  (sin theta sin phi, -cos theta, sin theta cos phi). With a vertical stereo
  baseline along +y, columns are epipolar lines. ``pole_axis="x"`` puts the
  pole on -x instead (the same image for a baseline along x).
- `Cassini`: the transverse equirectangular image (pole on the x axis) whose
  rows are epipolar lines for a horizontal baseline.
- `Cubemap`: six 90-degree pinhole faces in one strip image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np

from calibration.camera import CameraModel
from calibration.errors import CalibrationError
from calibration.pinhole import Pinhole
from calibration.types import F64, Bool

# Rotation taking the standard (pole -y) frame to the pole-on-x frame: -y -> -x, +z -> +z.
_R_POLE = {
    "y": np.eye(3),
    "x": np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
}


@dataclass(frozen=True)
class Equirectangular(CameraModel):
    """Equirectangular image of the sphere, full or cropped (the pitch is always pi/H_full).

    ``height_full`` is H_full, the row count of the full sphere; ``row_offset``
    and ``col_offset`` place this image inside the full one (pixel (i, j) here
    is pixel (i + col_offset, j + row_offset) of the full sphere). ``width``
    and ``height`` of 0 mean "the full sphere": 2 H_full x H_full.
    """

    height_full: int
    width: int = 0
    height: int = 0
    row_offset: int = 0
    col_offset: int = 0
    pole_axis: str = "y"

    def __post_init__(self) -> None:
        if not isinstance(self.height_full, int) or self.height_full <= 0:
            raise CalibrationError(
                f"Equirectangular: height_full must be a positive integer, got {self.height_full!r}"
            )
        if self.width == 0 and self.height == 0:
            object.__setattr__(self, "width", 2 * self.height_full)
            object.__setattr__(self, "height", self.height_full)
        if self.pole_axis not in _R_POLE:
            raise CalibrationError(f"Equirectangular: pole_axis must be 'y' or 'x', got {self.pole_axis!r}")
        if not (
            self.row_offset >= 0
            and self.row_offset + self.height <= self.height_full
            and self.col_offset >= 0
            and self.col_offset + self.width <= 2 * self.height_full
            and self.width > 0
            and self.height > 0
        ):
            raise CalibrationError(
                f"Equirectangular: crop rows {self.row_offset}..{self.row_offset + self.height}, "
                f"cols {self.col_offset}..{self.col_offset + self.width} do not fit in the full "
                f"sphere {self.height_full}x{2 * self.height_full}"
            )

    @property
    def pitch_rad(self) -> float:
        """Angle per pixel, pi / H_full."""
        return math.pi / self.height_full

    @property
    def is_full(self) -> bool:
        """True when this image is the whole sphere."""
        return (self.width, self.height) == (2 * self.height_full, self.height_full)

    def crop(self, row_offset: int, col_offset: int, height: int, width: int) -> Equirectangular:
        """A crop of the full sphere with the same pitch and pole axis."""
        return Equirectangular(self.height_full, width, height, row_offset, col_offset, self.pole_axis)

    def full(self) -> Equirectangular:
        """The full sphere this image is (a crop of)."""
        return Equirectangular(self.height_full, pole_axis=self.pole_axis)

    def theta_of_row(self, rows: F64) -> F64:
        """Latitude from the pole (radians) of row indices of this image."""
        return (np.asarray(rows, dtype=np.float64) + self.row_offset + 0.5) * self.pitch_rad

    def phi_of_col(self, cols: F64) -> F64:
        """Longitude (radians, from +z towards +x) of column indices of this image."""
        return (np.asarray(cols, dtype=np.float64) + self.col_offset + 0.5) * self.pitch_rad - math.pi

    def _project_fused(self, flat: F64) -> tuple[F64, Bool]:
        from calibration.kernels import project_equirect

        u0, v0 = 0.5 + self.col_offset, 0.5 + self.row_offset
        return project_equirect(np.ascontiguousarray(flat), _R_POLE[self.pole_axis], self.pitch_rad, u0, v0)

    def _project(self, x: F64, y: F64, z: F64) -> tuple[F64, F64, Bool]:
        if self.pole_axis != "y":
            R = _R_POLE[self.pole_axis]  # model frame -> standard frame is R^T
            x, y, z = (R[0, 0] * x + R[1, 0] * y + R[2, 0] * z, R[0, 1] * x + R[1, 1] * y + R[2, 1] * z,
                       R[0, 2] * x + R[1, 2] * y + R[2, 2] * z)  # fmt: skip
        theta = np.arctan2(np.hypot(x, z), -y)
        phi = np.arctan2(x, z)
        u = (phi + math.pi) / self.pitch_rad - 0.5 - self.col_offset
        v = theta / self.pitch_rad - 0.5 - self.row_offset
        return u, v, (x * x + y * y + z * z) > 0.0

    def _unproject(self, u: F64, v: F64) -> tuple[F64, F64, F64, Bool]:
        theta = self.theta_of_row(v)
        phi = self.phi_of_col(u)
        st = np.sin(theta)
        x, y, z = st * np.sin(phi), -np.cos(theta), st * np.cos(phi)
        if self.pole_axis != "y":
            R = _R_POLE[self.pole_axis]
            x, y, z = (R[0, 0] * x + R[0, 1] * y + R[0, 2] * z, R[1, 0] * x + R[1, 1] * y + R[1, 2] * z,
                       R[2, 0] * x + R[2, 1] * y + R[2, 2] * z)  # fmt: skip
        valid = (theta >= 0.0) & (theta <= math.pi) & (np.abs(phi) <= math.pi)
        return x, y, z, valid

    def _scaled_params(self, factor: float) -> dict[str, Any]:
        hf = max(1, round(self.height_full * factor))
        if self.is_full:
            return {"height_full": hf, "width": 2 * hf, "height": hf}
        row, col = round(self.row_offset * factor), round(self.col_offset * factor)
        return {
            "height_full": hf,
            "row_offset": row,
            "col_offset": col,
            "height": max(1, min(round(self.height * factor), hf - row)),
            "width": max(1, min(round(self.width * factor), 2 * hf - col)),
        }


@dataclass(frozen=True)
class Cassini(CameraModel):
    """Cassini (transverse equirectangular) image, pole on the x axis.

    Column i is at alpha = (i + 0.5) pi/H_full - pi/2 (angle out of the y-z
    plane, towards +x); row j at beta = (j + 0.5) pi/H_full - pi (rotation
    about x, from +z towards +y); ray = (sin a, cos a sin b, cos a cos b).
    The full image is H_full wide and 2 H_full high; rows are epipolar lines
    for a baseline along x.
    """

    height_full: int
    width: int = 0
    height: int = 0

    def __post_init__(self) -> None:
        if not isinstance(self.height_full, int) or self.height_full <= 0:
            raise CalibrationError(
                f"Cassini: height_full must be a positive integer, got {self.height_full!r}"
            )
        if self.width == 0 and self.height == 0:
            object.__setattr__(self, "width", self.height_full)
            object.__setattr__(self, "height", 2 * self.height_full)

    @property
    def pitch_rad(self) -> float:
        """Angle per pixel, pi / H_full."""
        return math.pi / self.height_full

    def _project(self, x: F64, y: F64, z: F64) -> tuple[F64, F64, Bool]:
        n = np.sqrt(x * x + y * y + z * z)
        a = np.arcsin(np.clip(x / n, -1.0, 1.0))
        b = np.arctan2(y, z)
        u = (a + math.pi / 2.0) / self.pitch_rad - 0.5
        v = (b + math.pi) / self.pitch_rad - 0.5
        return u, v, n > 0.0

    def _unproject(self, u: F64, v: F64) -> tuple[F64, F64, F64, Bool]:
        a = (u + 0.5) * self.pitch_rad - math.pi / 2.0
        b = (v + 0.5) * self.pitch_rad - math.pi
        ca = np.cos(a)
        valid = (np.abs(a) <= math.pi / 2.0) & (np.abs(b) <= math.pi)
        return np.sin(a), ca * np.sin(b), ca * np.cos(b), valid

    def _scaled_params(self, factor: float) -> dict[str, Any]:
        hf = max(1, round(self.height_full * factor))
        return {"height_full": hf, "width": hf, "height": 2 * hf}


# Face order of the strip layout and each face's rotation R_cube_face (columns: face x, y, z axes).
CUBE_FACES: tuple[tuple[str, F64], ...] = (
    ("front", np.eye(3)),
    ("right", np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])),
    ("back", np.array([[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]])),
    ("left", np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])),
    ("up", np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])),
    ("down", np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])),
)


@dataclass(frozen=True)
class Cubemap(CameraModel):
    """Six 90-degree pinhole faces of ``face_size`` pixels in one 6F x F strip.

    Faces left to right: front (+z), right (+x), back (-z), left (-x), up (-y),
    down (+y); each is `Cubemap.face_model` seen through ``R_cube_face``.
    Pixels of face k occupy columns k F .. (k + 1) F - 1.
    """

    face_size: int
    width: int = 0
    height: int = 0

    def __post_init__(self) -> None:
        if not isinstance(self.face_size, int) or self.face_size <= 0:
            raise CalibrationError(f"Cubemap: face_size must be a positive integer, got {self.face_size!r}")
        object.__setattr__(self, "width", 6 * self.face_size)
        object.__setattr__(self, "height", self.face_size)

    @cached_property
    def face_model(self) -> Pinhole:
        """The pinhole camera of one face: 90-degree FOV, f = F/2."""
        f = self.face_size / 2.0
        c = (self.face_size - 1) / 2.0
        return Pinhole(f, f, c, c, self.face_size, self.face_size)

    def faces(self) -> list[tuple[str, Pinhole, F64]]:
        """(name, pinhole model, R_cube_face) of the six faces, in strip order."""
        return [(name, self.face_model, R) for name, R in CUBE_FACES]

    def split(self, image: np.ndarray[Any, Any]) -> dict[str, np.ndarray[Any, Any]]:
        """Cut a strip image into its six face images (views, not copies)."""
        F = self.face_size
        return {name: image[:, k * F : (k + 1) * F] for k, (name, _) in enumerate(CUBE_FACES)}

    def _project(self, x: F64, y: F64, z: F64) -> tuple[F64, F64, Bool]:
        F = self.face_size
        pts = np.stack([x, y, z], axis=-1)
        # The face is the one whose axis has the largest positive component.
        scores = np.stack([pts @ R[:, 2] for _, R in CUBE_FACES], axis=-1)
        face = np.argmax(scores, axis=-1)
        u = np.full_like(x, np.nan)
        v = np.full_like(x, np.nan)
        f = F / 2.0
        c = (F - 1) / 2.0
        for k, (_, R) in enumerate(CUBE_FACES):
            sel = face == k
            local = pts[sel] @ R  # R_face_cube = R^T, applied to row vectors
            u[sel] = f * local[:, 0] / local[:, 2] + c + k * F
            v[sel] = f * local[:, 1] / local[:, 2] + c
        return u, v, np.max(scores, axis=-1) > 0.0

    def _unproject(self, u: F64, v: F64) -> tuple[F64, F64, F64, Bool]:
        F = self.face_size
        face = np.floor((u + 0.5) / F)
        valid = (face >= 0) & (face < 6) & (v >= -0.5) & (v <= F - 0.5)
        face_i = np.clip(face, 0, 5).astype(np.intp)
        f = F / 2.0
        c = (F - 1) / 2.0
        local = np.stack([(u - face_i * F - c) / f, (v - c) / f, np.ones_like(u)], axis=-1)
        rot = np.stack([R for _, R in CUBE_FACES])[face_i]  # (N, 3, 3) R_cube_face
        ray = np.einsum("nij,nj->ni", rot, local)
        return ray[:, 0], ray[:, 1], ray[:, 2], valid

    def _scaled_params(self, factor: float) -> dict[str, Any]:
        face = max(1, round(self.face_size * factor))
        return {"face_size": face, "width": 6 * face, "height": face}


def pinhole_for_fov(fov_rad: float, width: int, height: int) -> Pinhole:
    """An undistorted pinhole with the given horizontal FOV, principal point at the centre."""
    if not 0.0 < fov_rad < math.pi:
        raise CalibrationError(f"pinhole_for_fov: FOV must be in (0, pi) radians, got {fov_rad!r}")
    f = (width / 2.0) / math.tan(fov_rad / 2.0)
    return Pinhole(f, f, (width - 1) / 2.0, (height - 1) / 2.0, width, height)
