"""A synthetic terrestrial scan in numpy alone: a box room with a box inside it, seen from a scanner.

For renderer tests and timings on machines without Open3D (the simulator in
`sensorbox.sim` ray-casts meshes with it): every ray of a jittered
azimuth x elevation grid is intersected analytically with the room's walls
and the inner box, so ranges are exact (plus optional noise), with occlusion
edges, oblique walls and a floor. Colours are a texture of the hit position;
points on part of one wall can be labelled (masked) and a small glass pane in
front of the scanner gives a mask cloud.
"""

from __future__ import annotations

import math

import numpy as np

from calibration.types import F32, F64
from ingest.raster.scan import Scan

ROOM_LO = np.array([-4.0, -3.0, -1.5])  # scan frame, metres (scanner at the origin, z up)
ROOM_HI = np.array([5.0, 3.5, 2.5])
BOX_LO = np.array([1.2, -0.9, -1.5])
BOX_HI = np.array([2.0, -0.1, 0.3])
GLASS_X = 3.0  # a pane x = 3 m, y in [0.5, 1.5], z in [-0.5, 0.5]


def _box_entry(d: F64, lo: F64, hi: F64, origin: F64) -> F64:
    """Distance along unit rays ``d`` (N, 3) from ``origin`` to where they enter box [lo, hi] (inf: miss)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - origin) / d
        t2 = (hi - origin) / d
    t_near = np.nanmax(np.minimum(t1, t2), axis=1)
    t_far = np.nanmin(np.maximum(t1, t2), axis=1)
    hit = (t_far >= t_near) & (t_near > 0)
    out: F64 = np.where(hit, t_near, np.inf)
    return out


def _room_exit(d: F64, origin: F64) -> F64:
    """Distance along ``d`` from ``origin`` (inside the room) to its walls."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d > 0, (ROOM_HI - origin) / d, (ROOM_LO - origin) / d)
    out: F64 = np.nanmin(np.where(t > 0, t, np.inf), axis=1)
    return out


def room_scan(
    n_points: int, origin_world: tuple[float, float, float] = (0.0, 0.0, 0.0), seed: int = 0,
    noise_m: float = 0.0, name: str = "synthetic", label_wall: bool = False, glass: bool = False,
) -> Scan:  # fmt: skip
    """About ``n_points`` returns of a scanner at ``origin_world`` (levelled: scan axes = world axes).

    Elevations -60..+90 deg, the grid jittered by a quarter step (no
    aliasing with pixel grids); ``label_wall`` marks the points on the
    y = ROOM_HI wall with z > 0 as masked; ``glass`` adds a mask cloud.
    Built in chunks of 2 M rays: a 20 M-point scan needs no (N, 3) float64.
    """
    rng = np.random.default_rng(seed)
    o = np.asarray(origin_world, np.float64)
    el_span = math.radians(150.0)
    step = math.sqrt(2.0 * math.pi * el_span / n_points)
    n_az, n_el = int(2.0 * math.pi / step), int(el_span / step)
    xyz_parts, rgb_parts, mask_parts = [], [], []
    rows = max(1, (2_000_000 // n_az))
    for e0 in range(0, n_el, rows):
        ei, ai = np.meshgrid(np.arange(e0, min(n_el, e0 + rows)), np.arange(n_az), indexing="ij")
        az = (ai.ravel() + 0.5 + rng.uniform(-0.25, 0.25, ai.size)) * step
        el = math.radians(-60.0) + (ei.ravel() + 0.5 + rng.uniform(-0.25, 0.25, ei.size)) * step
        d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
        t = np.minimum(_room_exit(d, o), _box_entry(d, BOX_LO, BOX_HI, o))
        if noise_m:
            t = t + rng.normal(0.0, noise_m, t.shape)
        p_world = o + d * t[:, None]
        xyz_parts.append((p_world - o).astype(np.float32))
        rgb_parts.append(_texture(p_world))
        mask_parts.append((p_world[:, 1] > ROOM_HI[1] - 1e-6) & (p_world[:, 2] > 0.0))
    xyz = np.concatenate(xyz_parts)
    T = np.eye(4)
    T[:3, 3] = o
    return Scan(
        name, T, xyz, np.concatenate(rgb_parts),
        masked=np.concatenate(mask_parts) if label_wall else None,
        mask_xyz=_glass(o) if glass else np.zeros((0, 3), np.float32),
    )  # fmt: skip


def _texture(p: F64) -> np.ndarray:
    """A colour per point from its world position: 10 cm checks, one hue per axis."""
    c = (np.floor(p * 10.0).astype(np.int64) % 2) * 120 + 60
    return np.ascontiguousarray(c.astype(np.uint8))


def _glass(origin: F64) -> F32:
    """Mask cloud: a 1 x 1 m pane at x = GLASS_X, 2 cm grid, in the scan frame."""
    y, z = np.meshgrid(np.arange(0.5, 1.5, 0.02), np.arange(-0.5, 0.5, 0.02))
    pane = np.stack([np.full(y.size, GLASS_X), y.ravel(), z.ravel()], axis=1) - origin
    out: F32 = pane.astype(np.float32)
    return out
