"""How well one LiDAR's points lie on cam0's image: a photometric alignment that needs no truth.

A LiDAR point carries its return strength (reflectivity), and a surface that
returns more light looks brighter to the camera: painted marks, textures and
material borders appear in both. Placed in cam0 through the rig file and the
clocks, a point should land where the image shows its surface; when the rig
or the clocks are off, it lands beside it. `align_points` finds the small
rigid motion of the points (rotation vector and translation in cam0) that lays
their reflectivity best onto the image intensity:

    min over (w, t, a, b)  sum_i rho( I(pi(R(w) p_i + t)) - (a * refl_i + b) )

Gauss-Newton on the image's gradients, the affine intensity model (a, b)
fitted with the pose and then marginalised out, Cauchy weights against what
the model cannot explain (shading, occlusions, mixed returns), coarse to fine
(the image blurred by 4, 2 and 1 pixels, so that corrections of a few
degrees or centimetres are inside the basin). Only points that are the
nearest in their 2-pixel cell are used: a point hidden from the camera behind
a nearer one (the LiDAR sits beside the camera) shows the wrong surface's
intensity. This is direct_visual_lidar_calibration's idea with a plain least
squares cost on a fisheye model.

The result is the correction itself, its information matrix (from the
residuals' spread) and how far the correction moves the points on the image
(`shift_deg`): a sample whose points lie on the image within its noise has a
correction indistinguishable from zero. A camera clock offset `dt` shows up
as a correction equal to `dt` times the rig's motion (`twist`), a rig-file
error as the same correction in every sample: `ingest.train.gt.align_check.combine`
separates them over many samples.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from calibration.camera import CameraModel
from calibration.fisheye import DoubleSphere
from calibration.types import F32, F64, I64
from ingest.dataset.meta import AlignmentMeta
from ingest.train.gt.groundtruth import px_per_rad
from ingest.train.gt.window_fit import WINDOW_PARTS, stretch_of

SIGMAS_PX = (8.0, 4.0, 2.0, 1.0)
"""The image blur of each coarse-to-fine level (Gaussian sigma, pixels of a 1920-wide image)."""
ITERATIONS_PER_LEVEL = 3
MAX_POINTS = 20_000
"""Points used per LiDAR and sample: beyond this the correction's noise is below what the model explains."""
MIN_POINTS = 500
CELL_PX = 2.0
NEAREST_TOLERANCE = 0.03
"""A point is visible when its range is within 3 % of the nearest point's in its cell."""
CAUCHY_SCALE = 2.0
"""The Cauchy weights' scale, in robust standard deviations of the residual."""
REFERENCE_WIDTH_PX = 1920.0
JACOBIAN_STEP_M = 1e-5


