"""The WideDepth train layout on disk: atomic, resumable, deterministic writes.

```
OUT/
  left_fisheye/000000.png        RGB, upper camera (cam0), as recorded
  right_fisheye/000000.png       RGB, lower camera (cam1), as recorded
  equirect_up/000000.png         RGB, cam0 in its rectified full-sphere equirect
  equirect_down_virt/000000.png  RGB, cam1 rectified into cam0's rectified orientation
  disp_equirect/000000.png       uint16, disparity x 100 (px of the full sphere), 0 = invalid
  depth_fisheye/000000.png       uint16, range in mm along cam0's pixel rays, 0 = invalid
  disp_equirect_exr/, depth_fisheye_exr/   float32 copies (--exr; channel "Y", m or px)
  meta/000000.json               stamps, source bag, skews, motion decision, counts, density
  dataset.yaml                   geometry, conventions, parameters, versions
```

Every file is written to a temporary name in its folder and renamed into
place; `meta/<id>.json` is written last, with the size and SHA-256 of every
other file of the sample: a rerun skips a sample whose metadata is there
and whose files are whole (`ingest.dataset.identity`), and writes a damaged
one again. Values that do not fit uint16 are dropped (0) and counted, never
wrapped.
"""

from __future__ import annotations

import hashlib
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import OpenEXR

from calibration import files
from calibration.types import F32, U8
from ingest.dataset.meta import FileMeta, SampleMeta
from ingest.dataset.png import encode_png, read_image
from ingest.dataset.sparse import SparseImage
from ingest.errors import DatasetError, OutputError

IMAGE_DIRS = ("left_fisheye", "right_fisheye", "equirect_up", "equirect_down_virt")
GT_DIRS = ("disp_equirect", "depth_fisheye")
EXR_DIRS = ("disp_equirect_exr", "depth_fisheye_exr")
DISP_SCALE = 100.0  # uint16 = round(disp_px * 100)
DEPTH_SCALE = 1000.0  # uint16 = round(range_m * 1000)
ID_DIGITS = 6


def sample_id(index: int) -> str:
    """Zero-padded numeric id shared by every folder."""
    return f"{index:0{ID_DIGITS}d}"


def write_atomic(path: Path, data: bytes) -> None:
    """`calibration.files.write_atomic` with `OutputError`: `path` whole or unchanged, a device, FIFO or
    socket refused, one line naming the path (exit code 3)."""
    files.write_atomic(path, data, OutputError)


def refuse_special_target(path: Path) -> None:
    """`calibration.files.refuse_special_target` with `OutputError`: an output `path` that exists as a
    device, FIFO or socket (symlinks followed) is one line naming it and what it is."""
    files.refuse_special_target(path, OutputError)


def write_atomic_set(targets: Sequence[tuple[Path, bytes]]) -> None:
    """`calibration.files.write_atomic_set` with `OutputError`: all of `targets` written, or none changed."""
    files.write_atomic_set(targets, OutputError)


def to_uint16(values: SparseImage, scale: float) -> tuple[np.ndarray[Any, np.dtype[np.uint16]], int]:
    """round(values * scale) as a dense uint16 image; values that would not fit become 0 and are counted."""
    out = np.zeros(values.shape, np.uint16)
    scaled = np.round(values.value.astype(np.float64) * scale)
    fits = np.isfinite(scaled) & (scaled >= 0) & (scaled <= np.iinfo(np.uint16).max)
    out.reshape(-1)[values.pixel[fits]] = scaled[fits].astype(np.uint16)
    return out, int((np.isfinite(scaled) & (scaled > np.iinfo(np.uint16).max)).sum())


def encode_exr(values: F32) -> bytes:
    """Single-channel ("Y") float32 EXR, ZIP-compressed."""
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "x.exr"
        OpenEXR.File(header, {"Y": np.ascontiguousarray(values, np.float32)}).write(str(path))
        return path.read_bytes()


@dataclass(frozen=True)
class SampleFiles:
    """Everything one sample writes: BGR (or BGRA, alpha not written) uint8 images and the sparse GT
    (float32, m or px)."""

    left_fisheye: U8
    right_fisheye: U8
    equirect_up: U8
    equirect_down_virt: U8
    disp_px: SparseImage
    range_m: SparseImage
    meta: SampleMeta


def prepare_dirs(out: Path, exr: bool) -> None:
    """Create the layout's folders; refuse two of them that are one folder (`distinct_dirs`)."""
    names = (*IMAGE_DIRS, *GT_DIRS, "meta", *(EXR_DIRS if exr else ()))
    try:
        for name in names:
            (out / name).mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise OutputError(f"cannot create the dataset folders in {out}: {err.strerror or err}") from err
    distinct_dirs(out, names)


def distinct_dirs(out: Path, names: Sequence[str]) -> None:
    """Raise `DatasetError` when two of the layout's folders `names` in `out` are one folder (a symbolic
    link to another): each sample would write one image over the other, and a rerun that finds them
    damaged writes them again, one over the other."""
    seen: dict[Path, str] = {}
    for name in names:
        real = files.resolved(out / name, DatasetError)
        if real in seen:
            links = [n for n in (seen[real], name) if (out / n).is_symlink()]
            how = (
                f" ({', '.join(f'{n} is a link to {(out / n).readlink()}' for n in links)})" if links else ""
            )
            raise DatasetError(
                f"{out}: {seen[real]} and {name} are one folder{how}; "
                "each of a dataset's folders must be its own"
            )
        seen[real] = name


def write_sample(out: Path, sid: str, files: SampleFiles, exr: bool, png_level: int = 1) -> dict[str, int]:
    """Write one sample's files atomically, metadata last; returns the uint16 overflow drops.

    The metadata records every other file's size and SHA-256 (`SampleMeta.files`), by its path in the
    dataset, so that a rerun can tell a finished sample from a damaged one (`ingest.dataset.identity`).
    """
    disp_u16, disp_drop = to_uint16(files.disp_px, DISP_SCALE)
    depth_u16, depth_drop = to_uint16(files.range_m, DEPTH_SCALE)
    records: dict[str, FileMeta] = {}

    def put(name: str, data: bytes) -> None:
        write_atomic(out / name, data)
        records[name] = FileMeta(len(data), hashlib.sha256(data).hexdigest())

    for name in IMAGE_DIRS:
        put(f"{name}/{sid}.png", encode_png(getattr(files, name), png_level))
    put(f"disp_equirect/{sid}.png", encode_png(disp_u16, png_level))
    put(f"depth_fisheye/{sid}.png", encode_png(depth_u16, png_level))
    if exr:
        put(f"disp_equirect_exr/{sid}.exr", encode_exr(files.disp_px.dense()))
        put(f"depth_fisheye_exr/{sid}.exr", encode_exr(files.range_m.dense()))
    drops = {"disp_over_uint16": disp_drop, "depth_over_uint16": depth_drop}
    write_atomic(out / "meta" / f"{sid}.json", files.meta.written(sid, drops, records).to_json().encode())
    return drops


def read_png_u16(path: Path, scale: float) -> F32:
    """Read a uint16 GT PNG back into float32 physical units (0 stays 0)."""
    raw = read_image(path)
    if raw is None:
        size = path.stat().st_size if path.is_file() else 0
        raise DatasetError(f"{path}: cannot be decoded ({size} bytes: empty, cut short or not an image)")
    if raw.dtype != np.uint16:
        raise DatasetError(f"{path}: not a 16-bit PNG ({raw.dtype} pixels)")
    out: F32 = raw.astype(np.float32) / np.float32(scale)
    return out
