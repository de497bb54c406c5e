"""A SensorBox dataset as one Rerun recording (`sensorbox view`): images, GT, rig, trajectory, numbers.

Train layout (`sensorbox ingest`), one row per sample on the timeline
``time`` (the sample's `exposure_ns` from `meta/<id>.json`, else its
`stamp_ns`) and on ``sample`` (its id):

```
cam0/fisheye, cam1/fisheye          left_fisheye/, right_fisheye/ (JPEG-compressed RGB)
equirect/up, equirect/down_virt     equirect_up/, equirect_down_virt/
cam0/depth                          depth_fisheye/ as a depth image, 1000 units per metre (mm)
equirect/disparity                  disp_equirect/ as a depth image, 100 units per "metre" (px x 100)
meta/<key>/<key>...                 every number of meta/<id>.json as a scalar series
world/trajectory                    trajectories/<bag>.tum: T_world_cam0's positions (static line)
world/rig                           T_world_cam0 at the sample's time (the trajectory, interpolated)
world/rig/<cam1|lidar|imu>          the rig's frames in cam0 (rig/rig.yaml of the dataset, static)
```

Benchmark layout (`sensorbox render-benchmark`), one row per scene on
``scene`` (its index in name order): every image of every FOV, baseline and
camera under `<FOV>FOV/<B>mm/<CAMERA>/<image>`, CENTER's depth and disparity
as depth images beside them, `world/center` (T_world_center) with
`world/center/<B>mm/<PARTNER>` and every number of scene.yaml's `stats` and
`scans` as scalars (`scene/stats/<FOV>FOV/<B>mm/<CAMERA>/<image>/<field>`,
`scene/scans/<scan>/points`).

Images are shrunk by a whole factor until their longest side is at most
`max_side_px` (960 by default; `None` keeps them whole): colour by area
averaging, depth and disparity by the nearest surface of each block (the
smallest non-zero value), so sparse GT keeps its pixels and no value is
made up between two surfaces. Accumulated clouds are not stored in a
dataset and are not shown. Rerun is imported here, not at the top, so the
CLI starts without it.
"""

from __future__ import annotations

import errno
import json
import math
import os
import re
import shutil
import sys
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
import yaml
from scipy.spatial.transform import Rotation, Slerp

from calibration import read_rig
from ingest.dataset.layout import DEPTH_SCALE, DISP_SCALE
from ingest.dataset.png import read_image
from ingest.errors import DatasetError, OutputError
from ingest.eval.evaluate import Layout, detect_layout
from sensorbox.errors import ViewerError

if TYPE_CHECKING:
    import rerun as rr

MAX_SIDE_PX = 960
JPEG_QUALITY = 90
VIEWER_FLUSH_S = 120.0  # a spawned viewer that takes nothing for this long did not start
TIMELINE_TIME = "time"  # train: the sample's exposure (ns since the epoch)
TIMELINE_SAMPLE = "sample"  # train: the sample's id
TIMELINE_SCENE = "scene"  # benchmark: the scene's index in name order
TRAIN_IMAGES = {
    "left_fisheye": "cam0/fisheye",
    "right_fisheye": "cam1/fisheye",
    "equirect_up": "equirect/up",
    "equirect_down_virt": "equirect/down_virt",
}
# folder -> (entity, uint16 units per metre (depth) or per pixel of disparity)
TRAIN_GT = {"depth_fisheye": ("cam0/depth", DEPTH_SCALE), "disp_equirect": ("equirect/disparity", DISP_SCALE)}
# meta keys that are no per-sample measurement: the timeline itself, identities, the settings
META_NOT_SCALARS = frozenset(
    {"id", "stamp_ns", "exposure_ns", "lower_stamp_ns", "frames_sha256", "files", "settings", "source_bag"}
)
# names of a list's elements, by its key (else x, y, z for three, else the index)
ELEMENT_NAMES = {"twist_cam0": ("angular_x", "angular_y", "angular_z", "linear_x", "linear_y", "linear_z")}
XYZ = ("x", "y", "z")
SAMPLE_ID = re.compile(r"^\d+$")
BENCHMARK_FOLDER = re.compile(r"^(?P<fov>[\d.]+)FOV/(?P<baseline>[\d.]+)mm/(?P<camera>[A-Z]+)$")

