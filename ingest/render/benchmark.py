"""Benchmark views from dense laser scans, written in the WideDepth benchmark layout.

For every view (a scan centre of the site, a yaw and a height) the renderer
(`ingest.raster.view`) draws the scans of that centre's bundle (the central scan and
its nearest neighbours, the paper's bundle of three) through virtual cameras:

- CENTER: the reference camera, level at the scan centre (plus the view's
  height), looking along the view's yaw;
- DOWN: its vertical-stereo partner, the baseline below (+y of the camera);
- RIGHT: its horizontal-stereo partner, the baseline to the right (+x).

Layout (`<scene>` = `<site>_<centre scan>_<view>`, three digits each)::

    <scene>/scene.yaml                      every camera, pose, parameter and count (written last)
    <scene>/<FOV>FOV/<B>mm/CENTER/<image>.png
    <scene>/<FOV>FOV/<B>mm/CENTER/depth/<image>.png      uint16 mm (range; z for pinhole), 0 = invalid
    <scene>/<FOV>FOV/<B>mm/CENTER/disparity/<image>.png  uint16 px x 100, 0 = invalid
    <scene>/<FOV>FOV/<B>mm/DOWN/{fisheye,pano,pano_crop,pinhole,pinhole_crop}.png
    <scene>/<FOV>FOV/<B>mm/RIGHT/{fisheye,cassini_crop,pano,pano_crop,pinhole,pinhole_crop}.png
    (depth/ and disparity/ also hold float32 EXR copies, <image>.exr)

Images: `fisheye` (the virtual DS lens of that FOV), `pano` (the full-sphere
equirect, H_full x 2 H_full, showing what the fisheye sees), `pano_crop` (the
smallest window of it holding that), `cassini_crop` (the transverse equirect,
window likewise), `pinhole` (90 degrees wide, the fisheye's size) and
`pinhole_crop` (its centre). Disparity: `pano`/`pano_crop` for the vertical
pair CENTER-DOWN (DESIGN.md's angular formula, stability-masked);
`pinhole`/`pinhole_crop` (f B / z, the same for the vertical pinhole pair
CENTER-DOWN and the horizontal one CENTER-RIGHT: fx = fy) and `cassini_crop`
(the angular formula with the latitude from -x) for the horizontal pair. Both
partners get every image type, so each (image type, partner) pair the
WideDepth release loader reads has its images; `RIGHT/pano*` are exact images
of the RIGHT camera in CENTER's orientation, but a horizontal baseline has no
per-pixel disparity along an equirect's columns: that pair's exact disparity
is `cassini_crop`'s, and a loader that pairs `RIGHT/pano*` with
`disparity/pano*` gets the vertical pair's. The pinhole images go only to the
FOV folders of `pinhole_fovs` (120, as in the WideDepth release), the other
images to every folder.

Work is one task per rendered camera; tasks run in a local process pool
(forked, so the scans' level-of-detail index is shared, not copied). A scene
whose scene.yaml exists is skipped on a rerun when it was rendered with the
same cameras, baselines and render settings, from the same scans at the same
poses and view; otherwise the run is refused, naming what differs. scene.yaml
lists every file of its scene with its size and SHA-256: a finished scene
with a file deleted, cut short or overwritten is rendered again, as ingest
writes a damaged sample again.
"""

from __future__ import annotations

import hashlib
import math
import multiprocessing
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from calibration.camera import CameraModel
from calibration.opencv_yaml import yaml_error_line
from calibration.pinhole import Pinhole
from calibration.spherical import Equirectangular
from calibration.stereo import disparity_and_stability, pinhole_depth_to_disparity
from calibration.types import F32, F64
from calibration.virtual import (
    partner_pose,
)
from ingest.dataset.compare import first_difference
from ingest.dataset.identity import file_problem
from ingest.dataset.layout import DEPTH_SCALE, DISP_SCALE, encode_exr, to_uint16, write_atomic
from ingest.dataset.lock import hold_folder
from ingest.dataset.png import encode_png, read_image
from ingest.dataset.sparse import SparseImage
from ingest.errors import BenchmarkError, OutputError
from ingest.raster.lod import ScanIndex, build_index
from ingest.raster.scan import Scan
from ingest.raster.view import pixel_geometry, render_view
from ingest.render.plan import (
    BenchmarkConfig,
    FovCameras,
    Task,
    View,
    baseline_label,
    check_reference,
    fov_cameras,
    fov_label,
    pinhole_camera,
    plan_tasks,
    plan_views,
    task_key,
)
from ingest.render.scans import frame_hint
from ingest.runtime.executor import Executor, share_cores