@dataclass(frozen=True)
class Alignment:
    """The correction that lays one LiDAR's points best onto cam0's image: p' = R(rotation) p + translation.

    `rotation_rad` is a rotation vector in cam0 (rad), `translation_m` in cam0
    (m), `information` the inverse covariance of (rotation, translation)
    (1/rad^2, 1/m^2), `points` how many were used, `correlation` the
    correlation of image intensity and reflectivity at the solution, and
    `shift_deg` the median angle by which the correction moves the points
    as cam0 sees them (the misalignment the GT would carry).
    """

    rotation_rad: F64
    translation_m: F64
    information: F64
    points: int
    correlation: float
    shift_deg: float
    range_m: float  # the median range of the points used (m)
    pixel_rad: float  # the angle of one of cam0's pixels at its centre

    @property
    def covariance(self) -> F64:
        """The 6x6 covariance of (rotation rad, translation m)."""
        return np.asarray(np.linalg.pinv(self.information), np.float64)

    @property
    def sigma_rotation_deg(self) -> float:
        """1-sigma of the rotation's largest axis (deg)."""
        return float(np.degrees(np.sqrt(np.max(np.diag(self.covariance)[:3]))))

    @property
    def sigma_translation_mm(self) -> float:
        """1-sigma of the translation's largest axis (mm)."""
        return float(np.sqrt(np.max(np.diag(self.covariance)[3:])) * 1e3)

    def to_meta(self) -> AlignmentMeta:
        """As `meta/<id>.json` keeps it (deg and mm; the information matrix in rad and m)."""
        return AlignmentMeta(
            rotation_deg=[round(float(v), 5) for v in np.degrees(self.rotation_rad)],
            translation_mm=[round(float(v), 3) for v in self.translation_m * 1e3],
            sigma_rotation_deg=round(self.sigma_rotation_deg, 5),
            sigma_translation_mm=round(self.sigma_translation_mm, 3),
            shift_deg=round(self.shift_deg, 5), points=self.points, correlation=round(self.correlation, 4),
            information=[[float(f"{v:.6g}") for v in row] for row in self.information],
            range_m=round(self.range_m, 3), pixel_deg=float(f"{np.degrees(self.pixel_rad):.6g}"),
        )  # fmt: skip

    @classmethod
    def from_meta(cls, meta: AlignmentMeta) -> Alignment:
        """The alignment a sample's meta recorded."""
        return cls(
            np.radians(meta.rotation_deg), np.asarray(meta.translation_mm) / 1e3,
            np.asarray(meta.information, np.float64), meta.points, meta.correlation, meta.shift_deg,
            meta.range_m, float(np.radians(meta.pixel_deg)),
        )  # fmt: skip

    @property
    def vector(self) -> F64:
        """(rotation rad, translation m) as one 6-vector."""
        out: F64 = np.concatenate([self.rotation_rad, self.translation_m])
        return out


def rotation_matrix(rotvec: F64) -> F64:
    """The rotation matrix of a rotation vector (rad)."""
    R, _ = cv2.Rodrigues(np.asarray(rotvec, np.float64).reshape(3, 1))
    return np.asarray(R, np.float64)


def apply(rotation_rad: F64, translation_m: F64, pts: F64) -> F64:
    """R(rotation) p + translation for each row of `pts` (N, 3)."""
    out: F64 = pts @ rotation_matrix(rotation_rad).T + translation_m
    return out


def grey_levels(image: np.ndarray) -> F32:
    """A BGR, BGRA or grey 8-bit image as float32 grey levels."""
    if image.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        image = cv2.cvtColor(np.ascontiguousarray(image), code)
    out: F32 = image.astype(np.float32)
    return out


@dataclass(frozen=True)
class ImageLevels:
    """cam0's image as the alignment reads it: per coarse-to-fine level the blurred intensity and its
    x and y gradients (float32, intensity per pixel), as the channels of one image (one remap reads
    all three)."""

    levels: tuple[np.ndarray, ...]  # per level (H, W, 3) float32: intensity, d/dx, d/dy

    @classmethod
    def from_bgr(cls, image: np.ndarray) -> ImageLevels:
        """The levels of a BGR, BGRA or grey uint8 image (sigmas scaled to its width)."""
        grey = grey_levels(image)
        scale = grey.shape[1] / REFERENCE_WIDTH_PX
        levels = []
        for sigma in SIGMAS_PX:
            blurred = cv2.GaussianBlur(grey, (0, 0), max(0.5, sigma * scale))
            gx = cv2.Sobel(blurred, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8)
            gy = cv2.Sobel(blurred, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8)
            levels.append(cv2.merge([blurred, gx, gy]))
        return cls(tuple(levels))


