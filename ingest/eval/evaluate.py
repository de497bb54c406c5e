"""Score depth / disparity predictions against a WideDepth dataset's ground truth.

Two dataset layouts are recognised:

- train (written by `sensorbox ingest`): `disp_equirect/<id>.png` (stereo GT,
  uint16 px x 100) and `depth_fisheye/<id>.png` (mono / completion GT, uint16
  mm); 0 = invalid.
- benchmark (written by `sensorbox render-benchmark`):
  `<scene>/<FOV>FOV/<B>mm/CENTER/disparity/<view>.png` (stereo) and
  `.../CENTER/depth/<view>.png` (mono / completion), same encodings. The FOV
  (degrees) and baseline (mm) are read from those path components; `--by
  fov|baseline` groups by them.

A prediction has the GT file's relative path and stem under the prediction
folder, with extension `.png` (uint16, the GT's scale), `.exr` (float32, one
channel or "Y") or `.npy` (float): metres for depth, px for disparity; 0,
negative or non-finite = no prediction. Missing predictions are counted and
listed, never fatal; a shape mismatch is an `EvalError` naming both files.

Completion is scored exactly like mono (the sparse input is the caller's
business). Regions: "all" valid GT; "edges" = GT pixels within a few px of a
GT discontinuity (`ingest.eval.metrics.edge_band`); plus any mask folders given
(PNG named like the GT, non-zero = inside).
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from calibration.files import check_regular_file, file_kind, resolved
from calibration.types import F32
from ingest.dataset.layout import DEPTH_SCALE, DISP_SCALE, read_png_u16, write_atomic
from ingest.dataset.png import MAX_IMAGE_BYTES, read_image
from ingest.errors import DatasetError, EvalError
from ingest.eval.metrics import Accumulator, DepthAccumulator, StereoAccumulator, median_scale
from ingest.raster.edges import edge_band

Task = Literal["stereo", "mono", "completion"]
Layout = Literal["train", "benchmark"]
TASKS: tuple[Task, ...] = ("stereo", "mono", "completion")
GROUP_KEYS = ("fov", "baseline")
PRED_EXTS = (".png", ".exr", ".npy")

BENCHMARK_GT = re.compile(
    r"^(?P<scene>[^/]+)/(?P<fov>\d+(?:\.\d+)?)FOV/(?P<baseline>\d+(?:\.\d+)?)mm/CENTER/"
    r"(?P<kind>depth|disparity)/(?P<view>[^/]+)\.png$"
)
"""A benchmark GT file, relative to the dataset root (posix separators)."""
TRAIN_ID = re.compile(r"^\d+$")
CONFIG_LABEL = re.compile(r"^(?P<value>\d+(?:\.\d+)?)(?P<unit>FOV|mm)$")

STEREO_COLUMNS = ("epe_px", "median_px", "p95_px", "bad1", "bad2", "bad3")
DEPTH_COLUMNS = ("abs_rel", "mae_m", "rmse_m", "delta1", "delta2", "delta3")
EDGE_STEP = {"stereo": (0.25, 0.03), "depth": (0.05, 0.03)}  # (abs, rel) of `edge_band`, px or m


@dataclass(frozen=True)
class GtFile:
    """One ground-truth map and where it sits in the dataset."""

    rel: str  # posix path without extension: "disp_equirect/000001", "s1/120FOV/65mm/CENTER/depth/pano"
    path: Path
    scale: float  # uint16 value = physical value * scale
    scene: str | None = None
    fov_deg: float | None = None
    baseline_mm: float | None = None
    view: str | None = None


def _is_stereo(task: str) -> bool:
    return task == "stereo"


def what_it_is(path: Path) -> str:
    """What an existing path that is no folder is, in words: "a file", or "a character device (a link to
    /dev/zero)" and the like (`calibration.files.file_kind`)."""
    if path.is_file():
        return "a file"
    target = resolved(path, DatasetError)
    via = f" (a link to {target})" if target != path.absolute() else ""
    return f"{file_kind(path.stat().st_mode)}{via}"


