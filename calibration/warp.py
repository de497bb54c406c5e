"""One generic image warp between any two camera models, with cached remap maps.

For every target pixel: unproject it, rotate the ray into the source camera
(``R_src_dst``), project it into the source and sample there with
`cv2.remap`. Fisheye -> equirect, -> pinhole, -> cubemap and -> Cassini are
all calls of `warp`. Maps are cached by the (hashable, frozen) models and the
rotation, so a sequence of frames from one rig builds them once; maps of
large targets (a full-resolution equirect takes seconds to build) are also
kept on disk (`map_cache_dir`), so that a new process loads them instead.
"""

from __future__ import annotations

import hashlib
import io
import logging
import math
import os
import threading
import zipfile
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from calibration.camera import CameraModel
from calibration.errors import CalibrationError, WriteError
from calibration.files import check_regular_file, write_atomic
from calibration.spherical import Equirectangular
from calibration.types import F64, Bool

MAP_CACHE_SIZE = 8
INVALID_COORD = -1000.0
MAP_BLOCK_ROWS = 64  # rows of the target computed at once by build_maps
MIN_HEIGHT_FULL = 64
"""Fewest full-sphere rows a dataset or benchmark is made at (a pixel of 2.8 degrees). A network that
downsamples 32 times (five stride-2 stages, as common depth encoders do) keeps 2 rows of a 64-row
sphere, none of less; and the disparity of the 0.12 m baseline shrinks with the rows (1.2 px at 2 m
at 64 rows), below what the GT's stability mask keeps: `--height-full 7` wrote samples with no
disparity pixel and said nothing. 64 is also the smallest the tests' quick runs use."""
SPAN_ROWS = 32  # rows per span: the row block and the columns holding its valid pixels
SPHERE_PX_PER_CAMERA_PX = 16  # default equirect: full-sphere pixels per camera pixel, at most
SPHERE_BYTES_PER_PX = 90  # memory per full-sphere pixel of a train sample or a benchmark pano
"""Map value of target pixels with no source: so far outside that every interpolation tap
reads the constant border, so `cv2.remap` itself writes the fill value."""
_CACHE: OrderedDict[tuple[Any, ...], RemapMaps] = OrderedDict()
MAP_CACHE_ENV = "SENSORBOX_MAP_CACHE"
"""Environment variable: the folder of the on-disk map cache, or "off" (default: ~/.cache/sensorbox/maps)."""
DISK_CACHE_MIN_PX = 1 << 20  # targets with fewer pixels build in milliseconds: memory cache only
MAPS_FORMAT = 1  # part of every cache file's key: a new layout never reads an old file

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class RemapMaps:
    """cv2.remap maps from a target grid into a source image, and the target validity mask.

    ``map_x``/``map_y`` are float32 source pixel coordinates (`INVALID_COORD`
    where invalid); ``valid`` marks target pixels with a valid source sample
    inside the source image. (OpenCV's fixed-point CV_16SC2 maps take ~20 %
    less CPU per warp but round every sampling position to 1/32 px, which
    moves 0.2 % of the equirect's values by more than one level; float maps
    keep the images exact to the calibration.)
    ``spans`` are (row0, row1, col0, col1) blocks of `SPAN_ROWS` rows cut to
    the columns that hold valid pixels: every valid pixel lies in one, so a
    warp may remap only them (a fisheye covers ~30 % of a full-sphere equirect).
    """

    map_x: np.ndarray[Any, np.dtype[np.float32]]
    map_y: np.ndarray[Any, np.dtype[np.float32]]
    valid: Bool
    spans: tuple[tuple[int, int, int, int], ...] = ()
    _scratch: threading.local = field(default_factory=threading.local, repr=False)

    def scratch(self, shape: tuple[int, ...], dtype: np.dtype[Any], fill: float) -> np.ndarray[Any, Any]:
        """This thread's reusable output of this warp: `fill` outside the spans (kept from its creation)."""
        key = (shape, dtype.str, fill)
        bufs: dict[tuple[Any, ...], np.ndarray[Any, Any]] = self._scratch.__dict__.setdefault("bufs", {})
        if key not in bufs:
            bufs[key] = np.full(shape, fill, dtype)
        return bufs[key]


def valid_spans(valid: Bool, rows: int = SPAN_ROWS) -> tuple[tuple[int, int, int, int], ...]:
    """(row0, row1, col0, col1) per block of `rows` rows: the column range holding its valid pixels."""
    out = []
    for r0 in range(0, valid.shape[0], rows):
        cols = np.flatnonzero(valid[r0 : r0 + rows].any(axis=0))
        if len(cols):
            out.append((r0, min(r0 + rows, valid.shape[0]), int(cols[0]), int(cols[-1]) + 1))
    return tuple(out)


