"""A static terrestrial laser scanner (TLS) on the simulator's meshes: dense coloured scans with exact truth.

The scanner sits at `T_world_scan` (its frame: x forward, y left, z up,
levelled) and samples a regular azimuth x elevation grid, `step_deg` apart,
from `el_min_deg` (the tripod shadow below) up to the zenith, like a phase
scanner's panorama. Each ray is cast against the scene's opaque mesh; the
return is the exact hit (plus optional Gaussian range noise along the ray,
1-2 mm for a real TLS, 0 for exact tests), coloured by the simulator's texture
and lighting as a camera would see it (a TLS's colour panorama). Misses (sky)
give no point, as on a real scanner.

Glass is transparent to the scanner (it sees what is behind the pane, as real
scanners mostly do through clear glass). Where a ray crosses glass before its
hit, the crossing point goes into the scan's mask cloud, which the benchmark
renderer uses to write such pixels as invalid.

`true_range` answers the exact range along every pixel ray of any camera
model (and where glass lies in front), to score renderings of the scans.
`write_site` stores the scans as PLY or PCD (scan frame, float32 xyz + uchar
RGB; PCD files also carry the pose in their VIEWPOINT line) plus `site.yaml`
(every scan's file, pose and mask cloud) and the truth: `scene.ply`,
`transparent.ply` and the simulator parameters.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from calibration.camera import CameraModel
from calibration.errors import SensorboxError
from calibration.types import F32, F64, U8, Bool
from ingest.runtime.o3d import o3d
from sensorbox.sim.appearance import Texture, shade
from sensorbox.sim.raycast import Hits, RayCaster, write_ply
from sensorbox.sim.scenes import Scene

SITE_VERSION = 1


@dataclass(frozen=True)
class TlsParams:
    """Scanner parameters (angles in degrees at this edge, metres)."""

    step_deg: float = 0.2
    el_min_deg: float = -60.0
    el_max_deg: float = 90.0
    range_noise_m: float = 0.0
    min_range_m: float = 0.4
    max_range_m: float = 150.0
    seed: int = 0
    chunk_rays: int = 1_000_000  # rays per ray-cast batch: bounds the memory of a 20M-point scan

    def validate(self) -> None:
        if not (0.0 < self.step_deg <= 10.0):
            raise SensorboxError(f"TLS step_deg must be in (0, 10], got {self.step_deg!r}")
        if not (-90.0 <= self.el_min_deg < self.el_max_deg <= 90.0):
            raise SensorboxError(
                f"TLS elevation range {self.el_min_deg}..{self.el_max_deg} deg must lie in -90..90"
            )
        if self.range_noise_m < 0.0:
            raise SensorboxError(f"TLS range_noise_m must be >= 0, got {self.range_noise_m!r}")


@dataclass(frozen=True, eq=False)
class SimScan:
    """One simulated scan: points and colours in the scan frame, its pose and the glass crossings."""

    name: str
    T_world_scan: F64
    xyz_scan: F32  # (N, 3) metres
    rgb: U8  # (N, 3) RGB
    mask_xyz_scan: F32  # (M, 3) glass crossings, metres


def grid_size(params: TlsParams) -> tuple[int, int]:
    """(azimuth columns, elevation rows) of the scan grid."""
    n_az = round(360.0 / params.step_deg)
    n_el = math.floor((params.el_max_deg - params.el_min_deg) / params.step_deg) + 1
    return n_az, n_el


def scan_directions(params: TlsParams, rows: slice | None = None) -> F32:
    """Unit rays (N, 3) in the scan frame, elevation-row major; ``rows`` selects elevation rows."""
    n_az, n_el = grid_size(params)
    el = np.radians(params.el_min_deg + np.arange(n_el)[rows or slice(None)] * params.step_deg)
    az = np.radians(np.arange(n_az) * params.step_deg - 180.0)
    ce, se = np.cos(el)[:, None], np.sin(el)[:, None]
    d = np.empty((len(el), n_az, 3), np.float32)
    d[..., 0] = ce * np.cos(az)[None, :]
    d[..., 1] = ce * np.sin(az)[None, :]
    d[..., 2] = np.broadcast_to(se, (len(el), n_az))
    return d.reshape(-1, 3)


def simulate_scan(scene: Scene, texture: Texture, T_world_scan: F64, params: TlsParams, name: str) -> SimScan:
    """Cast the whole scan grid from `T_world_scan`; exact hits (plus noise), colours and glass crossings."""
    params.validate()
    rng = np.random.default_rng([params.seed, 0x715])
    glass_v, glass_t = scene.transparent_mesh()
    glass = RayCaster(glass_v, glass_t) if len(glass_t) else None
    n_az, n_el = grid_size(params)
    rows_per_chunk = max(1, params.chunk_rays // n_az)
    R, t = T_world_scan[:3, :3], T_world_scan[:3, 3]
    xyz_parts: list[F32] = []
    rgb_parts: list[U8] = []
    mask_parts: list[F32] = []
    for r0 in range(0, n_el, rows_per_chunk):
        dirs_scan = scan_directions(params, slice(r0, min(n_el, r0 + rows_per_chunk))).astype(np.float64)
        dirs = np.einsum("ij,nj->ni", R, dirs_scan)
        origins = np.broadcast_to(t, dirs.shape).copy()
        hits = scene.caster.cast(origins, dirs)
        rng_m = hits.range_m
        ok = np.isfinite(rng_m) & (rng_m >= params.min_range_m) & (rng_m <= params.max_range_m)
        colour = shade(scene, texture, origins[ok], dirs[ok], _subset(hits, ok))
        measured = rng_m[ok]
        if params.range_noise_m > 0.0:
            measured = measured + rng.normal(0.0, params.range_noise_m, measured.shape)
        xyz_parts.append((dirs_scan[ok] * measured[:, None]).astype(np.float32))
        rgb_parts.append(np.clip(np.round(colour[:, ::-1] * 255.0), 0, 255).astype(np.uint8))
        if glass is not None:
            g = glass.cast(origins, dirs).range_m
            crossing = np.isfinite(g) & (g < np.where(np.isfinite(rng_m), rng_m, np.inf))
            mask_parts.append((dirs_scan[crossing] * g[crossing, None]).astype(np.float32))
    mask = np.concatenate(mask_parts) if mask_parts else np.zeros((0, 3), np.float32)
    return SimScan(name, np.asarray(T_world_scan, np.float64), np.concatenate(xyz_parts),
                   np.concatenate(rgb_parts), mask)  # fmt: skip


def _subset(hits: Hits, ok: np.ndarray[Any, Any]) -> Hits:
    return Hits(hits.range_m[ok], hits.triangle[ok], hits.normal_world[ok])


def pose_at(position_world: F64 | list[float], yaw_deg: float = 0.0) -> F64:
    """A levelled scanner pose at ``position_world`` turned by ``yaw_deg`` about z."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    T[:3, 3] = np.asarray(position_world, np.float64)
    return T