U16 = np.ndarray[Any, np.dtype[np.uint16]]
U8 = np.ndarray[Any, np.dtype[np.uint8]]
F64 = np.ndarray[Any, np.dtype[np.float64]]
Progress = Callable[[int, int], None]


@dataclass
class ViewSummary:
    """What a recording holds: counts of samples (train) or scenes (benchmark) and of what was logged."""

    layout: Layout
    samples: int = 0
    images: int = 0
    depth_images: int = 0
    scalars: int = 0  # values logged
    series: set[str] = field(default_factory=set)  # entity paths of the scalar series
    poses: int = 0  # samples placed on the trajectory
    frames: int = 0  # static rig frames (cam1, LiDARs, IMUs; benchmark: partners per scene)
    missing_files: list[str] = field(default_factory=list)  # relative paths of a sample's absent files
    image_entities: set[str] = field(default_factory=set)  # entity paths of the images and depth images
    off_trajectory: int = 0  # train samples outside their trajectory's knots (or with none)


def downscale_factor(shape: tuple[int, ...], max_side_px: int | None) -> int:
    """The smallest whole factor that brings the image's longest side to `max_side_px` or below (1: none)."""
    if max_side_px is None:
        return 1
    return max(1, math.ceil(max(shape[:2]) / max_side_px))


def downscale_colour(image: U8, factor: int) -> U8:
    """`image` (H x W or H x W x C uint8) shrunk `factor` times by area averaging to ceil(H/f) x ceil(W/f)."""
    if factor == 1:
        return image
    h, w = image.shape[:2]
    size = (math.ceil(w / factor), math.ceil(h / factor))
    out: U8 = np.asarray(cv2.resize(image, size, interpolation=cv2.INTER_AREA), np.uint8)
    return out


def downscale_nearest_surface(values: U16, factor: int) -> U16:
    """A uint16 GT map (0 = invalid) shrunk `factor` times: each block's smallest non-zero value, else 0.

    Output is ceil(H/f) x ceil(W/f); the nearest surface of a block wins, as
    a z-buffer would, so a sparse map keeps a pixel wherever a block held
    one and no block gets a value between two surfaces.
    """
    if factor == 1:
        return values
    h, w = values.shape
    rows, cols = math.ceil(h / factor), math.ceil(w / factor)
    big = np.iinfo(np.uint16).max
    padded = np.full((rows * factor, cols * factor), big, np.uint16)
    padded[:h, :w] = np.where(values == 0, big, values)
    blocks = padded.reshape(rows, factor, cols, factor).min(axis=(1, 3))
    # a block whose only values are 65535 (a real range of 65.535 m) keeps it; an empty one is 0
    held = (values != 0).astype(np.uint8)
    any_held = np.zeros((rows * factor, cols * factor), np.uint8)
    any_held[:h, :w] = held
    has = any_held.reshape(rows, factor, cols, factor).max(axis=(1, 3)).astype(bool)
    out: U16 = np.where(has, blocks, 0).astype(np.uint16)
    return out


