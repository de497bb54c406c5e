"""A render-benchmark run as a user states it (files and option values) -> scans, reference camera, config.

`sensorbox render-benchmark` fills a `BenchmarkRequest` from its options;
`prepare` builds the `BenchmarkConfig` and checks it and the rig's cam0 (the
reference Double Sphere calibration) before it reads the scans, which can
take minutes; then it reads them and adds world-frame mask clouds to every
scan (in that scan's frame) for `run_benchmark`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from calibration.camera import CameraModel
from calibration.rig import read_rig
from calibration.types import F32, F64
from ingest.errors import BenchmarkError
from ingest.raster.params import RenderParams, backend_problem
from ingest.raster.scan import Scan
from ingest.render.plan import (
    BASELINES_MM,
    FOVS_DEG,
    BenchmarkConfig,
    check_reference,
    fov_fisheye,
    sphere_rows,
)
from ingest.render.scans import read_mask_points, read_scans


@dataclass(frozen=True)
class BenchmarkRequest:
    """Inputs of one run in the CLI's units (degrees, mm, m); None picks the default."""

    scans: Sequence[Path]
    rig: Path
    out: Path
    fovs_deg: Sequence[float] | None = None  # default FOVS_DEG
    baselines_mm: Sequence[float] | None = None  # default BASELINES_MM
    yaws_deg: Sequence[float] | None = None  # default (0,)
    heights_m: Sequence[float] | None = None  # above each scan centre; default (0,)
    pitch_deg: float = 0.0
    centers: Sequence[str] | None = None  # scan names to put views at; default every scan
    size: str = "2048x1152"  # WIDTHxHEIGHT of fisheye and pinhole images
    bundle: int = 3
    workers: int = 2
    clip_m: float | None = None
    clip_mode: str = "invalid"  # invalid | drop
    masks: Sequence[Path] | None = None  # world-frame mask clouds
    mask_label: str = "label"  # per-point field marking masked points; "" for none
    points_per_px: float = 2.0
    height_full: int | None = None
    pinhole_fovs: Sequence[float] | None = None  # default (120,)
    site_id: int = 0
    exr: bool = True
    png_level: int = 1
    backend: str = "numba"  # numba | numpy | torch | cuda (RenderParams.backend)


def parse_size(text: str) -> tuple[int, int]:
    """'2048x1152' -> (2048, 1152)."""
    w, sep, h = text.lower().partition("x")
    if not sep or not w.isdigit() or not h.isdigit():
        raise BenchmarkError(f"--size {text!r}: expected WIDTHxHEIGHT, e.g. 2048x1152")
    return int(w), int(h)


def _check_backend(backend: str) -> None:
    """--backend: a known renderer whose requirements are here (`ingest.raster.params.backend_problem`)."""
    problem = backend_problem(backend)
    if problem is not None:
        raise BenchmarkError(f"--backend {backend!r}: {problem}")


def _to_scan(pts_world: F64, T_world_scan: F64) -> F32:
    """World points into a scan's frame (float32)."""
    return ((pts_world - T_world_scan[:3, 3]) @ T_world_scan[:3, :3]).astype(np.float32)


def _config(req: BenchmarkRequest) -> BenchmarkConfig:
    if req.clip_mode not in ("invalid", "drop"):
        raise BenchmarkError(f"--clip-mode {req.clip_mode!r}: expected invalid or drop")
    if not 0 <= req.png_level <= 3:
        raise BenchmarkError(f"--png-level {req.png_level}: expected 0..3")
    if not (req.points_per_px > 0 and math.isfinite(req.points_per_px)):
        raise BenchmarkError(f"--points-per-px {req.points_per_px}: must be a finite number > 0")
    fovs = tuple(req.fovs_deg or FOVS_DEG)
    if req.pinhole_fovs is not None and (stray := [f for f in req.pinhole_fovs if f not in fovs]):
        raise BenchmarkError(
            f"--pinhole-in {stray[0]:g}: not one of the rendered FOVs ({', '.join(f'{f:g}' for f in fovs)}); "
            "the pinhole images go into those folders"
        )
    _check_backend(req.backend)
    width, height = parse_size(req.size)
    render = RenderParams(points_per_px=req.points_per_px, clip_m=req.clip_m, clip_mode=req.clip_mode,  # type: ignore[arg-type]
                          backend=req.backend)  # type: ignore[arg-type]  # fmt: skip
    return BenchmarkConfig(
        fovs_deg=tuple(req.fovs_deg or FOVS_DEG), baselines_mm=tuple(req.baselines_mm or BASELINES_MM),
        width=width, height=height, yaws_deg=tuple(req.yaws_deg or (0.0,)),
        heights_m=tuple(req.heights_m or (0.0,)), pitch_deg=req.pitch_deg, centers=tuple(req.centers or ()),
        bundle=req.bundle, pinhole_fovs=tuple(req.pinhole_fovs or (120.0,)), height_full=req.height_full,
        site_id=req.site_id, exr=req.exr, png_level=req.png_level, workers=req.workers, render=render,
    )  # fmt: skip


def prepare(req: BenchmarkRequest) -> tuple[list[Scan], CameraModel, BenchmarkConfig]:
    """The scans (masks joined), the reference camera and the config of a request."""
    cfg = _config(req)
    cfg.validate()  # every option and the rig before the scans, which may take minutes to read
    reference = check_reference(read_rig(req.rig).camera("cam0").model)
    for fov_deg in cfg.fovs_deg:  # each equirect within the memory budget, before the scans are read
        sphere_rows(fov_fisheye(reference, fov_deg, cfg).model, fov_deg, cfg)
    site = read_scans(list(req.scans), req.mask_label or None)
    for m in req.masks or ():  # a world-frame mask cloud joins every scan, in that scan's frame
        world = read_mask_points(m).astype(np.float64)
        site = [
            replace(s, mask_xyz=np.concatenate([s.mask_xyz, _to_scan(world, s.T_world_scan)])) for s in site
        ]
    return site, reference, cfg
