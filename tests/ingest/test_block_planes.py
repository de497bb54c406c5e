"""Dense GT's block planes: one normal per point, fitted in its block of time, in the world frame."""

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ingest.bags.decode import Sweep
from ingest.train.gt import block_planes
from ingest.train.gt.block_planes import (
    BlockPlanes,
    FreeSpaceSettings,
    PlaneSettings,
    cleared_for,
    world_normals,
)
from ingest.train.gt.free_space import RayTest, free_space_filter
from ingest.train.plausible import NOISE_TAG_BITS
from ingest.train.trajectory.rig_trajectory import RigTrajectory

KNOT_NS = 50_000_000
SWEEP_NS = 100_000_000
T0 = 1_700_000_000_000_000_000  # blocks are cut at multiples of the block length in absolute time


def _pose(rotvec, xyz):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = xyz
    return T


LIDARS = {"/a": _pose([0.0, 0.0, 0.3], [0.0, -0.1, 0.0]), "/b": _pose([np.pi, 0.0, -0.4], [0.0, 0.1, 0.05])}
N_WALL = np.array(
    [0.0, 0.0, 1.0]
)  # the wall z = 6 m and the floor y = 1.4 m (world = cam0 at the first knot)
N_FLOOR = np.array([0.0, 1.0, 0.0])


def _trajectory(seconds=3.0, gap_at_s=None):
    """Walking along x at 1 m/s, turning about y at 0.4 rad/s; the knot at `gap_at_s` predicted (NaN)."""
    stamps = T0 + np.arange(0, int(seconds * 1e9) + 1, KNOT_NS, dtype=np.int64)
    s = (stamps - T0) / 1e9
    R = Rotation.from_rotvec(np.outer(s, [0.0, 0.4, 0.0])).as_matrix()
    p = np.c_[s, np.zeros_like(s), np.zeros_like(s)]
    residual = np.zeros(len(stamps))
    if gap_at_s is not None:
        residual[round(gap_at_s * 1e9 / KNOT_NS)] = np.nan
    return RigTrajectory(stamps, R, p, residual)


def _sweep(traj, topic, t0_ns, n, rng):
    """`n` points on the wall and the floor seen by LiDAR `topic` over [t0_ns, t0_ns + SWEEP_NS)."""
    t = np.sort(rng.integers(t0_ns, t0_ns + SWEEP_NS, n)).astype(np.int64)
    on_wall = rng.random(n) < 0.5
    world = np.where(
        on_wall[:, None],
        np.c_[rng.uniform(-4, 8, n), rng.uniform(-2, 1.4, n), np.full(n, 6.0)],
        np.c_[rng.uniform(-4, 8, n), np.full(n, 1.4), rng.uniform(1, 6, n)],
    )  # fmt: skip
    R, p = traj.pose(t)
    cam0 = np.einsum("nji,nj->ni", R, world - p)  # R^T (world - p)
    T = LIDARS[topic]
    lidar = (cam0 - T[:3, 3]) @ T[:3, :3]
    return Sweep(int(t[-1]), topic, lidar.astype(np.float32), t, tag=np.zeros(n, np.uint8)), world, on_wall


def _settings(block_ns=1_000_000_000):
    return PlaneSettings(LIDARS, block_ns, neighbours=10, max_flatness=0.02, min_range_m=0.3)


