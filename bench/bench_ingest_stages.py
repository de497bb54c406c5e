"""Offline ingest at full resolution, part by part: LiDAR decode, per-stage cost, encoders, throughput.

(`bench/bench_ingest.py` prints the run-level table: CPU against the codec
floor, worker scaling, start-up, Dask; this script looks inside a sample.)

Input: a bag simulated into a temporary folder (indoor, static, `--seconds` of
1920x1200 raw fisheyes, two Livox Mid-360 CustomMsg streams with 2 cm range
noise, IMUs; about 2 s of rendering per image). Four parts, each printed as a
markdown table with the target next to it:

1. Livox CustomMsg decode of a real ~20k-point sweep from the bag: SensorBox's
   `decode_custom_msg` (+ xyz (N,3) float64 and per-point stamps) against
   rosbags' `deserialize_cdr` (+ the same arrays built from its point list);
   median of 20 x `--repeats` runs; target >= 100x.
2. Milliseconds per sample at full resolution: `process_sample` in this process
   (one worker), every planned sample once after a cold warm-up sample, medians
   over the written samples of its `stage_ms`; the write stage split into PNG
   encoding, uint16 conversion, file writes and the rest. Every SensorBox
   function process_sample calls directly (and write_sample's helpers) is
   wrapped with a timer for that pass, so the bottleneck is visible without
   copying the pipeline's steps; surface_normals is split into its k-NN
   covariance and eigen-solve parts on its captured input (Open3D vs cKDTree +
   numpy; closed form vs LAPACK eigh). The equirect warps run in a helper
   thread beside the clouds and GT stages: stage "images" is the calling
   thread's share (start, wait), the helper's own time is shown beside it and
   its calls are marked. Wall and CPU time (all threads: Open3D and cv2 use
   two) per sample. Target: everything except image encoding <= 60 ms per
   sample.
3. Encoders outside the pipeline on one sample's images (fisheye RGB, equirect
   RGB, both uint16 GT images): SensorBox's PNG writer (ISA-L levels 0-3), cv2 PNG
   levels, strategies and filters, and
   the other lossless cv2 writers of this build; median of `--repeats`.
4. `ingest(...)` with `workers=2`, full PNG layout, ISA-L PNG level 0-3: samples/s
   end to end and after each worker's first sample (median of up to 3 runs
   each); target >= 5 samples/s on the 2-core machine.
5. The same ingest with image encoding taken out (each image kind's PNG is
   encoded once and its bytes reused, so files and writes keep their real
   sizes): what everything except encoding costs per sample on 2 cores, main
   process (bag reading, decompression, sync) and workers together.

Writes out/bench/bench_ingest.png (per-stage bars, encoder time vs size).
`--bag PATH` reuses an existing simulated bag (rig from its truth folder).

File writes depend on the machine more than anything else here. The script
prints what writing fresh 3.5 MB files costs before each timed ingest part
(2, 4, 5). On a VM whose guest memory the host backs lazily (Firecracker,
some cloud VMs), the first touch of each guest page is a host fault: the page
cache's fresh pages make file writes ~8x slower (5.4 vs 0.7 ms per file
measured) until every page has been touched once, as on any long-running
machine, and such a VM may take idle memory back after a while.
`--prefault-gb N` touches N GB of memory before each of those parts so that
the numbers describe a machine with backed memory; the default measures the
machine as it is.
"""

from __future__ import annotations

import argparse
import inspect
import os
import pickle
import shutil
import statistics
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any, TypeVar

import cv2
import numpy as np
from scipy.spatial import cKDTree

from ingest.runtime.o3d import o3d

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import OUT_DIR, machine_line, markdown_table, median_seconds

import ingest.dataset.layout as dataset
import ingest.train.run.sample as sample_mod
import ingest.train.run.sample_dense as sample_dense_mod
import ingest.train.run.sample_parts as sample_parts_mod
import ingest.train.run.sample_sparse as sample_sparse_mod
import ingest.train.trajectory.clouds as clouds_mod
from calibration.linalg3 import sym3_smallest
from calibration.rig import read_rig
from calibration.warp import clear_map_cache
from ingest.bags.decode import decode
from ingest.bags.livox_msg import decode_custom_msg
from ingest.bags.reader import open_bags
from ingest.bags.rostypes import CUSTOM_MSG_TYPE, typestore
from ingest.dataset.png import LEVELS, encode_png, opencv_silenced
from ingest.train.run.pipeline import ingest
from ingest.train.run.plan import plan
from ingest.train.run.resolved import resolve_run
from ingest.train.run.sample import process_sample
from ingest.train.run.sample_job import Geometry, SampleJob, SampleParams
from ingest.train.run.settings import IngestConfig, resolve_topics
from ingest.train.run.stream import Shared, StreamedJob, decode_images, stream_jobs
from ingest.train.trajectory.planes import knn_covariances, neighbour_covariances
from sensorbox.sim.config import SimConfig
from sensorbox.sim.run import simulate
from sensorbox.sim.truth import truth_dir

T = TypeVar("T")
Arr = np.ndarray[Any, Any]

WORKERS = 2
PNG_LEVELS = LEVELS  # ISA-L deflate levels of ingest.dataset.png
DECODE_TARGET = 100.0  # x faster than rosbags
STAGE_TARGET_MS = 60.0  # everything except image encoding, per sample
THROUGHPUT_TARGET = 5.0  # samples/s with 2 workers on 2 cores
MAX_INGEST_RUNS = 3


# ---------------------------------------------------------------- helpers