def bundle_poses(centre_world: F64 | list[float], spacing_m: float = 1.0) -> list[F64]:
    """The paper's bundle of three: a central scan and two neighbours `spacing_m` to each side, set back."""
    c = np.asarray(centre_world, np.float64)
    return [
        pose_at(c),
        pose_at(c + np.array([-0.5 * spacing_m, spacing_m, 0.0]), 30.0),
        pose_at(c + np.array([-0.5 * spacing_m, -spacing_m, 0.0]), -30.0),
    ]


def true_range(scene: Scene, model: CameraModel, T_world_cam: F64) -> tuple[F64, Bool]:
    """Exact truth for a rendered view: range (m) along every pixel-centre ray, and glass in front.

    Returns ((H, W) range to the opaque mesh, NaN where the ray has none or
    hits nothing; (H, W) True where glass lies before that hit).
    """
    rays, ok = model.unproject(model.pixel_grid().reshape(-1, 2))
    dirs = np.einsum("ij,nj->ni", T_world_cam[:3, :3], rays[ok])
    origins = np.broadcast_to(T_world_cam[:3, 3], dirs.shape).copy()
    hit = scene.caster.cast(origins, dirs).range_m
    rng = np.full(len(rays), np.nan)
    rng[ok] = np.where(np.isfinite(hit), hit, np.nan)
    glass = np.zeros(len(rays), bool)
    gv, gt = scene.transparent_mesh()
    if len(gt):
        g = RayCaster(gv, gt).cast(origins, dirs).range_m
        glass[ok] = np.isfinite(g) & (g < np.where(np.isfinite(hit), hit, np.inf))
    shape = (model.height, model.width)
    return rng.reshape(shape), glass.reshape(shape)