BENCHMARK_VERSION = 1
EMPTY_RENDER_FRACTION = 0.01  # a render drawing a surface in fewer of its pixels with a ray is empty
# which disparity map belongs to which stereo pair (scene.yaml's conventions.pairs)
PAIRS_DOC = {
    "vertical CENTER-DOWN": {
        "pano, pano_crop": "exact: disparity/pano, disparity/pano_crop (along columns)",
        "pinhole, pinhole_crop": "exact: disparity/pinhole* (f B / z, along columns)",
    },
    "horizontal CENTER-RIGHT": {
        "cassini_crop": "exact: disparity/cassini_crop (along rows)",
        "pinhole, pinhole_crop": "exact: disparity/pinhole* (f B / z, along rows)",
        "pano, pano_crop": "images exact (RIGHT in CENTER's orientation); their exact disparity is "
        "given in cassini_crop: disparity/pano* is the vertical pair's, not this pair's",
    },
}


@dataclass
class BenchmarkSummary:
    """What a run did: scenes, renders, files and per-render counts."""

    out: Path
    scenes: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    renders: int = 0
    files: int = 0
    seconds: float = 0.0
    index_seconds: float = 0.0
    stats: dict[str, dict[str, dict[str, int]]] = field(default_factory=dict)  # scene -> render key -> counts
    empty: dict[str, list[str]] = field(default_factory=dict)  # scene -> renders showing (almost) nothing
    warnings: list[str] = field(default_factory=list)  # one line per scene with empty renders
    stale_temporaries: int = 0  # left by a killed run, removed (`ingest.dataset.lock`)
    damaged: list[str] = field(default_factory=list)  # finished scenes found damaged, rendered again: why


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
                cache[b] = self._encode(per_baseline(b), DISP_SCALE)
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
    return task, stats, w.files


def empty_renders(stats: dict[str, dict[str, int]]) -> list[str]:
    """Render keys of a scene drawing a surface in under EMPTY_RENDER_FRACTION of their pixels with a ray."""
    return [k for k, st in stats.items() if st["surface_px"] < EMPTY_RENDER_FRACTION * st["pixels_with_ray"]]


def _empty_warning(scene: str, empty: list[str], stats: dict[str, dict[str, int]], scan: Scan) -> str:
    worst = min(empty, key=lambda k: stats[k]["surface_px"] / max(stats[k]["pixels_with_ray"], 1))
    pct = 100.0 * stats[worst]["surface_px"] / max(stats[worst]["pixels_with_ray"], 1)
    limit = f"under {100 * EMPTY_RENDER_FRACTION:g} % of pixels drawn; {worst}: {pct:.2f} %"
    what = f"{len(empty)} of {len(stats)} renders show (almost) nothing ({limit})"
    return f"{scene}: {what}; {frame_hint(scan)}"


def _cameras_doc(
    cfg: BenchmarkConfig, fovs: dict[float, FovCameras], pinhole: tuple[Pinhole, tuple[int, int, int, int]]
) -> dict[str, Any]:
    """scene.yaml's `cameras`: every product's model per FOV folder."""
    ph, (c0, r0, cw, ch) = pinhole
    cams: dict[str, Any] = {}
    for f in cfg.fovs_deg:
        fc = fovs[f]
        eq, cas = fc.pano, fc.cassini
        cams[fov_label(f)] = {
            "fisheye": fc.fisheye.report(),
            "pano": {"model": "equirect", "height_full": eq.height_full, "width": 2 * eq.height_full,
                     "height": eq.height_full, "pole": "-y (up)", "content": "what the fisheye sees"},
            "pano_crop": {"model": "equirect", "height_full": eq.height_full, "row_offset": eq.row_offset,
                          "col_offset": eq.col_offset, "width": eq.width, "height": eq.height},
            "cassini_crop": {"model": "cassini", "height_full": fc.height_full,
                             "col_offset": cas.col_offset, "row_offset": cas.row_offset,
                             "width": cas.width, "height": cas.height},
            **({"pinhole": {"model": "pinhole", "fov_deg": cfg.pinhole_fov_deg, "fx": ph.fx, "fy": ph.fy,
                            "cx": ph.cx, "cy": ph.cy, "width": ph.width, "height": ph.height},
                "pinhole_crop": {"model": "pinhole", "fx": ph.fx, "fy": ph.fy, "cx": ph.cx - c0,
                                 "cy": ph.cy - r0, "width": cw, "height": ch, "col_offset": c0,
                                 "row_offset": r0}} if f in cfg.pinhole_fovs else {}),
        }  # fmt: skip
    return cams


