"""The ingest's stream pass and what travels to the workers: a sample's camera messages as stored.

The main process reads the bags once more in log-time order (after the plan
pass, `ingest.train.run.plan`), keeps a sliding buffer of sweeps and the IMU, and
hands a `StreamedJob` to a worker as soon as every sweep overlapping the
sample's +-window has arrived. The job carries the two camera messages as the
bag stores them (a CompressedImage's JPEG/PNG bytes, or a raw Image's bytes),
never decoded pixels: the worker decodes them (`run_streamed`), so decoding
costs one worker's CPU instead of the main process's, and a job is the size
of the compressed images. An image that ends its compressed MCAP chunk (a
raw image fills one) travels as that chunk's compressed bytes
(`ingest.bags.chunks.DeferredData`): the stream pass decompresses only the
records before it and its header, and the worker the rest (the plan pass
has checked every chunk). What every job needs and none should carry (the
rig's geometry, the recording's trajectory) is `Shared`, handed to the
executor once.

A camera message that does not decode in the worker skips its sample with
`UNDECODABLE_IMAGE`, and the result names the message (`SampleResult.undecodable`)
so that the main process counts it in `BadMessages` exactly as if it had
decoded it itself (`--max-bad`).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from calibration.types import F64, I64, Bool
from ingest.bags.decode import Frame, ImuSample, Sweep
from ingest.bags.image_pixels import grey_as_bgr
from ingest.bags.message import RawMessage
from ingest.bags.reader import BagSet
from ingest.dataset.identity import HeldFrame, Resume, frame_digest, resume_state
from ingest.dataset.layout import sample_id
from ingest.errors import BagError, MessageDecodeError
from ingest.rows import rows
from ingest.runtime.kept import Release, Task
from ingest.train.bad_messages import BadMessages
from ingest.train.gt.block_planes import NORMAL_DTYPE, BlockPlanes
from ingest.train.repeats import FirstCopies
from ingest.train.run.block_jobs import BlockTasks, ClearJob, FitJob, WindowBlocks, fill_window, run_block
from ingest.train.run.lidar_rate import LidarRates
from ingest.train.run.plan import Plan
from ingest.train.run.sample import process_sample
from ingest.train.run.sample_job import (
    Geometry,
    ImuWindow,
    LidarPoints,
    SampleJob,
    SampleParams,
    SampleResult,
)
from ingest.train.sync import IMU_MARGIN_NS
from ingest.train.trajectory.rig_trajectory import RigTrajectory

if TYPE_CHECKING:
    from ingest.train.run.resolved import ResolvedRun
    from ingest.train.run.settings import Topics

UNDECODABLE_IMAGE = "undecodable image (--max-bad)"
"""Why a sample was skipped when one of its camera images could not be decoded."""
ALREADY_HELD = "frame already in the dataset (another id)"
"""Why a sample was not written: another sample of the folder holds its frame (`ingest.dataset.identity`)."""

Array = np.ndarray[Any, Any]


@dataclass(frozen=True)
class Shared:
    """What every sample of a run needs: sent to each worker once, never with a job."""

    geometry: Geometry
    trajectory: RigTrajectory | None = None  # the recording's (dense GT)


@dataclass(frozen=True)
class StreamedJob:
    """One sample on its way to a worker: its camera messages as stored, its LiDAR and IMU windows."""

    out: Path
    sid: str
    source: str  # the bags' file names, for the sample's meta
    where: str  # the bags' paths, for error messages
    upper_stamp_ns: int  # header stamps, as recorded
    lower_stamp_ns: int
    upper: RawMessage
    lower: RawMessage
    lidars: tuple[LidarPoints, ...]
    imu: ImuWindow | None
    params: SampleParams
    thin_lidars: tuple[str, ...] = ()
    thin_lidars_sparse: tuple[str, ...] = ()  # over sparse GT's window, for a dense frame in a gap
    upper_shift_ns: int = 0  # the rig's camera clock offsets (`Plan.upper_shift_ns`)
    lower_shift_ns: int = 0
    same_stamps: tuple[HeldFrame, ...] = ()  # samples of the folder with this frame's stamps (other ids)
    settings: dict[str, Any] = field(default_factory=dict)  # the dataset's (`describe.sample_settings`)
    blocks: WindowBlocks | None = None  # dense GT on the workers: the normals and bits come from the blocks
    repeated: tuple[str, ...] = ()  # "upper", "lower": the cameras whose frame repeats the one before it

    def sample_job(self, shared: Shared, upper_bgr: Array, lower_bgr: Array) -> SampleJob:
        """The `process_sample` job of this sample, with its decoded images."""
        return SampleJob(
            self.out, self.sid, self.source, self.upper_stamp_ns, self.lower_stamp_ns, upper_bgr, lower_bgr,
            self.lidars, self.imu, None, shared.geometry, self.params, shared.trajectory, self.thin_lidars,
            self.thin_lidars_sparse, settings=self.settings, upper_shift_ns=self.upper_shift_ns,
            lower_shift_ns=self.lower_shift_ns, repeated=self.repeated,
        )  # fmt: skip


def check_image_size(image: Array, camera: Any, msg: RawMessage, where: str) -> None:
    """`BagError` naming bag, topic and log time when `image` is not the size of the rig's `camera`."""
    h, w = image.shape[:2]
    if (w, h) != (camera.model.width, camera.model.height):
        raise BagError(
            f"{where}: {msg.topic} at log time {msg.log_time}: the image is {w}x{h} but the rig's "
            f"{camera.name} is {camera.model.width}x{camera.model.height} (the wrong rig file for this bag, "
            "or a camera whose resolution changed during the recording)"
        )


