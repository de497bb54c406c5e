"""Dense GT's local planes, fitted once per point: per block of recording time, in the world frame.

Dense GT snaps every accumulated point onto its pixels' rays along the
point's local plane (`ingest.train.dense.snap_to_pixel_rays`). Fitted per
sample, the k-NN plane fit of a +-500 ms window was the largest cost of a
sample (about 220 ms of one core at full resolution), and consecutive
samples fitted nearly the same planes again: at every frame a point lies in
30 windows. Here the stream pass fits them once: the recording is cut into
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
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import open3d as o3d

from calibration.types import F64, I64
from ingest.bags.decode import Sweep
from ingest.raster.z_order import z_order
from ingest.rows import rows
from ingest.train.clouds import filter_points
from ingest.train.planes import plane_normals
from ingest.train.rig_trajectory import RigTrajectory

F16 = np.ndarray[Any, np.dtype[np.float16]]
NORMAL_DTYPE = np.float16  # 1e-3 rad at worst (a snap moves a range by micrometres for it); 6 bytes a point


@dataclass(frozen=True)
class PlaneSettings:
    """What a block's plane fit needs: the rig's LiDAR poses and the dense-GT settings it uses."""

    T_cam0_lidar: Mapping[str, F64]  # per LiDAR topic
    block_ns: int
    neighbours: int
    max_flatness: float
    min_range_m: float


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
        keep, _ = filter_points(xyz, tag, settings.min_range_m)
        idx = np.flatnonzero(keep)
        lidar = np.asarray(rows(xyz, idx), np.float64)
        pts.append(lidar @ T[:3, :3].T + T[:3, 3])
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
        self._fitted: set[int] = set()
        self.blocks_fitted = 0  # with at least one point
        self.seconds = 0.0  # spent fitting

    def block_start(self, t_ns: int) -> int:
        """The start (ns) of the block holding `t_ns`."""
        return (t_ns // self.settings.block_ns) * self.settings.block_ns

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
        b = self.settings.block_ns
        for j in range(t0_ns // b, t1_ns // b + 1):
            if j in self._fitted:
                continue
            lo, hi = j * b, (j + 1) * b - 1
            if not final and not all(
                self._buffered(v, lo, hi) >= self._planned(t, lo, hi) for t, v in sweeps.items()
            ):
                return False
            self._fit(sweeps, lo, hi)
            self._fitted.add(j)
        return True

    def forget(self, sweeps: Mapping[str, list[Sweep]]) -> None:
        """Drop the normals of sweeps no longer buffered."""
        alive = {id(s) for v in sweeps.values() for s in v}
        self._normals = {k: e for k, e in self._normals.items() if k in alive}

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