def _sample(image: np.ndarray, px: F64) -> F64:
    """Bilinear samples (N, channels) of a float32 image at pixel positions (N, 2)."""
    x = np.ascontiguousarray(px[:, 0], np.float32).reshape(-1, 1)
    y = np.ascontiguousarray(px[:, 1], np.float32).reshape(-1, 1)
    sampled = cv2.remap(image, x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return np.asarray(sampled, np.float64).reshape(len(px), -1)


def nearest_in_cell(px: F64, range_m: F64) -> np.ndarray:
    """Whether each projected point (pixels inside the image) is within `NEAREST_TOLERANCE` of the
    nearest range in its `CELL_PX` cell (a z-buffer: the others are hidden from the camera or lie on a
    mixed edge)."""
    from ingest.train.gt import align_kernels  # numba: loaded with the first alignment

    return align_kernels.nearest_in_cell(px, range_m, CELL_PX, NEAREST_TOLERANCE)


def _projected(model: CameraModel, pts: F64) -> tuple[F64, F64, np.ndarray]:
    """Pixels of `pts`, which points project into the image with a finite Jacobian, and at those points
    the projection's Jacobian d(pixel)/d(point) (M, 2, 3) by forward differences (M of them: the others
    are never sampled, and about half of a LiDAR's points lie outside a fisheye's view)."""
    if isinstance(model, DoubleSphere):  # the rig's cameras: one compiled pass
        from ingest.train.gt.align_kernels import visible_jacobians  # numba: loaded with the first alignment

        return visible_jacobians(model, pts, JACOBIAN_STEP_M)
    px, ok = _in_image(model, pts)
    inside = pts[ok]
    steps = np.eye(3) * JACOBIAN_STEP_M
    moved, _ = model.project(inside[None, :, :] + steps[:, None, :])  # (3, M, 2): one call for all three
    J = ((moved - px[ok]) / JACOBIAN_STEP_M).transpose(1, 2, 0)
    finite = np.isfinite(J.reshape(len(J), 6).sum(axis=1))  # NaN and inf spread to the sum
    ok[ok] = finite
    return px, np.ascontiguousarray(J[finite]), ok


def _in_image(model: CameraModel, pts: F64) -> tuple[F64, np.ndarray]:
    """`model.project(pts)` and which of those pixels lie in the image."""
    if isinstance(model, DoubleSphere):  # the rig's cameras: one compiled pass
        from ingest.train.gt.align_kernels import pixels_in_image  # numba: loaded with the first alignment

        return pixels_in_image(model, pts)
    px, ok = model.project(pts)
    return px, ok & model.in_image(px)


def _thinned(pts: F64, reflectivity: F64, limit: int) -> tuple[F64, F64]:
    """At most `limit` of the points, evenly spread over their order (deterministic)."""
    if len(pts) <= limit:
        return pts, reflectivity
    pick = np.linspace(0, len(pts) - 1, limit).round().astype(np.int64)
    return pts[pick], reflectivity[pick]


def align_points(
    model: CameraModel, image: ImageLevels, pts_cam0: F64, reflectivity: F64, max_points: int = MAX_POINTS
) -> Alignment | None:
    """The correction that lays `pts_cam0` (N, 3, m, in cam0 at the image's exposure) with their
    `reflectivity` best onto `image` (see the module docstring); None with fewer than `MIN_POINTS`
    visible points or no texture to align on.

    Which points are visible and the projection's Jacobian are taken once per
    level, at the level's start: within a level the points move by a fraction
    of its blur, and Gauss-Newton converges to the same minimum with them.
    """
    finite = np.isfinite(pts_cam0).all(axis=1) & np.isfinite(reflectivity)
    pts, refl = _thinned(pts_cam0[finite], np.asarray(reflectivity, np.float64)[finite], max_points)
    w_rad, t_m = np.zeros(3), np.zeros(3)
    affine = np.array([1.0, 0.0])  # intensity = gain * reflectivity + offset
    step: _Step | None = None
    for level in image.levels:
        px, J, ok = _projected(model, apply(w_rad, t_m, pts))
        nearest = nearest_in_cell(px[ok], np.linalg.norm(pts[ok], axis=1))
        ok[ok] = nearest
        if ok.sum() < MIN_POINTS:
            return None
        visible, J, rf = pts[ok], J[nearest], refl[ok]
        for _ in range(ITERATIONS_PER_LEVEL):
            step = _gauss_newton(model, level, apply(w_rad, t_m, visible), J, rf, affine)
            if step is None:
                return None
            dR = rotation_matrix(step.delta[:3])
            w_rad = np.asarray(cv2.Rodrigues(dR @ rotation_matrix(w_rad))[0], np.float64).ravel()
            t_m = dR @ t_m + step.delta[3:6]
            affine = affine + step.delta[6:]
    assert step is not None
    shift = np.arccos(np.clip(np.einsum("ij,ij->i", _unit(apply(w_rad, t_m, pts)), _unit(pts)), -1.0, 1.0))
    corr = np.corrcoef(step.intensity, step.reflectivity)[0, 1] if np.std(step.reflectivity) > 0 else 0.0
    return Alignment(
        w_rad, t_m, step.information, step.points, float(np.nan_to_num(corr)),
        float(np.degrees(np.median(shift))), float(np.median(np.linalg.norm(step.points_m, axis=1))),
        1.0 / px_per_rad(model),
    )  # fmt: skip


MIN_PART_POINTS = 300
"""Visible points a stretch needs for its correlation to be measured (noise about +-0.03 at 1,500)."""


def part_correlations(
    model: CameraModel, image: ImageLevels, pts_cam0: F64, reflectivity: F64, stamps_ns: I64
) -> list[float | None]:
    """The correlation of image intensity (the coarsest level) and reflectivity of each stretch of the
    points' times (`ingest.train.gt.window_fit.stretch_of`), where no correction is applied: one LiDAR's
    points placed in cam0 at the exposure (N, 3, m) with their stamps (ns). None for a stretch with
    under `MIN_PART_POINTS` visible points.

    Every stretch of a sweep meets the same image through the same pose, so they match it alike (the
    simulated fixtures' stretches lie within 0.84 of each other's correlation); a stretch whose points
    stand where the LiDAR did not measure them (a glitched sweep turned, moved or mirrored) matches it
    not at all.
    """
    out: list[float | None] = [None] * WINDOW_PARTS
    finite = np.isfinite(pts_cam0).all(axis=1) & np.isfinite(reflectivity)
    if finite.sum() < MIN_PART_POINTS:
        return out
    pts, refl, stamps = pts_cam0[finite], np.asarray(reflectivity, np.float64)[finite], stamps_ns[finite]
    px, ok = _in_image(model, pts)
    ok[ok] = nearest_in_cell(px[ok], np.linalg.norm(pts[ok], axis=1))
    part = stretch_of(stamps)
    for k in range(WINDOW_PARTS):
        mine = ok & (part == k)
        if mine.sum() < MIN_PART_POINTS or np.std(refl[mine]) == 0:
            continue
        intensity = _sample(image.levels[0], px[mine])[:, 0]
        if np.std(intensity) > 0:
            out[k] = round(float(np.corrcoef(intensity, refl[mine])[0, 1]), 4)
    return out


def _unit(v: F64) -> F64:
    out: F64 = v / np.linalg.norm(v, axis=1, keepdims=True)
    return out


@dataclass(frozen=True)
class _Step:
    delta: F64  # (rotation, translation, gain, offset) increments
    information: F64  # 6x6, the affine intensity model marginalised out
    points: int  # the points the step used
    points_m: F64  # the corrected points it used (N, 3)
    intensity: F64  # the image at them, and their reflectivity (for the correlation)
    reflectivity: F64


def _gauss_newton(
    model: CameraModel, level: np.ndarray, p: F64, J: F64, refl: F64, affine: F64
) -> _Step | None:
    """One robust Gauss-Newton step of the photometric cost at the corrected points `p`, with the
    projection's Jacobian `J` (N, 2, 3) and the intensity model `affine` (gain, offset)."""
    from ingest.train.gt.align_kernels import normal_equations  # numba: loaded with the first alignment

    px, ok = _in_image(model, p)
    if ok.sum() < MIN_POINTS:
        return None
    H, g, n, spread, weighted_sq, intensity, rf, used = normal_equations(
        px, ok, p, J, refl, level, affine, CAUCHY_SCALE
    )
    if not spread > 0:
        return None
    try:
        delta: F64 = np.negative(np.linalg.solve(H, g))
        pose, across = H[:6, :6], H[:6, 6:]
        variance = weighted_sq / max(1, n - 8)
        info: F64 = (pose - across @ np.linalg.solve(H[6:, 6:], across.T)) / variance
    except np.linalg.LinAlgError:
        return None
    return _Step(delta, info, n, used, intensity, rf)
