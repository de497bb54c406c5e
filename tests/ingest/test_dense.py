"""Dense ground truth against the simulator's exact truth: a handheld outdoor walk with movers.

One recording (2.4 s, people crossing and oncoming, a swinging door, a car;
noise-free ranges, 240x150 images) is ingested once with `--gt auto`; the
tests score its trajectory and every sample against the truth, at a reduced
resolution that fits CI (bench/bench_dense.py measures full resolution).
"""

import math
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from calibration.rig import read_rig
from ingest.bags.decode import Sweep
from ingest.bags.message import RawMessage
from ingest.bags.reader import BagSet, Progress, open_bags
from ingest.dataset.meta import read_meta
from ingest.train.gt.dense import DenseParams, dense_ground_truth, free_space_filter, snap_to_pixel_rays
from ingest.train.run.pipeline import ingest
from ingest.train.run.sample_job import SampleParams
from ingest.train.run.settings import IngestConfig, resolve_topics
from ingest.train.trajectory.estimate import read_gyro, trajectory_pass
from ingest.train.trajectory.local_map import OdometryParams
from ingest.train.trajectory.planes import Normals
from ingest.train.trajectory.rig_trajectory import RigTrajectory
from sensorbox.sim.config import SimConfig
from sensorbox.sim.run import simulate
from sensorbox.sim.score import score_dataset
from sensorbox.sim.truth import Truth

pytestmark = pytest.mark.xdist_group("dense")


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    root = tmp_path_factory.mktemp("dense")
    cfg = SimConfig(
        scene="outdoor", trajectory="walk", duration_s=2.2, scale=0.125, range_noise_m=0.0, image="jpeg",
        movers=True, seed=7,
    )  # fmt: skip
    bag = simulate(cfg, root / "walk").bag
    truth = Truth.load(bag)
    out = root / "train"
    summary = ingest(
        [bag], IngestConfig(rig=truth.path / "rig.yaml", out=out, workers=1, every=16, gt="auto")
    )
    return {"bag": bag, "truth": truth, "out": out, "summary": summary}


@pytest.fixture(scope="module")
def still_walk(tmp_path_factory):
    """The same walk with nothing moving, ingested with the free-space test and without it."""
    root = tmp_path_factory.mktemp("dense_static")
    cfg = SimConfig(
        scene="outdoor", trajectory="walk", duration_s=2.2, scale=0.125, range_noise_m=0.0, image="jpeg",
        seed=7,
    )  # fmt: skip
    bag = simulate(cfg, root / "walk").bag
    truth = Truth.load(bag)
    outs = {}
    for name, free in (("on", True), ("off", False)):
        params = SampleParams(dense=DenseParams(free_space=free))
        cfg_i = IngestConfig(
            rig=truth.path / "rig.yaml", out=root / name, workers=1, every=16, gt="dense", sample=params
        )
        ingest([bag], cfg_i)
        outs[name] = root / name
    return {"truth": truth, **outs}


def _read_tum(path: Path) -> tuple[np.ndarray, np.ndarray]:
    rows = np.array(
        [[float(v) for v in line.split()] for line in path.read_text().splitlines() if line[0] != "#"]
    )
    T = np.tile(np.eye(4), (len(rows), 1, 1))
    T[:, :3, :3] = Rotation.from_quat(rows[:, 4:]).as_matrix()
    T[:, :3, 3] = rows[:, 1:4]
    stamps = np.array([line.split()[0] for line in path.read_text().splitlines() if line[0] != "#"])
    ns = np.array([int(s.replace(".", "")) for s in stamps], np.int64)
    return ns, T


def test_auto_chose_dense_and_said_why(walk):
    s = walk["summary"]
    assert s.method == "dense" and s.decision.startswith("auto: trajectory residual")
    doc = yaml.safe_load((walk["out"] / "dataset.yaml").read_text())
    (source,) = doc["sources"]
    assert source["bags"] == ["walk"] and source["first_id"] == 0 and source["samples"] == s.planned
    gt = source["ground_truth"]
    assert gt["method"] == "dense" and gt["window_ms"] == 500.0 and gt["decision"] == s.decision
    assert (
        gt["trajectory"]["file"].endswith("trajectories/walk.tum") and doc["params"]["ground_truth"] == "auto"
    )
    meta = read_meta(walk["out"], "000002")
    assert meta.gt.method == "dense" and meta.gt.decision == s.decision and meta.gt.window_ms == 500.0
    assert meta.gt.accumulated_points > 100_000 and meta.gt.trajectory_residual_mm is not None