def detect_layout(root: Path) -> Layout:
    """'train' when the ingest folders exist, 'benchmark' when `<scene>/<FOV>FOV/<B>mm/CENTER` does."""
    if root.exists() and not root.is_dir():
        raise EvalError(f"{root}: is {what_it_is(root)}; expected a dataset folder")
    if not root.is_dir():
        raise EvalError(f"{root}: no such dataset folder")
    if (root / "disp_equirect").is_dir() or (root / "depth_fisheye").is_dir():
        return "train"
    if any(p.is_dir() for p in root.glob("*/*FOV/*mm/CENTER")):
        return "benchmark"
    raise EvalError(
        f"{root}: neither the WideDepth train layout (disp_equirect/, depth_fisheye/) nor the "
        "benchmark layout (<scene>/<FOV>FOV/<B>mm/CENTER/) is there"
    )


def discover_gt(root: Path, task: Task, image_type: str | None = None) -> tuple[Layout, list[GtFile]]:
    """Every GT file of `task` under `root`: train by id, benchmark by scene, FOV, baseline (numeric), view.

    `image_type` keeps only benchmark files of that view (e.g. "pano_crop"); a train
    layout has one GT view per task and no choice of view, so there it is refused
    rather than ignored.
    """
    if task not in TASKS:
        raise EvalError(f"task {task!r}: expected one of {', '.join(TASKS)}")
    layout = detect_layout(root)
    if layout == "train" and image_type is not None:
        raise EvalError(
            f"--image-type {image_type!r}: {root} is a train-layout dataset, which has one view per sample; "
            "--image-type selects benchmark views only (leave it out)"
        )
    scale = DISP_SCALE if _is_stereo(task) else DEPTH_SCALE
    found: list[GtFile] = []
    if layout == "train":
        folder = "disp_equirect" if _is_stereo(task) else "depth_fisheye"
        for p in sorted((root / folder).glob("*.png")):
            if TRAIN_ID.match(p.stem):
                found.append(GtFile(f"{folder}/{p.stem}", p, scale))
    else:
        kind = "disparity" if _is_stereo(task) else "depth"
        for p in sorted(root.glob(f"*/*FOV/*mm/CENTER/{kind}/*.png")):
            m = BENCHMARK_GT.match(p.relative_to(root).as_posix())
            if m is None or (image_type is not None and m["view"] != image_type):
                continue
            rel = p.relative_to(root).with_suffix("").as_posix()
            found.append(GtFile(rel, p, scale, m["scene"], float(m["fov"]), float(m["baseline"]), m["view"]))
        found.sort(key=lambda g: (g.scene or "", g.fov_deg or 0.0, g.baseline_mm or 0.0, g.view or ""))
    if not found:  # a view of another name than the benchmark's: the option is wrong, named with them
        kind, views = ("disparity" if _is_stereo(task) else "depth"), ""
        what = f"{'disp_equirect' if _is_stereo(task) else 'depth_fisheye'}/*.png"
        if layout == "benchmark":
            views = ", ".join(sorted({p.stem for p in root.glob(f"*/*FOV/*mm/CENTER/{kind}/*.png")}))
            what = f"<scene>/<FOV>FOV/<B>mm/CENTER/{kind}/{image_type or '<view>'}.png"
        if views and image_type is not None:
            raise EvalError(f"--image-type {image_type!r}: {root} has {kind} GT of the views {views}")
        raise EvalError(f"{root}: no {'disparity' if _is_stereo(task) else 'depth'} ground truth ({what})")
    return layout, found


def find_prediction(pred_root: Path, gt: GtFile) -> Path | None:
    """The prediction file for `gt` (same relative path and stem), or None; two candidates are an error.

    Any path that exists counts (a device or FIFO too: `read_prediction` refuses it, never skips it).
    """
    hits = [p for ext in PRED_EXTS if (p := pred_root / f"{gt.rel}{ext}").exists()]
    if len(hits) > 1:
        raise EvalError(f"{', '.join(map(str, hits))}: several predictions for {gt.rel}; keep one")
    return hits[0] if hits else None


def read_gt(gt: GtFile) -> F32:
    """A GT map in metres or px, NaN where invalid."""
    try:
        values = read_png_u16(gt.path, gt.scale)
    except DatasetError as err:
        raise EvalError(f"{err}; ground truth must be a 16-bit single-channel PNG") from err
    if values.ndim != 2:
        raise EvalError(f"{gt.path}: ground truth must be single-channel, got shape {values.shape}")
    out: F32 = np.where(values > 0, values, np.float32(np.nan)).astype(np.float32)
    return out


