"""One render task of a benchmark run: a camera of a view rendered from its bundle of scans, and its
images, depth and disparity maps encoded once and written into every FOV and baseline folder they
belong to (the layout is `ingest.render.benchmark`'s)."""

from __future__ import annotations

import hashlib
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from calibration.pinhole import Pinhole
from calibration.spherical import Equirectangular
from calibration.stereo import disparity_and_stability, pinhole_depth_to_disparity
from calibration.types import F32, F64
from calibration.virtual import partner_pose
from ingest.dataset.layout import DEPTH_SCALE, DISP_SCALE, encode_exr, to_uint16, write_atomic
from ingest.dataset.png import encode_png
from ingest.dataset.sparse import SparseImage
from ingest.errors import BenchmarkError
from ingest.raster.lod import ScanIndex
from ingest.raster.view import render_view
from ingest.render.plan import BenchmarkConfig, FovCameras, Task, View, baseline_label, fov_label


@dataclass
class RenderState:
    """What every render task of a run shares (the executor's `shared`: inherited by forked workers)."""

    out: Path
    cfg: BenchmarkConfig
    indexes: list[ScanIndex]
    views: dict[str, View]
    fovs: dict[float, FovCameras]
    pinhole: tuple[Pinhole, tuple[int, int, int, int]]


class _Writer:
    """Writes one task's files into every folder they belong to (encode once, write many)."""

    def __init__(self, state: RenderState, task: Task) -> None:
        self.state, self.task, self.dropped = state, task, 0
        self.disparity_px = 0  # valid pixels of the disparity maps, at the first baseline folder
        self.files: dict[str, dict[str, Any]] = {}  # path in the scene -> its bytes and SHA-256
        cfg, t = state.cfg, task
        fovs = [f for f in cfg.pinhole_fovs if f in cfg.fovs_deg] if t.fov_deg is None else [t.fov_deg]
        bases = cfg.baselines_mm if t.baseline_mm is None else (t.baseline_mm,)
        root = state.out / t.scene
        # (folder, baseline) for every <FOV>FOV/<B>mm/<camera> this render belongs to
        self.folders = [(root / fov_label(f) / baseline_label(b) / t.camera, b) for f in fovs for b in bases]

    def image(self, name: str, bgr: np.ndarray[Any, Any]) -> None:
        data = encode_png(bgr, self.state.cfg.png_level)
        for folder, _ in self.folders:
            self._write(folder / f"{name}.png", data)

    def depth(self, name: str, values: F32) -> None:
        """depth/<name>: one map for every baseline folder."""
        png, exr = self._encode(values, DEPTH_SCALE)
        for folder, _ in self.folders:
            self._put(folder / "depth", name, png, exr)

    def disparity(self, name: str, per_baseline: Callable[[float], F32]) -> None:
        """disparity/<name>: ``per_baseline(b_mm)`` for each baseline folder."""
        cache: dict[float, tuple[bytes, bytes | None]] = {}
        for folder, b in self.folders:
            if b not in cache:
                values = per_baseline(b)
                if not cache:
                    self.disparity_px += int(np.count_nonzero(values > 0))
                cache[b] = self._encode(values, DISP_SCALE)
            self._put(folder / "disparity", name, *cache[b])

    def _encode(self, values: F32, scale: float) -> tuple[bytes, bytes | None]:
        u16, dropped = to_uint16(SparseImage.from_dense(values), scale)
        self.dropped += dropped
        exr = encode_exr(values) if self.state.cfg.exr else None
        return encode_png(u16, self.state.cfg.png_level), exr

    def _put(self, folder: Path, name: str, png: bytes, exr: bytes | None) -> None:
        self._write(folder / f"{name}.png", png)
        if exr is not None:
            self._write(folder / f"{name}.exr", exr)

    def _write(self, path: Path, data: bytes) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(path, data)
        name = path.relative_to(self.state.out / self.task.scene).as_posix()
        self.files[name] = {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}


