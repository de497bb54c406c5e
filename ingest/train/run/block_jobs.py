"""Dense GT's blocks as executor tasks: planned by the stream pass, fitted and tested on the workers.

`ingest.train.gt.block_planes.BlockPlanes` fits each block's planes and runs
its free-space test in the process that streams the bags. `BlockTasks` keeps
its bookkeeping (which block is due when, which sweeps each one takes, which
blocks' normals a free-space test sees) but hands each fit and each test to
the executor as a keyed `Task` (`ingest.runtime.kept`): the block's points
travel once to one worker, its normals or bits stay with the workers
(`BlockNormals`, `BlockBits`, per sweep of the stream), and only a
`BlockReport` comes back. A sample's job names the sweeps of its window and
the rows it takes of each (`WindowBlocks`) and needs the keys of the blocks
that hold them; the worker puts its points' normals and bits together from
those (`fill_window`), the arrays `BlockPlanes` would have given it, bit for
bit: the same inputs reach the same functions, and a job needs exactly the
blocks done when the stream pass made it. Keys are released once no buffered
sweep belongs to their block.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from calibration.types import I64, U64
from ingest.bags.decode import Sweep
from ingest.rows import rows
from ingest.runtime.kept import Kept, Release, Task
from ingest.train.gt.block_planes import (
    F16,
    NORMAL_DTYPE,
    BlockPlanes,
    ClearInput,
    ClearSpan,
    PlaneSettings,
    clear_block,
    placed,
    world_normals,
)
from ingest.train.run.sample_job import LidarPoints
from ingest.train.trajectory.rig_trajectory import RigTrajectory

Array = np.ndarray[Any, Any]


@dataclass(frozen=True)
class FitPart:
    """The rows of one sweep (`serial`: the stream's count of it) in a block, as the fit takes them."""

    serial: int
    rows: I64
    xyz_m: Array
    stamps_ns: I64
    tag: Array | None
    topic: str


@dataclass(frozen=True)
class FitJob:
    """A block's plane fit (`world_normals` over every part at once)."""

    parts: tuple[FitPart, ...]
    settings: PlaneSettings


@dataclass(frozen=True)
class ClearSweep:
    """A whole sweep as a block's free-space test takes it (`lidar`: its topic's index)."""

    lidar: int
    serial: int
    xyz_m: Array
    stamps_ns: I64
    tag: Array | None


@dataclass(frozen=True)
class ClearJob:
    """A block's free-space test (`clear_block`); it needs the fits that hold normals of its sweeps."""

    span: ClearSpan
    topics: tuple[str, ...]
    sweeps: tuple[ClearSweep, ...]
    settings: PlaneSettings


@dataclass(frozen=True)
class BlockNormals:
    """A fit's value: per sweep serial, (rows, their world normals)."""

    rows: dict[int, tuple[I64, F16]]


@dataclass(frozen=True)
class BlockBits:
    """A free-space test's value: per sweep serial, (rows, their free-space bits)."""

    rows: dict[int, tuple[I64, U64]]


@dataclass(frozen=True)
class BlockReport:
    """What comes back of a block's task: whether it fitted points, and the worker's seconds on it."""

    fitted: bool
    seconds: float


@dataclass(frozen=True)
class WindowPart:
    """The rows one sample's window takes of one sweep (`n` points; rows None: all of them)."""

    serial: int
    n: int
    rows: I64 | None


@dataclass(frozen=True)
class WindowBlocks:
    """Per LiDAR of a job (in its order), the sweeps its window takes; `words` per point of free-space
    bits (0: no free-space test)."""

    lidars: tuple[tuple[WindowPart, ...], ...]
    words: int


def run_block(traj: RigTrajectory, job: FitJob | ClearJob, values: Mapping[str, Any]) -> Kept:
    """One block's fit or free-space test on a worker: its value kept, its report returned."""
    t0 = time.perf_counter()
    if isinstance(job, FitJob):
        poses = job.settings.T_cam0_lidar
        parts = [(p.xyz_m, p.stamps_ns, p.tag, poses[p.topic]) for p in job.parts]
        fitted = world_normals(parts, traj, job.settings)
        normals = BlockNormals({p.serial: (p.rows, n) for p, n in zip(job.parts, fitted, strict=True)})
        return Kept(normals, BlockReport(bool(job.parts), time.perf_counter() - t0))
    inputs = []
    for c in job.sweeps:
        T = job.settings.T_cam0_lidar[job.topics[c.lidar]]
        world, stretch = placed(c.xyz_m, c.tag, c.stamps_ns, T, traj, job.settings)
        normal = sweep_normals(c.serial, len(c.stamps_ns), values.values())
        inputs.append(ClearInput(c.lidar, world, stretch, c.stamps_ns, normal))
    cleared = clear_block(inputs, job.topics, job.span, traj, job.settings)
    bits = BlockBits({c.serial: got for c, got in zip(job.sweeps, cleared, strict=True)})
    return Kept(bits, BlockReport(False, time.perf_counter() - t0))


def sweep_normals(serial: int, n: int, values: Iterable[Any]) -> F16:
    """A sweep's world normals (n, 3) from the fits among `values` that hold its rows (NaN elsewhere)."""
    out = np.full((n, 3), np.nan, NORMAL_DTYPE)
    for v in values:
        if isinstance(v, BlockNormals) and serial in v.rows:
            r, normal = v.rows[serial]
            out[r] = normal
    return out


def sweep_bits(serial: int, n: int, words: int, values: Iterable[Any]) -> U64:
    """A sweep's free-space bits (n, words) from the tests among `values` that hold its rows (0 elsewhere)."""
    out = np.zeros((n, words), np.uint64)
    for v in values:
        if isinstance(v, BlockBits) and serial in v.rows:
            r, bits = v.rows[serial]
            out[r] = bits
    return out


def fill_window(
    points: LidarPoints, parts: tuple[WindowPart, ...], words: int, values: Mapping[str, Any]
) -> LidarPoints:
    """`points` (a job's window, without normals and bits) with its points' normals and bits from `values`."""
    vals = list(values.values())
    normals = [_rows(sweep_normals(p.serial, p.n, vals), p.rows) for p in parts]
    normal = np.concatenate(normals) if normals else np.zeros((0, 3), NORMAL_DTYPE)
    bits = None
    if words:
        got = [_rows(sweep_bits(p.serial, p.n, words, vals), p.rows) for p in parts]
        bits = np.concatenate(got) if got else np.zeros((0, words), np.uint64)
    return replace(points, normal_world=normal, clear_bits=bits)


def _rows(a: Array, which: I64 | None) -> Array:
    return a if which is None else rows(a, which)


class BlockTasks(BlockPlanes):
    """`BlockPlanes`' schedule, its fits and tests handed out as tasks (`take`) instead of run here."""

    def __init__(
        self, traj: RigTrajectory, spans: Mapping[str, list[tuple[int, int]]], settings: PlaneSettings
    ) -> None:
        super().__init__(traj, spans, settings)
        self._serial: dict[int, tuple[Sweep, int]] = {}  # id -> (the sweep, kept alive: ids stay unique)
        self._keys_of: dict[int, list[str]] = {}  # serial -> the blocks (fit and test keys) holding its rows
        self._sweeps_of: dict[str, set[int]] = {}  # key -> the serials of its sweeps still buffered
        self._out: list[Task[Any] | Release] = []
        self._next_serial = 0

    def take(self) -> list[Task[Any] | Release]:
        """The tasks and releases due since the last call, in order."""
        out, self._out = self._out, []
        return out

    @property
    def words(self) -> int:
        """Free-space words per point (0: no free-space test)."""
        fs = self.settings.free_space
        return 0 if fs is None else fs.words(self.settings.block_ns)

    def window(self, sweeps: list[tuple[Sweep, slice | I64]]) -> tuple[tuple[WindowPart, ...], set[str]]:
        """A window's parts (sweep, its rows: a slice for all of them) as `WindowPart`s, and the keys of the
        blocks done so far that hold rows of those sweeps."""
        parts, needs = [], set()
        for s, m in sweeps:
            serial = self._serial_of(s)
            parts.append(WindowPart(serial, len(s.stamps_ns), None if isinstance(m, slice) else m))
            needs.update(self._keys_of[serial])
        return tuple(parts), needs

    def _serial_of(self, sweep: Sweep) -> int:
        entry = self._serial.get(id(sweep))
        if entry is None:
            entry = (sweep, self._next_serial)
            self._next_serial += 1
            self._serial[id(sweep)] = entry
            self._keys_of[entry[1]] = []
        return entry[1]

    def _fit(self, sweeps: Mapping[str, list[Sweep]], lo: int, hi: int) -> None:
        parts = []
        for topic, v in sweeps.items():
            for s in v:
                if s.span_ns[1] < lo or s.span_ns[0] > hi:
                    continue
                m = np.flatnonzero((s.stamps_ns >= lo) & (s.stamps_ns <= hi))
                tag = None if s.tag is None else s.tag[m]
                parts.append(FitPart(self._serial_of(s), m, rows(s.xyz_m, m), s.stamps_ns[m], tag, topic))
        if parts:
            key = f"fit:{lo // self.settings.block_ns}"
            self._keep(key, [p.serial for p in parts])
            self._out.append(Task(FitJob(tuple(parts), self.settings), key=key))

    def _clear(self, sweeps: Mapping[str, list[Sweep]], lo: int, hi: int, k0: int, a: int, z: int) -> None:
        taken, needs = [], set[str]()
        for i, v in enumerate(sweeps.values()):
            for s in v:
                if s.span_ns[1] < a or s.span_ns[0] > z:
                    continue
                serial = self._serial_of(s)
                needs.update(k for k in self._keys_of[serial] if k.startswith("fit:"))
                taken.append(ClearSweep(i, serial, s.xyz_m, s.stamps_ns, s.tag))
        if not taken:
            return
        key = f"clear:{lo // self.settings.block_ns}"
        self._keep(key, [c.serial for c in taken])
        job = ClearJob(ClearSpan(lo, hi, k0, a, z), tuple(sweeps), tuple(taken), self.settings)
        self._out.append(Task(job, key=key, needs=tuple(sorted(needs))))

    def _keep(self, key: str, serials: list[int]) -> None:
        self._sweeps_of[key] = set(serials)
        for serial in serials:
            self._keys_of[serial].append(key)

    def forget(self, sweeps: Mapping[str, list[Sweep]]) -> None:
        """Forget the sweeps no longer buffered; release the blocks none of whose sweeps is."""
        super().forget(sweeps)
        alive = {id(s) for v in sweeps.values() for s in v}
        gone = {serial for k, (_, serial) in self._serial.items() if k not in alive}
        if not gone:
            return
        self._serial = {k: e for k, e in self._serial.items() if k in alive}
        released = []
        for serial in gone:
            for key in self._keys_of.pop(serial):
                held = self._sweeps_of[key]
                held.discard(serial)
                if not held:
                    released.append(key)
                    del self._sweeps_of[key]
        if released:
            self._out.append(Release(tuple(sorted(released))))