def decode_images(job: StreamedJob, shared: Shared) -> tuple[list[Array], list[tuple[str, int, str]]]:
    """The upper and lower images (BGR, a mono one grey; a raw bgra8 image as recorded, BGRA), and (topic,
    log ns, why) of each message that did not decode.

    Images of another size than the rig's cameras stop the run (`BagError`):
    the rig file does not belong to the bag.
    """
    rig = shared.geometry.rig
    images: list[Array] = []
    errors: list[tuple[str, int, str]] = []
    for msg, camera in ((job.upper, rig.upper), (job.lower, rig.lower)):
        try:
            frame = msg.decoded(job.where, keep_bgra=True)
        except MessageDecodeError as err:
            errors.append((msg.topic, msg.log_ns, str(err)))
            continue
        assert isinstance(frame, Frame)  # the camera topics hold Image or CompressedImage messages
        check_image_size(frame.image, camera, msg, job.where)
        images.append(grey_as_bgr(frame.image))  # the dataset's image folders are RGB
    return images, errors


def run_streamed(
    shared: Shared, job: StreamedJob | FitJob | ClearJob, values: dict[str, Any] | None = None
) -> Any:
    """The executor's job function: a dense-GT block's task (`run_block`, `values`: the blocks it needs),
    or a sample (`run_sample`; `values`: the blocks its window's normals and bits come from)."""
    if isinstance(job, FitJob | ClearJob):
        assert shared.trajectory is not None  # blocks run for dense GT only
        return run_block(shared.trajectory, job, values or {})
    if job.blocks is not None:
        filled = zip(job.lidars, job.blocks.lidars, strict=True)
        lidars = tuple(fill_window(lp, parts, job.blocks.words, values or {}) for lp, parts in filled)
        job = replace(job, lidars=lidars, blocks=None)
    return run_sample(shared, job)


def run_sample(shared: Shared, job: StreamedJob) -> SampleResult:
    """Decode the sample's two camera messages, then `process_sample`.

    A message that does not decode skips the sample (`UNDECODABLE_IMAGE`) and
    is named in the result for the main process to count. A frame that a
    sample of the folder with the same stamps holds already (the same
    `frame_digest`) is not written again (`ALREADY_HELD`, that sample's id),
    or, when that sample is damaged, written again under its id. The decoding
    time is stage "decode".
    """
    t0 = time.perf_counter()
    images, errors = decode_images(job, shared)
    if errors:
        return SampleResult(job.sid, False, UNDECODABLE_IMAGE, None, {}, undecodable=tuple(errors))
    if job.same_stamps:
        digest = frame_digest(images[0], images[1])
        held = next((h for h in job.same_stamps if h.frames_sha256 == digest), None)
        if held is not None and held.intact:
            return SampleResult(held.sid, False, ALREADY_HELD, None, {})
        if held is not None:
            job = replace(job, sid=held.sid)
    decode_ms = (time.perf_counter() - t0) * 1e3
    result = process_sample(job.sample_job(shared, images[0], images[1]))
    return replace(result, stage_ms={"decode": decode_ms, **result.stage_ms}) if result.written else result