def _write_cloud(path: Path, xyz: F32, rgb: U8 | None, T_world_scan: F64 | None) -> None:
    pc = o3d.t.geometry.PointCloud()
    pc.point.positions = o3d.core.Tensor.from_numpy(np.ascontiguousarray(xyz, np.float32))
    if rgb is not None:
        pc.point.colors = o3d.core.Tensor.from_numpy(np.ascontiguousarray(rgb, np.uint8))
    if not o3d.t.io.write_point_cloud(path, pc):
        raise SensorboxError(f"{path}: Open3D could not write the point cloud")
    if path.suffix == ".pcd" and T_world_scan is not None:
        _set_pcd_viewpoint(path, T_world_scan)


def _set_pcd_viewpoint(path: Path, T_world_scan: F64) -> None:
    """Rewrite the PCD header's VIEWPOINT (tx ty tz qw qx qy qz) to the scan pose."""
    data = path.read_bytes()
    start = data.index(b"VIEWPOINT")
    end = data.index(b"\n", start)
    qx, qy, qz, qw = Rotation.from_matrix(T_world_scan[:3, :3]).as_quat()
    tx, ty, tz = T_world_scan[:3, 3]
    line = "VIEWPOINT " + " ".join(f"{v:.10g}" for v in (tx, ty, tz, qw, qx, qy, qz))
    path.write_bytes(data[:start] + line.encode() + data[end:])


def write_site(
    out: Path,
    scene: Scene,
    scans: list[SimScan],
    fmt: Literal["ply", "pcd"] = "ply",
    params: TlsParams | None = None,
) -> Path:
    """Write the scans, their manifest `site.yaml` and the truth meshes into `out`; return the manifest."""
    if fmt not in ("ply", "pcd"):
        raise SensorboxError(f"TLS site format must be 'ply' or 'pcd', got {fmt!r}")
    out.mkdir(parents=True, exist_ok=True)
    entries = []
    for s in scans:
        cloud = out / f"{s.name}.{fmt}"
        _write_cloud(cloud, s.xyz_scan, s.rgb, s.T_world_scan)
        entry: dict[str, Any] = {
            "name": s.name, "file": cloud.name, "T_world_scan": np.round(s.T_world_scan, 12).tolist(),
        }  # fmt: skip
        if len(s.mask_xyz_scan):
            mask = out / f"{s.name}_mask.{fmt}"
            _write_cloud(mask, s.mask_xyz_scan, None, s.T_world_scan)
            entry["mask"] = mask.name
        entries.append(entry)
    write_ply(out / "scene.ply", *scene.opaque_mesh())
    write_ply(out / "transparent.ply", *scene.transparent_mesh())
    doc = {
        "sensorbox_site": SITE_VERSION,
        "name": f"{scene.name}-seed{scene.seed}",
        "frame": "world: x forward, y left, z up; metres; scan files hold points in their scan frame",
        "scans": entries,
        "truth": {
            "scene": scene.name, "seed": scene.seed, "mesh": "scene.ply", "transparent": "transparent.ply",
            "tls": asdict(params) if params is not None else None,
        },
    }  # fmt: skip
    manifest = out / "site.yaml"
    manifest.write_text("# SensorBox TLS site (simulated): scans, poses, mask clouds and truth\n"
                        + yaml.safe_dump(doc, sort_keys=False))  # fmt: skip
    return manifest