def _sweeps(traj, seconds, n=3000, seed=0):
    """Sweeps of both LiDARs from 50 ms on: the sweep of each block boundary straddles it."""
    rng = np.random.default_rng(seed)
    out: dict[str, list[Sweep]] = {topic: [] for topic in LIDARS}
    for k in range(round(seconds * 1e9 / SWEEP_NS) - 1):
        for topic in LIDARS:
            out[topic].append(_sweep(traj, topic, T0 + SWEEP_NS // 2 + k * SWEEP_NS, n, rng)[0])
    return out


def test_stretch_ids_follow_the_measured_spans():
    traj = _trajectory(1.0, gap_at_s=0.5)
    t = T0 + np.arange(-10_000_000, 1_020_000_001, 5_000_000, dtype=np.int64)
    ids = traj.stretch_of(t)
    for ti, i in zip(t, ids, strict=True):
        span = traj.measured_span(int(ti))
        if span is None:
            assert i == -1, ti
        else:  # the same id exactly over one measured span
            same = t[ids == i]
            assert span[0] <= same.min() and same.max() <= span[1], ti
    assert ids[0] == -1 and ids[-1] == -1  # outside the knots
    assert (ids[(t > T0 + 450_000_000) & (t < T0 + 550_000_000)] == -1).all()  # beside the predicted knot
    assert len(set(ids[ids >= 0].tolist())) == 2


def test_world_normals_are_the_planes_of_the_world_for_every_lidar():
    traj = _trajectory(1.0)
    rng = np.random.default_rng(1)
    parts, truth = [], []
    for topic in LIDARS:
        for k in range(10):
            sweep, _, on_wall = _sweep(traj, topic, T0 + k * SWEEP_NS, 4000, rng)
            parts.append((sweep.xyz_m, sweep.stamps_ns, sweep.tag, LIDARS[topic]))
            truth.append(np.where(on_wall[:, None], N_WALL, N_FLOOR))
    # a zero point and a tagged point get no normal
    parts[0][0][0] = 0.0
    parts[1][2][5] = NOISE_TAG_BITS
    normals = world_normals(parts, traj, _settings())
    assert [len(n) for n in normals] == [len(p[1]) for p in parts]
    n, expect = np.concatenate(normals).astype(np.float64), np.concatenate(truth)
    assert np.isnan(normals[0][0]).all() and np.isnan(normals[1][5]).all()
    fitted = np.isfinite(n[:, 0])
    assert fitted.mean() > 0.9  # all but the points where wall meets floor
    dot = np.abs((n[fitted] * expect[fitted]).sum(axis=1))
    assert np.median(dot) > 1 - 1e-5 and np.quantile(dot, 0.01) > 0.999  # float16 holds 1e-3


def test_points_beside_a_predicted_knot_get_no_normal_and_stretches_are_fitted_apart():
    traj = _trajectory(1.0, gap_at_s=0.5)
    rng = np.random.default_rng(2)
    sweeps = [_sweep(traj, "/a", T0 + k * SWEEP_NS, 3000, rng)[0] for k in range(10)]
    parts = [(s.xyz_m, s.stamps_ns, s.tag, LIDARS["/a"]) for s in sweeps]
    normals = np.concatenate(world_normals(parts, traj, _settings()))
    stamps = np.concatenate([s.stamps_ns for s in sweeps])
    off = traj.stretch_of(stamps) < 0
    assert off.any() and np.isnan(normals[off]).all()
    # each stretch alone gives the same normals: no neighbour is taken across the gap
    for part in (stamps < T0 + 450_000_000, stamps > T0 + 550_000_000):
        alone = world_normals([(np.concatenate([s.xyz_m for s in sweeps])[part], stamps[part], None,
                                LIDARS["/a"])], traj, _settings())[0]  # fmt: skip
        np.testing.assert_array_equal(alone, normals[part])


def _spans(sweeps):
    return {topic: [s.span_ns for s in v] for topic, v in sweeps.items()}


def test_a_block_is_fitted_once_all_its_sweeps_are_here_and_the_same_from_any_window():
    traj = _trajectory(3.0)
    every = _sweeps(traj, 3.0)
    planes = BlockPlanes(traj, _spans(every), _settings())
    # up to 1.45 s: block 0 (the first second) is complete, block 1 is not
    buffered = {topic: v[:14] for topic, v in every.items()}
    assert planes.complete(buffered, T0 + 200_000_000, T0 + 900_000_000)
    assert not planes.complete(buffered, T0 + 700_000_000, T0 + 1_200_000_000)
    assert planes.blocks_fitted == 1
    buffered = {topic: v[:20] for topic, v in every.items()}
    assert planes.complete(buffered, T0 + 700_000_000, T0 + 1_200_000_000)
    assert planes.blocks_fitted == 2  # block 0 is not fitted again

    # another run reaching the same blocks through other windows, in another order, gives the same normals
    other = BlockPlanes(traj, _spans(every), _settings())
    assert other.complete(buffered, T0 + 1_000_000_000, T0 + 1_000_000_000)  # block 1 first
    assert other.complete(buffered, T0, T0)
    for topic in LIDARS:
        for s in buffered[topic]:
            np.testing.assert_array_equal(planes.normals(s), other.normals(s))

    # each is the fit among exactly its block's points
    lo, hi = T0 + 1_000_000_000, T0 + 2_000_000_000 - 1
    parts, where = [], []
    for topic, v in buffered.items():
        for s in v:
            m = (s.stamps_ns >= lo) & (s.stamps_ns <= hi)
            if m.any():
                parts.append((s.xyz_m[m], s.stamps_ns[m], s.tag[m], LIDARS[topic]))
                where.append((s, m))
    for (s, m), normal in zip(where, world_normals(parts, traj, _settings()), strict=True):
        np.testing.assert_array_equal(planes.normals(s)[m], normal)


def test_a_block_whose_sweeps_never_all_came_is_fitted_at_the_end():
    traj = _trajectory(2.0)
    every = _sweeps(traj, 2.0)
    buffered = {topic: v[:17] for topic, v in every.items()}  # the bag ended 0.2 s early
    planes = BlockPlanes(traj, _spans(every), _settings())
    assert not planes.complete(buffered, T0 + 1_200_000_000, T0 + 1_500_000_000)
    assert planes.complete(buffered, T0 + 1_200_000_000, T0 + 1_500_000_000, final=True)
    assert np.isfinite(planes.normals(buffered["/a"][-1]).astype(float)).mean() > 0.9


@pytest.mark.parametrize("threads", [None, 1])
def test_a_fit_leaves_open3ds_thread_count_as_it_found_it(threads):
    from ingest.runtime.o3d import o3d

    before = o3d.utility.get_max_threads()
    traj = _trajectory(1.0)
    every = _sweeps(traj, 1.0, n=500)
    planes = BlockPlanes(traj, _spans(every), _settings(), threads=threads)
    assert planes.complete(every, T0, T0 + 900_000_000)
    assert o3d.utility.get_max_threads() == before


# ---------------------------------------------------------------- free space, once per block

SLICE_NS = 50_000_000


def _free_settings(window_ns: int, reference_ns: int = 0) -> FreeSpaceSettings:
    return FreeSpaceSettings(window_ns, reference_ns, SLICE_NS, RayTest(), min_slices=2)


def _still(seconds: float) -> RigTrajectory:
    stamps = T0 + np.arange(-KNOT_NS, int(seconds * 1e9) + 2 * KNOT_NS, KNOT_NS, dtype=np.int64)
    n = len(stamps)
    return RigTrajectory(stamps, np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3)), np.zeros(n))