def _key(src: CameraModel, dst: CameraModel, R_src_dst: F64) -> tuple[Any, ...]:
    return (src, dst, np.asarray(R_src_dst, dtype=np.float64).tobytes())


def build_maps(src: CameraModel, dst: CameraModel, R_src_dst: F64 | None = None) -> RemapMaps:
    """Remap maps that render ``dst``'s view from ``src``'s image (cached, LRU; large ones on disk too).

    ``R_src_dst`` rotates rays from the target frame into the source frame
    (identity when None).
    """
    R = np.eye(3) if R_src_dst is None else np.asarray(R_src_dst, dtype=np.float64)
    key = _key(src, dst, R)
    hit = _CACHE.get(key)
    if hit is not None:
        _CACHE.move_to_end(key)
        return hit
    path = maps_file(src, dst, R) if dst.width * dst.height >= DISK_CACHE_MIN_PX else None
    maps = load_maps(path, dst) if path is not None and path.exists() else None
    if maps is None:
        maps = _compute_maps(src, dst, R)
        if path is not None:
            save_maps(path, maps)
    _CACHE[key] = maps
    while len(_CACHE) > MAP_CACHE_SIZE:
        _CACHE.popitem(last=False)
    return maps


def _compute_maps(src: CameraModel, dst: CameraModel, R: F64) -> RemapMaps:
    map_x = np.empty((dst.height, dst.width), np.float32)
    map_y = np.empty((dst.height, dst.width), np.float32)
    valid = np.empty((dst.height, dst.width), bool)
    for r0 in range(0, dst.height, MAP_BLOCK_ROWS):  # blocks: temporaries stay in cache, not 200 MB each
        r1 = min(r0 + MAP_BLOCK_ROWS, dst.height)
        rays_dst, ok_dst = dst.unproject(dst.pixel_grid(r0, r1))
        rays_src = np.einsum("ij,...j->...i", R, rays_dst)  # not a tall BLAS matmul: threads fight the pool
        uv, ok_src = src.project(rays_src)
        ok = ok_dst & ok_src & src.in_image(uv)
        valid[r0:r1] = ok
        map_x[r0:r1] = np.where(ok, uv[..., 0], INVALID_COORD)
        map_y[r0:r1] = np.where(ok, uv[..., 1], INVALID_COORD)
    return RemapMaps(map_x, map_y, valid, valid_spans(valid))


# ---------------------------------------------------------------- on-disk cache


def map_cache_dir() -> Path | None:
    """The on-disk map cache: `$SENSORBOX_MAP_CACHE`, else `$XDG_CACHE_HOME` or ~/.cache + sensorbox/maps.

    None when the variable is "off" or empty. Forked workers inherit it; a
    Dask worker on another machine uses its own.
    """
    value = os.environ.get(MAP_CACHE_ENV)
    if value is not None:
        return None if value.strip() in ("", "off") else Path(value).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "sensorbox" / "maps"


def maps_file(src: CameraModel, dst: CameraModel, R_src_dst: F64) -> Path | None:
    """The cache file of these maps: named by a hash of both models' parameters, the rotation and sizes.

    Models are frozen dataclasses whose repr holds every parameter exactly
    (floats repr round-trip), so two calibrations differing in any digit get
    two files.
    """
    folder = map_cache_dir()
    if folder is None:
        return None
    R = np.asarray(R_src_dst, dtype=np.float64)
    text = f"maps v{MAPS_FORMAT}|{src!r}|{dst!r}|{R.tobytes().hex()}"
    return folder / f"{hashlib.sha256(text.encode()).hexdigest()[:32]}.npz"


MAX_CACHE_FILE_BYTES = 1 << 32
"""Largest remap map cache file read (4 GiB): two float32 maps and a mask of a 16k x 8k equirect."""


def load_maps(path: Path, dst: CameraModel) -> RemapMaps | None:
    """The maps stored at `path`, or None (with one warning line) when the file is not what was stored
    (a device or FIFO in its place is not read: a FIFO would wait forever)."""
    shape = (dst.height, dst.width)
    try:
        check_regular_file(path, "remap map cache", MAX_CACHE_FILE_BYTES)
        with np.load(path, allow_pickle=False) as data:
            map_x, map_y, valid, spans = (data[k] for k in ("map_x", "map_y", "valid", "spans"))
        ok = (
            map_x.shape == map_y.shape == valid.shape == shape
            and map_x.dtype == map_y.dtype == np.float32
            and valid.dtype == bool
            and spans.ndim == 2
            and spans.shape[1:] == (4,)
        )
        if not ok:
            raise ValueError(f"arrays are not {shape[1]}x{shape[0]} float32 maps, a mask and (n, 4) spans")
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, CalibrationError) as err:
        log.warning("%s: unreadable remap map cache file (%s); building the maps again", path, err)
        return None
    boxes = tuple((int(r0), int(r1), int(c0), int(c1)) for r0, r1, c0, c1 in spans.tolist())
    return RemapMaps(map_x, map_y, valid, boxes)