# ---------------------------------------------------------------- the stream pass


def window_parts(sweeps: list[Sweep], t_c: int, w: int) -> list[tuple[Sweep, slice | I64]]:
    """The sweeps overlapping +-`w` around `t_c` and the rows of each within it, in sweep order: a sweep
    inside the window is taken whole (a slice), only the (at most two) at its ends are cut."""
    lo, hi = t_c - w, t_c + w
    near = [s for s in sweeps if s.span_ns[1] >= lo and s.span_ns[0] <= hi]
    return [(s, slice(None) if lo <= s.span_ns[0] and s.span_ns[1] <= hi else
             np.flatnonzero((s.stamps_ns >= lo) & (s.stamps_ns <= hi))) for s in near]  # fmt: skip


def lidar_window(sweeps: list[Sweep], name: str, t_c: int, w: int, planes: BlockPlanes | None) -> LidarPoints:
    """The points of `sweeps` stamped within +-`w` of `t_c` as LiDAR `name`'s window, in sweep order
    (with their world normals and free-space bits when `planes` is given)."""
    return _window_points(window_parts(sweeps, t_c, w), name, planes)


def _window_points(
    parts: list[tuple[Sweep, slice | I64]], name: str, planes: BlockPlanes | None
) -> LidarPoints:
    xyz = np.concatenate([_rows(s.xyz_m, m) for s, m in parts]) if parts else np.zeros((0, 3), np.float32)
    st = np.concatenate([_rows(s.stamps_ns, m) for s, m in parts]) if parts else np.zeros(0, np.int64)
    tags = [_rows(s.tag, m) for s, m in parts if s.tag is not None]
    tag = np.concatenate(tags) if tags and len(tags) == len(parts) else None
    refls = [_rows(s.reflectivity, m) for s, m in parts if s.reflectivity is not None]
    refl = np.concatenate(refls) if refls and len(refls) == len(parts) else None
    normal = bits = None
    if planes is not None:
        normals = [_rows(planes.normals(s), m) for s, m in parts]
        normal = np.concatenate(normals) if normals else np.zeros((0, 3), NORMAL_DTYPE)
        if planes.settings.free_space is not None:
            words = [_rows(planes.clear_bits(s), m) for s, m in parts]
            bits = np.concatenate(words) if words else planes.clear_bits_empty()
    return LidarPoints(name, xyz, st, tag, normal, bits, refl)


def _rows(a: np.ndarray[Any, Any], which: slice | I64) -> np.ndarray[Any, Any]:
    return a if isinstance(which, slice) else rows(a, which)


def _sweeps_needed(the_plan: Plan, topics: Topics, w: int) -> dict[int, dict[str, int]]:
    """Per planned sample, per LiDAR topic: how many sweeps overlap its +-w window (from the plan pass).
    A sweep [a, b] (a <= b) overlaps [lo, hi] unless b < lo or a > hi, and no sweep is both, so the count
    is #(a <= hi) - #(b < lo): two binary searches per sample instead of a walk over every sweep."""
    tc = np.asarray(the_plan.upper_exposure_ns, np.int64)
    counts = {}
    for t in topics.lidars:
        spans = np.array(the_plan.spans[t], np.int64).reshape(-1, 2)
        starts, ends = np.sort(spans[:, 0]), np.sort(spans[:, 1])
        counts[t] = np.searchsorted(starts, tc + w, "right") - np.searchsorted(ends, tc - w, "left")
    return {k: {t: int(counts[t][k]) for t in topics.lidars} for k in range(len(tc))}


def _imu_window(
    imu_t: list[int], imu_g: list[Any], tc: int, w: int, R_cam0_imu: Any, spikes: Callable[[I64, F64], Bool]
) -> ImuWindow | None:
    """The gyro readings within the sample's window (+ IMU_MARGIN_NS each side) less the `spikes` among
    them (none when the IMU is silent there), or None without an IMU."""
    if R_cam0_imu is None:
        return None
    if not imu_t:
        return ImuWindow(np.zeros(0, np.int64), np.zeros((0, 3)), R_cam0_imu)
    readings = ImuWindow(np.array(imu_t, np.int64), np.array(imu_g), R_cam0_imu)
    near = readings.within(tc - w - IMU_MARGIN_NS, tc + w + IMU_MARGIN_NS)
    keep = ~spikes(near.stamps_ns, near.gyro_rad_s)
    return ImuWindow(near.stamps_ns[keep], near.gyro_rad_s[keep], R_cam0_imu)