def _read_exr(path: Path) -> np.ndarray[Any, Any]:
    import OpenEXR

    check_regular_file(path, ".exr prediction", MAX_IMAGE_BYTES, EvalError)
    try:
        channels = OpenEXR.File(str(path)).channels()
    except Exception as err:  # OpenEXR raises plain Exceptions for unreadable files
        raise EvalError(f"{path}: cannot read the EXR file ({err})") from err
    if "Y" in channels:
        return np.asarray(channels["Y"].pixels)
    if len(channels) == 1:
        return np.asarray(next(iter(channels.values())).pixels)
    raise EvalError(f"{path}: expected one channel (or 'Y'), found {sorted(channels)}")


def _npy_layout(path: Path) -> tuple[tuple[int, ...], np.dtype[Any], int]:
    """The shape and dtype a .npy file's header declares, and the bytes of data after the header."""
    try:
        with path.open("rb") as f:
            version = np.lib.format.read_magic(f)
            read = (
                np.lib.format.read_array_header_1_0
                if version == (1, 0)
                else np.lib.format.read_array_header_2_0
            )
            shape, _, dtype = read(f)
            offset = f.tell()
        return tuple(shape), dtype, path.stat().st_size - offset
    except (OSError, ValueError, EOFError) as err:  # an empty file: EOFError, which click reads as Ctrl-D
        raise EvalError(f"{path}: cannot read the .npy file ({err})") from err


def _read_npy(path: Path) -> np.ndarray[Any, Any]:
    """A .npy prediction, its header checked against the file's size before any array is allocated.

    A header may claim more than the file holds (1e10 values: numpy
    allocated 37 GiB before finding the data missing). A device or FIFO is
    refused before a byte is read.
    """
    check_regular_file(path, ".npy prediction", MAX_IMAGE_BYTES, EvalError)
    dims, dtype, have = _npy_layout(path)
    need = math.prod(dims) * dtype.itemsize
    if need > have:
        raise EvalError(
            f"{path}: the .npy header claims shape {dims} of {dtype} ({need} bytes), but the file holds "
            f"{have} bytes of data"
        )
    try:
        values = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as err:
        raise EvalError(f"{path}: cannot read the .npy file ({err})") from err
    squeezed: np.ndarray[Any, Any] = np.squeeze(values)
    return squeezed


def read_prediction(path: Path, scale: float) -> F32:
    """A prediction in metres or px (float32), NaN where there is none (0, negative, non-finite)."""
    ext = path.suffix.lower()
    if ext == ".png":
        raw = read_image(path, error=EvalError)
        if raw is None or raw.dtype != np.uint16 or raw.ndim != 2:
            got = "unreadable" if raw is None else f"{raw.dtype} with shape {raw.shape}"
            raise EvalError(f"{path}: expected a 16-bit single-channel PNG (value x {scale:g}), got {got}")
        values = raw.astype(np.float32) / np.float32(scale)
    elif ext == ".exr":
        values = _read_exr(path)
    elif ext == ".npy":
        values = _read_npy(path)
        if not (np.issubdtype(values.dtype, np.floating) or np.issubdtype(values.dtype, np.integer)):
            raise EvalError(f"{path}: expected a real-valued array, got dtype {values.dtype}")
    else:
        raise EvalError(f"{path}: predictions must be .png, .exr or .npy")
    if values.ndim != 2:
        raise EvalError(f"{path}: expected a single-channel 2-D map, got shape {values.shape}")
    v = values.astype(np.float32)
    with np.errstate(invalid="ignore"):
        out: F32 = np.where(np.isfinite(v) & (v > 0), v, np.float32(np.nan))
    return out


def read_mask(mask_root: Path, gt: GtFile, shape: tuple[int, ...]) -> np.ndarray[Any, np.dtype[np.bool_]]:
    """A region mask named like the GT (`<mask_root>/<rel>.png`), non-zero = inside."""
    path = mask_root / f"{gt.rel}.png"
    raw = read_image(path, error=EvalError)
    if raw is None:
        raise EvalError(f"{path}: missing or unreadable mask for {gt.rel}")
    if raw.shape[:2] != shape:
        raise EvalError(f"{path}: mask shape {raw.shape[:2]} but the GT {gt.path} is {shape}")
    inside = np.asarray(raw) != 0
    out: np.ndarray[Any, np.dtype[np.bool_]] = np.asarray(inside.any(axis=2) if inside.ndim == 3 else inside)
    return out


