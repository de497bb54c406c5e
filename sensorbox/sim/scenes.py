"""Procedural, seeded scenes for the virtual SensorBox (world frame: x forward, y left, z up, metres).

`indoor`: an 8 x 6 m room with tables, chairs on 2 cm legs, shelves, boxes and
hanging cables, a door into a 26 m corridor (a long depth tail), a glass pane
and a checkerboard. `outdoor`: a street with facades, poles, trees, a parked
car, a glass bus-stop panel and a checkerboard on a stand.

The seed moves and recolours the furniture; the checkerboard, the glass and the
walking lane (|y| < 0.7 m along x) are fixed, so trajectories never collide and
tests know where the checker corners are. Glass is `transparent`: both the
LiDARs and the cameras see through it (it is exported separately so users can
mask it), which is how a Mid-360 mostly behaves with clear glass.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from calibration.errors import SensorboxError
from calibration.types import F64
from sensorbox.sim.meshes import Mesh, box, cylinder, grid, merge, quad, sphere
from sensorbox.sim.movers import Mover, MovingCaster
from sensorbox.sim.raycast import Hits, RayCaster

SCENES = ("indoor", "outdoor")


@dataclass(frozen=True)
class Checkerboard:
    """A planar black/white board: square (i, j) spans origin + [i, i+1]*s*u + [j, j+1]*s*v.

    `u_world`, `v_world` are unit in-plane axes; the square at (0, 0) is black.
    """

    origin_world: F64
    u_world: F64
    v_world: F64
    square_m: float
    cols: int
    rows: int

    def inner_corners_world(self) -> F64:
        """((cols-1)*(rows-1), 3) inner corners, row-major in v then u."""
        i, j = np.meshgrid(np.arange(1, self.cols), np.arange(1, self.rows))
        return (
            self.origin_world
            + (i.reshape(-1, 1) * self.u_world + j.reshape(-1, 1) * self.v_world) * self.square_m
        )

    def shade(self, points_world: F64) -> F64:
        """Albedo in [0, 1] at points on the board: 0.05 black, 0.95 white, white border."""
        rel = points_world - self.origin_world
        a = rel @ self.u_world / self.square_m
        b = rel @ self.v_world / self.square_m
        inside = (a >= 0) & (a < self.cols) & (b >= 0) & (b < self.rows)
        black = ((np.floor(a) + np.floor(b)) % 2 == 0) & inside
        out: F64 = np.where(black, 0.05, 0.95)
        return out


@dataclass(frozen=True)
class SceneObject:
    """One named surface group with a base colour (BGR in [0, 1]) and a texture kind."""

    name: str
    mesh: Mesh
    color_bgr: tuple[float, float, float]
    texture: str = "noise"  # "noise" | "checker"
    transparent: bool = False
    checker: Checkerboard | None = None


@dataclass
class Scene:
    """A list of objects plus the merged opaque mesh the ray caster uses."""

    name: str
    seed: int
    objects: list[SceneObject]
    start_world: F64  # where trajectories begin (cam0 centre), metres
    sky: bool  # outdoor scenes are open: rays can miss everything
    movers: list[Mover] = field(default_factory=list)
    _caster: RayCaster | None = field(default=None, repr=False)
    _moving: MovingCaster | None = field(default=None, repr=False)
    _tri_object: np.ndarray[Any, np.dtype[np.int64]] | None = field(default=None, repr=False)

    def opaque_mesh(self) -> Mesh:
        return merge([o.mesh for o in self.objects if not o.transparent])

    def transparent_mesh(self) -> Mesh:
        parts = [o.mesh for o in self.objects if o.transparent]
        return merge(parts) if parts else (np.zeros((0, 3)), np.zeros((0, 3), np.int64))

    @property
    def caster(self) -> RayCaster:
        if self._caster is None:
            self._caster = RayCaster(*self.opaque_mesh())
        return self._caster

    def cast(self, origins_world: F64, dirs_world: F64, t_s: F64 | float = 0.0) -> Hits:
        """Rays at times `t_s` (s since the start; one per ray or one for all) against everything opaque.

        Triangle ids index `triangle_object`: the static mesh's, then each mover's.
        """
        if not self.movers:
            return self.caster.cast(origins_world, dirs_world)
        if self._moving is None:
            self._moving = MovingCaster(self.caster, self.movers)
        return self._moving.cast(origins_world, dirs_world, t_s)

    @property
    def triangle_object(self) -> np.ndarray[Any, np.dtype[np.int64]]:
        """Index into `shading_objects` for each triangle id `cast` returns."""
        if self._tri_object is None:
            ids = [np.full(len(o.mesh[1]), k) for k, o in enumerate(self.shading_objects)]
            self._tri_object = np.concatenate(ids).astype(np.int64)
        return self._tri_object

    @property
    def opaque_objects(self) -> list[SceneObject]:
        return [o for o in self.objects if not o.transparent]

    @property
    def shading_objects(self) -> list[SceneObject]:
        """The opaque objects, then the movers (body-frame meshes), in `cast`'s triangle order."""
        return self.opaque_objects + [SceneObject(m.name, m.mesh, m.color_bgr) for m in self.movers]

    @property
    def checkerboards(self) -> list[Checkerboard]:
        return [o.checker for o in self.objects if o.checker is not None]


