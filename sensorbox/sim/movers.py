"""Things that move: rigid objects on closed-form paths, and ray casting at each ray's own time.

A `Mover` is a mesh in its body frame and a pose T_world_body(t): a constant
velocity (people, a car) or a swing about the body's z axis (a door). Times are
seconds since the simulation start, like the trajectory's. `MovingCaster`
casts rays against the static mesh and every mover, each ray at its own time
(a LiDAR point's, or one camera exposure), by moving the ray into the mover's
body frame at that time: exact for rigid motion, no mesh is rebuilt.

`movers.yaml` + `mover_<name>.ply` in the truth folder hold them (body-frame
meshes in double precision), so `Truth` answers for them at any time.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from calibration.types import F64
from sensorbox.sim.meshes import Mesh, box, cylinder, merge, sphere
from sensorbox.sim.raycast import Hits, RayCaster, write_ply


@dataclass(frozen=True)
class Mover:
    """A rigid mover: body-frame mesh, colour (BGR in [0, 1]) and its path (metres, seconds, degrees)."""

    name: str
    mesh: Mesh
    color_bgr: tuple[float, float, float]
    origin_world: tuple[float, float, float]  # body origin at t = 0
    velocity_mps: tuple[float, float, float] = (0.0, 0.0, 0.0)
    yaw_deg: float = 0.0  # body heading about world z
    swing_amp_deg: float = 0.0  # door: yaw(t) = yaw + amp sin(2 pi f t + phase)
    swing_freq_hz: float = 0.0
    swing_phase_rad: float = 0.0

    def pose(self, t_s: F64) -> tuple[F64, F64]:
        """(R_world_body (N, 3, 3), p_world_body (N, 3)) at times `t_s` (N,)."""
        t = np.atleast_1d(np.asarray(t_s, np.float64))
        yaw = np.radians(
            self.yaw_deg
            + self.swing_amp_deg * np.sin(2 * np.pi * self.swing_freq_hz * t + self.swing_phase_rad)
        )
        c, s = np.cos(yaw), np.sin(yaw)
        R = np.zeros((len(t), 3, 3))
        R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
        p = np.asarray(self.origin_world) + t[:, None] * np.asarray(self.velocity_mps)
        return R, p

    def params(self) -> dict[str, Any]:
        """Everything but the mesh (written to movers.yaml)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items() if k != "mesh"}


def _person(height_m: float = 1.75) -> Mesh:
    """Torso box, head sphere and two legs, standing on z = 0, facing body +x."""
    return merge([
        box([-0.12, -0.22, 0.9], [0.12, 0.22, height_m - 0.25]),
        sphere([0.0, 0.0, height_m - 0.12], 0.12),
        cylinder([0.0, -0.1, 0.0], [0.0, -0.1, 0.9], 0.08, 10),
        cylinder([0.0, 0.1, 0.0], [0.0, 0.1, 0.9], 0.08, 10),
    ])  # fmt: skip


def default_movers(scene: str, start_world: F64) -> list[Mover]:
    """People crossing and walking towards the rig, a swinging door, and (outdoor) a passing car.

    Placed relative to the scene's start (the rig walks along +x at 1.2 m/s
    in |y| < 0.7 m), so every one is in view during the first seconds.
    """
    x0, y0 = float(start_world[0]), float(start_world[1])
    movers = [
        Mover(
            "person_crossing", _person(), (0.35, 0.25, 0.7), (x0 + 4.5, y0 - 3.0, 0.0), (0.0, 1.3, 0.0), 90.0
        ),
        Mover(
            "person_oncoming",
            _person(1.65),
            (0.6, 0.5, 0.2),
            (x0 + 9.0, y0 + 1.6, 0.0),
            (-1.1, 0.0, 0.0),
            180.0,
        ),
    ]
    door = box([0.0, 0.0, 0.0], [0.9, 0.04, 2.05])  # hinge on the body z axis
    if scene == "indoor":
        movers.append(Mover("door", door, (0.25, 0.45, 0.65), (4.0, 1.0, 0.0), yaw_deg=-90.0,
                            swing_amp_deg=40.0, swing_freq_hz=0.3))  # fmt: skip
    else:
        movers.append(Mover("door", door, (0.25, 0.45, 0.65), (x0 + 6.0, y0 - 3.5, 0.0), yaw_deg=0.0,
                            swing_amp_deg=40.0, swing_freq_hz=0.3))  # fmt: skip
        car = box([-2.1, -0.9, 0.15], [2.1, 0.9, 1.45])
        movers.append(Mover("car", car, (0.15, 0.15, 0.75), (x0 + 22.0, y0 + 4.0, 0.0), (-7.0, 0.0, 0.0)))
    return movers


