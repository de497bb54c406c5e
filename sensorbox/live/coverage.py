"""The live monitor's coverage preview: recent LiDAR points placed into the upper camera with the gyro.

Pure functions (no threads, no I/O), so the geometry is tested exactly:

- `gyro_orientations`, `orientation_at`: the rig's orientation at a time,
  integrated from gyro samples in cam0 (rotation only: the preview ignores how
  far the rig moved within the window).
- `place_sweeps`: each sweep's points, in cam0 at the sweep's time, rotated into
  cam0 at the image's time.
- `coverage`: those points projected into the upper camera at the preview's
  size; a preview pixel is covered when at least one point lands in it, and the
  covered fraction is covered pixels / all pixels of the preview: a live
  estimate of how much of the image the walk's dense ground truth will reach.
- `draw_coverage`: the points drawn over the image, coloured by range, with the
  fraction written in the corner.

Times are int64 ns; angular rates rad/s; points metres.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from calibration.camera import CameraModel
from calibration.transforms import rodrigues

F64 = np.ndarray[Any, np.dtype[np.float64]]
I64 = np.ndarray[Any, np.dtype[np.int64]]
U8 = np.ndarray[Any, np.dtype[np.uint8]]


@dataclass(frozen=True)
class Coverage:
    """Points placed into the preview: their pixels (int (N, 2) u, v), ranges (m), the covered mask
    (preview H x W bool) and the covered fraction of the preview's pixels."""

    pixels: np.ndarray[Any, np.dtype[np.int64]]
    range_m: F64
    covered: np.ndarray[Any, np.dtype[np.bool_]]
    fraction: float


def gyro_orientations(stamps_ns: I64, gyro_rad_s: F64) -> F64:
    """R_0_k (K, 3, 3): the gyro's frame at each sample time `stamps_ns[k]` in its frame at the first.

    Each sample's rate holds until the next sample (piecewise constant), so a
    constant rate w about an axis turns exactly w * (t_k - t_0) about it.
    """
    out = np.empty((len(stamps_ns), 3, 3))
    R = np.eye(3)
    for k in range(len(stamps_ns)):
        out[k] = R
        if k + 1 < len(stamps_ns):
            R = R @ rodrigues(gyro_rad_s[k] * ((int(stamps_ns[k + 1]) - int(stamps_ns[k])) * 1e-9))
    return out


def orientation_at(stamps_ns: I64, gyro_rad_s: F64, orientations: F64, t_ns: int) -> F64:
    """R_0_t: the orientation at `t_ns` from `gyro_orientations`, the rate of the sample before `t_ns`
    carried on to it; before the first sample, the identity."""
    if len(stamps_ns) == 0 or t_ns <= stamps_ns[0]:
        return np.eye(3)
    k = int(np.searchsorted(stamps_ns, t_ns, side="right")) - 1
    return np.asarray(orientations[k] @ rodrigues(gyro_rad_s[k] * ((t_ns - int(stamps_ns[k])) * 1e-9)))


def rigid(R: F64, t: F64, pts: Any) -> F64:
    """R p + t for points (N, 3), float64, column by column: numpy's matmul of an (N, 3) array goes
    through BLAS, whose threads spin on a busy machine (186 ms for 400k points on this 2-core VM under
    load, 18 ms this way)."""
    p = np.asarray(pts, np.float64)
    out = np.empty((len(p), 3))
    for i in range(3):
        out[:, i] = p[:, 0] * R[i, 0] + p[:, 1] * R[i, 1] + p[:, 2] * R[i, 2] + t[i]
    return out


def place_sweeps(
    sweeps: Sequence[tuple[int, Any]],
    stamps_ns: I64,
    gyro_cam0_rad_s: F64,
    image_ns: int,
    T_cam_cam0: F64 | None = None,
) -> F64:
    """Points of `sweeps` ((time ns, (N, 3) points in cam0 at that time), ...) at `image_ns`, in cam0,
    or in the camera `T_cam_cam0` takes cam0 to.

    With R(t) the orientation integrated from the gyro (rates in cam0, samples
    in time order), a point p seen at time t is R(image)^T R(t) p at the
    image's time (rotation only).
    """
    if not sweeps:
        return np.zeros((0, 3))
    T = np.eye(4) if T_cam_cam0 is None else T_cam_cam0
    Rs = gyro_orientations(stamps_ns, gyro_cam0_rad_s)
    R_image = orientation_at(stamps_ns, gyro_cam0_rad_s, Rs, image_ns)
    out = []
    for t_ns, pts in sweeps:
        R = T[:3, :3] @ R_image.T @ orientation_at(stamps_ns, gyro_cam0_rad_s, Rs, t_ns)
        out.append(rigid(R, T[:3, 3], pts))
    return np.concatenate(out)


def coverage(points_cam: F64, model: CameraModel) -> Coverage:
    """Project points in the camera's frame (m) with `model` (at the preview's size): the covered pixels.

    A point covers the pixel whose centre is nearest its projection (pixel
    centres at integer u, v); points behind the lens's valid region or outside
    the image cover nothing.
    """
    covered = np.zeros((model.height, model.width), bool)
    if len(points_cam) == 0:
        return Coverage(np.zeros((0, 2), np.int64), np.zeros(0), covered, 0.0)
    uv, valid = model.project(points_cam)
    valid &= model.in_image(uv)
    pix = np.rint(uv[valid]).astype(np.int64)
    pix[:, 0] = np.clip(pix[:, 0], 0, model.width - 1)
    pix[:, 1] = np.clip(pix[:, 1], 0, model.height - 1)
    covered[pix[:, 1], pix[:, 0]] = True
    range_m = np.linalg.norm(points_cam[valid], axis=1)
    return Coverage(pix, range_m, covered, float(covered.mean()))


def draw_coverage(
    image_bgr: U8, cov: Coverage, window_s: float, max_range_m: float = 12.0, note: str = ""
) -> U8:
    """The preview image with each covered pixel tinted by range (near red, `max_range_m` and beyond
    blue; 70 % colour, 30 % image) under a banner: the covered fraction, then `note` on a second line."""
    out = image_bgr.copy()
    if len(cov.pixels):
        levels = 255 - np.clip(cov.range_m / max_range_m * 255.0, 0, 255).astype(np.uint8)
        colours = cv2.applyColorMap(levels.reshape(-1, 1), cv2.COLORMAP_TURBO).reshape(-1, 3)
        under = out[cov.pixels[:, 1], cov.pixels[:, 0]].astype(np.float32)
        out[cov.pixels[:, 1], cov.pixels[:, 0]] = (0.3 * under + 0.7 * colours).astype(np.uint8)
    lines = [f"covered {100 * cov.fraction:.1f} % of pixels (last {window_s:g} s, both LiDARs)"]
    lines += [note] if note else []
    scale = max(0.4, out.shape[1] / 1000)
    step = int(20 * scale / 0.45)
    cv2.rectangle(out, (0, 0), (out.shape[1] - 1, step * len(lines) + 6), (0, 0, 0), -1)
    for k, text in enumerate(lines):
        org = (6, step * (k + 1))
        cv2.putText(out, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def preview_factor(width_px: int, max_width_px: int = 640) -> int:
    """The image reduction (1, 2, 4 or 8: the steps JPEG decodes directly) that brings `width_px` to at
    most `max_width_px`, or 8."""
    for factor in (1, 2, 4, 8):
        if width_px / factor <= max_width_px:
            return factor
    return 8