def _checker_object(name: str, center: list[float], facing_deg: float, cols: int, rows: int) -> SceneObject:
    """A vertical board centred at `center`, its normal pointing along `facing_deg` (yaw, world)."""
    yaw = np.radians(facing_deg)
    normal = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    u = np.array([-np.sin(yaw), np.cos(yaw), 0.0])  # left-to-right as seen from the front is -u
    v = np.array([0.0, 0.0, -1.0])
    s = 0.08
    c = np.asarray(center, np.float64) + 0.001 * normal
    origin = c - (cols * u + rows * v) * s / 2
    border = 0.04
    mesh = quad(origin - border * (u + v), (cols * s + 2 * border) * u, (rows * s + 2 * border) * v)
    board = Checkerboard(origin, u, v, s, cols, rows)
    return SceneObject(name, mesh, (0.9, 0.9, 0.9), texture="checker", checker=board)


def _color(rng: np.random.Generator) -> tuple[float, float, float]:
    b, g, r = rng.uniform(0.25, 0.95, 3)
    return (float(b), float(g), float(r))


def _table(rng: np.random.Generator, x: float, y: float) -> list[SceneObject]:
    w, d, h = 1.2, 0.7, 0.74
    c = _color(rng)
    legs = [
        cylinder(
            [x + sx * (w / 2 - 0.04), y + sy * (d / 2 - 0.04), 0],
            [x + sx * (w / 2 - 0.04), y + sy * (d / 2 - 0.04), h - 0.03],
            0.0125,
            10,
        )
        for sx in (-1, 1)
        for sy in (-1, 1)
    ]
    return [
        SceneObject("table_top", box([x - w / 2, y - d / 2, h - 0.03], [x + w / 2, y + d / 2, h]), c),
        SceneObject("table_legs", merge(legs), (0.3, 0.3, 0.32)),
    ]


def _chair(rng: np.random.Generator, x: float, y: float) -> list[SceneObject]:
    s, h = 0.45, 0.45
    legs = [
        cylinder([x + sx * 0.2, y + sy * 0.2, 0], [x + sx * 0.2, y + sy * 0.2, h], 0.01, 8)
        for sx in (-1, 1)
        for sy in (-1, 1)
    ]
    c = _color(rng)
    return [
        SceneObject("chair_seat", box([x - s / 2, y - s / 2, h], [x + s / 2, y + s / 2, h + 0.03]), c),
        SceneObject(
            "chair_back", box([x + s / 2 - 0.03, y - s / 2, h + 0.03], [x + s / 2, y + s / 2, h + 0.5]), c
        ),
        SceneObject("chair_legs", merge(legs), (0.2, 0.2, 0.2)),
    ]


def build_indoor(seed: int) -> Scene:
    """Room x in [-4, 4], y in [-3, 3], z in [0, 2.8]; corridor x in [4, 30], |y| < 1, z < 2.5."""
    rng = np.random.default_rng(seed)
    objs: list[SceneObject] = []
    wall = (0.78, 0.8, 0.82)
    objs.append(SceneObject("floor", quad([-4, -3, 0], [8, 0, 0], [0, 6, 0]), (0.45, 0.55, 0.62)))
    objs.append(SceneObject("ceiling", quad([-4, -3, 2.8], [8, 0, 0], [0, 6, 0]), (0.9, 0.9, 0.9)))
    objs.append(SceneObject("wall_back", quad([-4, -3, 0], [0, 6, 0], [0, 0, 2.8]), wall))
    objs.append(SceneObject("wall_right", quad([-4, -3, 0], [8, 0, 0], [0, 0, 2.8]), (0.7, 0.78, 0.85)))
    objs.append(SceneObject("wall_left", quad([-4, 3, 0], [8, 0, 0], [0, 0, 2.8]), (0.85, 0.78, 0.7)))
    front = merge(
        [
            quad([4, -3, 0], [0, 2, 0], [0, 0, 2.8]),
            quad([4, 1, 0], [0, 2, 0], [0, 0, 2.8]),
            quad([4, -1, 2.2], [0, 2, 0], [0, 0, 0.6]),
        ]
    )
    objs.append(SceneObject("wall_front", front, wall))
    corridor = merge(
        [
            quad([4, -1, 0], [26, 0, 0], [0, 2, 0]),
            quad([4, -1, 2.5], [26, 0, 0], [0, 2, 0]),
            quad([4, -1, 0], [26, 0, 0], [0, 0, 2.5]),
            quad([4, 1, 0], [26, 0, 0], [0, 0, 2.5]),
        ]
    )
    objs.append(SceneObject("corridor", corridor, (0.6, 0.72, 0.8)))
    objs.append(SceneObject("corridor_end", quad([30, -1, 0], [0, 2, 0], [0, 0, 2.5]), (0.5, 0.4, 0.7)))
    for side in (-1, 1):
        objs += _table(rng, rng.uniform(-1.5, 1.5), side * rng.uniform(2.0, 2.3))
        objs += _chair(rng, rng.uniform(-2.5, 2.5), side * rng.uniform(1.3, 1.6))
    objs.append(
        SceneObject("shelf", box([-3.9, -2.5 + rng.uniform(0, 1), 0], [-3.5, -0.9, 2.0]), _color(rng))
    )
    for _ in range(3):
        x, y = rng.uniform(-3, 3), rng.choice([-1, 1]) * rng.uniform(1.0, 2.8)
        size = rng.uniform(0.2, 0.5, 3)
        objs.append(SceneObject("box", box([x, y, 0], [x + size[0], y + size[1], size[2]]), _color(rng)))
    cables = [
        cylinder(
            [rng.uniform(-3, 3), side * rng.uniform(1.0, 2.5), 2.8],
            [rng.uniform(-3, 3), side * 2.9, 0.0],
            0.006,
            8,
        )
        for side in (-1, 1, 1)
    ]
    objs.append(SceneObject("cables", merge(cables), (0.1, 0.1, 0.12)))
    objs.append(
        SceneObject(
            "glass", quad([1.5, -2.6, 0.4], [0, 1.3, 0], [0, 0, 1.6]), (0.8, 0.9, 0.9), transparent=True
        )
    )
    objs.append(_checker_object("checkerboard", [0.0, 1.0, 1.35], 180.0, 7, 5))
    objs.append(SceneObject("checker_stand", box([0.02, 0.95, 0.0], [0.06, 1.05, 1.12]), (0.2, 0.2, 0.2)))
    return Scene("indoor", seed, objs, np.array([-2.0, 0.0, 1.5]), sky=False)