def test_the_planes_are_fitted_once_per_block_the_samples_reach(walk):
    """Each 1 s block a written sample's window touches is fitted, and none the recording has no point in."""
    blocks, seconds = walk["summary"].dense_planes
    block_ns, w = DenseParams().plane_block_ns, DenseParams().window_ns
    metas = [read_meta(walk["out"], f.stem) for f in sorted((walk["out"] / "meta").glob("*.json"))]
    reached = {
        b for m in metas for b in range((m.stamp_ns - w) // block_ns, (m.stamp_ns + w) // block_ns + 1)
    }
    with open_bags([walk["bag"]]) as bags:
        topics = [li.topic for li in walk["truth"].rig.lidars]
        sweeps = [msg.decoded(bags.label) for msg in bags.messages(topics=topics)]
    stamps = np.concatenate([s.stamps_ns for s in sweeps if isinstance(s, Sweep)])
    recorded = set((stamps // block_ns).tolist())
    assert len(reached & recorded) <= blocks <= len(recorded) and len(recorded) >= 3
    assert seconds > 0


def test_dense_meta_says_how_far_the_rig_moved_over_the_accumulated_points(walk):
    """motion.max_rotation_deg against the truth's largest turn from the frame time over its +-500 ms
    window (clipped to the trajectory): within 0.5 deg, the turn of a few ms at the window's edges."""
    truth = walk["truth"]
    knots, _ = _read_tum(walk["out"] / "trajectories" / "walk.tum")
    for sid in (f.stem for f in sorted((walk["out"] / "meta").iterdir())):
        meta = read_meta(walk["out"], sid)
        tc = meta.stamp_ns
        t = np.arange(tc - 500_000_000, tc + 500_000_000, 5_000_000, dtype=np.int64)
        t = t[(t >= knots[0]) & (t <= knots[-1])]
        T = truth.T_world_cam0(np.r_[tc, t])
        rel = np.einsum("ji,njk->nik", T[0, :3, :3], T[1:, :3, :3])
        turn_deg = np.degrees(np.linalg.norm(Rotation.from_matrix(rel).as_rotvec(), axis=1)).max()
        assert meta.motion.max_rotation_deg == pytest.approx(turn_deg, abs=0.5), sid
        assert turn_deg > 2.0 and meta.motion.predicted_motion_px > 1.0  # a handheld walk turns


def test_trajectory_matches_the_truth_to_a_centimetre(walk):
    """<= 1 cm and 0.1 deg at every knot (the issue's 20 s target; bench_dense measures 20 s)."""
    stamps, T_est = _read_tum(walk["out"] / "trajectories" / "walk.tum")
    T_true = walk["truth"].T_world_cam0(stamps)
    T_true = np.linalg.inv(T_true[0]) @ T_true  # the estimate's world is cam0 at its first knot
    pos_err = np.linalg.norm(T_est[:, :3, 3] - T_true[:, :3, 3], axis=1)
    rel = np.einsum("nji,njk->nik", T_true[:, :3, :3], T_est[:, :3, :3])
    rot_err_deg = np.degrees(np.linalg.norm(Rotation.from_matrix(rel).as_rotvec(), axis=1))
    assert len(stamps) >= 40
    assert pos_err.max() <= 0.01 and rot_err_deg.max() <= 0.1


def test_dense_gt_is_exact_where_it_is_and_dense(walk):
    scores = score_dataset(walk["out"], walk["truth"])
    assert len(scores) == walk["summary"].written >= 4
    for s in scores:
        meta = read_meta(walk["out"], s.sid)
        assert meta.gt.density >= 0.10, s.sid
        assert s.depth_median_abs_m <= 0.002 and s.depth_outlier_rate <= 0.005, s
        assert s.disp_median_abs_px <= 0.05 and s.disp_over_1px_rate <= 0.005, s
        # the equirect keeps cam0's GT: at this resolution the crop and the stability mask leave a quarter
        # to a half of it (about 1.1 at full resolution, bench/bench_dense.py)
        assert s.disp_pixels >= 0.2 * s.depth_pixels, s
        # little GT on the sky beside silhouettes: at 240x150 one sample's roof line against the sky holds
        # 0.53 % (its pixels' centre rays pass over the roof its points lie on; the movers filter no
        # longer removes those static points, and 2 degrees of GT around them, as it did)
        assert s.depth_no_surface_rate <= 0.006, s
        assert s.mover_trail_rate <= 0.0001, s  # no GT on a mover's earlier positions (<= 0.01 %)


def test_without_the_free_space_test_movers_leave_trails(walk):
    """The same samples with the free-space test off: GT appears on the movers' earlier positions."""
    on = score_dataset(walk["out"], walk["truth"])
    out2 = walk["out"].parent / "no_free_space"
    params = SampleParams(dense=DenseParams(free_space=False))
    cfg = IngestConfig(
        rig=walk["truth"].path / "rig.yaml", out=out2, workers=1, every=16, gt="dense", sample=params
    )
    ingest([walk["bag"]], cfg)
    off = score_dataset(out2, walk["truth"])
    assert [s.sid for s in off] == [s.sid for s in on]
    assert all(read_meta(out2, s.sid).gt.removed_moving == 0 for s in off)
    worst_off = max(s.mover_trail_rate for s in off)
    assert worst_off > 0.005 and worst_off > 20 * max(max(s.mover_trail_rate for s in on), 1e-4)


def test_where_nothing_moves_the_free_space_test_removes_almost_nothing(still_walk):
    """No movers: at most 1 % of each sample's accumulated points are removed as movers (5-8 % when one
    ray's cell said so, its nearest return beyond a point by the margin) and the GT keeps >= 95 % of its
    density without the test (91-95 % then), every sample scored against the truth."""
    on = score_dataset(still_walk["on"], still_walk["truth"])
    off = score_dataset(still_walk["off"], still_walk["truth"])
    assert [s.sid for s in on] == [s.sid for s in off] and len(on) >= 4
    for s_on, s_off in zip(on, off, strict=True):
        gt_on, gt_off = read_meta(still_walk["on"], s_on.sid).gt, read_meta(still_walk["off"], s_on.sid).gt
        removed = gt_on.removed_moving / (gt_on.accumulated_points + gt_on.removed_moving)
        assert 0 < removed <= 0.01, (s_on.sid, removed)
        assert gt_on.density >= 0.95 * gt_off.density, (s_on.sid, gt_on.density, gt_off.density)
        assert s_on.depth_outlier_rate <= s_off.depth_outlier_rate + 1e-4, (s_on, s_off)


def test_free_space_filter_clears_what_two_references_saw_through():
    """A wall at 5 m seen by two slices; a stale point 3 m out in front of it goes, one behind stays,
    one where no ray went stays; and one slice alone is not enough (`free_min_slices` 2)."""
    rng = np.random.default_rng(0)

    def wall(n: int) -> np.ndarray:
        d = rng.normal(size=(n, 3))
        d[:, 0] = np.abs(d[:, 0]) + 2.0
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return d * (5.0 / d[:, 0])[:, None]  # the plane x = 5

    probe = np.array([[3.0, 0.1, 0.05], [6.0, 0.12, 0.06], [3.0, 0.0, 30.0]])  # before, behind, unseen
    pts = np.concatenate([wall(20_000), wall(20_000), probe])
    slice_id = np.r_[np.zeros(20_000, np.int64), np.ones(20_000, np.int64), np.full(3, 2, np.int64)]
    refs = [(0, np.zeros(3)), (1, np.zeros(3))]
    keep = free_space_filter(pts, slice_id, refs, DenseParams())
    assert keep[-3:].tolist() == [False, True, True] and keep[:-3].all()
    assert free_space_filter(pts, slice_id, refs[:1], DenseParams())[-3:].all()


def test_snapped_points_lie_on_pixel_rays_and_on_the_plane():
    from calibration.fisheye import DoubleSphere

    model = DoubleSphere(120.0, 120.0, 160.0, 100.0, -0.2, 0.6, 320, 200)
    rng = np.random.default_rng(1)
    xy = rng.uniform(-1.5, 1.5, size=(3000, 2))
    n = np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0])
    pts = np.c_[xy, (3.0 - xy @ n[:2]) / n[2]]  # the plane n . p = 3
    normals = Normals(np.tile(n, (len(pts), 1)), np.ones(len(pts), bool))
    snapped = snap_to_pixel_rays(model, pts, normals, 1, 0.2)
    assert len(snapped) > 3 * len(pts)
    np.testing.assert_allclose(snapped @ n, 3.0, atol=1e-9)
    uv, ok = model.project(snapped)
    assert ok.all()
    np.testing.assert_allclose(uv, np.round(uv), atol=1e-6)  # on pixel centres


def test_equirect_ranges_meet_the_planes_of_cam0s_gt_and_stop_at_steps_and_holes():
    """`rect_ranges`: an equirect ray gets the range where it meets the plane of its nearest cam0 GT pixel.

    cam0 sees a tilted wall at 3 m whose left part (x < -0.4 m on the wall)
    is a step nearer (a box face at 2 m, parallel to the wall) and a square
    hole without GT. The equirect is cam0 rotated 10 deg about x
    (p_cam0 = R_cam0_rect p_rect). Against the analytic ranges along its
    rays: exact on both planes, nothing whose nearest cam0 pixel is a hole or
    has a neighbour on the other side of the step.
    """
    from calibration.fisheye import DoubleSphere
    from calibration.spherical import Equirectangular
    from ingest.dataset.sparse import SparseImage
    from ingest.raster.view import pixel_rays
    from ingest.train.gt.dense_rect import ResampleParams, cam0_window, rect_lookup, rect_ranges

    model = DoubleSphere(120.0, 120.0, 160.0, 100.0, -0.2, 0.6, 320, 200)
    n = np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0])

    def on_box(rays: np.ndarray) -> np.ndarray:
        with np.errstate(divide="ignore", invalid="ignore"):
            box: np.ndarray = rays[:, 0] * (3.0 / (rays @ n)) < -0.4
        return box

    def ranges(rays: np.ndarray) -> np.ndarray:
        """Range along unit rays (cam0) to the wall (n . p = 3) or the box (n . p = 2); 0: none."""
        cos = rays @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(cos > 0.05, np.where(on_box(rays), 2.0, 3.0) / cos, 0.0)

    rays, ok = pixel_rays(model)
    rays64 = rays.reshape(-1, 3).astype(np.float64)
    r = np.where(ok.reshape(-1), ranges(rays64), 0.0).reshape(model.height, model.width)
    box = on_box(rays64).reshape(model.height, model.width)
    r[80:100, 200:220] = 0.0  # a hole without GT
    # a patch of isolated L-shaped triples (a pixel, its right and lower neighbours): three points
    # always lie on a plane, so none of them can check it and none gives a value
    lone = np.zeros_like(r, bool)
    lone[120:150:3, 60:90:3] = True
    triples = lone | np.roll(lone, 1, axis=1) | np.roll(lone, 1, axis=0)
    r[118:153, 58:93] = np.where(triples[118:153, 58:93], r[118:153, 58:93], 0.0)
    R_cam0_rect = Rotation.from_euler("x", 10, degrees=True).as_matrix()
    win = cam0_window(model, Equirectangular(256), R_cam0_rect)
    p = DenseParams()
    resample = ResampleParams(p.resample_flat_m, p.resample_flat_rel, p.resample_max_change, p.plane_min_cos)
    got = rect_ranges(model, win, R_cam0_rect, SparseImage.from_dense(r), resample)

    rays_rect, _ = win.unproject(win.pixel_grid())
    rays_cam0 = rays_rect.reshape(-1, 3) @ R_cam0_rect.T  # p_cam0 = R_cam0_rect p_rect, as rows
    np.testing.assert_allclose(rect_lookup(model, win, R_cam0_rect)[2], rays_cam0, atol=1e-6)
    want = ranges(rays_cam0)
    has = got > 0
    assert has.mean() > 0.2
    np.testing.assert_allclose(got[has], want[has], rtol=2e-6)
    uv, _ = model.project(rays_cam0)
    near = np.floor(np.nan_to_num(uv, nan=-9.0) + 0.5).astype(np.int64)
    inside = (near >= 0).all(axis=1) & (near[:, 0] < model.width) & (near[:, 1] < model.height)
    col, row = near[:, 0].clip(0, model.width - 1), near[:, 1].clip(0, model.height - 1)
    assert not (has & inside & (r[row, col] == 0)).any()  # a hole or no ray: nothing
    assert not (has & ~inside).any()
    in_patch = inside & (row >= 120) & (row < 151) & (col >= 60) & (col < 91) & (r[row, col] > 0)
    assert in_patch.sum() > 20 and not (has & in_patch).any()
    # a ray whose nearest cam0 pixel has a GT neighbour on the other side of the step gets nothing
    across = np.zeros_like(has)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            rr, cc = (row + dr).clip(0, model.height - 1), (col + dc).clip(0, model.width - 1)
            across |= (r[rr, cc] > 0) & (box[rr, cc] != box[row, col])
    assert across[inside & (r[row, col] > 0)].sum() > 20
    assert not (has & across).any()