def _room_with_a_walker(seconds: float, seed: int = 0) -> dict[str, list[Sweep]]:
    """Both LiDARs of a still rig (world = cam0) see a wall, a floor and a person walking across.

    Every position lies on a 10 cm lattice, so points sharing a 5 cm voxel share their coordinates:
    whichever point stands for a voxel, the free-space test sees the same position.
    """
    rng = np.random.default_rng(seed)
    g = np.arange(-40, 41) * 0.1
    wall = np.array([[x, y, 6.0] for x in g for y in g[(g > -2.0) & (g < 1.45)]])
    floor = np.array([[x, 1.4, z] for x in g for z in np.arange(10, 60) * 0.1])
    static = np.concatenate([wall, floor])
    out: dict[str, list[Sweep]] = {topic: [] for topic in LIDARS}
    for k in range(round(seconds * 1e9 / SWEEP_NS)):
        for topic, T in LIDARS.items():
            t = np.sort(rng.integers(T0 + k * SWEEP_NS + 1, T0 + (k + 1) * SWEEP_NS - 1, 2500)).astype(
                np.int64
            )
            world = static[rng.integers(0, len(static), len(t))]
            walker = rng.random(len(t)) < 0.2  # a 0.4 m x 1.6 m slab at z = 3 m, walking along x at 1 m/s
            x = -1.5 + (t[walker] - T0) / 1e9
            body = np.c_[x + rng.integers(0, 5, walker.sum()) * 0.1, rng.integers(-12, 4, walker.sum()) * 0.1]
            world[walker] = np.c_[np.round(body, 1), np.full(walker.sum(), 3.0)]
            lidar = (world - T[:3, 3]) @ T[:3, :3]  # the still rig: cam0 = world
            out[topic].append(
                Sweep(int(t[-1]), topic, lidar.astype(np.float32), t, tag=np.zeros(len(t), np.uint8))
            )
    return out


def _lattice_normals(parts, traj, settings):
    """`world_normals` of `_room_with_a_walker`'s still rig, exact and a function of position alone: the
    floor's (y = 1.4 m) and the wall's and walker's (constant z). Points sharing a voxel share a normal,
    whichever block fitted it, as they share a position."""
    out = []
    for xyz, _, _, T in parts:
        cam0 = np.asarray(xyz, np.float64) @ T[:3, :3].T + T[:3, 3]
        floor = np.abs(cam0[:, 1] - 1.4) < 1e-3
        out.append(np.where(floor[:, None], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]).astype(np.float16))
    return out