def timed(times: dict[str, float], name: str, fn: Callable[[], T]) -> T:
    """Call `fn`, store its wall time in ms under `name`, return its result."""
    t0 = time.perf_counter()
    out = fn()
    times[name] = (time.perf_counter() - t0) * 1e3
    return out


def load() -> str:
    one, five, _ = os.getloadavg()
    return f"load average {one:.1f} (1 min), {five:.1f} (5 min)"


def prefault(gb: float) -> str:
    """Touch `gb` GB of memory once and free it (see the module docstring)."""
    t0 = time.perf_counter()
    for _ in range(int(gb)):  # 1 GB at a time: the pages return to the kernel after each
        block = np.ones(1 << 30, np.uint8)
        del block
    return f"prefaulted {int(gb)} GB of memory in {time.perf_counter() - t0:.1f} s"


def write_cost(folder: Path, files: int = 40, size: int = 3_500_000) -> str:
    """Median ms to write a fresh `size`-byte file in `folder` (page cache, no fsync)."""
    data = np.random.default_rng(0).integers(0, 256, size, np.uint8).tobytes()
    times = []
    for i in range(files):
        t0 = time.perf_counter()
        (folder / f"w{i}.bin").write_bytes(data)
        times.append(time.perf_counter() - t0)
    for i in range(files):
        (folder / f"w{i}.bin").unlink()
    ms = statistics.median(times) * 1e3
    return f"writing a fresh {size / 1e6:.1f} MB file: {ms:.2f} ms ({size / 1e6 / ms:.2f} GB/s)"


def med(values: list[float]) -> float:
    return statistics.median(values) if values else float("nan")


def image_key(image: Arr) -> str:
    h, w = image.shape[:2]
    kind = "RGB" if image.ndim == 3 else str(image.dtype)
    return f"{kind} {w}x{h}"


# ---------------------------------------------------------------- input


def make_bag(seconds: float, root: Path) -> tuple[Path, Path, float]:
    """Simulate the full-resolution input bag; returns (bag, rig.yaml, seconds taken)."""
    cfg = SimConfig(
        scene="indoor", trajectory="static", duration_s=seconds, scale=1.0, image="raw", range_noise_m=0.02
    )
    t0 = time.perf_counter()
    summary = simulate(cfg, root / "bag")
    return summary.bag, summary.truth / "rig.yaml", time.perf_counter() - t0


@dataclass
class Jobs:
    jobs: list[SampleJob]
    geometry: Geometry
    overhead_ms: dict[str, float]  # main-process costs


def load_jobs(bag: Path, rig_path: Path, out: Path) -> Jobs:
    """Plan and stream the bag the way `ingest` does; keep every sample's job, its images decoded."""
    rig = read_rig(rig_path)
    ms: dict[str, float] = {}
    geometry = timed(ms, "Geometry.from_rig", lambda: Geometry.from_rig(rig))
    cfg = IngestConfig(rig=rig_path, out=out, workers=1)
    with open_bags([bag]) as bags:
        topics = resolve_topics(rig, bags.topics(), str(bag))
        run = resolve_run(cfg)
        the_plan = timed(ms, "plan pass", lambda: plan(bags, topics, run))
        items = timed(ms, "stream_jobs pass", lambda: list(stream_jobs(bags, topics, the_plan, run)))
    shared = Shared(geometry)
    streamed = [j for j in items if isinstance(j, StreamedJob)]
    jobs = [j.sample_job(shared, *decode_images(j, shared)[0]) for j in streamed]
    if not jobs:
        raise SystemExit(f"{bag}: no sample could be planned; use a longer --seconds")
    return Jobs(jobs, geometry, ms)


# ---------------------------------------------------------------- 1. decode


def pick_sweep(bag: Path) -> bytes:
    """A full CustomMsg sweep (>= 95 % of the largest point count in the bag)."""
    with open_bags([bag]) as bags:
        topics = [t for t, s in bags.topics().items() if s.msgtype.endswith("/CustomMsg")]
        raws = [m.raw for m in bags.messages(topics=topics)]
    counts = [len(decode_custom_msg(r).points) for r in raws]
    return bytes(next(r for r, n in zip(raws, counts, strict=True) if n >= 0.95 * max(counts)))


def ours_arrays(raw: bytes) -> tuple[Arr, Arr]:
    msg = decode_custom_msg(raw)
    p = msg.points
    xyz = np.stack([p["x"], p["y"], p["z"]], axis=1).astype(np.float64)
    return xyz, msg.point_stamps_ns


def rosbags_arrays(raw: bytes) -> tuple[Arr, Arr]:
    msg: Any = typestore(2).deserialize_cdr(raw, CUSTOM_MSG_TYPE)
    xyz = np.array([(p.x, p.y, p.z) for p in msg.points], np.float64)
    stamps = np.int64(msg.timebase) + np.array([p.offset_time for p in msg.points], np.int64)
    return xyz, stamps


def bench_decode(raw: bytes, runs: int) -> list[tuple[str, float]]:
    a, b = ours_arrays(raw), rosbags_arrays(raw)
    if not (np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])):
        raise SystemExit("decode_custom_msg and rosbags disagree on the sweep's points")
    store = typestore(2)
    calls: list[tuple[str, Callable[[], object]]] = [
        ("rosbags deserialize_cdr only", lambda: store.deserialize_cdr(raw, CUSTOM_MSG_TYPE)),
        ("rosbags deserialize_cdr + xyz f64 + stamps", lambda: rosbags_arrays(raw)),
        ("decode_custom_msg only (structured view)", lambda: decode_custom_msg(raw)),
        ("decode_custom_msg + xyz f64 + stamps", lambda: ours_arrays(raw)),
        ("ingest.bags.decode.decode -> Sweep (xyz f32)", lambda: decode(CUSTOM_MSG_TYPE, raw)),
    ]
    return [(name, median_seconds(fn, runs)) for name, fn in calls]