def _box_and_wall(n_rays: int, noise_m: float, seed: int) -> np.ndarray:
    """Points cam0 sees of a box face 1.5 m in front of a wall at 3 m (z), ranges with Gaussian noise."""
    rng = np.random.default_rng(seed)
    rays = rng.normal(size=(n_rays, 3))
    rays[:, 2] = np.abs(rays[:, 2]) + 0.3
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    box = (np.abs(rays[:, 0]) < 0.3 * rays[:, 2]) & (np.abs(rays[:, 1]) < 0.3 * rays[:, 2])
    range_m = np.where(box, 1.5, 3.0) / rays[:, 2] + rng.normal(size=n_rays) * noise_m
    return rays * range_m[:, None]


def test_dense_disparity_is_the_analytic_disparity_of_the_equirect_rays():
    """End to end: dense GT's disparity against DESIGN.md's formula on the analytic ranges of its pixels' rays."""
    from calibration.fisheye import DoubleSphere
    from calibration.spherical import Equirectangular
    from calibration.stereo import depth_to_disparity

    model = DoubleSphere(120.0, 120.0, 160.0, 100.0, -0.2, 0.6, 320, 200)
    eq = Equirectangular(256).crop(20, 60, 200, 400)  # a crop: the window's offsets matter
    R_cam0_rect = Rotation.from_euler("x", 10, degrees=True).as_matrix()
    baseline_m = 0.12
    gt = dense_ground_truth(model, eq, R_cam0_rect, baseline_m, _box_and_wall(40_000, 0.0, 5), DenseParams())
    assert gt.disp_img.count > 3000
    rows, cols = np.divmod(gt.disp_img.pixel, eq.width)
    rays_rect, _ = eq.unproject(np.c_[cols, rows].astype(np.float64))
    d = rays_rect @ R_cam0_rect.T
    box = (np.abs(d[:, 0]) < 0.3 * d[:, 2]) & (np.abs(d[:, 1]) < 0.3 * d[:, 2])
    want = depth_to_disparity(np.where(box, 1.5, 3.0) / d[:, 2], eq.theta_of_row(rows), baseline_m, 256)
    err = np.abs(gt.disp_img.value - want)
    assert np.median(err) < 1e-4 and np.mean(err < 0.01) > 0.99, (np.median(err), np.mean(err < 0.01))