@dataclass(frozen=True)
class EvalOptions:
    """What to score and how to group it."""

    task: Task
    by: tuple[str, ...] = ()  # subset of GROUP_KEYS, in order
    image_type: str | None = None  # benchmark view filter ("pano_crop", ...)
    edges: bool = True
    edge_band_px: int = 3
    masks: tuple[tuple[str, Path], ...] = ()  # (region name, folder of mask PNGs)
    align: Literal["none", "median"] = "none"  # depth only: per-sample median scaling
    asked_by: tuple[str, ...] = ()  # the options that asked for the groups, as the user wrote them (messages)


@dataclass(frozen=True)
class SampleRow:
    """One scored sample: metrics per region (dicts of `Metrics.as_dict`)."""

    rel: str
    pred: str
    scene: str | None
    fov_deg: float | None
    baseline_mm: float | None
    view: str | None
    scale: float  # median scale applied (1.0 unless align="median")
    metrics: dict[str, dict[str, float | int]]


@dataclass(frozen=True)
class GroupRow:
    """Pooled metrics of a group of samples (or of all of them)."""

    label: str
    fov_deg: float | None
    baseline_mm: float | None
    samples: int
    metrics: dict[str, dict[str, float | int]]


@dataclass(frozen=True)
class EvalReport:
    """Per-sample and pooled metrics, groups, and the predictions that were missing."""

    dataset: Path
    pred: Path
    layout: Layout
    options: EvalOptions
    regions: tuple[str, ...]
    samples: tuple[SampleRow, ...]
    groups: tuple[GroupRow, ...]
    overall: GroupRow
    missing: tuple[str, ...]

    @property
    def columns(self) -> tuple[str, ...]:
        return STEREO_COLUMNS if _is_stereo(self.options.task) else DEPTH_COLUMNS

    def to_json(self) -> dict[str, Any]:
        """A JSON-ready dict (NaN -> null)."""
        opts = asdict(self.options)
        opts["masks"] = {name: str(p) for name, p in self.options.masks}
        doc = {
            "dataset": str(self.dataset),
            "pred": str(self.pred),
            "layout": self.layout,
            "options": opts,
            "regions": list(self.regions),
            "overall": asdict(self.overall),
            "groups": [asdict(g) for g in self.groups],
            "missing": list(self.missing),
            "samples": [asdict(s) for s in self.samples],
        }
        return json_safe(doc)  # type: ignore[no-any-return]