def build_outdoor(seed: int) -> Scene:
    """A 200 m square ground, facades along |y| > 9 m, street furniture along the kerbs."""
    rng = np.random.default_rng(seed)
    objs: list[SceneObject] = [
        SceneObject("ground", grid([-100, -100, 0], [200, 0, 0], [0, 200, 0], 20), (0.35, 0.38, 0.4))
    ]
    for side in (-1, 1):
        x = -40.0
        while x < 90:
            w, depth, h = rng.uniform(8, 15), rng.uniform(8, 12), rng.uniform(6, 20)
            y0 = side * rng.uniform(9.0, 10.5)
            y1 = y0 + side * depth
            objs.append(SceneObject("facade", box([x, min(y0, y1), 0], [x + w, max(y0, y1), h]), _color(rng)))
            x += w + rng.uniform(0.0, 3.0)
        for k in range(-4, 11):
            px = 8.0 * k + rng.uniform(-1, 1)
            objs.append(
                SceneObject(
                    "pole", cylinder([px, side * 5.0, 0], [px, side * 5.0, 4.0], 0.06, 12), (0.3, 0.3, 0.3)
                )
            )
            tx = px + 4.0
            objs.append(
                SceneObject(
                    "tree_trunk",
                    cylinder([tx, side * 6.5, 0], [tx, side * 6.5, 2.6], 0.15, 12),
                    (0.2, 0.3, 0.4),
                )
            )
            objs.append(
                SceneObject(
                    "tree_crown", sphere([tx, side * 6.5, 3.8], rng.uniform(1.2, 1.8)), (0.2, 0.55, 0.25)
                )
            )
    cx, cy = 6.0 + rng.uniform(-1, 1), 3.2
    car = [
        box([cx - 2.15, cy - 0.9, 0.3], [cx + 2.15, cy + 0.9, 1.0]),
        box([cx - 1.1, cy - 0.8, 1.0], [cx + 1.0, cy + 0.8, 1.5]),
    ]
    wheels = [
        cylinder(
            [cx + sx * 1.4, cy + sy * 0.95 - 0.12, 0.33],
            [cx + sx * 1.4, cy + sy * 0.95 + 0.12, 0.33],
            0.33,
            16,
        )
        for sx in (-1, 1)
        for sy in (-1, 1)
    ]
    objs.append(SceneObject("car_body", merge(car), _color(rng)))
    objs.append(SceneObject("car_wheels", merge(wheels), (0.08, 0.08, 0.08)))
    objs.append(
        SceneObject(
            "glass", quad([12.0, -4.2, 0.2], [2.5, 0, 0], [0, 0, 2.0]), (0.8, 0.9, 0.9), transparent=True
        )
    )
    objs.append(_checker_object("checkerboard", [1.5, -1.3, 1.4], 180.0, 7, 5))
    objs.append(SceneObject("checker_stand", box([1.52, -1.35, 0.0], [1.56, -1.25, 1.17]), (0.2, 0.2, 0.2)))
    return Scene("outdoor", seed, objs, np.array([-2.0, 0.0, 1.5]), sky=True)


def build_scene(name: str, seed: int) -> Scene:
    """The named procedural scene for `seed` (deterministic)."""
    if name == "indoor":
        return build_indoor(seed)
    if name == "outdoor":
        return build_outdoor(seed)
    raise SensorboxError(f"unknown scene {name!r}; expected one of {', '.join(SCENES)}")