def _setup_doc(
    cfg: BenchmarkConfig, fovs: dict[float, FovCameras], pinhole: tuple[Pinhole, tuple[int, int, int, int]]
) -> dict[str, Any]:
    """What a finished scene must share with a rerun that skips it: cameras, baselines, render settings
    (as scene.yaml holds them, so that a read-back file compares equal)."""
    doc = {"cameras": _cameras_doc(cfg, fovs, pinhole), "baselines_mm": list(cfg.baselines_mm),
           "render": asdict(cfg.render)}  # fmt: skip
    out: dict[str, Any] = yaml.safe_load(yaml.safe_dump(doc))
    return out


def _read_scene(path: Path) -> dict[str, Any]:
    """A finished scene's scene.yaml ({} when it holds no mapping); BenchmarkError when it cannot be read."""
    try:
        doc = yaml.safe_load(path.read_text())
    except yaml.YAMLError as err:
        raise BenchmarkError(f"finished scene {yaml_error_line(path, err)}") from err
    except (OSError, ValueError) as err:
        raise BenchmarkError(f"{path}: cannot read the finished scene's description: {err}") from err
    return doc if isinstance(doc, dict) else {}


def _same_setup(path: Path, doc: dict[str, Any], setup: dict[str, Any], source: dict[str, Any]) -> None:
    """A BenchmarkError naming the first difference when the finished scene `path` (its scene.yaml `doc`)
    was rendered otherwise: other cameras, baselines or render settings (`setup`), or from other scans, scan
    poses or another view (`source`)."""
    found = first_difference({key: doc.get(key) for key in setup}, setup)
    if found:
        raise BenchmarkError(
            f"{path}: this scene was rendered with other settings{found}; choose a new --out or delete "
            f"{path.parent}"
        )
    found = _source_difference(doc, source)
    if found:
        raise BenchmarkError(
            f"{path.parent}: this scene was rendered from other scans or another view{found}; choose a new "
            f"--out or delete {path.parent}"
        )


def _scene_problem(folder: Path, doc: dict[str, Any]) -> str:
    """Why finished scene `folder` is not whole, naming the file ('' when it is): every file its
    scene.yaml lists with the bytes and SHA-256 written; a scene.yaml listing none (an older SensorBox):
    every PNG in the folder decodes."""
    files = doc.get("files")
    if not isinstance(files, dict):
        for path in sorted(folder.rglob("*.png")):
            if read_image(path) is None:
                return f"{path}: cannot be decoded ({path.stat().st_size} bytes)"
        return ""
    for name, written in files.items():
        try:
            problem = file_problem(folder / name, int(written["bytes"]), str(written["sha256"]))
        except (TypeError, KeyError, ValueError):
            problem = f"{folder / 'scene.yaml'}: files.{name}: expected bytes and sha256"
        if problem:
            return problem
    return ""


def _source_doc(view: View, scans: list[Scan], cfg: BenchmarkConfig) -> dict[str, Any]:
    """scene.yaml's `view` and `scans`: what a scene was rendered from (as scene.yaml holds them, so that
    a read-back file compares equal)."""
    doc = {
        "view": {
            "center_scan": scans[view.center].name,
            "bundle": [scans[i].name for i in view.bundle],
            "yaw_deg": view.yaw_deg,
            "pitch_deg": cfg.pitch_deg,
            "height_m": view.height_m,
            "T_world_center": np.round(view.T_world_center, 12).tolist(),
        },
        "scans": [
            {
                "name": scans[i].name,
                "source": scans[i].source,
                "points": len(scans[i].xyz),
                "dropped_points": scans[i].dropped_points,  # not finite or at the scanner origin
                "T_world_scan": np.round(scans[i].T_world_scan, 12).tolist(),
            }
            for i in view.bundle
        ],
    }
    out: dict[str, Any] = yaml.safe_load(yaml.safe_dump(doc, sort_keys=False))
    return out


