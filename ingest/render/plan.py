"""What a benchmark run renders: its config, the virtual cameras per FOV, the views (poses, scan
bundles) and one task per camera."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from calibration.camera import CameraModel
from calibration.errors import CalibrationError
from calibration.fisheye import DoubleSphere
from calibration.kalibr import MAX_IMAGE_SIDE_PX
from calibration.pinhole import Pinhole
from calibration.spherical import Cassini, Equirectangular, pinhole_for_fov
from calibration.types import F64, Bool
from calibration.virtual import (
    CroppedModel,
    R_up_cam,
    VirtualFisheye,
    crop_bounds,
    virtual_fisheye,
)
from calibration.warp import (
    build_maps,
    check_height_full,
    covering_crop,
    default_height_full,
    height_full_problem,
)
from ingest.errors import BenchmarkError
from ingest.raster.lod import VOXEL_M
from ingest.raster.params import RenderParams
from ingest.raster.scan import Scan

FOVS_DEG = (120.0, 140.0, 165.0, 195.0)


BASELINES_MM = (20.0, 65.0, 120.0, 200.0, 300.0)
MAX_YAW_DEG = 360.0
"""Largest |--yaw| (degrees): one turn either way names every heading. Beyond it a value is a typo or
another unit, and far beyond it the float's rounding picks the heading: 1e300 was rendered at
some arbitrary yaw (sin -0.75, cos -0.67) and recorded as 1e300 degrees."""

MAX_BASELINE_MM = 2000.0
"""Largest --baseline (mm): two metres, the most a handheld rig spans (the rig's lever arms are bounded
alike). 1e300 was rendered with float overflow warnings into a folder named `1e+300mm`."""
MAX_VIEW_HEIGHT_M = 100.0
"""Largest |--height| (m) of a view above its scan centre: a terrestrial scan sees a few tens of metres
up or down, so a view beyond 100 m is outside the scanned space (1e300 overflowed as --baseline did)."""


@dataclass(frozen=True)
class BenchmarkConfig:
    """Everything a benchmark run depends on (degrees and millimetres at this edge, as in the layout)."""

    fovs_deg: tuple[float, ...] = FOVS_DEG
    baselines_mm: tuple[float, ...] = BASELINES_MM
    width: int = 2048
    height: int = 1152
    yaws_deg: tuple[float, ...] = (0.0,)
    heights_m: tuple[float, ...] = (0.0,)
    pitch_deg: float = 0.0
    centers: tuple[str, ...] = ()  # scan names used as view centres; empty = every scan
    bundle: int = 3  # scans rendered per view: the centre and its nearest neighbours
    pinhole_fov_deg: float = 90.0
    pinhole_fovs: tuple[float, ...] = (120.0,)  # FOV folders that get the pinhole images
    pinhole_crop: float = 0.5  # pinhole_crop = the central fraction of the pinhole image per axis
    height_full: int | None = None  # rows of the full sphere; default: each fisheye's centre resolution
    site_id: int = 0
    voxel_m: float = VOXEL_M
    stability_max_rel_error: float = 0.5  # disparity stability mask (calibration.stereo)
    stability_disp_error_px: float = 0.5
    exr: bool = True
    png_level: int = 1
    workers: int = 2
    render: RenderParams = field(default_factory=RenderParams)

    def validate(self) -> None:
        if not self.fovs_deg or any(not 0.0 < f < 360.0 for f in self.fovs_deg):
            raise BenchmarkError(f"--fov {list(self.fovs_deg)}: each FOV must be in (0, 360) degrees")
        if not self.baselines_mm or any(not (b > 0.0 and math.isfinite(b)) for b in self.baselines_mm):
            raise BenchmarkError(
                f"--baseline {list(self.baselines_mm)}: each baseline must be a finite number > 0 mm"
            )
        for option, values in (
            ("--yaw", self.yaws_deg),
            ("--height", self.heights_m),
            ("--pitch", (self.pitch_deg,)),
        ):
            if not all(math.isfinite(v) for v in values):
                raise BenchmarkError(f"{option} {list(values)}: each value must be a finite number")
        _given_once("--fov", self.fovs_deg)
        _given_once("--baseline", self.baselines_mm)
        _given_once("--yaw", self.yaws_deg, turn=True)
        _given_once("--height", self.heights_m)
        _given_once("--center", self.centers)
        if any(b > MAX_BASELINE_MM for b in self.baselines_mm):
            raise BenchmarkError(
                f"--baseline {list(self.baselines_mm)}: each baseline must be at most {MAX_BASELINE_MM:g} mm"
            )
        if any(abs(h) > MAX_VIEW_HEIGHT_M for h in self.heights_m):
            raise BenchmarkError(
                f"--height {list(self.heights_m)}: each height must be within -{MAX_VIEW_HEIGHT_M:g}.."
                f"{MAX_VIEW_HEIGHT_M:g} m"
            )
        if any(abs(yaw) > MAX_YAW_DEG for yaw in self.yaws_deg):
            raise BenchmarkError(
                f"--yaw {list(self.yaws_deg)}: each yaw must be within -{MAX_YAW_DEG:g}..{MAX_YAW_DEG:g} "
                "degrees"
            )
        if not -90.0 <= self.pitch_deg <= 90.0:
            raise BenchmarkError(f"--pitch {self.pitch_deg}: must be within -90..90 degrees (up > 0)")
        clip = self.render.clip_m
        if clip is not None and not (clip > 0.0 and math.isfinite(clip)):
            raise BenchmarkError(f"--clip {clip}: must be a finite number > 0 m")
        if self.height_full is not None and (problem := height_full_problem(self.height_full)) is not None:
            raise BenchmarkError(problem)
        if self.site_id < 0:
            raise BenchmarkError(f"--site-id must be >= 0, got {self.site_id}")
        if self.width < 8 or self.height < 8:
            raise BenchmarkError(f"image size {self.width}x{self.height}: both must be >= 8 px")
        if max(self.width, self.height) > MAX_IMAGE_SIDE_PX:
            raise BenchmarkError(
                f"--size {self.width}x{self.height}: expected at most {MAX_IMAGE_SIDE_PX} px a side"
            )
        if self.bundle < 1 or self.workers < 1:
            raise BenchmarkError(f"--bundle {self.bundle} and --workers {self.workers} must be >= 1")
        if not 0.0 < self.pinhole_crop <= 1.0 or not 0.0 < self.pinhole_fov_deg < 180.0:
            raise BenchmarkError("pinhole FOV must be in (0, 180) degrees and its crop fraction in (0, 1]")


def _given_once(option: str, values: Sequence[float | str], turn: bool = False) -> None:
    """Refuse a value given twice (`turn`: yaws, the same modulo 360 degrees): its views would be
    rendered twice, as two scenes or folders weighing double in every score."""
    seen: dict[float | str, float | str] = {}
    for value in values:
        key = value % 360.0 if turn and isinstance(value, float) else value
        if key in seen:
            first = seen[key]
            same = "" if first == value else f" (the same as {_text(first)})"
            raise BenchmarkError(
                f"{option} {_text(value)}{same} is given twice; its views would be rendered twice and "
                "weigh double in every score"
            )
        seen[key] = value


def _text(value: float | str) -> str:
    return f"{value:g}" if isinstance(value, float) else value


@dataclass(frozen=True)
class FovCameras:
    """The cameras of one FOV folder (all in the CENTER camera's frame; partners share it)."""

    fisheye: VirtualFisheye
    pano: Equirectangular  # the crop; its full sphere is pano.full()
    pano_mask: Bool
    cassini: CroppedModel  # window of Cassini(height_full)
    cassini_mask: Bool
    height_full: int  # rows of the full sphere (pano) = columns of the full Cassini


@dataclass(frozen=True)
class View:
    """One benchmark scene: a centre scan, its bundle, yaw, height and the CENTER pose."""

    scene: str
    center: int
    bundle: tuple[int, ...]
    yaw_deg: float
    height_m: float
    T_world_center: F64


@dataclass(frozen=True)
class Task:
    """One rendered camera: CENTER (baseline None) or a partner at one baseline."""

    scene: str
    camera: str  # CENTER | DOWN | RIGHT
    product: str  # fisheye | pano | cassini | pinhole
    fov_deg: float | None  # None for the pinhole (FOV-independent)
    baseline_mm: float | None


def fov_label(fov: float) -> str:
    return f"{fov:g}FOV"


def baseline_label(b_mm: float) -> str:
    return f"{b_mm:g}mm"


def _window_mask(fisheye: CameraModel, full: CameraModel, factor: int = 8) -> tuple[int, int, int, int]:
    """Window (col, row, width, height) of ``full`` holding every ray the fisheye sees.

    Decided on a ``factor``-times coarser grid of ``full``'s pixels (their rays
    projected into the fisheye), grown by one coarse pixel: robust to seams.
    """
    H, W = full.height, full.width
    us = np.arange(0, W, factor, dtype=np.float64) + (factor - 1) / 2.0
    vs = np.arange(0, H, factor, dtype=np.float64) + (factor - 1) / 2.0
    grid = np.stack(np.meshgrid(us, vs), axis=-1)
    rays, ok = full.unproject(grid)
    uv, ok2 = fisheye.project(np.where(ok[..., None], rays, 0.0))
    seen = ok & ok2 & fisheye.in_image(uv)
    c0, r0, w, h = crop_bounds(seen, 1)
    return (c0 * factor, r0 * factor, min(W - c0 * factor, w * factor), min(H - r0 * factor, h * factor))


def check_reference(reference: CameraModel) -> DoubleSphere:
    """The rig's cam0, which must be Double Sphere: the virtual fisheyes' FOV laws are fitted to it."""
    if not isinstance(reference, DoubleSphere):
        raise BenchmarkError(
            f"the reference camera must be Double Sphere (the FOV laws), got {type(reference).__name__}"
        )
    return reference


def sphere_rows(fisheye: CameraModel, fov_deg: float, cfg: BenchmarkConfig) -> int:
    """Rows of the full sphere for a fisheye of `fov_deg`: --height-full, else its centre's resolution;
    refused when over the memory budget, naming what chose it (--height-full or --size)."""
    if cfg.height_full is not None:
        return check_height_full(cfg.height_full)
    rows = default_height_full(fisheye)
    given_by = f"--size {cfg.width}x{cfg.height} (the {fov_deg:g} deg fisheye's default --height-full {rows})"
    return check_height_full(rows, given_by=given_by)


def fov_fisheye(reference: DoubleSphere, fov_deg: float, cfg: BenchmarkConfig) -> VirtualFisheye:
    """The virtual fisheye of ``fov_deg`` at --size; BenchmarkError naming --fov when no camera of that
    FOV fits the size (0.001 deg asked for a focal length of 7.5e6 px, beyond the models' bounds)."""
    try:
        return virtual_fisheye(reference, fov_deg, cfg.width, cfg.height)
    except CalibrationError as err:
        raise BenchmarkError(
            f"--fov {fov_deg:g}: no {cfg.width}x{cfg.height} fisheye of that FOV ({err})"
        ) from err


def fov_cameras(reference: DoubleSphere, fov_deg: float, cfg: BenchmarkConfig) -> FovCameras:
    """The fisheye of ``fov_deg`` and the equirect/Cassini windows covering it."""
    fish = fov_fisheye(reference, fov_deg, cfg)
    hf = sphere_rows(fish.model, fov_deg, cfg)
    pano = covering_crop(fish.model, np.eye(3), hf)
    c0, r0, w, h = _window_mask(fish.model, Cassini(hf))
    cas = CroppedModel(Cassini(hf), c0, r0, w, h)
    return FovCameras(
        fish, pano, build_maps(fish.model, pano).valid, cas, build_maps(fish.model, cas).valid, hf
    )


def pinhole_camera(cfg: BenchmarkConfig) -> tuple[Pinhole, tuple[int, int, int, int]]:
    """The pinhole and its central crop window (col, row, width, height)."""
    ph = pinhole_for_fov(math.radians(cfg.pinhole_fov_deg), cfg.width, cfg.height)
    w = max(1, round(cfg.width * cfg.pinhole_crop))
    h = max(1, round(cfg.height * cfg.pinhole_crop))
    return ph, ((cfg.width - w) // 2, (cfg.height - h) // 2, w, h)


def bundles(scans: list[Scan], size: int) -> list[tuple[int, ...]]:
    """For each scan: itself and its ``size - 1`` nearest scans (by scanner position)."""
    pos = np.array([s.origin_world for s in scans])
    out = []
    for k in range(len(scans)):
        d = np.linalg.norm(pos - pos[k], axis=1)
        d[k] = -1.0
        out.append(tuple(int(i) for i in np.argsort(d, kind="stable")[: min(size, len(scans))]))
    return out


def plan_views(scans: list[Scan], cfg: BenchmarkConfig) -> list[View]:
    """Every (centre, yaw, height) view; scene ids `<site>_<centre>_<view>`."""
    names = [s.name for s in scans]
    centers: list[int] = list(range(len(scans))) if not cfg.centers else []
    for name in cfg.centers:
        if name not in names:
            raise BenchmarkError(f"--center {name!r}: no such scan (have: {', '.join(names)})")
        centers.append(names.index(name))
    groups = bundles(scans, cfg.bundle)
    views = []
    for c in centers:
        k = 0
        for height in cfg.heights_m:
            for yaw in cfg.yaws_deg:
                T_scan_cam = np.eye(4)
                T_scan_cam[:3, :3] = R_up_cam(math.radians(yaw), math.radians(cfg.pitch_deg))
                T_scan_cam[2, 3] = height
                scene = f"{cfg.site_id:03d}_{c:03d}_{k:03d}"
                views.append(View(scene, c, groups[c], yaw, height, scans[c].T_world_scan @ T_scan_cam))
                k += 1
    return views


# What each camera renders. Both partners get the pinhole and the pano, so every (image type,
# partner) pair of the WideDepth release loader has its images: DOWN/pinhole* is the vertical
# pinhole pair (f B / z serves it too); RIGHT/pano* is exact as images, but the horizontal pair's
# exact disparity is cassini_crop's (disparity/pano* is the vertical pair's)
PRODUCTS = {
    "CENTER": ("fisheye", "pano", "cassini"),
    "DOWN": ("fisheye", "pano"),
    "RIGHT": ("fisheye", "cassini", "pano"),
}


def plan_tasks(views: list[View], cfg: BenchmarkConfig) -> list[Task]:
    """One task per rendered camera of every view (pinholes are FOV-independent: one per camera)."""
    tasks = []
    for v in views:
        tasks.append(Task(v.scene, "CENTER", "pinhole", None, None))
        tasks += [Task(v.scene, "CENTER", p, f, None) for f in cfg.fovs_deg for p in PRODUCTS["CENTER"]]
        for b in cfg.baselines_mm:
            for cam in ("DOWN", "RIGHT"):
                tasks.append(Task(v.scene, cam, "pinhole", None, b))
                tasks += [Task(v.scene, cam, p, f, b) for f in cfg.fovs_deg for p in PRODUCTS[cam]]
    return tasks


def task_key(t: Task) -> str:
    """'120FOV/65mm/DOWN/fisheye' style name of a render (CENTER: 'CENTER/...'; pinhole: no FOV)."""
    parts = [] if t.fov_deg is None else [fov_label(t.fov_deg)]
    parts += [] if t.baseline_mm is None else [baseline_label(t.baseline_mm)]
    return "/".join([*parts, t.camera, t.product])