def meta_scalars(meta: Mapping[str, Any], prefix: tuple[str, ...] = ()) -> dict[tuple[str, ...], float]:
    """Every number of a sample's metadata, by its key path: the series `sensorbox view` plots.

    Numbers as they are, booleans as 0/1, a list of numbers element by element
    (key path + x/y/z for a vector, `twist_cam0`'s angular_x .. linear_z, else
    the index), a list of names (e.g. `points.silent_lidars`) as its
    length; strings, nulls (e.g. a sparse sample's `trajectory_residual_mm`)
    and nested lists (the alignment's `information` matrix) are no series.
    The keys of `META_NOT_SCALARS` (stamps, identities, settings) are left
    out at the top level.
    """
    out: dict[tuple[str, ...], float] = {}
    for key, value in meta.items():
        if not prefix and key in META_NOT_SCALARS:
            continue
        path = (*prefix, str(key))
        if isinstance(value, Mapping):
            out.update(meta_scalars(value, path))
        elif isinstance(value, bool | int | float):  # bool: 0/1
            out[path] = float(value)
        elif isinstance(value, list):
            if all(isinstance(v, str) for v in value):
                out[path] = float(len(value))
            elif all(isinstance(v, int | float) and not isinstance(v, bool) for v in value):
                names = _element_names(str(key), len(value))
                out.update({(*path, name): float(v) for name, v in zip(names, value, strict=True)})
    return out


def _element_names(key: str, n: int) -> tuple[str, ...]:
    """Names of the `n` elements of the list under `key`: its own (ELEMENT_NAMES), x/y/z, else 0, 1, ..."""
    named = ELEMENT_NAMES.get(key)
    if named is not None and len(named) == n:
        return named
    return XYZ if n == 3 else tuple(str(k) for k in range(n))


def sample_time_ns(meta: Mapping[str, Any], where: Path) -> int:
    """The sample's time on the timeline: `exposure_ns` (the GT's time), else `stamp_ns` (older datasets)."""
    for key in ("exposure_ns", "stamp_ns"):
        value = meta.get(key)
        if isinstance(value, int) and not isinstance(value, bool):
            return value
    raise DatasetError(
        f"{where}: neither 'exposure_ns' nor 'stamp_ns' is an integer (ns); not a sample's metadata"
    )


def read_tum(path: Path) -> tuple[np.ndarray[Any, np.dtype[np.int64]], F64]:
    """A `trajectories/<bag>.tum` file: knot stamps (ns) and T_world_cam0 (N x 4 x 4, metres)."""
    stamps: list[int] = []
    poses: list[list[float]] = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        words = line.split()
        if not words or words[0].startswith("#"):
            continue
        try:
            if len(words) != 8:
                raise ValueError(f"{len(words)} values")
            sec, _, frac = words[0].partition(".")
            stamps.append(int(sec) * 1_000_000_000 + int((frac + "000000000")[:9]))
            poses.append([float(w) for w in words[1:]])
        except ValueError as err:
            raise DatasetError(f"{path}:{n}: expected 't_sec tx ty tz qx qy qz qw' ({err})") from err
    T = np.tile(np.eye(4), (len(poses), 1, 1))
    if poses:
        values = np.asarray(poses, np.float64)
        T[:, :3, 3] = values[:, :3]
        T[:, :3, :3] = Rotation.from_quat(values[:, 3:]).as_matrix()
    return np.asarray(stamps, np.int64), T


def pose_at(stamps_ns: np.ndarray[Any, np.dtype[np.int64]], T_world_cam0: F64, t_ns: int) -> F64 | None:
    """T_world_cam0 at `t_ns`: position linear and rotation slerped between the two knots around it;
    None outside the knots."""
    if len(stamps_ns) == 0 or t_ns < stamps_ns[0] or t_ns > stamps_ns[-1]:
        return None
    k = int(np.clip(np.searchsorted(stamps_ns, t_ns, side="right") - 1, 0, max(len(stamps_ns) - 2, 0)))
    if len(stamps_ns) == 1:
        return np.asarray(T_world_cam0[0], np.float64)
    t0, t1 = int(stamps_ns[k]), int(stamps_ns[k + 1])
    f = (t_ns - t0) / (t1 - t0) if t1 > t0 else 0.0
    T = np.eye(4)
    T[:3, 3] = (1 - f) * T_world_cam0[k, :3, 3] + f * T_world_cam0[k + 1, :3, 3]
    slerp = Slerp([0.0, 1.0], Rotation.from_matrix(T_world_cam0[k : k + 2, :3, :3]))
    T[:3, :3] = slerp([f]).as_matrix()[0]
    return T