def _pad_full(crop: Equirectangular, img: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    full = np.zeros((crop.height_full, 2 * crop.height_full, *img.shape[2:]), img.dtype)
    full[crop.row_offset : crop.row_offset + crop.height, crop.col_offset : crop.col_offset + crop.width] = (
        img
    )
    return full


def _angular_disparity(
    range_m: F32, theta: F64, height_full: int, cfg: BenchmarkConfig
) -> Callable[[float], F32]:
    """Baseline (mm) -> angular disparity (px of the full sphere) of a range image, stability-masked.

    ``theta`` is each pixel's latitude from the pole opposite the partner
    (broadcast against the image).
    """
    r = range_m.astype(np.float64)
    th = np.broadcast_to(theta, r.shape)

    def disparity(b_mm: float) -> F32:
        b = b_mm / 1000.0
        d, stable = disparity_and_stability(
            r, th, b, height_full, cfg.stability_max_rel_error, cfg.stability_disp_error_px
        )
        out: F32 = np.where(stable & (r > 0), d, 0.0).astype(np.float32)
        return out

    return disparity


def _pinhole_disparity(z_m: F32, focal_px: float) -> Callable[[float], F32]:
    """Baseline (mm) -> f B / z of a z-depth image (0 stays 0)."""
    return lambda b_mm: pinhole_depth_to_disparity(z_m, focal_px, b_mm / 1000.0).astype(np.float32)


def run_task(s: RenderState, task: Task) -> tuple[Task, dict[str, int], dict[str, dict[str, Any]]]:
    """Render one camera and write its files; returns (task, render counts, the files written: path in
    the scene -> bytes and SHA-256)."""
    view = s.views[task.scene]
    T = view.T_world_center if task.baseline_mm is None else \
        partner_pose(view.T_world_center, task.camera, task.baseline_mm / 1000.0)  # fmt: skip
    sources = [s.indexes[i] for i in view.bundle]
    w = _Writer(s, task)
    center = task.camera == "CENTER"
    if task.product == "pinhole":
        model, (c0, r0, cw, ch) = s.pinhole
        rend = render_view(sources, model, T, s.cfg.render)
        crop = (slice(r0, r0 + ch), slice(c0, c0 + cw))
        w.image("pinhole", rend.bgr)
        w.image("pinhole_crop", np.ascontiguousarray(rend.bgr[crop]))
        if center:
            rays, _ = model.unproject(model.pixel_grid())
            z_full = (rend.range_m * rays[..., 2]).astype(np.float32)
            for name, z in (("pinhole", z_full), ("pinhole_crop", np.ascontiguousarray(z_full[crop]))):
                w.depth(name, z)
                w.disparity(name, _pinhole_disparity(z, model.fx))
    else:
        assert task.fov_deg is not None
        cams = s.fovs[task.fov_deg]
        if task.product == "fisheye":
            rend = render_view(sources, cams.fisheye.model, T, s.cfg.render)
            w.image("fisheye", rend.bgr)
            if center:
                w.depth("fisheye", rend.range_m)
        elif task.product == "pano":
            eq = cams.pano
            rend = render_view(sources, eq, T, s.cfg.render, pixel_mask=cams.pano_mask)
            w.image("pano_crop", rend.bgr)
            w.image("pano", _pad_full(eq, rend.bgr))
            if center:
                theta = eq.theta_of_row(np.arange(eq.height, dtype=np.float64))[:, None]
                disp = _angular_disparity(rend.range_m, theta, eq.height_full, s.cfg)
                w.depth("pano_crop", rend.range_m)
                w.disparity("pano_crop", disp)
                w.depth("pano", _pad_full(eq, rend.range_m))
                w.disparity("pano", lambda b: _pad_full(eq, disp(b)))
        elif task.product == "cassini":
            cas, hf = cams.cassini, cams.height_full
            rend = render_view(sources, cas, T, s.cfg.render, pixel_mask=cams.cassini_mask)
            w.image("cassini_crop", rend.bgr)
            if center:
                cols = np.arange(cas.width, dtype=np.float64) + cas.col_offset
                theta = ((cols + 0.5) * math.pi / hf)[None, :]  # latitude from -x: alpha + pi/2
                w.depth("cassini_crop", rend.range_m)
                w.disparity("cassini_crop", _angular_disparity(rend.range_m, theta, hf, s.cfg))
        else:  # pragma: no cover - plan_tasks makes only these
            raise BenchmarkError(f"unknown product {task.product!r}")
    stats = dict(rend.stats)
    stats["uint16_dropped"] = w.dropped
    if center and task.product != "fisheye":
        stats["disparity_px"] = w.disparity_px
    return task, stats, w.files