def json_safe(value: Any) -> Any:
    """`value` with non-finite floats replaced by None (strict JSON has no NaN)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    return value


def config_component(key: str, value: float | None) -> str:
    """The path component of a grouping value: ('fov', 195) -> '195FOV', ('baseline', 65) -> '65mm'."""
    return f"{value:g}FOV" if key == "fov" else f"{value:g}mm"


def group_label(by: Sequence[str], fov_deg: float | None, baseline_mm: float | None) -> str:
    """'195FOV/65mm' style label of a group; 'all' without keys."""
    parts = [config_component(k, fov_deg if k == "fov" else baseline_mm) for k in by]
    return "/".join(parts) or "all"


@dataclass
class _Pool:
    fov_deg: float | None
    baseline_mm: float | None
    samples: int = 0
    acc: dict[str, Accumulator] = field(default_factory=dict)


def _new_acc(task: Task) -> Accumulator:
    return StereoAccumulator() if _is_stereo(task) else DepthAccumulator()


def _regions(opts: EvalOptions) -> tuple[str, ...]:
    return ("all", *(["edges"] if opts.edges else []), *(name for name, _ in opts.masks))


def _check_options(opts: EvalOptions, layout: Layout) -> None:
    bad = [k for k in opts.by if k not in GROUP_KEYS]
    if bad:
        raise EvalError(f"--by {bad[0]!r}: expected one of {', '.join(GROUP_KEYS)}")
    if opts.by and layout != "benchmark":
        asked = ", ".join(opts.asked_by) or f"--by {'/'.join(opts.by)}"
        raise EvalError(
            f"{asked}: grouping by {'/'.join(opts.by)} needs the benchmark layout "
            "(<scene>/<FOV>FOV/<B>mm/...); this dataset is the train layout"
        )
    names = [name for name, _ in opts.masks]
    if len(set(names)) != len(names) or {"all", "edges"} & set(names):
        raise EvalError(f"mask names {names}: must be unique and not 'all' or 'edges'")
    if opts.align not in ("none", "median") or (opts.align == "median" and _is_stereo(opts.task)):
        raise EvalError(f"align {opts.align!r}: 'none', or 'median' for depth tasks only")


def _masks(
    opts: EvalOptions, gt: GtFile, g: np.ndarray[Any, Any], step_abs: float, step_rel: float
) -> dict[str, np.ndarray[Any, Any] | None]:
    """Region -> the pixels of GT `g` it scores: "all" (None), "edges" (`opts.edges`), each `opts.masks`."""
    masks: dict[str, np.ndarray[Any, Any] | None] = {"all": None}
    if opts.edges:
        masks["edges"] = edge_band(g, opts.edge_band_px, step_abs, step_rel)
    for name, root in opts.masks:
        masks[name] = read_mask(root, gt, g.shape)
    return masks


def evaluate(
    dataset: Path,
    pred: Path,
    opts: EvalOptions,
    progress: Callable[[int, int], None] | None = None,
) -> EvalReport:
    """Score every prediction under `pred` against the GT of `dataset`; `progress(done, total)`."""
    layout, gts = discover_gt(dataset, opts.task, opts.image_type)
    _check_options(opts, layout)
    if pred.exists() and not pred.is_dir():
        raise EvalError(f"--pred {pred}: is {what_it_is(pred)}; expected a folder of predictions")
    if not pred.is_dir():
        raise EvalError(f"{pred}: no such prediction folder")
    regions = _regions(opts)
    stereo = _is_stereo(opts.task)
    step_abs, step_rel = EDGE_STEP["stereo" if stereo else "depth"]
    overall = _Pool(None, None)
    pools: dict[tuple[float | None, ...], _Pool] = {}
    rows: list[SampleRow] = []
    missing: list[str] = []
    for k, gt in enumerate(gts):
        pred_path = find_prediction(pred, gt)
        if pred_path is None:
            missing.append(gt.rel)
        else:
            g = read_gt(gt)
            p = read_prediction(pred_path, gt.scale)
            if p.shape != g.shape:
                raise EvalError(f"{pred_path}: prediction shape {p.shape} but the GT {gt.path} is {g.shape}")
            scale = 1.0
            if opts.align == "median":
                scale = median_scale(p, g)
                p = (p * np.float32(scale)).astype(np.float32)
            masks = _masks(opts, gt, g, step_abs, step_rel)
            key = tuple(gt.fov_deg if b == "fov" else gt.baseline_mm for b in opts.by)
            if key not in pools:
                pools[key] = _Pool(
                    gt.fov_deg if "fov" in opts.by else None,
                    gt.baseline_mm if "baseline" in opts.by else None,
                )
            pool = pools[key]
            per_region: dict[str, dict[str, float | int]] = {}
            for region in regions:
                acc = _new_acc(opts.task)
                per_region[region] = acc.add(p, g, masks[region]).as_dict()
                for target in (pool, overall):
                    target.acc.setdefault(region, _new_acc(opts.task)).merge(acc)  # type: ignore[arg-type]
            pool.samples += 1
            overall.samples += 1
            rows.append(
                SampleRow(
                    gt.rel,
                    pred_path.relative_to(pred).as_posix(),
                    gt.scene,
                    gt.fov_deg,
                    gt.baseline_mm,
                    gt.view,
                    scale,
                    per_region,
                )
            )
        if progress:
            progress(k + 1, len(gts))

    def finish(label: str, pool: _Pool) -> GroupRow:
        metrics = {
            r: (pool.acc[r] if r in pool.acc else _new_acc(opts.task)).result().as_dict() for r in regions
        }
        return GroupRow(label, pool.fov_deg, pool.baseline_mm, pool.samples, metrics)

    order = sorted(pools, key=lambda t: tuple(-math.inf if v is None else v for v in t))
    groups = tuple(
        finish(group_label(opts.by, pools[t].fov_deg, pools[t].baseline_mm), pools[t]) for t in order
    )
    return EvalReport(
        dataset, pred, layout, opts, regions, tuple(rows), groups if opts.by else (), finish("all", overall),
        tuple(missing),
    )  # fmt: skip


def report_json(report: EvalReport) -> bytes:
    """The report as the bytes of its JSON file."""
    return (json.dumps(report.to_json(), indent=1) + "\n").encode()


def write_report_json(report: EvalReport, path: Path) -> Path:
    """Write the report as JSON (atomically)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, report_json(report))
    return path
