"""Global-shutter camera rendering by ray casting every valid pixel of a camera model.

The camera is rendered at the pose of its stamp (mid-exposure). Pixels the
model cannot unproject (outside the Double Sphere's valid disc) stay black, as
on the real ZED X One fisheye image corners. `supersample` s casts s x s rays
per pixel at sub-pixel centres and averages them (anti-aliasing for tests that
locate edges to a fraction of a pixel).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from calibration.camera import CameraModel
from calibration.types import F64, U8, Bool
from sensorbox.sim.appearance import Texture, shade
from sensorbox.sim.scenes import Scene


@dataclass(frozen=True)
class CameraSim:
    """One simulated camera: its model (at render resolution) and pose on the rig."""

    name: str
    model: CameraModel
    T_cam0_cam: F64


@lru_cache(maxsize=8)
def _rays(model: CameraModel, supersample: int) -> tuple[F64, Bool]:
    """Unit rays (H*W*s*s, 3) in the camera frame and their validity, sub-pixel major last."""
    offs = (np.arange(supersample) + 0.5) / supersample - 0.5
    u, v = np.meshgrid(np.arange(model.width, dtype=np.float64), np.arange(model.height, dtype=np.float64))
    du, dv = np.meshgrid(offs, offs)
    px = np.stack([(u[..., None] + du.ravel()).ravel(), (v[..., None] + dv.ravel()).ravel()], axis=1)
    rays, ok = model.unproject(px)
    rays[~ok] = 0.0
    return rays, ok


def render(
    cam: CameraSim, scene: Scene, texture: Texture, T_world_cam0: F64, supersample: int = 1, t_s: float = 0.0
) -> U8:
    """BGR uint8 image (H, W, 3) seen by `cam` when cam0 is at `T_world_cam0` (4x4), movers at `t_s`."""
    rays, ok = _rays(cam.model, supersample)
    T_world_cam = T_world_cam0 @ cam.T_cam0_cam
    # einsum, not @: a tall (N,3)x(3,3) BLAS call can spin up OpenBLAS threads that fight the
    # render pool and make frames 3-4x slower at random (bench_sim)
    dirs = np.einsum("ij,kj->ik", rays[ok], T_world_cam[:3, :3])
    origins = np.broadcast_to(T_world_cam[:3, 3], dirs.shape)
    colour = np.zeros((len(rays), 3))
    colour[ok] = shade(scene, texture, origins, dirs, scene.cast(np.ascontiguousarray(origins), dirs, t_s))
    h, w, s2 = cam.model.height, cam.model.width, supersample * supersample
    mean = colour.reshape(h, w, s2, 3).mean(axis=2)
    image: U8 = np.clip(np.round(mean * 255.0), 0, 255).astype(np.uint8)
    return image