def test_noise_on_the_points_costs_disparity_no_more_than_depth():
    """Noisy ranges still give planes within the render's same-surface tolerance: the equirect keeps its
    share of the fisheye's GT (a millimetre tolerance kept 0.74 of it at 5 mm noise)."""
    from calibration.fisheye import DoubleSphere
    from calibration.spherical import Equirectangular

    model = DoubleSphere(120.0, 120.0, 160.0, 100.0, -0.2, 0.6, 320, 200)
    args = (model, Equirectangular(256), Rotation.from_euler("x", 10, degrees=True).as_matrix(), 0.12)
    share = []
    for noise_m in (0.0, 0.005):
        gt = dense_ground_truth(*args, _box_and_wall(40_000, noise_m, 5), DenseParams())
        share.append(gt.disp_img.count / gt.range_img.count)
    assert share[1] >= 0.9 * share[0], share


def test_no_points_no_gt():
    from calibration.fisheye import DoubleSphere
    from calibration.spherical import Equirectangular

    model = DoubleSphere(120.0, 120.0, 160.0, 100.0, -0.2, 0.6, 320, 200)
    gt = dense_ground_truth(model, Equirectangular(64), np.eye(3), 0.1, np.zeros((0, 3)), DenseParams())
    assert gt.range_img.count == 0 and gt.disp_img.count == 0


def test_dense_gt_does_not_depend_on_the_order_of_its_points():
    """Points are put in Z-order inside; any input order gives the same pixels and values."""
    from calibration.fisheye import DoubleSphere
    from calibration.spherical import Equirectangular

    model = DoubleSphere(120.0, 120.0, 160.0, 100.0, -0.2, 0.6, 320, 200)
    rng = np.random.default_rng(5)
    pts = _box_and_wall(40_000, 0.0, 5)
    args = (model, Equirectangular(256), np.eye(3), 0.1)
    a = dense_ground_truth(*args, pts, DenseParams())
    b = dense_ground_truth(*args, pts[rng.permutation(len(pts))], DenseParams())
    assert a.range_img.count > 5000 and a.disp_img.count > 5000
    for x, y in ((a.range_img, b.range_img), (a.disp_img, b.disp_img)):
        np.testing.assert_array_equal(x.pixel, y.pixel)
        np.testing.assert_allclose(x.value, y.value, rtol=0, atol=1e-6)