def _read_json(path: Path) -> dict[str, Any]:
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise DatasetError(f"{path}: cannot be read as JSON ({err})") from err
    if not isinstance(doc, dict):
        raise DatasetError(f"{path}: expected a JSON object, found {type(doc).__name__}")
    return doc


def _read_yaml(path: Path) -> dict[str, Any]:
    try:
        doc = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as err:
        raise DatasetError(f"{path}: cannot be read as YAML ({err})") from err
    if not isinstance(doc, dict):
        raise DatasetError(f"{path}: expected a YAML mapping, found {type(doc).__name__}")
    return doc


def _image(path: Path, colour: bool) -> np.ndarray[Any, Any]:
    """A dataset image: RGB uint8 (`colour`) or the uint16 GT map as stored; a damaged file is an error."""
    raw = read_image(path, cv2.IMREAD_COLOR if colour else cv2.IMREAD_UNCHANGED)
    if raw is None:
        size = path.stat().st_size
        raise DatasetError(f"{path}: cannot be decoded ({size} bytes: empty, cut short or not an image)")
    if colour:
        rgb: np.ndarray[Any, Any] = cv2.cvtColor(raw, cv2.COLOR_BGR2RGB)
        return rgb
    if raw.dtype != np.uint16 or raw.ndim != 2:
        raise DatasetError(f"{path}: not a one-channel 16-bit PNG ({raw.dtype} pixels, shape {raw.shape})")
    return raw


def _transform(rr_mod: Any, T: F64) -> Any:
    """A 4x4 parent-from-child pose as a Rerun transform."""
    return rr_mod.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3])


class _Logger:
    """Logs files of one sample or scene onto an open recording, counting into the summary."""

    def __init__(self, rec: rr.RecordingStream, summary: ViewSummary, max_side_px: int | None) -> None:
        import rerun

        self.rr = rerun
        self.rec = rec
        self.summary = summary
        self.max_side_px = max_side_px

    def colour(self, entity: str, path: Path, root: Path) -> None:
        if not path.is_file():
            self.summary.missing_files.append(path.relative_to(root).as_posix())
            return
        rgb = _image(path, colour=True)
        small = downscale_colour(rgb, downscale_factor(rgb.shape, self.max_side_px))
        self.rec.log(entity, self.rr.Image(small).compress(jpeg_quality=JPEG_QUALITY))
        self.summary.images += 1
        self.summary.image_entities.add(entity)

    def depth(self, entity: str, path: Path, root: Path, units_per_metre: float) -> None:
        if not path.is_file():
            self.summary.missing_files.append(path.relative_to(root).as_posix())
            return
        values = _image(path, colour=False)
        small = downscale_nearest_surface(values, downscale_factor(values.shape, self.max_side_px))
        self.rec.log(entity, self.rr.DepthImage(small, meter=units_per_metre))
        self.summary.depth_images += 1
        self.summary.image_entities.add(entity)

    def scalars(self, prefix: str, values: Mapping[tuple[str, ...], float]) -> None:
        for keys, value in values.items():
            entity = self.rr.new_entity_path([prefix, *keys])
            self.rec.log(entity, self.rr.Scalars(value))
            self.summary.series.add(entity)
            self.summary.scalars += 1


def _train_ids(root: Path) -> list[str]:
    """Sample ids of the finished samples (their `meta/<id>.json`, written last), in order."""
    return sorted((p.stem for p in (root / "meta").glob("*.json") if SAMPLE_ID.match(p.stem)), key=int)


