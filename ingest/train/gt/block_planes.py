"""Dense GT's per-point work, once per block of recording time in the world: planes, free space.

Dense GT snaps every accumulated point onto its pixels' rays along the
point's local plane (`ingest.train.gt.dense.snap_to_pixel_rays`). Fitted per
sample, the k-NN plane fit of a +-500 ms window would be the largest cost of
a sample (about 220 ms of one core at full resolution), and consecutive
samples would fit nearly the same planes again: at every frame a point lies in
30 windows. Here they are fitted once (`BlockPlanes` in the process that
streams the bags; `ingest.train.run.block_jobs.BlockTasks` hands the same
fits to the workers as tasks): the recording is cut into
blocks of `DenseParams.plane_block_ns` (1 s, as many points as a window
holds), each block's points are placed in the world with the trajectory
and every point gets the normal of its k nearest neighbours in its block
(`plane_normals`). A job carries the world normals of its points
(`LidarPoints.normal_world`) and the worker turns them into cam0 at the
frame time. The blocks are fixed in time, so a point's normal is the same
in every sample and with any number of workers.

Points of two stretches of the trajectory (`RigTrajectory.stretch_of`: a
LiDAR gap between them) are never neighbours; points outside every
stretch, and those `filter_points` drops, get no normal (NaN).

The free-space test that removes movers (`ingest.train.gt.free_space`) runs
here too, once per block instead of once per sample (per sample, it would be
a sample's second largest cost). Every slice of `DenseParams.free_slice_ns` of one
LiDAR (fixed in absolute time) is a reference; a sample's references are
the slices within +-`free_reference_ns` (0: its window) of its frame time.
A block's points are tested, in the world, against every slice some sample
holding them can use: those within the window plus the reference reach of
the block (`FreeSpaceSettings.reach_ns`), and each point keeps one bit per
such slice time that saw through it and one per slice time that hit it
(`LidarPoints.clear_bits`). The worker removes the points whose bits name
at least `FreeSpaceSettings.min_slices` of its sample's slices that saw
through them outside the span of those that hit them (`cleared_for`,
`ingest.train.gt.free_space.stale_slices`). Points of one stretch are tested only by slices of it.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from calibration.types import F64, I64, U64, Bool
from ingest.bags.decode import Sweep
from ingest.raster.z_order import z_order
from ingest.rows import rows
from ingest.runtime.o3d import o3d
from ingest.train.gt.free_space import RayTest, free_space_bits, stale_slices
from ingest.train.trajectory.clouds import filter_points
from ingest.train.trajectory.planes import plane_normals
from ingest.train.trajectory.rig_trajectory import RigTrajectory

F16 = np.ndarray[Any, np.dtype[np.float16]]
NORMAL_DTYPE = np.float16  # 1e-3 rad at worst (a snap moves a range by micrometres for it); 6 bytes a point


@dataclass(frozen=True)
class FreeSpaceSettings:
    """Dense GT's free-space test as the blocks run it (`DenseParams`' window and free_* settings)."""

    window_ns: int  # a sample's +- window
    reference_ns: int  # a sample's references: slices within this of its frame time (0: its window)
    slice_ns: int
    ray_test: RayTest = field(default_factory=RayTest)
    min_slices: int = 1  # a point is removed once this many slice times of its sample saw through it

    @property
    def reach_ns(self) -> int:
        """How far from a point a slice that tests it can lie: a window and a reference span."""
        return self.window_ns + (self.reference_ns or self.window_ns)

    def n_bits(self, block_ns: int) -> int:
        """Slice times a block's points keep a bit for (an upper bound, the same for every block)."""
        return (block_ns + 2 * self.reach_ns) // self.slice_ns + 2

    def words(self, block_ns: int) -> int:
        """uint64 words per point: `n_bits` slices that saw through it, then as many that hit it."""
        return 2 * -(-self.n_bits(block_ns) // 64)

    def first_slice(self, block_start_ns: I64 | int) -> I64:
        """The slice (`slice_ns` steps since t = 0) of bit 0 of the block starting at `block_start_ns`."""
        out: I64 = (np.asarray(block_start_ns, np.int64) - self.reach_ns) // self.slice_ns
        return out


@dataclass(frozen=True)
class PlaneSettings:
    """What a block's plane fit needs: the rig's LiDAR poses and the dense-GT settings it uses."""

    T_cam0_lidar: Mapping[str, F64]  # per LiDAR topic
    block_ns: int
    neighbours: int
    max_flatness: float
    min_range_m: float
    free_space: FreeSpaceSettings | None = None  # None: no free-space test

    @property
    def task_span_ns(self) -> int:
        """The longest time whose sweeps one block's fit or free-space test takes (ns): the test's slices
        (`n_bits` of `slice_ns`: the block and its reach each side), or the block without a test."""
        fs = self.free_space
        return self.block_ns if fs is None else max(self.block_ns, fs.n_bits(self.block_ns) * fs.slice_ns)


def world_normals(
    parts: Sequence[tuple[np.ndarray[Any, Any], I64, np.ndarray[Any, Any] | None, F64]],
    traj: RigTrajectory,
    settings: PlaneSettings,
) -> list[F16]:
    """Unit normals (N_i, 3) in the world frame of the points of `parts`, fitted among all of them.

    Each part is (xyz_m in its LiDAR's frame (N_i, 3), stamps_ns (N_i,), Livox
    tags or None, T_cam0_lidar). The points are placed with `traj` at their
    own times; neighbours are looked for within each stretch of the
    trajectory. NaN where a point is filtered out, off every stretch, or its
    neighbourhood is not planar and local (`plane_normals`; "local" against
    the point's range from its LiDAR).
    """
    if not parts:
        return []
    sizes = [len(stamps) for _, stamps, _, _ in parts]
    flat = np.full((sum(sizes), 3), np.nan, NORMAL_DTYPE)
    pts, stamps, range_m, at = [], [], [], []
    offset = 0
    for (xyz, st, tag, T), n in zip(parts, sizes, strict=True):
        idx, lidar, cam0 = _kept_in_cam0(xyz, tag, T, settings.min_range_m)
        pts.append(cam0)
        stamps.append(st[idx])
        range_m.append(np.linalg.norm(lidar, axis=1))
        at.append(offset + idx)
        offset += n
    if offset:
        all_stamps, where = np.concatenate(stamps), np.concatenate(at)
        stretch = traj.stretch_of(all_stamps)
        on = np.flatnonzero(stretch >= 0)
        world = traj.transform(rows(np.concatenate(pts), on), all_stamps[on])
        r, stretch, where = np.concatenate(range_m)[on], stretch[on], where[on]
        for s in np.unique(stretch):
            sel = np.flatnonzero(stretch == s)
            sel = sel[z_order(rows(world, sel))]  # neighbours in memory: the k-NN runs about twice as fast
            fit = plane_normals(rows(world, sel), settings.neighbours, settings.max_flatness, r[sel])
            flat[where[sel]] = np.where(fit.planar[:, None], fit.normal, np.nan)
    return np.split(flat, np.cumsum(sizes)[:-1])


def _kept_in_cam0(xyz: np.ndarray[Any, Any], tag: np.ndarray[Any, Any] | None, T_cam0_lidar: F64,
                  min_range_m: float) -> tuple[I64, F64, F64]:  # fmt: skip
    """The points `filter_points` keeps: their indices, and their positions (m) in their LiDAR and in cam0."""
    keep, _ = filter_points(xyz, tag, min_range_m)
    idx = np.flatnonzero(keep)
    lidar = np.asarray(rows(xyz, idx), np.float64)
    return idx, lidar, lidar @ T_cam0_lidar[:3, :3].T + T_cam0_lidar[:3, 3]


def cleared_for(bits: U64, stamps_ns: I64, t_ns: int, settings: FreeSpaceSettings, block_ns: int) -> Bool:
    """Which points `settings.min_slices` reference slices of the sample at `t_ns` saw through before the
    first or after the last of its references that hit them (`stale_slices`), from their blocks' bits.

    `bits` (N, words) are the points' `BlockPlanes.clear_bits`, `stamps_ns`
    their times; the sample's references are the slices overlapping
    [t - span, t + span), span = `reference_ns` (0: the window).
    """
    span, S = settings.reference_ns or settings.window_ns, settings.slice_ns
    first, last = (t_ns - span) // S, (t_ns + span - 1) // S  # the slices overlapping [t - span, t + span)
    block = stamps_ns // block_ns
    out = np.zeros(len(stamps_ns), bool)
    for j in np.unique(block):
        sel = np.flatnonzero(block == j)
        k0 = int(settings.first_slice(int(j) * block_ns))
        lo, hi = max(first - k0, 0), min(last - k0, bits.shape[1] // 2 * 64 - 1)
        if lo <= hi:
            mask = np.tile(_bit_range(lo, hi, bits.shape[1] // 2), 2)  # both halves: saw through, hit
            out[sel] = stale_slices(rows(bits, sel) & mask) >= settings.min_slices
    return out


def _bit_range(lo: int, hi: int, words: int) -> U64:
    """Bits lo..hi (inclusive) set, as `words` uint64 words (bit b in word b // 64)."""
    m = ((1 << (hi + 1)) - 1) ^ ((1 << lo) - 1)
    return np.array([(m >> (64 * w)) & ((1 << 64) - 1) for w in range(words)], np.uint64)


class BlockPlanes:
    """The stream pass's normals: each block fitted once, when all its sweeps have arrived.

    `complete(sweeps, t0, t1)` fits every block overlapping [t0, t1] whose
    sweeps are all buffered (the plan pass counted them), and says whether
    all of those blocks are fitted; `normals(sweep)` gives a sweep's world
    normals (NaN for points of blocks not fitted yet). The stream pass keeps
    sweeps back to `block_start` of its oldest window, so a block's first
    sweeps are still there when its last one arrives. `threads` bounds
    Open3D's threads during a fit (1 where the workers already occupy every
    core; None: as they are).

    With `PlaneSettings.free_space`, a block is also tested for free space
    once every slice that can test it has arrived (`FreeSpaceSettings.
    reach_ns` beyond it), and `clear_bits(sweep)` gives its points' bits;
    the stream pass then keeps sweeps back to `keep_from` of its oldest
    window.
    """

    def __init__(
        self,
        traj: RigTrajectory,
        spans: Mapping[str, list[tuple[int, int]]],
        settings: PlaneSettings,
        threads: int | None = None,
    ) -> None:
        self.traj = traj
        self.settings = settings
        self.threads = threads
        self._starts = {t: np.sort(np.array(v, np.int64).reshape(-1, 2)[:, 0]) for t, v in spans.items()}
        self._ends = {t: np.sort(np.array(v, np.int64).reshape(-1, 2)[:, 1]) for t, v in spans.items()}
        self._normals: dict[int, tuple[Sweep, F16]] = {}  # id -> (the sweep, kept alive: ids stay unique)
        self._bits: dict[int, tuple[Sweep, U64]] = {}
        self._world: dict[int, tuple[Sweep, F64, I64]] = {}  # id -> (sweep, world points, stretch; -1: none)
        self._fitted: set[int] = set()
        self._cleared: set[int] = set()
        self.blocks_fitted = 0  # with at least one point
        self.seconds = 0.0  # spent fitting and testing free space

    def block_start(self, t_ns: int) -> int:
        """The start (ns) of the block holding `t_ns`."""
        return (t_ns // self.settings.block_ns) * self.settings.block_ns

    def keep_from(self, t_ns: int) -> int:
        """The earliest time whose sweeps the blocks of a window starting at `t_ns` still need."""
        start = self.block_start(t_ns)
        fs = self.settings.free_space
        return start if fs is None else int(fs.first_slice(start)) * fs.slice_ns

    def clear_bits(self, sweep: Sweep) -> U64:
        """Per point of `sweep`, the slices that saw through it and those that hit it (`cleared_for`); zero
        rows until tested."""
        fs = self.settings.free_space
        if fs is None:
            raise ValueError("these blocks run no free-space test (PlaneSettings.free_space is None)")
        entry = self._bits.get(id(sweep))
        if entry is None:
            entry = (sweep, np.zeros((len(sweep.stamps_ns), fs.words(self.settings.block_ns)), np.uint64))
            self._bits[id(sweep)] = entry
        return entry[1]

    def clear_bits_empty(self) -> U64:
        """No point's `clear_bits` (0, words)."""
        fs = self.settings.free_space
        return np.zeros((0, 1 if fs is None else fs.words(self.settings.block_ns)), np.uint64)

    def normals(self, sweep: Sweep) -> F16:
        """World normals (N, 3) of `sweep`'s points."""
        entry = self._normals.get(id(sweep))
        if entry is None:
            entry = (sweep, np.full((len(sweep.stamps_ns), 3), np.nan, NORMAL_DTYPE))
            self._normals[id(sweep)] = entry
        return entry[1]

    def complete(
        self, sweeps: Mapping[str, list[Sweep]], t0_ns: int, t1_ns: int, final: bool = False
    ) -> bool:
        """Whether every block overlapping [t0_ns, t1_ns] is fitted; fits those whose sweeps are all here
        (`final`: the bag ended, fit with whatever arrived)."""
        b, fs = self.settings.block_ns, self.settings.free_space
        for j in range(t0_ns // b, t1_ns // b + 1):
            lo, hi = j * b, (j + 1) * b - 1
            if j not in self._fitted:
                if not final and not self._all_here(sweeps, lo, hi):
                    return False
                self._fit(sweeps, lo, hi)
                self._fitted.add(j)
            if fs is not None and j not in self._cleared:
                k0 = int(fs.first_slice(lo))
                a, z = k0 * fs.slice_ns, ((hi + fs.reach_ns) // fs.slice_ns + 1) * fs.slice_ns - 1
                if not final and not self._all_here(sweeps, a, z):
                    return False
                self._clear(sweeps, lo, hi, k0, a, z)
                self._cleared.add(j)
        return True

    def _all_here(self, sweeps: Mapping[str, list[Sweep]], lo: int, hi: int) -> bool:
        return all(self._buffered(v, lo, hi) >= self._planned(t, lo, hi) for t, v in sweeps.items())

    def forget(self, sweeps: Mapping[str, list[Sweep]]) -> None:
        """Drop the normals, bits and world points of sweeps no longer buffered."""
        alive = {id(s) for v in sweeps.values() for s in v}
        self._normals = {k: e for k, e in self._normals.items() if k in alive}
        self._bits = {k: e for k, e in self._bits.items() if k in alive}
        self._world = {k: e for k, e in self._world.items() if k in alive}

    def _planned(self, topic: str, lo: int, hi: int) -> int:
        starts, ends = self._starts[topic], self._ends[topic]
        return int(np.searchsorted(starts, hi, "right") - np.searchsorted(ends, lo, "left"))

    @staticmethod
    def _buffered(v: list[Sweep], lo: int, hi: int) -> int:
        return sum(1 for s in v if s.span_ns[1] >= lo and s.span_ns[0] <= hi)

    def _fit(self, sweeps: Mapping[str, list[Sweep]], lo: int, hi: int) -> None:
        t0 = time.perf_counter()
        parts, targets = [], []
        for topic, v in sweeps.items():
            T = self.settings.T_cam0_lidar[topic]
            for s in v:
                if s.span_ns[1] < lo or s.span_ns[0] > hi:
                    continue
                m = np.flatnonzero((s.stamps_ns >= lo) & (s.stamps_ns <= hi))
                parts.append((rows(s.xyz_m, m), s.stamps_ns[m], None if s.tag is None else s.tag[m], T))
                targets.append((s, m))
        before = o3d.utility.get_max_threads()
        if self.threads is not None:
            o3d.utility.set_max_threads(self.threads)
        try:
            fitted = world_normals(parts, self.traj, self.settings)
        finally:
            o3d.utility.set_max_threads(before)
        for (s, m), normal in zip(targets, fitted, strict=True):
            self.normals(s)[m] = normal
        self.blocks_fitted += bool(parts)
        self.seconds += time.perf_counter() - t0

    def _placed(self, topic: str, sweep: Sweep) -> tuple[F64, I64]:
        """`sweep`'s points in the world and their stretch (`placed`), once per sweep."""
        entry = self._world.get(id(sweep))
        if entry is None:
            T = self.settings.T_cam0_lidar[topic]
            world, stretch = placed(sweep.xyz_m, sweep.tag, sweep.stamps_ns, T, self.traj, self.settings)
            entry = (sweep, world, stretch)
            self._world[id(sweep)] = entry
        return entry[1], entry[2]

    def _clear(self, sweeps: Mapping[str, list[Sweep]], lo: int, hi: int, k0: int, a: int, z: int) -> None:
        """The free-space bits of the points stamped in [lo, hi], from every slice in [a, z] (slice k0 on)."""
        t0 = time.perf_counter()
        inputs, targets = [], []
        for i, (topic, v) in enumerate(sweeps.items()):
            for s in v:
                if s.span_ns[1] < a or s.span_ns[0] > z:
                    continue
                world, on = self._placed(topic, s)
                inputs.append(ClearInput(i, world, on, s.stamps_ns, self.normals(s)))
                targets.append(s)
        cleared = clear_block(inputs, list(sweeps), ClearSpan(lo, hi, k0, a, z), self.traj, self.settings)
        for s, (m, bits) in zip(targets, cleared, strict=True):
            self.clear_bits(s)[m] = bits
        if inputs:
            self.seconds += time.perf_counter() - t0


def placed(
    xyz_m: np.ndarray[Any, Any], tag: np.ndarray[Any, Any] | None, stamps_ns: I64, T_cam0_lidar: F64,
    traj: RigTrajectory, settings: PlaneSettings,
) -> tuple[F64, I64]:  # fmt: skip
    """A sweep's points in the world (NaN where filtered out or off every stretch) and their stretch (-1:
    none), placed with `traj` at their own times."""
    idx, _, cam0 = _kept_in_cam0(xyz_m, tag, T_cam0_lidar, settings.min_range_m)
    stretch = np.full(len(stamps_ns), -1, np.int64)
    stretch[idx] = traj.stretch_of(stamps_ns[idx])
    on = stretch[idx] >= 0
    world = np.full((len(stretch), 3), np.nan)
    world[idx[on]] = traj.transform(rows(cam0, on), stamps_ns[idx[on]])
    return world, stretch


@dataclass(frozen=True)
class ClearInput:
    """One sweep as a block's free-space test takes it: its LiDAR (index in the topics' order), its points
    `placed` in the world with their stretch, their stamps and their world normals (NaN: none yet)."""

    lidar: int
    world: F64
    stretch: I64
    stamps_ns: I64
    normal_world: F16


@dataclass(frozen=True)
class ClearSpan:
    """A block's free-space test in time: its points are those in [lo, hi], its slices those in [a, z],
    bit 0 is slice k0 (`FreeSpaceSettings.first_slice`)."""

    lo: int
    hi: int
    k0: int
    a: int
    z: int


def clear_block(
    inputs: Sequence[ClearInput], topics: Sequence[str], span: ClearSpan, traj: RigTrajectory,
    settings: PlaneSettings,
) -> list[tuple[I64, U64]]:  # fmt: skip
    """Per input sweep, (its rows stamped in [lo, hi] and placed, their free-space bits), the block's points
    tested against every slice in [a, z] of every LiDAR of `topics` (within each stretch)."""
    fs = settings.free_space
    assert fs is not None
    S, n_topics = fs.slice_ns, len(topics)
    pts, stamps, lidar, stretch, normal, rows_of = [], [], [], [], [], []
    for c in inputs:
        m = np.flatnonzero((c.stamps_ns >= span.a) & (c.stamps_ns <= span.z) & (c.stretch >= 0))
        pts.append(rows(c.world, m))
        normal.append(np.asarray(rows(c.normal_world, m), np.float64))
        stamps.append(c.stamps_ns[m])
        lidar.append(np.full(len(m), c.lidar, np.int64))
        stretch.append(c.stretch[m])
        rows_of.append(m)
    if not pts:
        return []
    all_pts, all_st, all_stretch = np.concatenate(pts), np.concatenate(stamps), np.concatenate(stretch)
    all_lidar, all_normal = np.concatenate(lidar), np.concatenate(normal)
    slice_id = (all_st // S) * n_topics + all_lidar
    tested = (all_st >= span.lo) & (all_st <= span.hi)
    bits = np.zeros((len(all_st), fs.words(settings.block_ns)), np.uint64)
    origin_cam0 = np.array([settings.T_cam0_lidar[t][:3, 3] for t in topics]).reshape(-1, 3)
    for st in np.unique(all_stretch[tested]):
        sel = np.flatnonzero(all_stretch == st)
        sids = np.unique(slice_id[sel])
        k, which = sids // n_topics, sids % n_topics
        t_mid = k * S + S // 2
        origins = traj.transform(origin_cam0[which], t_mid)
        refs = [(int(sid), o, int(kk - span.k0)) for sid, o, kk in zip(sids, origins, k, strict=True)]
        ray_origin = traj.transform(origin_cam0[all_lidar[sel]], all_st[sel])  # each ray's own time
        bits[sel] = free_space_bits(
            rows(all_pts, sel), slice_id[sel], refs, fs.n_bits(settings.block_ns), fs.ray_test,
            tested[sel], ray_origin, rows(all_normal, sel),
        )  # fmt: skip
    out, offset = [], 0
    for c, m in zip(inputs, rows_of, strict=True):
        mine = (c.stamps_ns[m] >= span.lo) & (c.stamps_ns[m] <= span.hi)
        out.append((m[mine], bits[offset : offset + len(m)][mine]))
        offset += len(m)
    return out
