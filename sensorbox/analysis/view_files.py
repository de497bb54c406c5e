"""What `sensorbox view` reads from a dataset and how it logs it: the entities' names, image
shrinking (colour by area, depth by the nearest surface), meta numbers as scalar series, TUM
trajectories, and the `Logger` that puts one sample's or scene's files onto a Rerun recording."""

from __future__ import annotations

import json
import math
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
import yaml
from scipy.spatial.transform import Rotation, Slerp

from calibration.files import read_text
from ingest.dataset.layout import DEPTH_SCALE, DISP_SCALE
from ingest.dataset.png import read_image
from ingest.errors import DatasetError
from ingest.eval.evaluate import Layout

if TYPE_CHECKING:
    import rerun as rr

MAX_TEXT_BYTES = 256 << 20
"""A dataset's JSON, YAML and TUM files are KiB to MiB (a TUM of an hour at 20 knots/s: 7 MiB); a file
beyond this is not one of them."""
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
ELEMENT_NAMES = {
    "twist_cam0": ("angular_x", "angular_y", "angular_z", "linear_x", "linear_y", "linear_z"),
    "range_ratio": ("ratio", "pixels", "scatter"),  # per LiDAR: named by the key above it
    "plane_scatter": ("sigma_m", "points"),  # per LiDAR
    "stereo_offset": ("across_px", "along_px", "pixels"),
}
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
                names = element_names(path, len(value))
                out.update({(*path, name): float(v) for name, v in zip(names, value, strict=True)})
    return out


def element_names(path: tuple[str, ...], n: int) -> tuple[str, ...]:
    """Names of the `n` elements of the list at key `path`: its key's own (ELEMENT_NAMES) or those of the
    key above it (a list per LiDAR), x/y/z, else 0, 1, ..."""
    for key in path[::-1][:2]:
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
    text = read_text(path, "trajectory", "TUM", MAX_TEXT_BYTES, DatasetError)
    for n, line in enumerate(text.splitlines(), 1):
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


def read_json(path: Path, what: str = "sample metadata") -> dict[str, Any]:
    """A JSON object; `what` names the file in messages (a FIFO, a device or a binary file is refused)."""
    text = read_text(path, what, "JSON", MAX_TEXT_BYTES, DatasetError)
    try:
        doc = json.loads(text)
    except (OSError, ValueError) as err:
        raise DatasetError(f"{path}: cannot be read as JSON ({err})") from err
    if not isinstance(doc, dict):
        raise DatasetError(f"{path}: expected a JSON object, found {type(doc).__name__}")
    return doc


def read_yaml(path: Path, what: str = "scene") -> dict[str, Any]:
    """A YAML mapping; `what` names the file in messages (a FIFO, a device or a binary file is refused)."""
    text = read_text(path, what, "YAML", MAX_TEXT_BYTES, DatasetError)
    try:
        doc = yaml.safe_load(text)
    except (OSError, yaml.YAMLError) as err:
        raise DatasetError(f"{path}: cannot be read as YAML ({err})") from err
    if not isinstance(doc, dict):
        raise DatasetError(f"{path}: expected a YAML mapping, found {type(doc).__name__}")
    return doc


def load_image(path: Path, colour: bool) -> np.ndarray[Any, Any]:
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


def rerun_transform(rr_mod: Any, T: F64) -> Any:
    """A 4x4 parent-from-child pose as a Rerun transform."""
    return rr_mod.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3])


class Logger:
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
        rgb = load_image(path, colour=True)
        small = downscale_colour(rgb, downscale_factor(rgb.shape, self.max_side_px))
        self.rec.log(entity, self.rr.Image(small).compress(jpeg_quality=JPEG_QUALITY))
        self.summary.images += 1
        self.summary.image_entities.add(entity)

    def depth(self, entity: str, path: Path, root: Path, units_per_metre: float) -> None:
        if not path.is_file():
            self.summary.missing_files.append(path.relative_to(root).as_posix())
            return
        values = load_image(path, colour=False)
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