def _log_rig(log: _Logger, root: Path) -> None:
    """The rig of `root/rig/rig.yaml` as static frames under world/rig (= cam0)."""
    rig_file = root / "rig" / "rig.yaml"
    if not rig_file.is_file():
        return
    rig = read_rig(rig_file)
    rr_mod, rec = log.rr, log.rec
    rec.log("world/rig", rr_mod.TransformAxes3D(0.1), static=True)
    frames: list[tuple[str, F64]] = [(c.name, c.T_cam0_cam) for c in rig.cameras if c.name != "cam0"]
    frames += [(lidar.name, lidar.T_cam0_lidar) for lidar in rig.lidars]
    frames += [(imu.name, imu.T_cam0_imu) for imu in rig.imus]
    for name, T in frames:
        entity = rr_mod.new_entity_path(["world", "rig", name])
        rec.log(
            entity, _transform(rr_mod, np.asarray(T, np.float64)), rr_mod.TransformAxes3D(0.05), static=True
        )
        log.summary.frames += 1


def _trajectories(log: _Logger, root: Path) -> dict[str, tuple[np.ndarray[Any, np.dtype[np.int64]], F64]]:
    """Every `trajectories/<bag>.tum`, by bag name, logged as static lines of cam0's positions."""
    found: dict[str, tuple[np.ndarray[Any, np.dtype[np.int64]], F64]] = {}
    for path in sorted((root / "trajectories").glob("*.tum")):
        stamps, T = read_tum(path)
        found[path.stem] = (stamps, T)
        entity = log.rr.new_entity_path(["world", "trajectory", path.stem])
        log.rec.log(entity, log.rr.LineStrips3D([T[:, :3, 3]]), static=True)
    return found


def log_train(
    rec: rr.RecordingStream, root: Path, max_side_px: int | None, progress: Progress | None
) -> ViewSummary:
    """Every finished sample of a train-layout dataset onto `rec` (module doc); returns what was logged."""
    summary = ViewSummary(layout="train")
    log = _Logger(rec, summary, max_side_px)
    ids = _train_ids(root)
    if not ids:
        raise DatasetError(f"{root}: no finished sample (meta/<id>.json); nothing to view")
    _log_rig(log, root)
    trajectories = _trajectories(log, root)
    for n, sid in enumerate(ids):
        meta_path = root / "meta" / f"{sid}.json"
        meta = _read_json(meta_path)
        t_ns = sample_time_ns(meta, meta_path)
        rec.set_time(TIMELINE_TIME, timestamp=np.datetime64(t_ns, "ns"))
        rec.set_time(TIMELINE_SAMPLE, sequence=int(sid))
        for folder, entity in TRAIN_IMAGES.items():
            log.colour(entity, root / folder / f"{sid}.png", root)
        for folder, (entity, scale) in TRAIN_GT.items():
            log.depth(entity, root / folder / f"{sid}.png", root, scale)
        log.scalars("meta", meta_scalars(meta))
        bag = meta.get("source_bag")
        pose = pose_at(*trajectories[bag], t_ns) if isinstance(bag, str) and bag in trajectories else None
        if pose is None:
            summary.off_trajectory += 1
        else:
            rec.log("world/rig", _transform(log.rr, pose))
            summary.poses += 1
        summary.samples += 1
        if progress is not None:
            progress(n + 1, len(ids))
    _send_train_blueprint(log)
    return summary


def _benchmark_scenes(root: Path) -> list[Path]:
    """Scene folders (those with a `<FOV>FOV/<B>mm/CENTER` folder), in name order."""
    return sorted(p for p in root.iterdir() if p.is_dir() and any(p.glob("*FOV/*mm/CENTER")))


def _benchmark_folders(scene: Path) -> Iterator[tuple[str, Path]]:
    """(`<FOV>FOV/<B>mm/<CAMERA>`, folder) of every camera of a scene, in name order."""
    for folder in sorted(scene.glob("*FOV/*mm/*")):
        rel = folder.relative_to(scene).as_posix()
        if folder.is_dir() and BENCHMARK_FOLDER.match(rel):
            yield rel, folder