# ---------------------------------------------------------------- 2. stages


WRAPPED_MODULES = ("ingest.", "calibration.")
SAMPLE_MODULES = (sample_mod, sample_sparse_mod, sample_dense_mod, sample_parts_mod)


@dataclass
class Calls:
    """Per-sample wall time (ms) and call count of each instrumented function."""

    ms: dict[str, float] = field(default_factory=dict)
    count: dict[str, int] = field(default_factory=dict)
    args: dict[str, tuple[Any, ...]] = field(default_factory=dict)  # first call's arguments


@contextmanager
def instrument(calls: Calls, capture: tuple[str, ...] = ()) -> Iterator[None]:
    """Time what process_sample calls directly, and write_sample's encode / convert / write helpers.

    Every function of the `ingest.train.run.sample*` modules' namespaces that comes from SensorBox is
    wrapped (so nested calls, e.g. filter_points inside points_by_lidar, are in
    their caller's time too), plus the GyroTrack methods and `ingest.dataset.layout`'s
    encode_png (keyed by image kind), to_uint16 and write_atomic. Restored on exit.
    """
    patches: list[tuple[Any, str, Any]] = []

    def wrap(owner: Any, name: str, key: Callable[[tuple[Any, ...]], str]) -> None:
        fn = getattr(owner, name)

        def timed_fn(*args: Any, **kwargs: Any) -> Any:
            k = key(args)
            if threading.current_thread() is not threading.main_thread():
                k += " [helper thread, beside clouds + GT]"
            calls.ms.setdefault(k, 0.0)  # first-call order
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                calls.ms[k] = calls.ms.get(k, 0.0) + (time.perf_counter() - t0) * 1e3
                calls.count[k] = calls.count.get(k, 0) + 1
                if name in capture:
                    calls.args.setdefault(name, (*args, kwargs))

        patches.append((owner, name, fn))
        setattr(owner, name, timed_fn)

    for module in SAMPLE_MODULES:  # each call is wrapped once: in the namespace of the module that makes it
        for name, obj in list(vars(module).items()):
            if (
                inspect.isfunction(obj)
                and obj.__module__.startswith(WRAPPED_MODULES)
                and name not in ("process_sample", "_process")
            ):
                wrap(module, name, lambda a, n=name: n)  # type: ignore[misc]
    for name in ("covers", "relative", "rotate"):
        if hasattr(clouds_mod.GyroTrack, name):
            wrap(clouds_mod.GyroTrack, name, lambda a, n=name: f"GyroTrack.{n}")  # type: ignore[misc]
    wrap(dataset, "encode_png", lambda a: f"  write_sample > encode_png {image_key(a[0])}")
    wrap(dataset, "to_uint16", lambda a: "  write_sample > to_uint16")
    wrap(dataset, "write_atomic", lambda a: "  write_sample > write_atomic (files)")
    try:
        yield
    finally:
        for owner, name, fn in reversed(patches):
            setattr(owner, name, fn)


@dataclass
class StageRun:
    cold_images_ms: float
    stage_ms: list[dict[str, float]]  # per written sample
    overlapped_ms: list[dict[str, float]]  # per written sample: helper-thread work beside the stages
    cpu_ms: list[float]  # per written sample: CPU time of this process (all threads)
    calls: list[Calls]  # per written sample
    skipped: dict[str, int]
    captured: Calls  # the middle sample's, with surface_normals' and write_sample's arguments


def stage_times(jobs: list[SampleJob]) -> StageRun:
    """Cold images stage of the first written sample (map build), then every sample once, instrumented."""
    cold = float("nan")
    for job in jobs:
        clear_map_cache()
        first = process_sample(job)
        if "images" in first.stage_ms:
            cold = first.stage_ms["images"]
            break
    run = StageRun(cold, [], [], [], [], {}, Calls())
    for i, job in enumerate(jobs):
        calls = Calls()
        with instrument(calls, ("surface_normals", "write_sample") if i == len(jobs) // 2 else ()):
            cpu0 = time.process_time()
            res = process_sample(job)
            cpu = (time.process_time() - cpu0) * 1e3
        if i == len(jobs) // 2:
            run.captured = calls
        if not res.written:
            run.skipped[res.reason] = run.skipped.get(res.reason, 0) + 1
            continue
        run.stage_ms.append(res.stage_ms)
        run.overlapped_ms.append(res.overlapped_ms)
        run.cpu_ms.append(cpu)
        run.calls.append(calls)
    return run


def normals_split(args: tuple[Any, ...], runs: int) -> list[tuple[str, float]]:
    """surface_normals' parts on its captured input: k-NN covariances, and the 3x3 eigen-solve.

    Open3D's covariances (what SensorBox uses) are timed against a cKDTree
    query plus numpy on the same points; Open3D's eigen-solve (estimate_normals
    on those covariances, what SensorBox uses) against numpy's closed form
    (sym3_smallest) and LAPACK's batched np.linalg.eigh on the same matrices.
    """
    pts, k, kwargs = np.asarray(args[0]), min(int(args[1]), len(args[0])), args[-1]
    query = kwargs.get("query") if isinstance(kwargs, dict) else None
    q = pts if query is None else pts[query]
    cov = knn_covariances(q, k)
    t_o3d = median_seconds(lambda: knn_covariances(q, k), runs) * 1e3
    t_scipy = (
        median_seconds(
            lambda: neighbour_covariances(q, cKDTree(q, balanced_tree=False).query(q, k=k)[1]), runs
        )
        * 1e3
    )
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(q))
    search = o3d.geometry.KDTreeSearchParamKNN(k)
    cloud.estimate_covariances(search)

    def eigen_only() -> None:  # knn_planes' second step, on covariances already on the cloud
        cloud.normals = o3d.utility.Vector3dVector()  # none: estimate_normals does not orient to them
        cloud.estimate_normals(search)

    t_o3d_eig = median_seconds(eigen_only, runs) * 1e3
    t_closed = median_seconds(lambda: sym3_smallest(cov), runs) * 1e3
    t_eigh = median_seconds(lambda: np.linalg.eigh(cov), runs) * 1e3
    return [
        (f"  surface_normals > Open3D k-NN covariances ({len(q):,} pts, k={k})", t_o3d),
        (f"    (cKDTree query + numpy on the same points, not used: {t_scipy / t_o3d:.1f}x slower)", t_scipy),
        ("  surface_normals > Open3D 3x3 eigen (estimate_normals on those covariances)", t_o3d_eig),
        (f"    (numpy closed form sym3_smallest, not used: {t_closed / t_o3d_eig:.1f}x slower)", t_closed),
        (f"    (np.linalg.eigh on the same matrices, not used: {t_eigh / t_o3d_eig:.1f}x slower)", t_eigh),
    ]