class MovingCaster:
    """A static mesh plus movers; triangle ids run static first, then each mover's in order."""

    def __init__(self, static: RayCaster, movers: list[Mover]) -> None:
        self.static = static
        self.movers = movers
        self._casters = [RayCaster(*m.mesh) for m in movers]
        sizes = [len(static.triangles), *(len(m.mesh[1]) for m in movers)]
        self.offsets = np.cumsum([0, *sizes])[:-1]

    def cast(self, origins_world: F64, dirs_world: F64, t_s: F64 | float, static: bool = True) -> Hits:
        """Rays at times `t_s` (one per ray, or one for all): the nearest hit, static mesh or mover.

        `static=False` casts against the movers alone.
        """
        if static:
            best = self.static.cast(origins_world, dirs_world)
        else:
            n = len(origins_world)
            best = Hits(np.full(n, np.inf), np.full(n, -1, np.int64), np.zeros((n, 3)))
        rng, tri, normal = best.range_m.copy(), best.triangle.copy(), best.normal_world.copy()
        one_time = np.ndim(t_s) == 0
        for k, (mover, caster) in enumerate(zip(self.movers, self._casters, strict=True)):
            if one_time:  # a camera frame: one pose for every ray
                R1, p1 = mover.pose(np.array([float(t_s)]))
                o_body = (origins_world - p1[0]) @ R1[0]
                d_body = dirs_world @ R1[0]
            else:
                R, p = _poses(mover, np.asarray(t_s, np.float64))
                o_body = np.einsum("nji,nj->ni", R, origins_world - p)
                d_body = np.einsum("nji,nj->ni", R, dirs_world)
            hit = caster.cast(o_body, d_body)
            nearer = hit.range_m < rng
            rng[nearer] = hit.range_m[nearer]
            tri[nearer] = hit.triangle[nearer] + self.offsets[k + 1]
            if one_time:
                normal[nearer] = hit.normal_world[nearer] @ R1[0].T
            else:
                normal[nearer] = np.einsum("nij,nj->ni", R[nearer], hit.normal_world[nearer])
        return Hits(rng, tri, normal)


def _poses(mover: Mover, t: F64) -> tuple[F64, F64]:
    """Per-ray poses, computed once per distinct time (a camera frame has one)."""
    times, inv = np.unique(t, return_inverse=True)
    R, p = mover.pose(times)
    return R[inv], p[inv]


def write_movers(folder: Path, movers: list[Mover]) -> None:
    """`movers.yaml` and one `mover_<name>.ply` per mover (body frame) into the truth folder."""
    for m in movers:
        write_ply(folder / f"mover_{m.name}.ply", *m.mesh)
    doc = {"movers": [m.params() for m in movers]}
    (folder / "movers.yaml").write_text(
        "# Simulated movers: body-frame meshes in mover_<name>.ply; pose(t) = Rz(yaw(t)), origin + v t\n"
        + yaml.safe_dump(doc, sort_keys=False)
    )


def read_movers(folder: Path) -> list[Mover]:
    """The movers of a truth folder (none when it has no movers.yaml)."""
    path = folder / "movers.yaml"
    if not path.exists():
        return []
    out = []
    for d in yaml.safe_load(path.read_text())["movers"]:
        caster = RayCaster.from_ply(folder / f"mover_{d['name']}.ply")
        fields: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}
        out.append(Mover(mesh=(caster.vertices, caster.triangles), **fields))
    return out
