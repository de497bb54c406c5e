"""Surface colour: a 3D procedural texture at the hit point, and fixed lighting.

The texture is a sum of 16 sinusoidal gratings with seeded random directions
and frequencies from 1.5 to 90 cycles/m, pushed through tanh so it has sharp
blotches at every scale from decimetres to about 1 cm. Being a function of the
3D point (not of the pixel), it is view-consistent: both cameras and all frames
see the same surface pattern, which is what stereo matching needs.
Lighting is Lambert from one fixed direction plus ambient; no shadows.
"""

from __future__ import annotations

import numpy as np

from calibration.types import F64, I64
from sensorbox.sim.raycast import Hits
from sensorbox.sim.scenes import Scene

N_GRATINGS = 16
LIGHT_DIR_WORLD = np.array([0.3, -0.25, 0.92]) / np.linalg.norm([0.3, -0.25, 0.92])
AMBIENT = 0.45
SKY_BGR = np.array([0.92, 0.78, 0.55])


class Texture:
    """Seeded grating set; `__call__` maps world points (N,3) to a modulation in [0, 1]."""

    def __init__(self, seed: int) -> None:
        rng = np.random.default_rng([seed, 0x7E57])
        d = rng.normal(size=(N_GRATINGS, 3))
        freqs = np.geomspace(1.5, 90.0, N_GRATINGS)
        self.waves = d / np.linalg.norm(d, axis=1, keepdims=True) * (2 * np.pi * freqs)[:, None]
        self.phases = rng.uniform(0, 2 * np.pi, N_GRATINGS)
        self.amps = freqs**-0.35
        self.norm = float(np.sqrt(np.sum(self.amps**2) / 2))

    def __call__(self, points_world: F64) -> F64:
        # float32: half the time of float64 sines, and 3e-3 rad phase error at 50 m is invisible.
        # Each phase summed over the three axes in order, as einsum("ij,kj->ik") sums them (the same
        # bits) at a third less time; not a BLAS matmul, which may sum otherwise: see camera.render
        p, waves = points_world.astype(np.float32), self.waves.astype(np.float32)
        arg = np.multiply(p[:, 0:1], waves[:, 0])
        arg += p[:, 1:2] * waves[:, 1]
        arg += p[:, 2:3] * waves[:, 2]
        arg += self.phases.astype(np.float32)
        s = np.einsum("ij,j->i", np.sin(arg, out=arg), self.amps.astype(np.float32))
        out: F64 = 0.5 + 0.5 * np.tanh(2.0 * s.astype(np.float64) / self.norm)
        return out


def shade(scene: Scene, texture: Texture, origins_world: F64, dirs_world: F64, hits: Hits) -> F64:
    """Linear BGR colour in [0, 1] (N,3) for each ray; sky (outdoor) or black (indoor) on a miss."""
    hit = hits.triangle >= 0
    out = np.zeros((len(dirs_world), 3))
    if scene.sky:
        elev = np.clip(dirs_world[:, 2], 0.0, 1.0)[:, None]
        out[:] = SKY_BGR * (0.75 + 0.25 * elev)
    if not hit.any():
        return out
    p = origins_world[hit] + dirs_world[hit] * hits.range_m[hit, None]
    obj_index = scene.triangle_object[hits.triangle[hit]]
    objects = scene.shading_objects
    albedo = np.empty((len(p), 3))
    base = np.array([o.color_bgr for o in objects])[obj_index]
    albedo[:] = base * (0.3 + 0.7 * texture(p))[:, None]
    for k, obj in enumerate(objects):
        if obj.checker is None:
            continue
        sel = obj_index == k
        albedo[sel] = obj.checker.shade(p[sel])[:, None]
    lambert = np.abs(np.einsum("ij,j->i", hits.normal_world[hit], LIGHT_DIR_WORLD))
    out[hit] = albedo * (AMBIENT + (1 - AMBIENT) * lambert)[:, None]
    return out


def reflectivity(scene: Scene, texture: Texture, points_world: F64, triangles: I64) -> F64:
    """Livox-like reflectivity 0..255 from the albedo's luminance at each hit point."""
    objects = scene.shading_objects
    base = np.array([o.color_bgr for o in objects])[scene.triangle_object[triangles]]
    lum = base @ np.array([0.114, 0.587, 0.299]) * (0.3 + 0.7 * texture(points_world))
    out: F64 = np.clip(lum * 255.0, 0, 255)
    return out