@dataclass
class SampleImages:
    fisheye: Arr
    equirect: Arr
    disp_u16: Arr
    depth_u16: Arr

    @classmethod
    def from_write_args(cls, args: tuple[Any, ...]) -> SampleImages:
        files = args[2]  # write_sample(out, sid, files, exr, png_level)
        disp, _ = dataset.to_uint16(files.disp_px, dataset.DISP_SCALE)
        depth, _ = dataset.to_uint16(files.range_m, dataset.DEPTH_SCALE)
        return cls(stored_colour(files.left_fisheye), stored_colour(files.equirect_up), disp, depth)


def stored_colour(image: Arr) -> Arr:
    """A colour image as its PNG stores it: BGR, a raw bgra8 camera's alpha dropped.

    The PNG writer drops the alpha (a camera's constant one; 0 outside an
    equirect's valid pixels, like the colour), so the encoders are compared on,
    and checked against, the three channels they all store. Given the BGRA
    array, cv2's writers would store four channels and ours would never decode
    back equal to its input.
    """
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    return np.ascontiguousarray(image)


# ---------------------------------------------------------------- 3. encoders


@dataclass(frozen=True)
class Encoder:
    name: str
    ext: str
    params: tuple[int, ...]
    u16: bool = True  # can store uint16 losslessly
    fn: Callable[[Arr], bytes] | None = None  # not cv2.imencode (SensorBox's own PNG writer)

    def encode(self, image: Arr) -> bytes:
        if self.fn is not None:
            return self.fn(image)
        ok, buf = cv2.imencode(self.ext, image, list(self.params))
        if not ok:
            raise cv2.error(f"{self.name}: imencode returned False")
        return bytes(buf.tobytes())


def encoders() -> tuple[list[Encoder], list[str]]:
    """Encoders to compare, and notes on the ones this cv2 build cannot write."""
    png = cv2.IMWRITE_PNG_COMPRESSION
    cands = [
        *(
            Encoder(f"SensorBox PNG, ISA-L {lv}", ".png", (), fn=partial(encode_png, level=lv))
            for lv in PNG_LEVELS
        ),
        *(Encoder(f"PNG level {lv}", ".png", (png, lv)) for lv in (0, 1, 3, 6, 9)),
        Encoder("PNG 0 filter NONE", ".png", (png, 0, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_NONE)),
        Encoder(
            "PNG 1 strategy RLE", ".png", (png, 1, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE)
        ),
        Encoder(
            "PNG 1 strategy FILTERED",
            ".png",
            (png, 1, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_FILTERED),
        ),
        Encoder(
            "PNG strategy HUFFMAN_ONLY",
            ".png",
            (png, 1, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY),
        ),
        Encoder("PNG 1 filter NONE", ".png", (png, 1, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_NONE)),
        Encoder("PNG 1 filter SUB", ".png", (png, 1, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_SUB)),
        Encoder(
            "PNG 1 RLE + filter SUB",
            ".png",
            (
                png,
                1,
                cv2.IMWRITE_PNG_STRATEGY,
                cv2.IMWRITE_PNG_STRATEGY_RLE,
                cv2.IMWRITE_PNG_FILTER,
                cv2.IMWRITE_PNG_FILTER_SUB,
            ),
        ),
        Encoder("WebP lossless (q 101)", ".webp", (cv2.IMWRITE_WEBP_QUALITY, 101), u16=False),
        Encoder("AVIF lossless (q 100)", ".avif", (cv2.IMWRITE_AVIF_QUALITY, 100), u16=False),
        Encoder("JPEG 2000 lossless", ".jp2", (cv2.IMWRITE_JPEG2000_COMPRESSION_X1000, 1000)),
        Encoder("JPEG-XL lossless", ".jxl", (cv2.IMWRITE_JPEGXL_DISTANCE, 0)),
    ]
    tiff = cv2.IMWRITE_TIFF_COMPRESSION
    for name in ("NONE", "PACKBITS", "LZW", "ADOBE_DEFLATE", "ZSTD", "LZMA"):
        cands.append(
            Encoder(f"TIFF {name}", ".tiff", (tiff, getattr(cv2, f"IMWRITE_TIFF_COMPRESSION_{name}")))
        )
    probe = np.zeros((64, 64, 3), np.uint8)
    usable, notes = [], []
    with opencv_silenced():
        for e in cands:
            try:
                ok = cv2.haveImageWriter("x" + e.ext) and bool(e.encode(probe))
            except cv2.error:
                ok = False
            if ok:
                usable.append(e)
            else:
                notes.append(f"{e.name}: not available in this cv2 {cv2.__version__} build")
    return usable, notes