def save_maps(path: Path, maps: RemapMaps) -> None:
    """Store `maps` at `path` whole (`calibration.files.write_atomic`); a failure, or a `path` that is a
    device or FIFO (never written into nor replaced), is one warning line: the cache is only a cache."""
    buffer = io.BytesIO()
    spans = np.array(maps.spans, np.int64).reshape(-1, 4)
    np.savez(buffer, map_x=maps.map_x, map_y=maps.map_y, valid=maps.valid, spans=spans)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(path, buffer.getvalue(), WriteError)
    except (OSError, WriteError) as err:
        log.warning("%s: cannot store the remap maps (%s); they will be built again next time", path, err)


def clear_map_cache() -> None:
    """Forget every map cached in memory (the disk cache is keyed by the parameters: never stale)."""
    _CACHE.clear()


def check_source(image: np.ndarray[Any, Any], src_model: CameraModel) -> None:
    """Raise ValueError unless `image` has `src_model`'s size."""
    if image.shape[:2] != (src_model.height, src_model.width):
        raise ValueError(
            f"warp: image is {image.shape[1]}x{image.shape[0]}, but the source model is "
            f"{src_model.width}x{src_model.height}"
        )


def remap_spans(
    image: np.ndarray[Any, Any],
    maps: RemapMaps,
    out: np.ndarray[Any, Any],
    interpolation: int = cv2.INTER_LINEAR,
    fill: float = 0.0,
) -> None:
    """`cv2.remap` of `image` into `out` (the maps' target size), over the maps' spans only.

    `out` must already hold `fill` outside the spans, as a fresh `np.full`
    or a `RemapMaps.scratch` buffer does. cv2 releases the GIL, so this may
    run in a helper thread beside numpy work.
    """
    border = (fill, fill, fill, fill)
    for r0, r1, c0, c1 in maps.spans:  # cv2 writes into the strided views in place
        cv2.remap(
            image, maps.map_x[r0:r1, c0:c1], maps.map_y[r0:r1, c0:c1], interpolation,
            dst=out[r0:r1, c0:c1], borderMode=cv2.BORDER_CONSTANT, borderValue=border,
        )  # fmt: skip


def warp(
    image: np.ndarray[Any, Any],
    src_model: CameraModel,
    dst_model: CameraModel,
    R_src_dst: F64 | None = None,
    interpolation: int = cv2.INTER_LINEAR,
    fill: float = 0.0,
) -> tuple[np.ndarray[Any, Any], Bool]:
    """Render ``dst_model``'s view from an image taken with ``src_model``.

    Returns ``(warped, valid)``: pixels with no valid source are set to
    ``fill`` and are False in ``valid``. ``interpolation`` is a cv2 flag
    (INTER_NEAREST for label/depth images, INTER_LINEAR or INTER_CUBIC for
    colour). Only the maps' spans are remapped. A caller warping frame after
    frame can skip the output's allocation and fill with `remap_spans` into
    `RemapMaps.scratch` (as `ingest.train.run.sample.start_equirects` does).
    """
    check_source(image, src_model)
    maps = build_maps(src_model, dst_model, R_src_dst)
    shape = (dst_model.height, dst_model.width, *image.shape[2:])
    out = np.full(shape, fill, image.dtype)
    remap_spans(image, maps, out, interpolation, fill)
    return out, maps.valid


