"""Truth written next to every simulated bag, and exact range/disparity queries on it.

`<bag>.truth/` holds:
- `scene.ply`: the opaque world-frame triangle mesh (metres, float64 vertices);
- `transparent.ply`: surfaces both LiDARs and cameras see through (glass);
- `trajectory.tum`: T_world_cam0 at 1 kHz, `t_sec tx ty tz qx qy qz qw`;
- `rig.yaml` + `camchain.yaml`: the exact rig at the rendered resolution;
- `sim.yaml`: every parameter, the seed and the closed-form trajectory;
- with `--movers`: `movers.yaml` (each mover's closed-form path) and
  `mover_<name>.ply` (its body-frame mesh).

`Truth.load()` rebuilds the analytic trajectory from sim.yaml (the TUM file is
for other tools) and the movers' paths, so queries are exact at any time, not
interpolated: a ray at a stamp meets every mover where it is at that stamp.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from calibration.camera import CameraModel
from calibration.errors import SensorboxError
from calibration.rectify import StereoRectification, rectify_rig
from calibration.rig import Rig, read_rig, write_rig
from calibration.spherical import Equirectangular
from calibration.stereo import depth_to_disparity
from calibration.types import F64, I64
from sensorbox.sim.movers import Mover, MovingCaster, read_movers, write_movers
from sensorbox.sim.raycast import RayCaster, write_ply
from sensorbox.sim.scenes import Scene
from sensorbox.sim.trajectory import Trajectory, trajectory_from_params

TUM_RATE_HZ = 1000


def truth_dir(bag: Path) -> Path:
    """`<bag>.truth` beside a bag file or rosbag2 folder."""
    bag = Path(bag)
    return bag.with_name(bag.name + ".truth")


def write_truth(
    out: Path, scene: Scene, traj: Trajectory, rig: Rig, sim_params: dict[str, Any], tum_source: Path | None
) -> None:
    """Write the truth folder `out` (created; must not exist)."""
    out.mkdir(parents=True)
    write_ply(out / "scene.ply", *scene.opaque_mesh())
    write_ply(out / "transparent.ply", *scene.transparent_mesh())
    start_ns = int(sim_params["start_ns"])
    n = int(np.floor(float(sim_params["duration_s"]) * TUM_RATE_HZ)) + 1
    t_ns = np.arange(n, dtype=np.int64) * (1_000_000_000 // TUM_RATE_HZ)
    T = traj.T_world_cam0(t_ns / 1e9)
    q = Rotation.from_matrix(T[:, :3, :3]).as_quat()  # x, y, z, w
    with (out / "trajectory.tum").open("w") as f:
        f.write("# T_world_cam0: t_sec tx ty tz qx qy qz qw (world z up, metres)\n")
        for k in range(n):
            sec, nsec = divmod(start_ns + int(t_ns[k]), 1_000_000_000)
            f.write(f"{sec}.{nsec:09d} " + " ".join(f"{v:.9f}" for v in (*T[k, :3, 3], *q[k])) + "\n")
    write_rig(rig, out / "rig.yaml", camchain_name="camchain.yaml")
    if scene.movers:
        write_movers(out, scene.movers)
    if tum_source is not None:
        shutil.copyfile(tum_source, out / str(sim_params["trajectory"]["tum"]))
    (out / "sim.yaml").write_text(
        "# SensorBox simulator: every parameter of this run (times in ns, lengths in m)\n"
        + yaml.safe_dump(sim_params, sort_keys=False)
    )


@dataclass
class Truth:
    """Exact answers about a simulated run (times are header-stamp int64 ns)."""

    path: Path
    params: dict[str, Any]
    rig: Rig
    mesh: RayCaster
    trajectory: Trajectory
    movers: list[Mover] = field(default_factory=list)

    def __post_init__(self) -> None:
        self._moving = MovingCaster(self.mesh, self.movers) if self.movers else None

    def cast(self, origins_world: F64, dirs_world: F64, stamp_ns: int) -> F64:
        """Range (m) of rays at header stamp `stamp_ns` against the scene and its movers; inf on a miss."""
        t_s = (stamp_ns - self.start_ns) / 1e9
        if self._moving is None:
            return self.mesh.cast(origins_world, dirs_world).range_m
        return self._moving.cast(origins_world, dirs_world, t_s).range_m

    @classmethod
    def load(cls, path: Path) -> Truth:
        """Load `<bag>.truth/` (or pass the bag; its truth folder is found beside it)."""
        p = Path(path)
        if not (p / "sim.yaml").exists():
            p = truth_dir(p)
        if not (p / "sim.yaml").exists():
            raise SensorboxError(f"{path}: no simulator truth here (expected sim.yaml in {p})")
        params = yaml.safe_load((p / "sim.yaml").read_text())
        traj = trajectory_from_params(params["trajectory"], p)
        mesh = RayCaster.from_ply(p / "scene.ply")
        return cls(p, params, read_rig(p / "rig.yaml"), mesh, traj, read_movers(p))

    @property
    def start_ns(self) -> int:
        return int(self.params["start_ns"])

    @property
    def camera_offset_ns(self) -> tuple[int, int]:
        """(upper, lower) header stamp minus true mid-exposure (ns): `simulate --camera-offset-ms`."""
        upper, lower = self.params.get("realism", {}).get("camera_offset_ns", (0, 0))
        return int(upper), int(lower)

    def exposure_ns(self, stamp_ns: int, camera: int = 0) -> int:
        """The true mid-exposure time (LiDAR clock, ns) of a frame of camera 0 (upper) or 1 (lower)
        stamped `stamp_ns` in the bag."""
        return int(stamp_ns) - self.camera_offset_ns[camera]

    def T_world_cam0(self, stamps_ns: I64) -> F64:
        """(N,4,4) exact cam0 poses at header stamps `stamps_ns`."""
        t = (np.atleast_1d(np.asarray(stamps_ns, np.int64)) - self.start_ns) / 1e9
        return self.trajectory.T_world_cam0(t)

    def mover_range_along(self, rays_cam0: F64, stamp_ns: int, mover_stamp_ns: int) -> F64:
        """Range (m) along rays from cam0 at `stamp_ns` to the movers where they were at `mover_stamp_ns`.

        NaN where no mover is hit (and everywhere without movers).
        """
        if self._moving is None:
            return np.full(len(rays_cam0), np.nan)
        T = self.T_world_cam0(np.array([stamp_ns]))[0]
        dirs = np.asarray(rays_cam0, np.float64) @ T[:3, :3].T
        origins = np.broadcast_to(T[:3, 3], dirs.shape).copy()
        t_s = (mover_stamp_ns - self.start_ns) / 1e9
        r = self._moving.cast(origins, dirs, t_s, static=False).range_m
        out: F64 = np.where(np.isfinite(r), r, np.nan)
        return out

    def range_along(self, rays_cam0: F64, stamp_ns: int) -> F64:
        """Exact range (m) from cam0's centre along unit rays given in cam0; NaN where nothing is hit."""
        T = self.T_world_cam0(np.array([stamp_ns]))[0]
        dirs = np.asarray(rays_cam0, np.float64) @ T[:3, :3].T
        range_m = self.cast(np.broadcast_to(T[:3, 3], dirs.shape).copy(), dirs, stamp_ns)
        out: F64 = np.where(np.isfinite(range_m), range_m, np.nan)
        return out

    def range_at(
        self, model: CameraModel, pixels: F64, stamp_ns: int, R_cam0_model: F64 | None = None
    ) -> F64:
        """Exact range at `pixels` of `model` (cam0's centre; rotated by R_cam0_model); NaN if invalid."""
        rays, ok = model.unproject(pixels)
        if R_cam0_model is not None:
            rays = rays @ np.asarray(R_cam0_model).T
        out = np.full(len(rays), np.nan)
        out[ok] = self.range_along(rays[ok], stamp_ns)
        return out

    def rectification(self) -> StereoRectification:
        return rectify_rig(self.rig)

    def disparity_at(self, eq: Equirectangular, pixels: F64, stamp_ns: int) -> F64:
        """Exact vertical-stereo disparity (px of `eq`'s full sphere) at pixels of cam0's rectified equirect.

        NaN where the ray hits nothing.
        """
        rect = self.rectification()
        rays, ok = eq.unproject(pixels)
        range_m = self.range_at(eq, pixels, stamp_ns, rect.R_cam0_rect)
        theta = np.arccos(np.clip(-rays[:, 1], -1.0, 1.0))
        disp = depth_to_disparity(np.nan_to_num(range_m, nan=0.0), theta, rect.baseline_m, eq.height_full)
        out: F64 = np.where(ok & np.isfinite(range_m), disp, np.nan)
        return out