def test_every_equirect_pixel_with_range_is_disparity_gt_or_counted_unstable():
    """`DenseGt.unstable` counts the equirect pixels with a range that fail the stability mask.

    Which equirect pixels get a range does not depend on the baseline; which are stable does.
    With a 1 m baseline every pixel of the box (1.5 m) and wall (3 m) scene is stable: its
    disparities give each pixel's range (DESIGN.md's inverse formula). At 0.12 m, the numpy
    stability mask of those ranges says which pixels keep disparity and how many are
    unstable; at 1 micron none is stable and all of them are counted.
    """
    from calibration.fisheye import DoubleSphere
    from calibration.spherical import Equirectangular
    from calibration.stereo import disparity_stability_mask, disparity_to_depth

    model = DoubleSphere(120.0, 120.0, 160.0, 100.0, -0.2, 0.6, 320, 200)
    eq = Equirectangular(256)
    args = (model, eq, Rotation.from_euler("x", 10, degrees=True).as_matrix())
    pts = _box_and_wall(40_000, 0.0, 5)
    wide = dense_ground_truth(*args, 1.0, pts, DenseParams())
    assert wide.unstable == 0 and wide.disp_img.count > 10_000
    theta = eq.theta_of_row((wide.disp_img.pixel // eq.width).astype(np.float64))
    range_m = disparity_to_depth(wide.disp_img.value, theta, 1.0, 256)
    stable = disparity_stability_mask(theta, range_m, 0.12, 256, 0.5, 0.5)

    gt = dense_ground_truth(*args, 0.12, pts, DenseParams())
    assert gt.unstable == int((~stable).sum()) > 0
    np.testing.assert_array_equal(gt.disp_img.pixel, wide.disp_img.pixel[stable])
    tiny = dense_ground_truth(*args, 1e-6, pts, DenseParams())
    assert tiny.disp_img.count == 0 and tiny.unstable == wide.disp_img.count


def test_away_from_edges_drops_pixels_next_to_a_range_step_or_a_hole():
    """GT pixels within `edge_px` of a range step (`edge_band`: 5 cm / 3 %) or of a ray without surface go.

    A 12 x 20 rendering: 2 m in columns 0-9, 4 m in columns 10-19, and one hole (a ray with no
    surface) at row 6, column 3. The step's 3 x 3 neighbourhoods mark columns 9 and 10; 1 px
    around them drops columns 8-11. The hole drops the 3 x 3 block around it.
    """
    from ingest.raster.view import Rendering
    from ingest.train.gt.dense import away_from_edges

    shape = (12, 20)
    range_m = np.full(shape, 2.0, np.float32)
    range_m[:, 10:] = 4.0
    surface = np.ones(shape, bool)
    surface[6, 3] = False
    range_m[6, 3] = 0.0
    no = np.zeros(shape, bool)
    rend = Rendering(np.zeros((*shape, 3), np.uint8), range_m, surface, no, no, np.ones(shape, bool))
    want = np.ones(shape, bool)
    want[:, 8:12] = False
    want[5:8, 2:5] = False
    np.testing.assert_array_equal(away_from_edges(rend, 1).reshape(shape), want)
    np.testing.assert_array_equal(away_from_edges(rend, 0).reshape(shape), range_m > 0)


def test_a_plane_seen_edge_on_keeps_its_points():
    """Planar points whose own ray grazes their plane (|n . ray| < min_cos) are not snapped (their pixels'
    rays would meet the plane nowhere near them) but kept as they are: their pixels still hold a surface.
    A wall x = 1 seen from the origin at 84-87 deg from its normal, beside a facing one at z = 3."""
    from calibration.fisheye import DoubleSphere

    model = DoubleSphere(120.0, 120.0, 160.0, 100.0, -0.2, 0.6, 320, 200)
    rng = np.random.default_rng(2)
    z = rng.uniform(10.0, 19.0, 500)
    edge_on = np.c_[np.ones(500), rng.uniform(-0.5, 0.5, 500), z]  # cos to the normal: 1 / |p| < 0.1
    facing = np.c_[rng.uniform(-0.5, 0.5, (500, 2)), np.full(500, 3.0)]
    pts = np.concatenate([edge_on, facing])
    normal = np.r_[np.tile([1.0, 0.0, 0.0], (500, 1)), np.tile([0.0, 0.0, 1.0], (500, 1))]
    snapped = snap_to_pixel_rays(model, pts, Normals(normal, np.ones(1000, bool)), 1, 0.2)
    np.testing.assert_array_equal(snapped[:500], edge_on)  # first, as they were
    assert len(snapped) > 500 + 3 * 500 and np.allclose(snapped[500:, 2], 3.0)


def test_a_surfel_stops_at_the_outline_of_the_points_at_its_range_or_nearer():
    """A pole's surfels do not reach onto the wall beside it, where the pixel-centre rays miss the pole.

    Points on a 3 px grid of pixel positions (rows 80.5-119.5): a pole 3 m out at columns 151.3-163.3
    (its silhouette at 150.6 and 163.7), a wall 6 m out at columns 140.5-149.5 and 152.5-179.5 (behind
    the pole too: the LiDARs saw it past the pole). The pole's outermost points sit within a pixel of
    its silhouette, so their 3x3 surfels reached columns 150 and 164 (80 pole values on rays that meet
    the wall); there a square of `front_px` holds only wall points. Every pole pixel within a surfel of
    a pole point keeps its value (13 columns x 40 rows), and the wall's surfels still reach the pole
    (rows 81-120: the grid's pixels; a row beyond them lies outside the points' outline).
    """
    from calibration.fisheye import DoubleSphere

    model = DoubleSphere(120.0, 120.0, 160.0, 100.0, -0.2, 0.6, 320, 200)
    rows_px = np.arange(80.5, 120.0, 3.0)

    def grid(cols_px: np.ndarray, z_m: float) -> np.ndarray:
        uv = np.array([(u, v) for u in cols_px for v in rows_px])
        rays, _ = model.unproject(uv)
        return rays * (z_m / rays[:, 2])[:, None]

    pole = grid(np.arange(151.3, 164.0, 3.0), 3.0)
    wall = grid(np.r_[np.arange(140.5, 150.0, 3.0), np.arange(152.5, 180.0, 3.0)], 6.0)
    pts = np.concatenate([pole, wall])
    normals = Normals(np.tile([0.0, 0.0, 1.0], (len(pts), 1)), np.ones(len(pts), bool))
    snapped = snap_to_pixel_rays(model, pts, normals, 1, 0.2)
    uv, _ = model.project(snapped)
    col, row = np.round(uv).astype(int).T
    on_pole = np.abs(snapped[:, 2] - 3.0) < 1e-9
    assert int((on_pole & ((col <= 150) | (col >= 164))).sum()) == 0
    assert len(set(zip(row[on_pole], col[on_pole], strict=True))) == int(on_pole.sum()) == 13 * 40
    assert {(r, c) for r, c in zip(row[~on_pole], col[~on_pole], strict=True) if c in (150, 164)} == {
        (r, c) for r in range(81, 121) for c in (150, 164)
    }


def test_front_range_is_the_farthest_nearest_point_of_the_squares_around_a_pixel():
    """3 px squares on a 9 x 9 image: a point at 3 m at (4, 4), points at 6 m down column 7.

    (4, 4): every square around it holds the 3 m point. (4, 5): the square centred on (4, 6) holds only
    6 m points, so a 3 m value there lies in front of that square's points (beyond the 3 m outline).
    (2, 2): the squares around it that hold a point hold the 3 m one; the empty ones say nothing.
    (0, 0): none holds a point. (8, 8): squares reaching past the image's edge hold what lies inside it.
    """
    from ingest.train.gt.dense import front_range

    nearest = np.full((9, 9), np.inf, np.float32)
    nearest[4, 4] = 3.0
    nearest[:, 7] = 6.0
    front = front_range(nearest, 3)
    assert front.dtype == np.float32
    assert (front[4, 4], front[4, 5], front[2, 2], front[8, 8]) == (3.0, 6.0, 3.0, 6.0)
    assert front[0, 0] == -np.inf


def test_gt_behind_a_point_near_it_is_dropped():
    """Background GT within the occlusion margin of a nearer point goes: a pole point 2 m out on the optical
    axis (pixel 160, 100) in front of GT at 5 m drops the Euclidean disc of 3 px around it (0.02 rad at
    150 px/rad, 29 pixels), except a pixel of its own surface (2.04 m: within 5 cm) and one without GT."""
    from calibration.fisheye import DoubleSphere
    from ingest.train.gt.dense import behind_near

    model = DoubleSphere(120.0, 120.0, 160.0, 100.0, -0.2, 0.6, 320, 200)
    range_m = np.full((model.height, model.width), 5.0, np.float32)
    range_m[100, 162], range_m[101, 160] = 2.04, 0.0
    pole = np.array([[0.0, 0.0, 2.0]])
    rows, cols = np.mgrid[: model.height, : model.width]
    want = (cols - 160) ** 2 + (rows - 100) ** 2 <= 9
    want[100, 162] = want[101, 160] = False
    assert want.sum() == 29 - 2
    np.testing.assert_array_equal(behind_near(model, pole, range_m, 3), want)
    assert not behind_near(model, pole, range_m, 0).any()
    assert not behind_near(model, pole * 3.0, range_m, 3).any()  # 6 m: behind the GT, hides nothing


def test_near_movers_is_a_disc_of_the_margin_in_pixels():
    """The mover margin is an angle: 0.035 rad at this model's 150 px/rad is round(5.25) = 5 px.

    A removed point on the optical axis lands on pixel (160, 100); the mask is the Euclidean
    disc of radius 5 around it (81 pixels), at 0.02 rad one of radius 3 (29 pixels).
    """
    from calibration.fisheye import DoubleSphere
    from ingest.train.gt.dense import near_movers

    model = DoubleSphere(120.0, 120.0, 160.0, 100.0, -0.2, 0.6, 320, 200)
    rows, cols = np.mgrid[: model.height, : model.width]
    for radius_rad, radius_px, count in ((0.035, 5, 81), (0.02, 3, 29)):
        disc = (cols - 160) ** 2 + (rows - 100) ** 2 <= radius_px**2
        assert disc.sum() == count
        np.testing.assert_array_equal(near_movers(model, np.array([[0.0, 0.0, 5.0]]), radius_rad), disc)


def test_near_view_and_may_matter_reach_their_margins_on_every_side():
    """`near_view` keeps points within `margin_px` of the image (pixels -m .. W-1+m); `may_matter`
    widens the view margin (16 px) by the mover margin (0.035 rad x 150 px/rad = 5.25 px) and 1 px.

    Points 5 m out on the rays of pixels beyond the border of the 320 x 200 model, on each side.
    """
    from calibration.fisheye import DoubleSphere
    from ingest.train.gt.dense import VIEW_MARGIN_PX, may_matter, near_view

    model = DoubleSphere(120.0, 120.0, 160.0, 100.0, -0.2, 0.6, 320, 200)
    assert VIEW_MARGIN_PX == 16
    W, H = model.width, model.height

    def pts(beyond: float) -> np.ndarray:
        """Points `beyond` px outside the right, left, bottom and top borders."""
        uv = np.array([[W - 1 + beyond, 100.0], [-beyond, 100.0], [160.0, H - 1 + beyond], [160.0, -beyond]])
        rays, ok = model.unproject(uv)
        assert ok.all()
        return rays * 5.0

    for beyond, view, matter in ((10, True, True), (15.9, True, True), (16.1, False, True), (22.1, False, True),
                                 (22.4, False, False)):  # fmt: skip
        assert near_view(model, pts(beyond), 16).tolist() == [view] * 4, beyond
        assert may_matter(model, pts(beyond), DenseParams()).tolist() == [matter] * 4, beyond


def test_the_warm_up_runs_beside_the_trajectory_pass_and_its_error_stops_the_run(tmp_path, monkeypatch):
    import threading

    from ingest.errors import OutputError
    from ingest.train.run.sample_job import Geometry
    from sensorbox.sim.fixtures import fixture_bag
    from tests.paths import FIXTURES_DIR

    bag = fixture_bag("indoor_static_mcap", FIXTURES_DIR)
    threads = []

    def fail(self, params):
        threads.append(threading.current_thread().name)
        raise OutputError("no space left for the warm-up")

    monkeypatch.setattr(Geometry, "warm_dense", fail)
    cfg = IngestConfig(rig=Truth.load(bag).path / "rig.yaml", out=tmp_path, workers=1, every=10, gt="dense")
    with pytest.raises(OutputError, match="no space left for the warm-up"):
        ingest([bag], cfg)
    assert threads and threads[0].startswith("warm-up")  # not the main thread
    assert not list((tmp_path / "meta").glob("*.json"))  # no sample was written


def test_auto_widens_the_window_for_a_static_rig(tmp_path):
    from sensorbox.sim.fixtures import fixture_bag
    from tests.paths import FIXTURES_DIR

    bag = fixture_bag("indoor_static_mcap", FIXTURES_DIR)
    rig = Truth.load(bag).path / "rig.yaml"
    summary = ingest([bag], IngestConfig(rig=rig, out=tmp_path / "a", workers=1, every=10, gt="auto"))
    assert summary.method == "dense" and summary.decision.endswith("rig static: window +-1000 ms")
    assert summary.trajectory is not None and summary.trajectory.static
    assert read_meta(tmp_path / "a", "000000").gt.window_ms == 1000.0
    # a window the user gave (the CLI's --gt-window-ms 500) is kept, whatever its value
    given = IngestConfig(rig=rig, out=tmp_path / "b", workers=1, every=10, gt="auto", widen_static=False)
    summary = ingest([bag], given)
    assert summary.method == "dense" and "window" not in summary.decision
    assert read_meta(tmp_path / "b", "000000").gt.window_ms == 500.0


def test_free_space_clears_exactly_the_voxels_the_references_saw_through():
    # two slices at the origin see a wall at 10 m along +x (a 5 cm grid); a stale point at 5 m in front of
    # the wall (another slice) is cleared, one behind the wall (12 m) and one beside it (no ray there) stay
    from ingest.train.gt.dense import DenseParams, free_space_filter

    ys, zs = np.meshgrid(np.linspace(-1, 1, 41), np.linspace(-1, 1, 41))
    wall = np.c_[np.full(ys.size, 10.0), ys.ravel(), zs.ravel()]
    stale = np.array([[5.0, 0.0, 0.0], [12.0, 0.2, 0.1], [0.0, 5.0, 0.0]])
    pts = np.concatenate([wall, wall, stale])
    slice_id = np.r_[np.zeros(len(wall), np.int64), np.ones(len(wall), np.int64), np.full(3, 2, np.int64)]
    refs = [(0, np.zeros(3)), (1, np.zeros(3))]
    keep = free_space_filter(pts, slice_id, refs, DenseParams())
    assert keep[: 2 * len(wall)].all()
    assert keep[2 * len(wall) :].tolist() == [False, True, True]
    # the ray to the return beyond the wall (12 m) crosses it at (10, 0.167, 0.083): as a reference it
    # clears the one wall point within its footprint (0.035 m at 10 m), (10, 0.15, 0.10) 2.4 cm away,
    # not the 1-degree cell around it (17 cm at 10 m) the test once cleared
    keep2 = free_space_filter(pts, slice_id, [(2, np.zeros(3))], replace(DenseParams(), free_min_slices=1))
    for copy in (keep2[: len(wall)], keep2[len(wall) : 2 * len(wall)]):  # one voxel: both slices' points
        np.testing.assert_allclose(wall[~copy], [[10.0, 0.15, 0.1]], atol=1e-12)
    assert keep2[2 * len(wall) :].all()


def test_free_space_tests_only_the_voxels_asked_about():
    """A stale point outside the tested set is kept; the same point tested is cleared."""
    ys, zs = np.meshgrid(np.linspace(-1, 1, 41), np.linspace(-1, 1, 41))
    wall = np.c_[np.full(ys.size, 10.0), ys.ravel(), zs.ravel()]
    pts = np.concatenate([wall, wall, [[5.0, 0.0, 0.0], [5.0, 0.5, 0.0]]])
    slice_id = np.r_[np.zeros(len(wall), np.int64), np.ones(len(wall), np.int64), np.full(2, 2, np.int64)]
    test = np.zeros(len(pts), bool)
    test[-1] = True
    keep = free_space_filter(pts, slice_id, [(0, np.zeros(3)), (1, np.zeros(3))], DenseParams(), test)
    assert keep[:-2].all() and keep[-2:].tolist() == [True, False]


def _trajectory_without_lidar(
    walk: dict[str, Any], lo_ns: int, hi_ns: int, prm: OdometryParams | None = None
) -> RigTrajectory:
    """The walk's trajectory pass with both LiDARs' messages logged in [start + lo_ns, start + hi_ns) lost."""
    truth = walk["truth"]
    rig = read_rig(truth.path / "rig.yaml")
    with open_bags([walk["bag"]]) as bags:
        topics = resolve_topics(rig, bags.topics(), str(walk["bag"]))
        gyro = read_gyro(bags, topics.imu, topics.R_cam0_imu)
        lost = _WithoutLidar(bags, topics.lidars, truth.start_ns + lo_ns, truth.start_ns + hi_ns)
        return trajectory_pass(lost, topics.lidars, rig, gyro, 0.3, prm)  # type: ignore[arg-type]


class _WithoutLidar:
    """A bag set whose LiDAR messages logged in [lo_ns, hi_ns) are gone (a dropped sweep per LiDAR)."""

    def __init__(self, bags: BagSet, lidars: dict[str, str], lo_ns: int, hi_ns: int) -> None:
        self.bags, self.lidars, self.lo_ns, self.hi_ns = bags, lidars, lo_ns, hi_ns
        self.label = bags.label

    def messages(self, topics: list[str], progress: Progress | None = None) -> Iterator[RawMessage]:
        for msg in self.bags.messages(topics=topics, progress=progress):
            if not (msg.topic in self.lidars and self.lo_ns <= msg.log_ns < self.hi_ns):
                yield msg


def test_a_lost_sweep_leaves_a_gap_in_the_trajectory_not_a_wild_knot(walk):
    """100 ms of both LiDARs lost mid-chunk: a knot after a thin interval is carried by prediction
    (residual NaN: a gap that `auto` and dense GT see) instead of being solved on a sliver of points,
    which placed it 0.88 m off with a normal residual; every registered knot stays within 1 cm."""
    truth = walk["truth"]
    traj = _trajectory_without_lidar(walk, 1_050_000_000, 1_150_000_000)
    T_true = truth.T_world_cam0(traj.stamps_ns)
    T_true = np.linalg.inv(T_true[0]) @ T_true
    err_m = np.linalg.norm(T_true[:, :3, 3] - traj.p_world_cam0, axis=1)
    measured = np.isfinite(traj.residual_m)
    gap_s = (traj.stamps_ns[~measured] - truth.start_ns) / 1e9
    assert len(gap_s) >= 1 and ((gap_s > 1.0) & (gap_s < 1.25)).all(), gap_s
    assert err_m[measured].max() <= 0.01
    assert traj.measured_span(truth.start_ns + 1_100_000_000) is None
    first, last = traj.measured_span(truth.start_ns + 500_000_000) or (0, 0)
    assert first == traj.stamps_ns[0] and last < truth.start_ns + 1_100_000_000


@pytest.mark.parametrize(
    ("rule", "prm"),
    [
        ("the jump gate alone", OdometryParams(min_segment_points=1)),
        ("neither rule", OdometryParams(min_segment_points=1, max_jump_m=math.inf)),
    ],
)
def test_the_jump_gate_alone_keeps_the_wild_knot_out(walk, rule, prm):
    """The lost sweep of the test above with the support rule off: the knot solved on the sliver lands
    more than `max_jump_m` from its prediction and is carried instead; without the gate it stays."""
    truth = walk["truth"]
    traj = _trajectory_without_lidar(walk, 1_050_000_000, 1_150_000_000, prm)
    T_true = truth.T_world_cam0(traj.stamps_ns)
    T_true = np.linalg.inv(T_true[0]) @ T_true
    err_m = np.linalg.norm(T_true[:, :3, 3] - traj.p_world_cam0, axis=1)
    measured = np.isfinite(traj.residual_m)
    if rule == "neither rule":
        assert err_m[measured].max() > 0.1
    else:
        assert not measured.all() and err_m[measured].max() <= 0.01


def test_a_stretch_too_short_to_solve_its_start_again_is_not_registered(walk):
    """After a gap longer than the map's horizon the odometry starts afresh; a stretch that ends before
    its start is solved again keeps the constant-velocity guess (5.5 mm off over 0.25 s on a 0.9 s
    stretch, against 1.6 mm elsewhere): its knots are gaps, so dense GT does not build on them. Scaled to
    CI: a 0.2 s horizon, the start solved again after 0.5 s, and 0.4 s of LiDAR after a 1 s gap."""
    truth = walk["truth"]
    traj = _trajectory_without_lidar(
        walk, 800_000_000, 1_800_000_000, OdometryParams(map_horizon_s=0.2, refine_start_s=0.5)
    )
    assert traj.stamps_ns[-1] > truth.start_ns + 2_000_000_000  # the stretch after the gap has knots
    assert traj.measured_span(truth.start_ns + 400_000_000) is not None  # the first, refined, stays
    late = traj.stamps_ns > truth.start_ns + 1_800_000_000
    assert not np.isfinite(traj.residual_m[late]).any()


def test_a_start_followed_by_a_long_gap_is_left_unrefined_not_a_crash(walk):
    """0.2 s of LiDAR, then none for a second: the start is due to be solved again once the chain spans
    `refine_start_s`, but no later point exists to solve it against (an empty map raised IndexError).
    The gap is carried by prediction and the odometry goes on after it."""
    truth = walk["truth"]
    traj = _trajectory_without_lidar(
        walk, 200_000_000, 1_200_000_000, OdometryParams(map_horizon_s=0.5, refine_start_s=0.5)
    )
    assert traj.measured_span(truth.start_ns + 700_000_000) is None
    after = traj.measured_span(truth.start_ns + 1_800_000_000)
    assert after is not None and after[0] > truth.start_ns + 1_000_000_000
    assert _worst_relative_error_m(traj, truth, 5) <= 0.005


def _worst_relative_error_m(traj: RigTrajectory, truth: Truth, steps: int) -> float:
    """Largest error of the motion over `steps` knots, between knots of one registered stretch."""
    T_true = truth.T_world_cam0(traj.stamps_ns)
    worst = 0.0
    for k in range(len(traj.stamps_ns) - steps):
        span = traj.measured_span(int(traj.stamps_ns[k]))
        if span is None or traj.stamps_ns[k + steps] > span[1]:
            continue
        T_est = np.tile(np.eye(4), (2, 1, 1))
        T_est[:, :3, :3], T_est[:, :3, 3] = (
            traj.R_world_cam0[[k, k + steps]],
            traj.p_world_cam0[[k, k + steps]],
        )
        est = np.linalg.inv(T_est[0]) @ T_est[1]
        true = np.linalg.inv(T_true[k]) @ T_true[k + steps]
        worst = max(worst, float(np.linalg.norm(est[:3, 3] - true[:3, 3])))
    return worst


def test_after_a_gap_longer_than_the_map_horizon_the_odometry_starts_again(walk):
    """Registering against the map from before a long gap placed the next knots up to 0.7 m apart (a 6 s
    gap on a 10 s walk); the odometry starts afresh instead. Scaled to CI: a 0.7 s gap against a 0.2 s
    horizon, where registering against the old map put 9 mm into the motion over 0.25 s (1.6 mm now)."""
    truth = walk["truth"]
    traj = _trajectory_without_lidar(
        walk, 800_000_000, 1_500_000_000, OdometryParams(map_horizon_s=0.2, refine_start_s=0.5)
    )
    assert traj.measured_span(truth.start_ns + 1_100_000_000) is None
    before = traj.measured_span(truth.start_ns + 400_000_000)
    after = traj.measured_span(truth.start_ns + 1_900_000_000)
    assert before is not None and after is not None and before[1] < after[0]
    assert _worst_relative_error_m(traj, truth, 5) <= 0.005


_WARM_UP_CHECK = """
import sys
from pathlib import Path

from importlib import import_module

from numba.core.registry import CPUDispatcher

from calibration.rig import read_rig
from ingest.train.run.pipeline import ingest
from ingest.train.run.settings import IngestConfig
from ingest.train.run.sample_job import Geometry, SampleParams

MODULES = [import_module(name) for name in ("calibration.kernels", "ingest.raster.kernels",
           "ingest.raster.pixel_kernels", "ingest.raster.point_kernels", "ingest.train.gt.free_space")]


def signatures():
    return {f"{m.__name__}.{name}": {str(s) for s in obj.signatures}
            for m in MODULES for name, obj in vars(m).items() if isinstance(obj, CPUDispatcher)}


bag, rig, out = (Path(a) for a in sys.argv[1:4])
geometry = Geometry.from_rig(read_rig(rig))
geometry.warm_maps()
geometry.warm_dense(SampleParams().dense)
warmed = signatures()
summary = ingest([bag], IngestConfig(rig=rig, out=out, workers=1, every=20, gt="dense"))
assert summary.written >= 3, summary
new = {k: sorted(v - warmed.get(k, set())) for k, v in signatures().items() if v - warmed.get(k, set())}
print(f"kernels: {sum(map(len, warmed.values()))} signatures warmed, {summary.written} samples; new: {new}")
sys.exit(1 if new else 0)
"""


def test_the_warm_up_builds_every_kernel_a_dense_sample_runs(walk, tmp_path):
    """Workers fork after `Geometry.warm_dense`: a kernel signature it misses is compiled in every worker.

    A fresh interpreter warms up, then ingests the walk in-process; the
    samples must add no compiled signature (from numba's cache or new).
    """
    import subprocess
    import sys

    args = [str(walk["bag"]), str(walk["truth"].path / "rig.yaml"), str(tmp_path / "out")]
    res = subprocess.run([sys.executable, "-c", _WARM_UP_CHECK, *args], capture_output=True, text=True,
                         cwd=Path(__file__).resolve().parents[2], check=False, timeout=600)  # fmt: skip
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-3000:]
    assert "new: {}" in res.stdout