def _pose_change(old: Any, new: Any) -> str:
    """How far pose `new` (4x4) lies from `old`: 'moved by X m and turned by Y deg'."""
    a, b = np.asarray(old, np.float64), np.asarray(new, np.float64)
    if a.shape != (4, 4) or b.shape != (4, 4):
        return f"{old} -> {new}"
    cos = (np.trace(a[:3, :3].T @ b[:3, :3]) - 1.0) / 2.0
    turn = math.degrees(math.acos(min(1.0, max(-1.0, cos))))
    return f"moved by {np.linalg.norm(b[:3, 3] - a[:3, 3]):.6g} m and turned by {turn:.6g} deg"


def _source_difference(old: dict[str, Any], new: dict[str, Any]) -> str:
    """' (what: old -> new)' for the first difference between two `_source_doc`s ('' when equal)."""
    old_scans, new_scans = old.get("scans"), new["scans"]
    if isinstance(old_scans, list) and len(old_scans) == len(new_scans):
        for was, now in zip(old_scans, new_scans, strict=True):
            if not isinstance(was, dict):
                break
            name = now["name"]
            for key, value in now.items():
                if was.get(key) == value:
                    continue
                if key == "T_world_scan":
                    return f" (scan {name}: T_world_scan {_pose_change(was.get(key), value)})"
                return f" (scan {name}: {key}: {was.get(key, 'absent')} -> {value})"
    found = first_difference({"scans": old_scans, "view": old.get("view")}, new)
    if found.startswith(" (view.T_world_center:"):
        was, now = old["view"]["T_world_center"], new["view"]["T_world_center"]
        return f" (view.T_world_center {_pose_change(was, now)})"
    return found


def _scene_doc(
    state: RenderState, view: View, scans: list[Scan], stats: dict[str, dict[str, int]],
    files: dict[str, dict[str, Any]],
) -> dict[str, Any]:  # fmt: skip
    cfg = state.cfg
    cams = _cameras_doc(cfg, state.fovs, state.pinhole)
    partners = {
        cam: {baseline_label(b): partner_pose(np.eye(4), cam, b / 1000.0).tolist() for b in cfg.baselines_mm}
        for cam in ("DOWN", "RIGHT")
    }
    return {
        "sensorbox_benchmark": BENCHMARK_VERSION,
        "scene": view.scene,
        **_source_doc(view, scans, cfg),
        "T_center_partner": partners,
        "conventions": {
            "camera_frame": "x right, y down, z forward; metres",
            "depth": "uint16 PNG, millimetres: range from the camera centre (fisheye, pano, cassini), "
            "z for pinhole; EXR float32 metres; 0 = invalid",
            "disparity": "uint16 PNG, px x 100, 0 = invalid; pano*: vertical pair CENTER-DOWN, "
            "angular with the full sphere's pitch, latitude from -y; cassini_crop: horizontal "
            "pair CENTER-RIGHT, angular, latitude from -x (alpha + pi/2); pinhole*: f B / z, "
            "both pairs (fx = fy)",
            "pairs": PAIRS_DOC,
            "stability_mask": {
                "max_rel_error": cfg.stability_max_rel_error,
                "disp_error_px": cfg.stability_disp_error_px,
            },
            "invalid_also": "reflective/transparent (mask) surfaces, ranges beyond clip_m, holes",
        },
        "cameras": cams,
        "fovs_deg": list(cfg.fovs_deg),
        "baselines_mm": list(cfg.baselines_mm),
        "render": asdict(cfg.render),
        "stats": stats,
        "files": dict(sorted(files.items())),  # every file of the scene: bytes, SHA-256 (a rerun checks them)
    }


PASS_INDEX = "indexing the scans"
"""`run_benchmark`'s pass before the first view: each scan the views use sorted into its level-of-detail
index (unit: scans)."""