@dataclass
class EncResult:
    encoder: str
    image: str
    ms: float
    mb: float
    lossless: bool | None  # None: the encoder cannot store this image type


def bench_encoders(images: dict[str, Arr], encs: list[Encoder], runs: int) -> list[EncResult]:
    """Every encoder on every image: ms, MB and whether it decodes back bit-exact.

    OpenCV's log is silenced meanwhile, so that its codecs' warnings do not
    break up the tables.
    """
    out = []
    with opencv_silenced():
        for label, img in images.items():
            for e in encs:
                if img.dtype != np.uint8 and not e.u16:
                    out.append(EncResult(e.name, label, float("nan"), float("nan"), None))
                    continue
                buf = e.encode(img)
                back = cv2.imdecode(np.frombuffer(buf, np.uint8), cv2.IMREAD_UNCHANGED)
                same = back is not None and back.dtype == img.dtype and np.array_equal(back, img)
                t = median_seconds(lambda e=e, img=img: e.encode(img), runs, warmup=1)  # type: ignore[misc]
                out.append(EncResult(e.name, label, t * 1e3, len(buf) / 1e6, same))
    return out


# ---------------------------------------------------------------- 4. ingest


@dataclass
class IngestRun:
    level: int
    written: int
    seconds: float
    steady: float  # samples/s after each worker's first sample
    mb_per_sample: float
    write_ms: float  # median write stage inside the workers
    worker_ms: float  # sum of the median stages inside the workers


@contextmanager
def encoding_free() -> Iterator[None]:
    """`ingest.dataset.layout.encode_png` replaced by a cache: each image kind is encoded once, then reused.

    Set before `ingest` forks its workers, so they inherit it. Files keep their
    real sizes, so writing them still costs what it costs.
    """
    real = dataset.encode_png  # type: ignore[attr-defined]
    cache: dict[tuple[Any, ...], bytes] = {}

    def cached(image: Arr, level: int = 1) -> bytes:
        key = (image.shape, image.dtype.str, level)
        if key not in cache:
            cache[key] = real(image, level)
        return cache[key]

    dataset.encode_png = cached  # type: ignore[attr-defined,assignment]
    try:
        yield
    finally:
        dataset.encode_png = real  # type: ignore[attr-defined]


def ingest_once(bag: Path, rig: Path, level: int, root: Path) -> IngestRun:
    out = Path(tempfile.mkdtemp(prefix=f"png{level}_", dir=root))
    stamps: list[float] = []
    cfg = IngestConfig(rig=rig, out=out, workers=WORKERS, sample=SampleParams(png_level=level))
    summary = ingest([bag], cfg, progress=lambda done, total: stamps.append(time.perf_counter()))
    size = sum(p.stat().st_size for p in out.rglob("*.png"))
    shutil.rmtree(out)
    k = WORKERS
    steady = (len(stamps) - k) / (stamps[-1] - stamps[k - 1]) if len(stamps) > k + 1 else float("nan")
    return IngestRun(
        level, summary.written, summary.seconds, steady, size / 1e6 / max(summary.written, 1),
        med(summary.stage_ms.get("write", [])), sum(med(v) for v in summary.stage_ms.values()),
    )  # fmt: skip


# ---------------------------------------------------------------- main


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--repeats", type=int, default=5, help="runs per timing (median); default 5")
    ap.add_argument("--seconds", type=float, default=0.5, help="simulated input seconds; default 0.5")
    ap.add_argument("--bag", type=Path, default=None, help="reuse a simulated bag instead of simulating one")
    ap.add_argument(
        "--prefault-gb", type=float, default=0.0,
        help="touch this many GB of memory first (VMs with lazily backed memory); default 0",
    )  # fmt: skip
    args = ap.parse_args()
    repeats = max(1, args.repeats)

    with tempfile.TemporaryDirectory(prefix="bench_ingest_") as tmp:
        root = Path(tmp)
        if args.bag is None:
            bag, rig, sim_s = make_bag(args.seconds, root)
            source = (
                f"simulated indoor/static, {args.seconds:g} s, scale 1.0, raw images "
                f"({sim_s:.0f} s to simulate)"
            )
        else:
            bag, rig = args.bag, truth_dir(args.bag) / "rig.yaml"
            source = f"{bag}"
        run_all(bag, rig, root, repeats, source, args.prefault_gb)


def part_decode(bag: Path, repeats: int) -> None:
    """## 1: CustomMsg decoders on one real sweep, against rosbags + numpy."""
    raw = pick_sweep(bag)
    npts = len(decode_custom_msg(raw).points)
    runs = 20 * repeats
    dec = bench_decode(raw, runs)
    base = dec[1][1]
    print(f"\n## 1. Livox CustomMsg decode: one real sweep, {npts:,} points, {len(raw) / 1e3:.0f} kB, "
          f"median of {runs} runs\n")  # fmt: skip
    rows = []
    for name, t in dec:
        target = f">= {DECODE_TARGET:.0f}x" if name.startswith("decode_custom_msg +") else ""
        met = ("met" if base / t >= DECODE_TARGET else "NOT met") if target else ""
        rows.append([name, f"{t * 1e3:.3f}", f"{base / t:.1f}x", target, met])
    markdown_table(["decoder", "ms", "speed-up vs rosbags + numpy", "target", "status"], rows)
    ratio = base / dec[3][1]
    print(f"\nspeed-up decode_custom_msg (+arrays) vs rosbags (+arrays): {ratio:.0f}x (target >= 100x)")