@pytest.mark.parametrize("reference_ns", [0, 100_000_000])
def test_a_blocks_free_space_bits_give_each_sample_what_its_own_test_gives(reference_ns, monkeypatch):
    """For every frame time, the points the block bits clear are those the per-sample test clears
    (the same rays, planes and number of agreeing slices)."""
    monkeypatch.setattr(block_planes, "world_normals", _lattice_normals)
    seconds, window_ns, block_ns = 3.0, 500_000_000, 1_000_000_000
    traj, sweeps = _still(seconds), _room_with_a_walker(seconds)
    fs = _free_settings(window_ns, reference_ns)
    settings = replace(_settings(block_ns), free_space=fs)
    spans = {t: [s.span_ns for s in v] for t, v in sweeps.items()}
    planes = BlockPlanes(traj, spans, settings)
    assert planes.complete(sweeps, T0, T0 + int(seconds * 1e9) - 1)
    topics = list(sweeps)
    xyz = np.concatenate(
        [s.xyz_m @ LIDARS[t][:3, :3].T + LIDARS[t][:3, 3] for t in topics for s in sweeps[t]]
    )
    st = np.concatenate([s.stamps_ns for t in topics for s in sweeps[t]])
    lidar = np.concatenate([np.full(len(s.stamps_ns), i) for i, t in enumerate(topics) for s in sweeps[t]])
    bits = np.concatenate([planes.clear_bits(s) for t in topics for s in sweeps[t]])
    normal = np.concatenate([planes.normals(s) for t in topics for s in sweeps[t]]).astype(np.float64)
    cleared_somewhere = 0
    for tc in T0 + np.arange(600, 2500, 150) * 1_000_000:
        w = np.flatnonzero(np.abs(st - tc) <= window_ns)
        k = (st[w] - tc) // SLICE_NS
        sid = k * 2 + lidar[w]
        near = sid[np.abs(st[w] - tc) <= reference_ns] if reference_ns else sid
        refs = [(int(s), LIDARS[topics[s % 2]][:3, 3].astype(float)) for s in np.unique(near)]
        keep = free_space_filter(
            xyz[w].astype(np.float64), sid, refs, fs.ray_test, normal=normal[w], min_slices=2, lidars=2
        )
        cleared = cleared_for(bits[w], st[w], int(tc), fs, block_ns)
        np.testing.assert_array_equal(cleared, ~keep, err_msg=str(tc - T0))
        cleared_somewhere += int(cleared.sum())
    assert cleared_somewhere > 1000  # the walker's trail: what the test is there for


def test_free_space_waits_for_the_slices_beyond_its_block():
    """A block's bits need the slices a reach beyond it; until they are here the block is not done."""
    traj, sweeps = _still(3.0), _room_with_a_walker(3.0)
    settings = replace(_settings(), free_space=_free_settings(500_000_000))
    spans = {t: [s.span_ns for s in v] for t, v in sweeps.items()}
    planes = BlockPlanes(traj, spans, settings)
    until = T0 + 1_900_000_000  # block 0 needs slices to 1 s + 1 s (window + reference reach)
    early = {t: [s for s in v if s.span_ns[0] < until] for t, v in sweeps.items()}
    assert not planes.complete(early, T0, T0 + 999_999_999)
    assert planes.blocks_fitted == 1  # the planes need only the block itself
    assert planes.complete(sweeps, T0, T0 + 999_999_999)
    assert planes.keep_from(T0 + 1_200_000_000) == T0
    assert planes.keep_from(T0 + 2_200_000_000) == T0 + 1_000_000_000


def test_free_space_rays_start_where_each_lidar_was_in_the_middle_of_its_slice(monkeypatch):
    """Walking at 1 m/s and turning: each slice's reference origin is its LiDAR's position at the slice's
    middle, T_world_cam0(k S + S / 2) applied to the LiDAR's origin in cam0 (its start would be
    2.5 cm behind), taken from the trajectory's exact pose; that groups its rays, each of which starts
    where its LiDAR was at its point's own time (within the 2.5 cm of half a slice of the middle)."""
    refs: list[tuple[int, np.ndarray, int]] = []
    spread: list[float] = []

    def spy(pts, slice_id, references, n_bits, ray_test, test, ray_origin, normal):
        refs.extend(references)
        for sid, origin, _ in references:
            spread.append(float(np.linalg.norm(ray_origin[slice_id == sid] - origin, axis=1).max()))
        return np.zeros((len(pts), -(-n_bits // 64)), np.uint64)

    monkeypatch.setattr(block_planes, "free_space_bits", spy)
    traj = _trajectory(2.0)
    sweeps = _sweeps(traj, 2.0, n=300)
    settings = replace(_settings(), free_space=_free_settings(200_000_000))
    planes = BlockPlanes(traj, {t: [s.span_ns for s in v] for t, v in sweeps.items()}, settings)
    assert planes.complete(sweeps, T0, T0 + 999_999_999)
    topics = list(sweeps)
    assert len(refs) > 20 and len({sid for sid, _, _ in refs}) == len(refs)
    for sid, origin, _ in refs:
        t_mid = (sid // 2) * SLICE_NS + SLICE_NS // 2
        R, p = traj.pose(np.array([t_mid]))
        np.testing.assert_allclose(origin, R[0] @ LIDARS[topics[sid % 2]][:3, 3] + p[0], atol=1e-9)
    assert 0.015 < max(spread) <= 0.026