def benchmark_scalars(doc: Mapping[str, Any]) -> dict[tuple[str, ...], float]:
    """The numbers of a scene.yaml: each view's render `stats` and each scan's point counts."""
    out: dict[tuple[str, ...], float] = {}
    stats = doc.get("stats")
    for view, counts in (stats or {}).items() if isinstance(stats, Mapping) else ():
        if isinstance(counts, Mapping):  # "120FOV/65mm/DOWN/fisheye" as four levels of the entity tree
            out.update(meta_scalars(counts, ("stats", *str(view).split("/"))))
    for scan in doc.get("scans") or []:
        if isinstance(scan, Mapping) and isinstance(scan.get("name"), str):
            counts = {k: scan[k] for k in ("points", "dropped_points") if k in scan}
            out.update(meta_scalars(counts, ("scans", scan["name"])))
    return out


def _matrix(value: object, where: str) -> F64:
    T = np.asarray(value, np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise DatasetError(f"{where}: expected a finite 4x4 matrix, found {value!r}")
    return T


def _log_scene_poses(log: _Logger, doc: Mapping[str, Any], where: Path) -> None:
    """`world/center` (T_world_center) and each partner in it, per baseline, as in scene.yaml."""
    view = doc.get("view")
    if isinstance(view, Mapping) and "T_world_center" in view:
        log.rec.log("world/center", _transform(log.rr, _matrix(view["T_world_center"], f"{where}: view")))
    partners = doc.get("T_center_partner")
    if not isinstance(partners, Mapping):
        return
    for partner, by_baseline in partners.items():
        for baseline, T in (by_baseline or {}).items():
            entity = log.rr.new_entity_path(["world", "center", str(baseline), str(partner)])
            T_c = _matrix(T, f"{where}: T_center_partner.{partner}.{baseline}")
            log.rec.log(entity, _transform(log.rr, T_c), log.rr.TransformAxes3D(0.05))
            log.summary.frames += 1


def train_layout(series: Iterable[str]) -> list[tuple[str, list[str]]]:
    """The time-series panels of the train layout's default viewer layout: (title, entity paths) of the
    numbers a bad stretch shows in first, from the series logged; every other series stays one click
    away in the viewer's entity tree."""
    logged = sorted(series)
    picks = (
        ("GT density", lambda e: e == "/meta/gt/density"),
        (
            "misalignment per LiDAR (shift_deg)",
            lambda e: e.startswith("/meta/alignment/") and e.endswith("/shift_deg"),
        ),
        ("points per filter", lambda e: e.startswith("/meta/points/")),
        (
            "motion and trajectory residual",
            lambda e: e in ("/meta/motion/predicted_motion_px", "/meta/gt/trajectory_residual_mm"),
        ),
    )
    panels = [(title, [e for e in logged if keep(e)]) for title, keep in picks]
    return [(title, entities) for title, entities in panels if entities]


def _send_train_blueprint(log: _Logger) -> None:
    """The default layout of a train recording: cam0 with its GT depth over it, cam1, the equirects
    with the disparity over the upper one, the rig in 3D and the panels of `train_layout`."""
    import rerun.blueprint as rrb

    images = rrb.Grid(
        rrb.Spatial2DView(origin="cam0", name="cam0 + GT depth"),
        rrb.Spatial2DView(origin="cam1", name="cam1"),
        rrb.Spatial2DView(
            origin="equirect", contents=["equirect/up", "equirect/disparity"], name="equirect up + disparity"
        ),
        rrb.Spatial2DView(origin="equirect/down_virt", name="equirect down (virtual)"),
    )
    charts = [
        rrb.TimeSeriesView(origin="/", contents=entities, name=title)
        for title, entities in train_layout(log.summary.series)
    ]
    rig = rrb.Spatial3DView(origin="world", name="rig and trajectory")
    right = rrb.Vertical(rig, *charts, row_shares=[2.0] + [1.0] * len(charts))
    log.rec.send_blueprint(
        rrb.Blueprint(
            rrb.Horizontal(images, right, column_shares=[3, 2]), auto_views=False, collapse_panels=True
        )
    )


def log_benchmark(
    rec: rr.RecordingStream, root: Path, max_side_px: int | None, progress: Progress | None
) -> ViewSummary:
    """Every scene of a benchmark-layout dataset onto `rec` (module doc); returns what was logged."""
    summary = ViewSummary(layout="benchmark")
    log = _Logger(rec, summary, max_side_px)
    scenes = _benchmark_scenes(root)
    for n, scene in enumerate(scenes):
        rec.set_time(TIMELINE_SCENE, sequence=n)
        for rel, folder in _benchmark_folders(scene):
            for png in sorted(folder.glob("*.png")):
                log.colour(f"{rel}/{png.stem}", png, root)
            for kind, scale in (("depth", DEPTH_SCALE), ("disparity", DISP_SCALE)):
                for png in sorted((folder / kind).glob("*.png")):
                    log.depth(f"{rel}/{kind}/{png.stem}", png, root, scale)
        scene_yaml = scene / "scene.yaml"
        if scene_yaml.is_file():
            doc = _read_yaml(scene_yaml)
            _log_scene_poses(log, doc, scene_yaml)
            log.scalars("scene", benchmark_scalars(doc))
        else:
            summary.missing_files.append(scene_yaml.relative_to(root).as_posix())
        summary.samples += 1
        if progress is not None:
            progress(n + 1, len(scenes))
    _send_benchmark_blueprint(log)
    return summary


BENCHMARK_CHARTS = ("hole_px", "valid_px", "masked_px", "filled_px")  # render stats charted per view


def benchmark_layout(images: Iterable[str]) -> dict[str, list[tuple[str, list[str]]]]:
    """The image panels of the benchmark layout's default viewer layout: per `<FOV>FOV/<B>mm`, (title,
    entity paths) of each camera image, CENTER's with its depth over it, and of each disparity map."""
    logged = set(images)
    tabs: dict[str, list[tuple[str, list[str]]]] = {}
    for entity in sorted(logged):
        parts = entity.split("/")  # <FOV>FOV, <B>mm, <CAMERA>, then <image> or depth|disparity, <image>
        pair, camera, rest = "/".join(parts[:2]), parts[2], parts[3:]
        if len(rest) == 1:  # a camera's image: <pair>/<CAMERA>/<image>
            depth = f"{pair}/{camera}/depth/{rest[0]}"
            title = f"{camera} {rest[0]}" + (" + depth" if depth in logged else "")
            tabs.setdefault(pair, []).append((title, [entity] + ([depth] if depth in logged else [])))
        elif rest[0] == "disparity":
            tabs.setdefault(pair, []).append((f"{camera} {rest[1]} disparity", [entity]))
    # per camera its images first, then its disparity maps
    return {
        pair: sorted(panels, key=lambda p: (p[0].split()[0], p[0].endswith(" disparity")))
        for pair, panels in tabs.items()
    }


def _send_benchmark_blueprint(log: _Logger) -> None:
    """The default layout of a benchmark recording: a tab per FOV and baseline with a view per image
    (`benchmark_layout`), one with the scene's cameras in 3D and one with the render stats' charts."""
    import rerun.blueprint as rrb

    tabs: list[Any] = [
        rrb.Grid(*(rrb.Spatial2DView(origin="/", contents=c, name=t) for t, c in panels), name=pair)
        for pair, panels in benchmark_layout(log.summary.image_entities).items()
    ]
    tabs.append(rrb.Spatial3DView(origin="world", name="cameras"))
    charts = [
        rrb.TimeSeriesView(origin="/", contents=entities, name=field)
        for field in BENCHMARK_CHARTS
        if (entities := sorted(e for e in log.summary.series if e.endswith(f"/{field}")))
    ]
    if charts:
        tabs.append(rrb.Grid(*charts, name="render stats"))
    log.rec.send_blueprint(rrb.Blueprint(rrb.Tabs(*tabs), auto_views=False, collapse_panels=True))


def view_dataset(
    root: Path,
    save: Path | None = None,
    max_side_px: int | None = MAX_SIDE_PX,
    progress: Progress | None = None,
) -> ViewSummary:
    """`root` (train or benchmark layout) as a Rerun recording: written to `save` (.rrd), else streamed
    to a Rerun viewer spawned for it.

    The .rrd is written to a temporary name beside `save` and renamed when
    complete, so a failed run leaves no partial recording. A folder that is
    neither layout is an `EvalError` naming it; a damaged file a `DatasetError`;
    a viewer that cannot be started (no display, no `rerun` executable) or
    does not take the recording within `VIEWER_FLUSH_S` a `ViewerError`,
    before any file is read in the first two cases.
    """
    import rerun

    layout = detect_layout(root)
    rec = rerun.RecordingStream("sensorbox")  # a fresh recording id: a second view is not merged in
    tmp = _staging(save) if save is not None else None
    if tmp is not None:
        rec.save(tmp)
    else:
        _spawn(rec)
    try:
        rec.send_recording_name(root.resolve().name)
        log = log_train if layout == "train" else log_benchmark
        summary = log(rec, root, max_side_px, progress)
        _flush(rec, streamed=tmp is None)
    except BaseException:
        rec.disconnect()
        if tmp is not None:
            tmp.unlink(missing_ok=True)
        raise
    rec.disconnect()
    if save is not None and tmp is not None:
        try:
            tmp.replace(save)
        except OSError as err:
            tmp.unlink(missing_ok=True)
            raise OutputError(f"cannot write {save}: {err.strerror or err}") from err
    return summary


def display_problem(env: Mapping[str, str], platform: str) -> str | None:
    """Why no viewer window can open here (Linux without X11 or Wayland), or None when one can."""
    if platform.startswith("linux") and not (env.get("DISPLAY") or env.get("WAYLAND_DISPLAY")):
        return "no display for the Rerun viewer (DISPLAY and WAYLAND_DISPLAY are unset)"
    return None


def viewer_executable(path_env: str, python: Path) -> Path | None:
    """The `rerun` viewer rerun-sdk installs: on PATH, else beside the Python running this (a virtual
    environment used without activating it); None when neither has one."""
    found = shutil.which("rerun", path=os.pathsep.join(p for p in (path_env, str(python.parent)) if p))
    return Path(found) if found else None


def _spawn(rec: rr.RecordingStream) -> None:
    """Start a Rerun viewer and stream `rec` to it; refused in one line where it cannot start."""
    hint = "; save the recording with --save FILE.rrd and open it where there is one ('rerun FILE.rrd')"
    if (problem := display_problem(os.environ, sys.platform)) is not None:
        raise ViewerError(problem + hint)
    exe = viewer_executable(os.environ.get("PATH", ""), Path(sys.executable))
    if exe is None:
        raise ViewerError(f"no Rerun viewer executable 'rerun' on PATH nor beside {sys.executable}{hint}")
    path_env = os.environ.get("PATH", "")
    os.environ["PATH"] = os.pathsep.join(p for p in (str(exe.parent), path_env) if p)  # rerun looks there
    try:
        rec.spawn()
    finally:
        os.environ["PATH"] = path_env


def _flush(rec: rr.RecordingStream, streamed: bool) -> None:
    """Wait until everything logged is written (a file) or taken by the viewer (at most VIEWER_FLUSH_S)."""
    if not streamed:
        rec.flush()
        return
    try:
        rec.flush(timeout_sec=VIEWER_FLUSH_S)
    except Exception as err:  # the binding raises a plain RuntimeError-like error on its timeout
        raise ViewerError(
            f"the Rerun viewer did not take the recording within {VIEWER_FLUSH_S:g} s ({err})"
        ) from err


def _staging(save: Path) -> Path:
    """The temporary file beside `save` that the recording goes to first (its folders made); a folder
    that cannot be made or written is an `OutputError` naming `save`."""
    tmp = save.with_name(f".{save.name}.tmp")
    try:
        if save.is_dir():
            raise IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR), str(save))
        save.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_bytes(b"")  # a refused write shows here, not in Rerun's writer thread
    except OSError as err:
        raise OutputError(f"cannot write {save}: {err.strerror or err}") from err
    return tmp