@dataclass
class StagePart:
    """What part 2 measured, for the parts and the chart after it."""

    sr: StageRun
    stage_rows: list[tuple[str, float]]
    no_png: list[float]


def _call_sum(c: Calls, part: str) -> float:
    return sum(v for k, v in c.ms.items() if part in k)


def part_stages(jobs: list[SampleJob]) -> StagePart:
    """## 2: per-stage ms per sample in this process (one worker), PNG encoding split out."""
    sr = stage_times(jobs)
    per = sr.stage_ms
    if not per:
        raise SystemExit(f"no sample was written: {sr.skipped}")
    written = len(per)
    stages = list(per[0])

    png = [_call_sum(c, "encode_png") for c in sr.calls]
    u16 = [_call_sum(c, "to_uint16") for c in sr.calls]
    files = [_call_sum(c, "write_atomic") for c in sr.calls]
    total = [sum(p.values()) for p in per]
    no_png = [t - e for t, e in zip(total, png, strict=True)]
    skipped = f"; skipped: {sr.skipped}" if sr.skipped else ""
    print(f"\n## 2. Per-stage ms per sample (process_sample in this process = one worker, PNG level "
          f"{jobs[0].params.png_level}, median over {written} written samples{skipped})\n")  # fmt: skip
    stage_rows: list[tuple[str, float]] = []
    for st in stages:
        stage_rows.append((st, med([p[st] for p in per])))
        if st == "images":
            for k in sr.overlapped_ms[0]:
                helper = med([o[k] for o in sr.overlapped_ms])
                stage_rows.append((f"  ({k}: helper thread, beside clouds + GT)", helper))
        if st == "write":
            rest = [p["write"] - e - u - f for p, e, u, f in zip(per, png, u16, files, strict=True)]
            stage_rows += [
                ("  write: to_uint16 (GT images)", med(u16)),
                ("  write: write_atomic (files)", med(files)),
                ("  write: rest (meta counts, json)", med(rest)),
                ("  write: PNG encoding", med(png)),
            ]
    rows = [[name, f"{v:.1f}", ""] for name, v in stage_rows]
    met = "met" if med(no_png) <= STAGE_TARGET_MS else "NOT met"
    rows.append(["all except PNG encoding", f"{med(no_png):.1f}", f"<= {STAGE_TARGET_MS:.0f} ms ({met})"])
    rows.append(["total per sample", f"{med(total):.1f}", ""])
    png_cpu = med([c - p for c, p in zip(sr.cpu_ms, png, strict=True)])
    rows.append(["CPU time, all threads, except PNG encoding", f"{png_cpu:.1f}", "(Open3D, cv2: 2 threads)"])
    rows.append(
        ["first sample, images stage, cold maps", f"{sr.cold_images_ms:.0f}", "once per worker process"]
    )
    markdown_table(["stage", "ms / sample", "target"], rows)

    return StagePart(sr, stage_rows, no_png)


