"""The odometry's settings (`OdometryParams`) and its local map: the registered points of the last
`map_horizon_s` on a voxel grid, with the PCA normals ICP matches against (`LocalMap`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from calibration.types import F64, I64, Bool
from ingest.train.trajectory.odometry_kernels import neighbourhood_planes
from ingest.train.trajectory.planes import planar_normals
from ingest.train.trajectory.voxel_hash import VoxelHash, VoxelSet, first_free, voxel_keys


@dataclass(frozen=True)
class OdometryParams:
    """Odometry settings (metres, nanoseconds)."""

    knot_ns: int = 50_000_000
    knots_per_chunk: int = 2
    source_voxel_m: float = 0.2  # one point per voxel of a chunk takes part in the fit
    max_source_points: int = 4000
    map_voxel_m: float = 0.1
    map_horizon_s: float = 2.0
    map_range_m: float = 30.0  # what lies this close to the rig joins the map (far voxels hold few points)
    map_neighbours: int = 10
    map_normal_radius_m: float = 1.0  # a normal needs `map_neighbours` points this close
    map_cell_m: float = 0.5  # cube of the map's search hash
    map_max_flatness: float = 0.05
    max_correspondence_m: float = 0.5
    iterations: int = 15
    # Gauss-Newton stops once no knot moves by more than `tol_m` and no point within `tol_range_m` of it
    # turns by more. From a chunk's prediction (gyro and velocity) the steps about halve each time: 3-5 of
    # them, where 0.05 mm took 10, to the same error against truth (docs/speed.md, six simulated walks);
    # a wrong prediction (an IMU with a bias, or late stamps) keeps stepping until the LiDARs decide
    tol_m: float = 1e-3
    tol_range_m: float = 10.0
    refine_start_s: float = 1.0  # then the start's knots are solved again against the map built since
    min_segment_points: int = 50  # a knot is solved only when the knot interval before it has this many
    max_jump_m: float = 0.5  # a solved knot this far from its predicted position is a failed solve


def voxel_subsample(pts: F64, voxel_m: float) -> I64:
    """Index of the first point in each occupied `voxel_m` cube (in input order)."""
    return first_free(voxel_keys(pts, voxel_m), np.zeros(0, np.int64))


@dataclass
class LocalMap:
    """World-frame points on a voxel grid, each remembering when and from where it joined.

    Normals are computed when ICP first matches a point (`normals_at`), not
    when it joins: most map points are never matched, and the k-neighbour
    query and covariance of every new point would be the odometry's largest
    cost. A normal is the PCA normal of the point's neighbours in the map at
    that time; "planar" is judged at its range from where the rig was when
    it joined.
    """

    params: OdometryParams
    xyz: F64 = field(default_factory=lambda: np.zeros((0, 3)))
    normal: F64 = field(default_factory=lambda: np.zeros((0, 3)))
    planar: Bool = field(default_factory=lambda: np.zeros(0, bool))
    known: Bool = field(default_factory=lambda: np.zeros(0, bool))  # normal computed
    origin: F64 = field(default_factory=lambda: np.zeros((0, 3)))  # the rig when the point joined
    added_ns: I64 = field(default_factory=lambda: np.zeros(0, np.int64))
    grid: VoxelHash | None = None
    voxels: VoxelSet = field(default_factory=VoxelSet)  # the voxels the points hold; ids: dropped + index
    dropped: int = 0  # points that left so far
    store: dict[str, np.ndarray[Any, Any]] = field(default_factory=dict)  # the arrays above are windows of
    store_from: int = 0  # ... these, from this row, with room after them (`_joined`)

    def add(self, pts_world: F64, t_ns: int, origin_world: F64) -> None:
        """A registered chunk joins (one point per free voxel); points older than the horizon leave.

        Points join in time order, so the expired ones are a prefix of the arrays.
        """
        prm = self.params
        first = int(np.searchsorted(self.added_ns, t_ns - int(prm.map_horizon_s * 1e9)))
        rel = pts_world - origin_world
        near = pts_world[np.einsum("ij,ij->i", rel, rel) <= prm.map_range_m**2]
        near_keys = voxel_keys(near, prm.map_voxel_m)
        self.dropped += first
        fresh = self.voxels.claim(near_keys, self.dropped)  # one point per voxel the map does not hold yet
        m = len(fresh)
        self._joined(first, {
            "xyz": near[fresh], "normal": np.zeros((m, 3)), "planar": np.zeros(m, bool),
            "known": np.zeros(m, bool), "origin": np.broadcast_to(origin_world, (m, 3)),
            "added_ns": np.full(m, t_ns, np.int64),
        })  # fmt: skip
        self.grid = VoxelHash.build(self.xyz, prm.map_cell_m, self.grid.buckets if self.grid else 0)

    def _joined(self, first: int, rows: dict[str, np.ndarray[Any, Any]]) -> None:
        """The first `first` points leave and `rows` join (per field): each field stays a window of a
        `store` array with room after it, so that a chunk costs its own rows, not the whole map's. When the
        room runs out the live rows move to the front of arrays twice their size."""
        live, m = len(self.xyz) - first, len(rows["xyz"])
        lo = self.store_from + first
        if not self.store or lo + live + m > len(self.store["xyz"]):
            size = 2 * (live + m) + 1024
            store = {}
            for name, new in rows.items():
                store[name] = np.empty((size, *new.shape[1:]), new.dtype)
                store[name][:live] = getattr(self, name)[first:]
            self.store, lo = store, 0
        for name, new in rows.items():
            self.store[name][lo + live : lo + live + m] = new
            setattr(self, name, self.store[name][lo : lo + live + m])
        self.store_from = lo

    def normals_at(self, j: I64) -> None:
        """Compute the normals of map points `j` that have none yet."""
        assert self.grid is not None
        prm = self.params
        todo = np.unique(j[~self.known[j]])
        self.known[todo] = True
        _, idx = self.grid.query(self.xyz[todo], prm.map_neighbours, prm.map_normal_radius_m)
        todo, idx = todo[idx[:, -1] >= 0], idx[idx[:, -1] >= 0]  # too few neighbours: never planar
        if len(todo) == 0:
            return
        evals, normal = neighbourhood_planes(self.xyz, idx)
        fit = planar_normals(evals, normal, self.xyz[todo] - self.origin[todo], prm.map_max_flatness)
        self.normal[todo], self.planar[todo] = fit.normal, fit.planar