def _thin_lidars(
    rates: LidarRates, topics: Topics, lidars: tuple[LidarPoints, ...], t_ns: int, w: int
) -> tuple[str, ...]:
    """The LiDARs whose window holds far fewer points than their rate promises (lidar_rate's rule)."""
    return tuple(
        lp.name
        for topic, lp in zip(topics.lidars, lidars, strict=True)
        if rates.is_thin(topic, len(lp.stamps_ns), t_ns, w)
    )


def _file_reading(
    topic: str, decoded: Sweep | Frame | ImuSample | None, imu_t: list[int], imu_g: list[Any],
    sweeps: dict[str, list[Sweep]], copies: FirstCopies,
) -> None:  # fmt: skip
    """Keep an IMU reading or a LiDAR sweep (with points) for the samples, but not a repeated one (`copies`;
    the plan pass counted it); None was skipped as undecodable."""
    if isinstance(decoded, ImuSample):
        if copies.stamped(topic, decoded.stamp_ns):
            imu_t.append(decoded.stamp_ns)
            imu_g.append(decoded.gyro_rad_s)
    elif isinstance(decoded, Sweep) and len(decoded.stamps_ns) and copies.sweep(topic, decoded):
        sweeps[topic].append(decoded)


def _forget_readings(imu_t: list[int], imu_g: list[Any], before_ns: int) -> None:
    """Drop the IMU readings stamped before `before_ns` from both lists, in place: every sample's
    window is built from them, so kept whole they made each job cost time in the recording's length."""
    if imu_t and min(imu_t) < before_ns:
        keep = [k for k, t in enumerate(imu_t) if t >= before_ns]
        imu_t[:] = [imu_t[k] for k in keep]
        imu_g[:] = [imu_g[k] for k in keep]


def _repeated(the_plan: Plan, topics: Topics, k: int) -> tuple[str, ...]:
    """The cameras whose frame of planned sample `k` repeats the frame before it (`Plan.repeated`)."""
    stamps = (("upper", topics.upper, the_plan.upper_ns[k]), ("lower", topics.lower, the_plan.lower_ns[k]))
    return tuple(side for side, topic, t in stamps if int(t) in the_plan.repeated.get(topic, ()))


def planned_stamps(the_plan: Plan) -> list[tuple[int, int]]:
    """The upper and lower header stamps (ns) of every planned sample, in plan order."""
    return [(int(u), int(lo)) for u, lo in zip(the_plan.upper_ns, the_plan.lower_ns, strict=True)]


MISSING_IMAGE = "missing image"
"""Why a planned sample is not run when the bag ended before one of its two frames came."""


@dataclass(frozen=True)
class AlreadyDone:
    """A planned sample an earlier run finished whole (`Resume.done`): counted, not run again."""

    sid: str


@dataclass(frozen=True)
class NotRun:
    """A planned sample that cannot run, and why (`MISSING_IMAGE`)."""

    sid: str
    reason: str


StreamEvent = StreamedJob | AlreadyDone | NotRun | Task[Any] | Release
"""What the stream pass says of each planned sample, in plan order; with `BlockTasks`, a sample's job is a
`Task` that needs its blocks, and the blocks' tasks and releases come between them."""


def stream_jobs(
    bags: BagSet, topics: Topics, the_plan: Plan, run: ResolvedRun, first_id: int = 0,
    bad: BadMessages | None = None, planes: BlockPlanes | None = None, resume: Resume | None = None,
    settings: dict[str, Any] | None = None,
) -> Iterator[StreamEvent]:  # fmt: skip
    """Second pass: per planned sample, in plan order, a StreamedJob, or `AlreadyDone` or `NotRun`.

    With `planes` (dense GT) every job's points carry their world normals (and
    free-space bits), and a job waits until the blocks its window overlaps
    are done; with `BlockTasks` the blocks are tasks for the workers, yielded
    as soon as they are due, and each job a `Task` that needs them (its
    normals and bits filled in on the worker, `run_streamed`). `resume` is
    what the output folder holds of the planned samples
    (`resume_state` of it when not given): a whole one is done, a damaged
    one goes again, and a job carries the folder's samples with its stamps.
    `settings` go into every sample's meta (`describe.sample_settings`).
    """
    sids = [sample_id(first_id + k) for k in range(len(the_plan.upper_ns))]
    if resume is None:
        resume = resume_state(run.out, sids, planned_stamps(the_plan))
    stream = _Stream(bags, topics, the_plan, run, sids, bad or BadMessages(), planes, resume, settings or {})
    wanted = [topics.upper, topics.lower, *topics.lidars, *([topics.imu] if topics.imu else [])]
    for msg in bags.messages(topics=wanted, defer=(topics.upper, topics.lower)):
        stream.take(msg)
        yield from stream.released()
    yield from stream.rest()