def run_benchmark(
    scans: list[Scan],
    reference: CameraModel,
    out: Path,
    cfg: BenchmarkConfig,
    progress: Callable[[int, int], None] | None = None,
    passes: Callable[[str, int, int], None] | None = None,
) -> BenchmarkSummary:
    """Render every view of the site into ``out`` (see the module doc); resumable per scene.

    `progress(done, total)` after each view; `passes(PASS_INDEX, done, total)` before the first
    view, per scan indexed (seconds to minutes each for a large scan).
    """
    cfg.validate()
    ds = check_reference(reference)
    if not scans:
        raise BenchmarkError("no scans given")
    t0 = time.perf_counter()
    fovs = {f: fov_cameras(ds, f, cfg) for f in cfg.fovs_deg}  # first: refuses an equirect too big
    summary = BenchmarkSummary(out)
    views = plan_views(scans, cfg)
    ph = pinhole_camera(cfg)
    setup = _setup_doc(cfg, fovs, ph)
    done_before: set[str] = set()
    for view in views:  # a finished scene is skipped only when it was rendered as asked now, and is whole
        path = out / view.scene / "scene.yaml"
        if not path.exists():
            continue
        doc = _read_scene(path)
        _same_setup(path, doc, setup, _source_doc(view, scans, cfg))
        problem = _scene_problem(path.parent, doc)
        if problem:
            summary.damaged.append(problem)
        else:
            done_before.add(view.scene)
    todo = [v for v in views if v.scene not in done_before]
    summary.skipped = [v.scene for v in views if v.scene in done_before]
    used = sorted({i for v in todo for i in v.bundle})
    indexes: list[ScanIndex] = [None] * len(scans)  # type: ignore[list-item]
    t_index = time.perf_counter()
    for k, i in enumerate(used):
        if passes:
            passes(PASS_INDEX, k, len(used))
        indexes[i] = build_index(scans[i], cfg.voxel_m)
    if passes:
        passes(PASS_INDEX, len(used), len(used))
    summary.index_seconds = time.perf_counter() - t_index
    for fc in fovs.values():  # warm the per-model caches before forking
        for m in (fc.fisheye.model, fc.pano, fc.cassini):
            pixel_geometry(m)
    pixel_geometry(ph[0])
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise OutputError(f"cannot create {out}: {err.strerror or err}") from err
    with hold_folder(out) as stale:  # one run at a time into `out`; a killed run's temporaries are removed
        summary.stale_temporaries = stale
        state = RenderState(out, cfg, indexes, {v.scene: v for v in todo}, fovs, ph)
        summary.stats = _render_tasks(state, scans, plan_tasks(todo, cfg), summary, progress)
    summary.seconds = time.perf_counter() - t0
    return summary


def _render_tasks(
    state: RenderState,
    scans: list[Scan],
    tasks: list[Task],
    summary: BenchmarkSummary,
    progress: Callable[[int, int], None] | None,
) -> dict[str, dict[str, dict[str, int]]]:
    """Every render task of `state`'s views; each scene's scene.yaml once its last render is written.

    Returns the per-render counts of each scene.
    """
    out = state.out
    stats: dict[str, dict[str, dict[str, int]]] = {scene: {} for scene in state.views}
    written: dict[str, dict[str, dict[str, Any]]] = {scene: {} for scene in state.views}
    remaining = {scene: sum(t.scene == scene for t in tasks) for scene in state.views}
    done = 0

    def finished(task: Task, st: dict[str, int], files: dict[str, dict[str, Any]]) -> None:
        nonlocal done
        done += 1
        summary.renders += 1
        summary.files += len(files)
        stats[task.scene][task_key(task)] = st
        written[task.scene].update(files)
        remaining[task.scene] -= 1
        if remaining[task.scene] == 0:  # scene.yaml last: it marks the scene finished
            view = state.views[task.scene]
            doc = _scene_doc(state, view, scans, dict(sorted(stats[task.scene].items())), written[task.scene])
            empty = empty_renders(stats[task.scene])
            if empty:
                summary.empty[task.scene] = empty
                doc["warnings"] = [_empty_warning(task.scene, empty, stats[task.scene], scans[view.center])]
                summary.warnings += doc["warnings"]
            text = "# SensorBox benchmark scene (WideDepth layout)\n" + yaml.safe_dump(
                doc, sort_keys=False, default_flow_style=None
            )
            write_atomic(out / task.scene / "scene.yaml", text.encode())
            summary.files += 1
            summary.scenes.append(task.scene)
        if progress:
            progress(done, len(tasks))

    # workers share the scans' index by fork; without fork the run stays in this process (no copies)
    # OpenCV's threads are set before the fork (`Executor`): reconfiguring a forked OpenCV pool deadlocks
    workers = state.cfg.workers if len(tasks) > 1 and "fork" in multiprocessing.get_all_start_methods() else 1
    results = Executor(workers, worker_init=partial(share_cores, workers)).run(run_task, tasks, shared=state)
    try:
        for result in results:
            finished(*result)
    finally:
        results.close()
    return stats