def default_height_full(fisheye: CameraModel, multiple: int = 256) -> int:
    """Full-sphere rows so the equirect pitch matches the camera's centre resolution, within reason.

    The camera's angular resolution at its principal point (pixels per
    radian, from a small ray step) times pi, rounded up to ``multiple`` so
    the image stays friendly to networks that downsample; the reference rig
    gives 2048 (a 2048 x 4096 sphere). A narrow camera resolves finely but
    sees a sliver of the sphere, so the sphere is also held to
    SPHERE_PX_PER_CAMERA_PX times the camera's pixels (rounded down): a
    1920 x 1200 pinhole of 54 degrees gets 4096 rows, not 6144.
    """
    eps = 1e-6
    uv, ok = fisheye.project(np.array([[0.0, 0.0, 1.0], [math.sin(eps), 0.0, math.cos(eps)],
                                       [0.0, math.sin(eps), math.cos(eps)]]))  # fmt: skip
    if not ok.all():
        raise ValueError("default_height_full: the camera does not see along its optical axis")
    px_per_rad = max(abs(uv[1, 0] - uv[0, 0]), abs(uv[2, 1] - uv[0, 1])) / eps
    centre = int(math.ceil(px_per_rad * math.pi / multiple) * multiple)
    by_pixels = math.sqrt(SPHERE_PX_PER_CAMERA_PX * fisheye.width * fisheye.height / 2.0)
    return min(centre, max(multiple, int(by_pixels // multiple) * multiple))


def memory_budget_bytes() -> int:
    """The default budget of one equirect's work: half of this machine's physical memory."""
    return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE") // 2


HEIGHT_FULL_EXPECTED = (
    f">= {MIN_HEIGHT_FULL} rows (a pixel of 2.8 degrees; fewer leave no image a network can downsample, "
    "nor disparity)"
)
"""What a full sphere's height must be (`MIN_HEIGHT_FULL`), said in the error line."""


def height_full_problem(height_full: int) -> str | None:
    """Why ``height_full`` rows are too few for a dataset (`MIN_HEIGHT_FULL`), in one line; None if not."""
    if height_full >= MIN_HEIGHT_FULL:
        return None
    return f"--height-full must be {HEIGHT_FULL_EXPECTED}, got {height_full}"


def check_height_full(height_full: int, budget_bytes: int | None = None, given_by: str | None = None) -> int:
    """``height_full`` if a full sphere of it fits the memory budget, else a CalibrationError.

    The cost is SPHERE_BYTES_PER_PX per full-sphere pixel (remap maps, images,
    range, disparity and masks; measured: 6 GB RSS for ingest at 5888 rows).
    `given_by` names what chose ``height_full`` when no --height-full did
    (an image size, through `default_height_full`), so the message blames it.
    """
    budget = memory_budget_bytes() if budget_bytes is None else budget_bytes
    if (problem := height_full_problem(height_full)) is not None:
        raise CalibrationError(problem)
    need = 2 * height_full * height_full * SPHERE_BYTES_PER_PX
    if need > budget:
        most = max(2, int(math.sqrt(budget / (2 * SPHERE_BYTES_PER_PX))) // 256 * 256)
        raise CalibrationError(
            f"{given_by or f'--height-full {height_full}'}: a full-sphere equirect of {height_full} x "
            f"{2 * height_full} "
            f"needs about {need / 1e9:.1f} GB, over the budget of {budget / 1e9:.1f} GB (half this "
            f"machine's memory); pass --height-full {most} or less"
        )
    return height_full


def covering_crop(
    fisheye: CameraModel, R_src_eq: F64, height_full: int, margin_px: int = 1, samples: int = 400
) -> Equirectangular:
    """Smallest equirect crop (same pitch as the full sphere) covering everything the fisheye sees.

    ``R_src_eq`` rotates equirect-frame rays into the fisheye frame (e.g.
    ``R_cam0_rect``). Valid fisheye pixels are sampled on a dense grid plus
    the whole border, their rays rotated into the equirect frame, and the
    bounding rows/columns kept with ``margin_px`` spare. If the fisheye sees
    across the equirect's +-pi seam, the crop keeps the full width.
    """
    full = Equirectangular(height_full)
    W, H = fisheye.width, fisheye.height
    us = np.linspace(-0.5, W - 0.5, samples)
    vs = np.linspace(-0.5, H - 0.5, samples)
    grid = np.stack(np.meshgrid(us, vs), axis=-1).reshape(-1, 2)
    rays, ok = fisheye.unproject(grid)
    rays_eq = rays[ok] @ np.asarray(R_src_eq, dtype=np.float64)  # R_eq_src = R_src_eq^T
    uv, _ = full.project(rays_eq)
    r0 = max(0, math.floor(uv[:, 1].min() + 0.5) - margin_px)
    r1 = min(height_full, math.floor(uv[:, 1].max() + 0.5) + 1 + margin_px)
    # The seen longitudes form an arc; it avoids the +-pi seam iff the widest gap between
    # neighbouring longitudes is the one that wraps around from the largest to the smallest.
    phi = np.sort(np.arctan2(rays_eq[:, 0], rays_eq[:, 2]))
    inner_gap = float(np.max(np.diff(phi))) if phi.size > 1 else 0.0
    wrap_gap = float(phi[0] + 2.0 * math.pi - phi[-1])
    if inner_gap > wrap_gap:
        c0, c1 = 0, 2 * height_full  # the view crosses the seam behind the camera
    else:
        c0 = max(0, math.floor(uv[:, 0].min() + 0.5) - margin_px)
        c1 = min(2 * height_full, math.floor(uv[:, 0].max() + 0.5) + 1 + margin_px)
    return full.crop(r0, c0, r1 - r0, c1 - c0)