def part_calls(loaded: Jobs, sr: StageRun, repeats: int) -> list[str]:
    """## 2, continued: the calls inside process_sample and the main process's share; the call names."""
    jobs, n = loaded.jobs, len(loaded.jobs)
    written = len(sr.stage_ms)
    names = list(dict.fromkeys(k for c in sr.calls for k in c.ms))
    npts_sample = med([float(sum(len(lp.xyz_m) for lp in j.lidars)) for j in jobs])
    print(f"\n### Calls inside process_sample (ms per sample incl. nested calls, median over {written} "
          f"samples, {npts_sample:,.0f} raw LiDAR points per sample)\n")  # fmt: skip
    rows = []
    for k in names:
        count = med([float(c.count.get(k, 0)) for c in sr.calls])
        rows.append([k, f"{count:.0f}", f"{med([c.ms.get(k, 0.0) for c in sr.calls]):.1f}"])
        if k == "surface_normals" and "surface_normals" in sr.captured.args:
            split = normals_split(sr.captured.args["surface_normals"], repeats)
            rows += [[name, "1", f"{v:.1f}"] for name, v in split]
    job = jobs[n // 2]
    t_pickle = median_seconds(lambda: pickle.dumps(job, pickle.HIGHEST_PROTOCOL), repeats) * 1e3
    job_mb = len(pickle.dumps(job, pickle.HIGHEST_PROTOCOL)) / 1e6
    oh = loaded.overhead_ms
    rows += [
        ["main process: Geometry.from_rig (once)", "1", f"{oh['Geometry.from_rig']:.1f}"],
        [f"main process: plan pass (/ {n} samples)", "-", f"{oh['plan pass'] / n:.1f}"],
        [f"main process: stream_jobs pass (/ {n} samples)", "-", f"{oh['stream_jobs pass'] / n:.1f}"],
        [f"main process: pickle SampleJob ({job_mb:.1f} MB)", "1", f"{t_pickle:.1f}"],
    ]
    markdown_table(["call", "calls / sample", "ms / sample"], rows)
    return names


def part_encoders(images: SampleImages, repeats: int) -> dict[str, tuple[float, float]]:
    """## 3: every encoder on one sample's images; (ms, MB) per sample for each."""
    encs, notes = encoders()
    imgs = {
        f"equirect RGB {images.equirect.shape[1]}x{images.equirect.shape[0]}": images.equirect,
        f"fisheye RGB {images.fisheye.shape[1]}x{images.fisheye.shape[0]}": images.fisheye,
        f"disp_equirect uint16 {images.disp_u16.shape[1]}x{images.disp_u16.shape[0]}": images.disp_u16,
        f"depth_fisheye uint16 {images.depth_u16.shape[1]}x{images.depth_u16.shape[0]}": images.depth_u16,
    }
    enc = bench_encoders(imgs, encs, repeats)
    print(f"\n## 3. Encoders on one sample's images (cv2.imencode, median of {repeats} runs; "
          "ratios vs PNG level 1; lossless = decoded back bit-exact)\n")  # fmt: skip
    for label in imgs:
        res = [r for r in enc if r.image == label]
        ref = next(r for r in res if r.encoder == "PNG level 1")
        print(f"\n### {label} ({imgs[label].nbytes / 1e6:.1f} MB raw)\n")
        rows = []
        for r in res:
            if r.lossless is None:
                rows.append([r.encoder, "-", "-", "-", "-", "8-bit only"])
                continue
            rows.append([r.encoder, f"{r.ms:.1f}", f"{r.mb:.2f}", f"{r.ms / ref.ms:.2f}",
                         f"{r.mb / ref.mb:.2f}", "yes" if r.lossless else "NO"])  # fmt: skip
        markdown_table(["encoder", "ms", "MB", "time / PNG 1", "size / PNG 1", "lossless"], rows)
    print("\n### One sample's 6 images (2 fisheye + 2 equirect as the upper ones, disp + depth; "
          "GT in PNG level 1 where the encoder is 8-bit only)\n")  # fmt: skip
    keys_img = list(imgs)
    weight = dict(zip(keys_img, (2, 2, 1, 1), strict=True))
    per_enc: dict[str, tuple[float, float]] = {}
    for e in encs:
        t = s = 0.0
        for label in keys_img:
            r = next(x for x in enc if x.image == label and x.encoder == e.name)
            if r.lossless is None:
                r = next(x for x in enc if x.image == label and x.encoder == "PNG level 1")
            t, s = t + weight[label] * r.ms, s + weight[label] * r.mb
        per_enc[e.name] = (t, s)
    t1, s1 = per_enc["PNG level 1"]
    rows = [[k, f"{t:.0f}", f"{s:.1f}", f"{t / t1:.2f}", f"{s / s1:.2f}"] for k, (t, s) in per_enc.items()]
    markdown_table(["encoder", "ms / sample", "MB / sample", "time / PNG 1", "size / PNG 1"], rows)
    for note in notes:
        print(f"- {note}")

    return per_enc


def part_throughput(bag: Path, rig: Path, root: Path, n: int, n_runs: int) -> None:
    """## 4: ingest with WORKERS workers, full PNG layout, at each PNG level."""
    runs_by_level: dict[int, list[IngestRun]] = {lv: [] for lv in PNG_LEVELS}
    for _ in range(n_runs):
        for lv in PNG_LEVELS:
            runs_by_level[lv].append(ingest_once(bag, rig, lv, root))
    print(f"\n## 4. ingest(..., workers={WORKERS}), full PNG layout, {n} planned samples, "
          f"median of {n_runs} runs per level\n")  # fmt: skip
    rows = []
    for lv, rs in runs_by_level.items():
        e2e = med([r.written / r.seconds for r in rs])
        steady = med([r.steady for r in rs])
        met = "met" if e2e >= THROUGHPUT_TARGET else "NOT met"
        rows.append([f"ISA-L PNG level {lv}", f"{med([r.written for r in rs]):.0f}",
                     f"{med([r.seconds for r in rs]):.1f}", f"{e2e:.2f}", f"{steady:.2f}",
                     f"{med([r.worker_ms for r in rs]):.0f}", f"{med([r.write_ms for r in rs]):.0f}",
                     f"{med([r.mb_per_sample for r in rs]):.1f}",
                     f">= {THROUGHPUT_TARGET:.0f} ({met})"])  # fmt: skip
    markdown_table(["encoder", "written", "wall s", "written samples/s", "completions/s after 1st per worker",
           "worker ms / sample", "of which write", "MB / sample", "target samples/s"], rows)  # fmt: skip
    print(f"\n{load()} (other processes share this machine: timings include their contention)")
    print("(samples/s = written / IngestSummary.seconds, startup included; worker ms = sum of the median "
          "stage_ms inside the 2 workers)")  # fmt: skip


def part_encoding_free(bag: Path, rig: Path, root: Path, n_runs: int) -> None:
    """## 5: ingest with WORKERS workers and encoding taken out, end to end and steady."""
    free: list[IngestRun] = []
    with encoding_free():
        for _ in range(n_runs):
            free.append(ingest_once(bag, rig, 1, root))
    steady = med([r.steady for r in free])
    e2e = med([r.written / r.seconds for r in free])
    met = "met" if 1e3 / steady <= STAGE_TARGET_MS else "NOT met"
    print(f"\n## 5. ingest(..., workers={WORKERS}) without image encoding (one PNG per image kind, reused), "
          f"median of {n_runs} runs\n")  # fmt: skip
    markdown_table(["run", "written", "wall s", "samples/s", "ms / sample on 2 cores", "target"], [
        ["end to end (startup included)", f"{med([r.written for r in free]):.0f}",
         f"{med([r.seconds for r in free]):.1f}", f"{e2e:.2f}", f"{1e3 / e2e:.0f}", ""],
        ["after each worker's first sample", "", "", f"{steady:.2f}", f"{1e3 / steady:.0f}",
         f"<= {STAGE_TARGET_MS:.0f} ms ({met})"],
    ])  # fmt: skip
    print(f"\n{load()}")


def run_all(bag: Path, rig: Path, root: Path, repeats: int, source: str, prefault_gb: float = 0.0) -> None:
    scratch = root / "scratch"
    dataset.prepare_dirs(scratch, False)

    def memory_state() -> None:
        """Before each timed ingest part: touch memory again if asked, say what a file write costs now."""
        if prefault_gb >= 1:  # a lazily backed VM takes untouched memory back after a while
            print(prefault(prefault_gb))
        print(write_cost(scratch))

    memory_state()
    loaded = load_jobs(bag, rig, scratch)
    jobs, geo = loaded.jobs, loaded.geometry
    n = len(jobs)
    cam = geo.rig.upper.model
    print(f"\ninput: {source}; {n} samples; fisheye {cam.width}x{cam.height}, "
          f"equirect {geo.equirect.width}x{geo.equirect.height}; cv2 {cv2.__version__}, "
          f"cv2 threads = {cv2.getNumThreads()}; {load()}\n{machine_line()}")  # fmt: skip

    part_decode(bag, repeats)
    print()
    memory_state()
    stage = part_stages(jobs)
    names = part_calls(loaded, stage.sr, repeats)
    if "write_sample" not in stage.sr.captured.args:
        raise SystemExit("the middle sample was not written; no images for the encoder comparison")
    per_enc = part_encoders(SampleImages.from_write_args(stage.sr.captured.args["write_sample"]), repeats)
    n_runs = min(repeats, MAX_INGEST_RUNS)
    print()
    memory_state()
    part_throughput(bag, rig, root, n, n_runs)
    print()
    memory_state()
    part_encoding_free(bag, rig, root, n_runs)
    sr = stage.sr
    top = sorted(((k, med([c.ms.get(k, 0.0) for c in sr.calls])) for k in names if k != "write_sample"),
                 key=lambda kv: -kv[1])[:10]  # fmt: skip
    chart(stage.stage_rows, med(stage.no_png), top, per_enc)


def chart(
    stage_rows: list[tuple[str, float]],
    no_png: float,
    top: list[tuple[str, float]],
    per_enc: dict[str, tuple[float, float]],
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    fig, (ax1, ax2, ax3) = plt.subplots(1, 3, figsize=(21, 5.5), width_ratios=[1, 1, 1.1])
    names = [n.strip() for n, _ in stage_rows] + ["all except PNG encoding"]
    vals = [v for _, v in stage_rows] + [no_png]

    def colour(raw_name: str) -> str:
        if raw_name == "all except PNG encoding":
            return "C1"
        if "PNG" in raw_name:
            return "C3"
        return "#8fb8de" if raw_name.startswith(" ") else "C0"

    colours = [colour(n) for n, _ in stage_rows] + [colour("all except PNG encoding")]
    y = np.arange(len(names))
    ax1.barh(y, vals, color=colours)
    ax1.axvline(STAGE_TARGET_MS, color="k", ls="--", lw=1, label=f"target {STAGE_TARGET_MS:.0f} ms")
    for yi, v in zip(y, vals, strict=True):
        ax1.text(v, yi, f" {v:.0f}", va="center", fontsize=8)
    ax1.set_yticks(y, names, fontsize=8)
    ax1.invert_yaxis()
    ax1.set_xlabel("ms per sample (median over samples)")
    ax1.set_title("process_sample stages, full resolution")
    ax1.legend(loc="lower right", fontsize=8)
    ax1.grid(axis="x", alpha=0.3)

    y = np.arange(len(top))
    ax2.barh(y, [v for _, v in top], color=["C3" if "encode_png" in n else "C0" for n, _ in top])
    for yi, (_, v) in zip(y, top, strict=True):
        ax2.text(v, yi, f" {v:.0f}", va="center", fontsize=8)
    ax2.set_yticks(y, [n.strip().replace("write_sample > ", "") for n, _ in top], fontsize=8)
    ax2.invert_yaxis()
    ax2.set_xlabel("ms per sample (incl. nested calls)")
    ax2.set_title("largest calls inside process_sample")
    ax2.grid(axis="x", alpha=0.3)

    listing = []
    for k, (name, (t, mb)) in enumerate(per_enc.items(), start=1):
        dot = "C3" if name == "PNG level 1" else "C0" if name.startswith("PNG") else "C2"
        ax3.scatter(t, mb, color=dot, zorder=3)
        ax3.annotate(str(k), (t, mb), fontsize=7, xytext=(3, 3), textcoords="offset points")
        listing.append(f"{k:>2} {name}")
    ax3.text(1.02, 1.0, "\n".join(listing), transform=ax3.transAxes, va="top", fontsize=7, family="monospace")
    ax3.set_xscale("log")
    ax3.set_yscale("log")
    ax3.yaxis.set_major_locator(matplotlib.ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
    ax3.yaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
    ax3.yaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax3.set_xlabel("encode ms per sample (6 images, median)")
    ax3.set_ylabel("MB per sample")
    ax3.set_title("lossless encoders per sample (red: PNG level 1, the default)")
    ax3.grid(alpha=0.3, which="both")
    fig.tight_layout()
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    fig.savefig(OUT_DIR / "bench_ingest.png", dpi=110)
    print(f"\nchart: {OUT_DIR / 'bench_ingest.png'}")


if __name__ == "__main__":
    main()
