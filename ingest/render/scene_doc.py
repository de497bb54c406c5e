"""A benchmark scene's scene.yaml: what it was rendered from and with (cameras, baselines, render
settings, scans, view), its conventions and files; and, on a rerun, whether a finished scene was
rendered as asked now and is whole."""

from __future__ import annotations

import math
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from calibration.files import read_text
from calibration.opencv_yaml import yaml_error_line
from calibration.pinhole import Pinhole
from calibration.virtual import partner_pose
from ingest.dataset.compare import first_difference
from ingest.dataset.identity import file_problem
from ingest.dataset.png import read_image
from ingest.errors import BenchmarkError
from ingest.raster.scan import Scan
from ingest.render.plan import BenchmarkConfig, FovCameras, View, baseline_label, fov_label
from ingest.render.render_task import RenderState

BENCHMARK_VERSION = 1
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


def cameras_doc(
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


def setup_doc(
    cfg: BenchmarkConfig, fovs: dict[float, FovCameras], pinhole: tuple[Pinhole, tuple[int, int, int, int]]
) -> dict[str, Any]:
    """What a finished scene must share with a rerun that skips it: cameras, baselines, render settings
    (as scene.yaml holds them, so that a read-back file compares equal)."""
    doc = {"cameras": cameras_doc(cfg, fovs, pinhole), "baselines_mm": list(cfg.baselines_mm),
           "render": asdict(cfg.render)}  # fmt: skip
    out: dict[str, Any] = yaml.safe_load(yaml.safe_dump(doc))
    return out


def read_scene(path: Path) -> dict[str, Any]:
    """A finished scene's scene.yaml ({} when it holds no mapping); BenchmarkError when it cannot be read."""
    text = read_text(path, "finished scene description", error=BenchmarkError)
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise BenchmarkError(f"finished scene {yaml_error_line(path, err)}") from err
    except (OSError, ValueError) as err:
        raise BenchmarkError(f"{path}: cannot read the finished scene's description: {err}") from err
    return doc if isinstance(doc, dict) else {}


def check_same_setup(path: Path, doc: dict[str, Any], setup: dict[str, Any], source: dict[str, Any]) -> None:
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


def scene_problem(folder: Path, doc: dict[str, Any]) -> str:
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


def source_doc(view: View, scans: list[Scan], cfg: BenchmarkConfig) -> dict[str, Any]:
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
    """' (what: old -> new)' for the first difference between two `source_doc`s ('' when equal)."""
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


def scene_doc(
    state: RenderState, view: View, scans: list[Scan], stats: dict[str, dict[str, int]],
    files: dict[str, dict[str, Any]],
) -> dict[str, Any]:  # fmt: skip
    cfg = state.cfg
    cams = cameras_doc(cfg, state.fovs, state.pinhole)
    partners = {
        cam: {baseline_label(b): partner_pose(np.eye(4), cam, b / 1000.0).tolist() for b in cfg.baselines_mm}
        for cam in ("DOWN", "RIGHT")
    }
    return {
        "sensorbox_benchmark": BENCHMARK_VERSION,
        "scene": view.scene,
        **source_doc(view, scans, cfg),
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