class _Stream:
    """The stream pass's state: the frames, sweeps and gyro readings read so far, and the next planned
    sample to release (`stream_jobs`)."""

    def __init__(
        self, bags: BagSet, topics: Topics, the_plan: Plan, run: ResolvedRun, sids: list[str],
        bad: BadMessages, planes: BlockPlanes | None, resume: Resume, settings: dict[str, Any],
    ) -> None:  # fmt: skip
        self.bags, self.topics, self.plan, self.run, self.sids = bags, topics, the_plan, run, sids
        self.bad, self.planes, self.resume, self.settings = bad, planes, resume, settings
        self.w = run.window_ns
        self.index = {int(t): k for k, t in enumerate(the_plan.upper_ns)}
        self.lower_index = {int(t): k for k, t in enumerate(the_plan.lower_ns)}
        self.frames: dict[int, dict[str, RawMessage]] = {}  # as stored: the workers decode them
        self.sweeps: dict[str, list[Sweep]] = {t: [] for t in topics.lidars}
        self.need = _sweeps_needed(the_plan, topics, self.w)
        self.imu_t: list[int] = []
        self.imu_g: list[Any] = []
        self.copies = FirstCopies()  # sweeps and IMU readings: each once
        # a sweep is logged at its end, often before the gyro readings past it: a sample also waits for those
        self.imu_last = the_plan.imu_last_ns if topics.imu else None
        self.imu_max = -(1 << 62)
        self.next_k = 0
        self.exposure_ns = the_plan.upper_exposure_ns
        self.sweeps_read = 0  # LiDAR messages taken and forgets: `_ready`'s sweep checks change only with it
        self.short_of_sweeps: tuple[int, int] | None = None  # (sample, sweeps_read) the sweeps fell short at
        self.source = ",".join(p.name for p in bags.paths)

    def take(self, msg: RawMessage) -> None:
        """Keep what `msg` brings: a planned frame (not decoded), a sweep, gyro readings."""
        topics, where = self.topics, self.bags.label
        if msg.topic in (topics.upper, topics.lower):
            stamp = self.bad.stamp(msg, where)
            side = "upper" if msg.topic == topics.upper else "lower"
            k = None if stamp is None else (self.index if side == "upper" else self.lower_index).get(stamp)
            if k is None or k < self.next_k:
                return
            self.frames.setdefault(k, {})
            if self.sids[k] not in self.resume.done:
                self.frames[k][side] = msg
            return
        _file_reading(
            msg.topic, self.bad.decoded(msg, where), self.imu_t, self.imu_g, self.sweeps, self.copies
        )
        if msg.topic == topics.imu and self.imu_t:
            self.imu_max = max(self.imu_max, self.imu_t[-1])
        elif msg.topic in self.sweeps:
            self.sweeps_read += 1

    def released(self) -> Iterator[StreamEvent]:
        """The next samples in plan order that are done already or have all they need, each followed by
        forgetting the sweeps and readings no later sample can use (and the block tasks due)."""
        while self.next_k < len(self.sids) and (self.sids[self.next_k] in self.resume.done or self._ready()):
            k = self.next_k
            yield from self._block_tasks()
            if self.sids[k] in self.resume.done:
                self.frames.pop(k, None)
                yield AlreadyDone(self.sids[k])
            else:
                yield self._job(k)
            self.next_k += 1
            if self.next_k < len(self.sids):
                self._forget(int(self.exposure_ns[self.next_k]) - self.w)
        yield from self._block_tasks()

    def _block_tasks(self) -> Iterator[Task[Any] | Release]:
        """The block tasks and releases due (`BlockTasks`), none for blocks done here."""
        if isinstance(self.planes, BlockTasks):
            yield from self.planes.take()

    def rest(self) -> Iterator[StreamEvent]:
        """After the bag's end: whatever is complete still goes, the rest is `NotRun`."""
        for k in range(self.next_k, len(self.sids)):
            if self.sids[k] in self.resume.done:
                yield AlreadyDone(self.sids[k])
            elif len(self.frames.get(k, {})) != 2:
                yield NotRun(self.sids[k], MISSING_IMAGE)
            else:
                if self.planes is not None:
                    tc = int(self.exposure_ns[k])
                    self.planes.complete(self.sweeps, tc - self.w, tc + self.w, final=True)
                    yield from self._block_tasks()
                yield self._job(k)

    def _ready(self) -> bool:
        """Whether the next sample has its frames, the gyro past its window, its window's sweeps and their
        blocks (dense GT). Called after every message: the sweep checks rerun only once a sweep came or went
        since they fell short (with the same sweeps `BlockPlanes.complete` would fit nothing new)."""
        k, w = self.next_k, self.w
        if len(self.frames.get(k, {})) != 2 or self.short_of_sweeps == (k, self.sweeps_read):
            return False
        tc = int(self.exposure_ns[k])
        if self.imu_last is not None and self.imu_max < min(tc + w + IMU_MARGIN_NS, self.imu_last):
            return False
        have = {
            t: sum(1 for s in v if s.span_ns[1] >= tc - w and s.span_ns[0] <= tc + w)
            for t, v in self.sweeps.items()
        }
        ready = all(have[t] >= n for t, n in self.need[k].items())
        ready = ready and (self.planes is None or self.planes.complete(self.sweeps, tc - w, tc + w))
        if not ready:
            self.short_of_sweeps = (k, self.sweeps_read)
        return ready

    def _forget(self, horizon: int) -> None:
        """Drop the sweeps and IMU readings that end before `horizon` (ns); a block is fitted whole, and
        tested by slices around it: its sweeps and those stay."""
        kept_from = horizon if self.planes is None else self.planes.keep_from(horizon)
        for t in self.sweeps:
            self.sweeps[t] = [s for s in self.sweeps[t] if s.span_ns[1] >= kept_from]
        self.sweeps_read += 1
        if self.planes is not None:
            self.planes.forget(self.sweeps)
        _forget_readings(self.imu_t, self.imu_g, horizon - IMU_MARGIN_NS)

    def _job(self, k: int) -> StreamedJob | Task[StreamedJob]:
        the_plan, topics, run, w = self.plan, self.topics, self.run, self.w
        tc = int(self.exposure_ns[k])
        parts = [(window_parts(self.sweeps[t], tc, w), name) for t, name in topics.lidars.items()]
        tasks = self.planes if isinstance(self.planes, BlockTasks) else None
        lidars = tuple(_window_points(p, name, None if tasks else self.planes) for p, name in parts)
        thin = _thin_lidars(the_plan.rates, topics, lidars, tc, w)
        thin_sparse: tuple[str, ...] = ()
        if run.sample.gap_fallback:
            ws = run.sample.window_ns
            narrow = tuple(lp.within(tc - ws, tc + ws) for lp in lidars)
            thin_sparse = _thin_lidars(the_plan.rates, topics, narrow, tc, ws)
        spikes = partial(self.bad.dropped.spikes, topics.imu or "")
        imu = _imu_window(self.imu_t, self.imu_g, tc, w, topics.R_cam0_imu, spikes)
        f = self.frames.pop(k)
        sid = self.sids[k]
        blocks, needs = None, set()
        if tasks is not None:
            windows = [tasks.window(p) for p, _ in parts]
            blocks = WindowBlocks(tuple(refs for refs, _ in windows), tasks.words)
            needs = set().union(*(keys for _, keys in windows))
        job = StreamedJob(
            run.out, sid, self.source, self.bags.label, int(the_plan.upper_ns[k]), int(the_plan.lower_ns[k]),
            f["upper"], f["lower"], lidars, imu, run.sample, thin, thin_sparse, the_plan.upper_shift_ns,
            the_plan.lower_shift_ns, self.resume.same_stamps.get(sid, ()), dict(self.settings), blocks,
            _repeated(the_plan, topics, k),
        )  # fmt: skip
        return job if tasks is None else Task(job, needs=tuple(sorted(needs)))
