"""Odometry pieces against closed-form answers: the knot chain, its gyro shape, TUM output, failures."""

import math
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calibration.linalg3 import rotvec_to_matrix
from ingest.bags.decode import Sweep
from ingest.errors import OdometryError
from ingest.train.trajectory import estimate as trajectory
from ingest.train.trajectory.clouds import integrate_gyro
from ingest.train.trajectory.estimate import AUTO_MAX_RESIDUAL_MM, TrajectorySummary, choose_method, summarize
from ingest.train.trajectory.local_map import LocalMap, OdometryParams, voxel_subsample
from ingest.train.trajectory.odometry import Odometry, _Chain, _joined, _register_chunk
from ingest.train.trajectory.rig_trajectory import RigTrajectory, still


def _constant_rate_gyro(rate_rad_s, seconds=1.0, hz=200):
    t = np.arange(int(seconds * hz) + 1, dtype=np.int64) * (1_000_000_000 // hz)
    return integrate_gyro(t, np.tile(rate_rad_s, (len(t), 1)), np.eye(3))


def test_gyro_between_matches_the_integrated_track():
    track = _constant_rate_gyro([0.3, -0.2, 0.5])
    t = np.array([0, 12_345_678, 500_000_000, 987_654_321], np.int64)
    want = np.matmul(np.swapaxes(track.at(np.zeros(4, np.int64)), 1, 2), track.at(t))  # G(0)^T G(t)
    np.testing.assert_allclose(track.between(np.zeros(4, np.int64), t), want, atol=1e-12)
    # constant rate: the rotation is exp(w t) exactly
    np.testing.assert_allclose(
        track.at(t[2:3])[0], rotvec_to_matrix(np.array([[0.15, -0.1, 0.25]]))[0], atol=1e-9
    )


def test_gyro_track_covers_both_ends_of_its_span():
    """Points stamped exactly at the first or the last IMU sample have a known rotation: both ends are
    inside the integrated span, a nanosecond beyond either is not."""
    track = integrate_gyro(np.array([0, 10], np.int64), np.zeros((2, 3)), np.eye(3))
    t = np.array([-1, 0, 5, 10, 11], np.int64)
    assert track.covers(t).tolist() == [False, True, True, True, False]


def test_chain_is_exact_at_knots_and_linear_in_position_between():
    stamps = np.array([0, 50_000_000, 100_000_000], np.int64)
    R = Rotation.from_rotvec([[0, 0, 0], [0, 0, 0.1], [0, 0, 0.2]]).as_matrix()
    p = np.array([[0.0, 0, 0], [0.05, 0, 0], [0.1, 0.02, 0]])
    traj = RigTrajectory(stamps, R, p, np.zeros(3))
    Rk, pk = traj.pose(stamps)
    np.testing.assert_allclose(Rk, R, atol=1e-12)
    np.testing.assert_allclose(pk, p, atol=1e-12)
    Rm, pm = traj.pose(np.array([75_000_000]))
    np.testing.assert_allclose(pm[0], [0.075, 0.01, 0.0], atol=1e-12)
    np.testing.assert_allclose(Rotation.from_matrix(Rm[0]).as_rotvec(), [0, 0, 0.15], atol=1e-12)  # slerp


def test_chain_follows_the_gyro_between_knots():
    """Knots placed on a constant-rate rotation: the gyro's shape makes every time between them exact."""
    track = _constant_rate_gyro([0.0, 0.0, 2.0])  # 2 rad/s yaw: 0.1 rad per 50 ms knot
    stamps = np.arange(0, 500_000_001, 50_000_000, dtype=np.int64)
    R = rotvec_to_matrix(np.outer(stamps / 1e9, [0.0, 0.0, 2.0]))
    traj = RigTrajectory(stamps, R, np.zeros((len(stamps), 3)), np.zeros(len(stamps)), track)
    t = np.array([13_000_000, 233_333_333, 499_000_000], np.int64)
    np.testing.assert_allclose(traj.pose(t)[0], rotvec_to_matrix(np.outer(t / 1e9, [0, 0, 2.0])), atol=1e-9)


def test_to_frame_round_trip():
    stamps = np.array([0, 100_000_000], np.int64)
    R = Rotation.from_rotvec([[0, 0, 0], [0.1, -0.2, 0.3]]).as_matrix()
    traj = RigTrajectory(stamps, R, np.array([[0.0, 0, 0], [0.3, -0.1, 0.05]]), np.zeros(2))
    pts = np.random.default_rng(0).normal(size=(20, 3)) * 5
    t = np.full(20, 30_000_000, np.int64)
    there = traj.to_frame(pts, t, 80_000_000)
    back = traj.to_frame(there, np.full(20, 80_000_000, np.int64), 30_000_000)
    np.testing.assert_allclose(back, pts, atol=1e-12)


def test_tum_file_holds_every_knot(tmp_path):
    stamps = np.array([1_700_000_000_000_000_000, 1_700_000_000_050_000_000], np.int64)
    R = Rotation.from_rotvec([[0, 0, 0], [0, 0, 0.1]]).as_matrix()
    traj = RigTrajectory(stamps, R, np.array([[0.0, 0, 0], [0.06, 0, 0]]), np.array([0.0, 0.001]))
    traj.write_tum(tmp_path / "t.tum")
    rows = [
        line.split() for line in (tmp_path / "t.tum").read_text().splitlines() if not line.startswith("#")
    ]
    assert [r[0] for r in rows] == ["1700000000.000000000", "1700000000.050000000"]
    np.testing.assert_allclose(
        [float(v) for v in rows[1][1:]], [0.06, 0, 0, *Rotation.from_matrix(R[1]).as_quat()]
    )
    assert not (tmp_path / "t.tum.partial").exists()


def test_voxel_subsample_keeps_one_point_per_voxel_in_order():
    pts = np.array([[0.01, 0, 0], [0.02, 0, 0], [0.31, 0, 0], [-0.01, 0, 0]])
    assert voxel_subsample(pts, 0.1).tolist() == [0, 2, 3]


def test_too_little_lidar_is_an_odometry_error():
    odo = Odometry(None)
    odo.add(
        np.random.default_rng(1).normal(size=(500, 3)) * 5, np.linspace(0, 100_000_000, 500).astype(np.int64)
    )
    with pytest.raises(OdometryError, match="less than 200 ms"):
        odo.result()


def _summary(median_mm, gaps=0):
    return TrajectorySummary(knots=40, span_s=2.0, residual_median_mm=median_mm, residual_p95_mm=median_mm * 2,
                             gaps=gaps, seconds=1.0, file="t.tum")  # fmt: skip


def test_still_needs_both_slow_travel_and_slow_turning():
    """A rig stood still only when it neither moved (< 5 cm/s) nor turned (< 2 deg/s): walking at 1 m/s
    without turning, or turning on the spot, is motion."""
    assert still(0.0, 0.0) and still(0.049, 1.9)
    assert not still(1.0, 0.0)
    assert not still(0.0, 10.0)
    assert not still(0.05, 0.0) and not still(0.0, 2.0)  # the limits themselves are motion


def test_a_short_recording_of_a_rig_that_stood_still_gets_dense_gt():
    """Under `refine_start_s` the start's knots are a constant-velocity guess, which is exact for a rig
    that stood still: auto keeps dense GT for it, but not for a short recording of a moving rig."""
    stood = TrajectorySummary(knots=11, span_s=0.5, residual_median_mm=1.0, residual_p95_mm=2.0, gaps=0,
                              seconds=1.0, file="t.tum", max_speed_mps=0.0, max_rate_deg_s=0.0)  # fmt: skip
    walked = replace(stood, max_speed_mps=1.0)
    assert choose_method("auto", stood)[0] == "dense"
    method, why = choose_method("auto", walked)
    assert method == "sparse" and "spans 0.50 s" in why


def test_auto_chooses_dense_only_with_a_sound_trajectory():
    assert choose_method("sparse", _summary(1.0)) == ("sparse", "asked")
    assert choose_method("dense", None) == ("dense", "asked")
    assert choose_method("auto", _summary(1.0))[0] == "dense"
    method, why = choose_method("auto", _summary(AUTO_MAX_RESIDUAL_MM * 2))
    assert method == "sparse" and "residual" in why
    method, why = choose_method("auto", _summary(1.0, gaps=3))  # the frames in the gaps get sparse GT
    assert method == "dense" and "3 in LiDAR gaps: frames there get sparse GT" in why
    method, why = choose_method("auto", None, "odometry: less than 200 ms of LiDAR points")
    assert method == "sparse" and "200 ms" in why


def test_summary_measures_speed_and_turn_rate(tmp_path):
    from ingest.train.trajectory.estimate import summarize

    stamps = np.arange(0, 500_000_001, 50_000_000, dtype=np.int64)
    R = rotvec_to_matrix(np.outer(stamps / 1e9, [0.0, 0.0, np.radians(30.0)]))  # 30 deg/s yaw
    p = np.outer(stamps / 1e9, [1.2, 0.0, 0.0])  # 1.2 m/s
    s = summarize(RigTrajectory(stamps, R, p, np.full(len(stamps), 0.002)), 1.0, tmp_path / "t.tum")
    assert s.max_speed_mps == pytest.approx(1.2) and s.max_rate_deg_s == pytest.approx(30.0)
    assert s.residual_median_mm == pytest.approx(2.0) and not s.static
    still = summarize(
        RigTrajectory(stamps, np.tile(np.eye(3), (len(stamps), 1, 1)), 0 * p, np.zeros(len(stamps))),
        1.0,
        tmp_path,
    )
    assert still.static


def test_summary_leaves_out_the_first_knots_zero_residual(tmp_path):
    """The first knot's residual is 0 by definition (it defines the world), not a measurement: the median
    and 95th percentile are of the later knots only, [2, 4] mm: 3.0 and 2 + 0.95 * 2 = 3.9 mm."""
    stamps = np.array([0, 50_000_000, 100_000_000], np.int64)
    traj = RigTrajectory(
        stamps, np.tile(np.eye(3), (3, 1, 1)), np.zeros((3, 3)), np.array([0.0, 0.002, 0.004])
    )
    s = summarize(traj, 1.0, tmp_path / "t.tum")
    assert s.residual_median_mm == pytest.approx(3.0) and s.residual_p95_mm == pytest.approx(3.9)
    assert s.gaps == 0 and s.knots == 3 and s.span_s == pytest.approx(0.1)


def test_peak_motion_is_the_fastest_knot_interval_not_the_average():
    """Knots at x = 0, 0.1 and 0.105 m, 50 ms apart: 2.0 m/s, then 0.1 m/s; the peak is 2.0 m/s (the
    mean, 1.05 m/s, would hide the fast interval), so the rig did not stand still."""
    stamps = np.array([0, 50_000_000, 100_000_000], np.int64)
    p = np.array([[0.0, 0, 0], [0.1, 0, 0], [0.105, 0, 0]])
    traj = RigTrajectory(stamps, np.tile(np.eye(3), (3, 1, 1)), p, np.zeros(3))
    speed, rate = traj.peak_motion()
    assert speed == pytest.approx(2.0) and rate == 0.0
    assert not traj.stood_still()


def test_speed_is_metres_per_second_over_the_knot_interval_of_a_time():
    """Knots at x = 0, 0.06 and 0.12 m, 50 ms apart: 0.06 m / 0.05 s = 1.2 m/s in either interval."""
    stamps = np.array([0, 50_000_000, 100_000_000], np.int64)
    p = np.array([[0.0, 0, 0], [0.06, 0, 0], [0.12, 0, 0]])
    traj = RigTrajectory(stamps, np.tile(np.eye(3), (3, 1, 1)), p, np.zeros(3))
    assert traj.speed_mps(25_000_000) == pytest.approx(1.2)
    assert traj.speed_mps(75_000_000) == pytest.approx(1.2)


def test_a_chain_after_a_long_gap_starts_with_an_unregistered_knot():
    """Chains joined across a gap: the later chain's world is placed at the earlier chain's last knot (a
    prediction), so its first knot's residual is NaN (a gap knot), its later residuals are kept."""
    yaw90 = Rotation.from_rotvec([0, 0, np.pi / 2]).as_matrix()
    first = _Chain([0, 50, 100], [np.eye(3), np.eye(3), yaw90], [np.zeros(3), np.zeros(3), np.array([1.0, 0, 0])],
                   [0.0, 0.001, 0.001])  # fmt: skip
    second = _Chain([300, 350], [np.eye(3)] * 2, [np.zeros(3), np.array([0.1, 0, 0])], [0.0, 0.002])
    out = _joined([first, second])
    assert out.stamps == [0, 50, 100, 300, 350]
    np.testing.assert_array_equal(out.residual, [0.0, 0.001, 0.001, math.nan, 0.002])
    np.testing.assert_allclose(out.p[3:], [[1.0, 0, 0], [1.0, 0.1, 0]], atol=1e-15)  # x turned onto y


def test_a_chunk_without_points_carries_the_knots_at_the_last_velocity():
    """Knots moving 1 m/s along x (0, 5, 10 cm at 50 ms steps) and a chunk with no points: the two new
    knots are the constant-velocity prediction, 15 and 20 cm, and are gap knots (residual NaN)."""
    prm = OdometryParams()
    chain = _Chain([0, 50_000_000, 100_000_000], [np.eye(3)] * 3,
                   [np.array([0.0, 0, 0]), np.array([0.05, 0, 0]), np.array([0.1, 0, 0])],
                   [0.0, 0.001, 0.001])  # fmt: skip
    _register_chunk(chain, np.zeros((0, 3)), np.zeros(0, np.int64), LocalMap(prm), None, prm)
    assert chain.stamps[3:] == [150_000_000, 200_000_000]
    np.testing.assert_allclose(chain.p[3:], [[0.15, 0, 0], [0.2, 0, 0]], atol=1e-12)
    np.testing.assert_allclose(chain.R[3:], [np.eye(3)] * 2)
    assert all(math.isnan(r) for r in chain.residual[3:])


class _OdometrySpy:
    """Stands in for `Odometry` in `trajectory_pass`: records what it is told to register."""

    last: "_OdometrySpy"

    def __init__(self, gyro, params=None, start_ns=None):
        self.added: list[int] = []
        self.advanced: list[int] = []
        _OdometrySpy.last = self

    def add(self, pts, stamps):
        self.added.append(len(stamps))

    def advance(self, complete_ns):
        self.advanced.append(complete_ns)

    def result(self):
        return None


def test_odometry_registers_only_up_to_where_every_lidar_has_delivered(monkeypatch):
    """Sweeps of two LiDARs ending at 100 and 150 ms: chunks are complete only to 100 ms, the slower
    LiDAR's end (its points up to 150 ms have not arrived yet); before the second LiDAR has spoken,
    nothing is complete."""
    monkeypatch.setattr(trajectory, "Odometry", _OdometrySpy)

    def msg(topic, end_ns):
        t = np.linspace(end_ns - 50_000_000, end_ns, 10).astype(np.int64)
        sweep = Sweep(end_ns, topic, np.full((10, 3), 5.0), t)
        return SimpleNamespace(topic=topic, log_ns=end_ns, decoded=lambda where: sweep)

    msgs = [msg("/a", 150_000_000), msg("/b", 100_000_000)]
    bags = SimpleNamespace(label="bag", messages=lambda topics, progress: iter(msgs))
    rig = SimpleNamespace(lidar=lambda name: SimpleNamespace(T_cam0_lidar=np.eye(4)))
    trajectory.trajectory_pass(bags, {"/a": "a", "/b": "b"}, rig, None, 0.3)  # type: ignore[arg-type]  # stand-ins
    assert _OdometrySpy.last.added == [10, 10]
    assert _OdometrySpy.last.advanced == [-(2**62), 100_000_000]


def _random_knots(rng: np.random.Generator, K: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """K knots 50 ms apart: stamps (ns), a random walk of rotations (about 3 deg a knot) and of positions."""
    stamps = np.arange(K, dtype=np.int64) * 50_000_000
    R = Rotation.from_rotvec(np.cumsum(rng.normal(0, 0.05, (K, 3)), 0)).as_matrix()
    p = np.cumsum(rng.normal(0, 0.06, (K, 3)), 0)
    return stamps, R, p


def test_many_points_take_the_pose_grid_within_a_tenth_of_a_millimetre():
    # knots every 50 ms with random turns, a gyro at 200 Hz turning up to ~60 deg/s: the grid's linear
    # blend between exact poses every 0.5 ms (knots are nodes) moves a point 10 m away by < 10 um
    rng = np.random.default_rng(0)
    K = 41
    stamps, R, p = _random_knots(rng, K)
    ti = np.arange(0, 2_000_000_001, 5_000_000, dtype=np.int64)
    gyro = integrate_gyro(ti, np.c_[np.sin(ti / 2e8), np.cos(ti / 3e8), np.sin(ti / 1e8)], np.eye(3))
    traj = RigTrajectory(stamps, R, p, np.zeros(K), gyro)
    t = np.sort(rng.integers(0, 2_000_000_000, 50_000))
    x = rng.normal(size=(len(t), 3))
    x *= 10.0 / np.linalg.norm(x, axis=1)[:, None]
    R_grid, p_grid = traj.pose(t)
    R_exact, p_exact = traj._pose_exact(t)
    err = np.linalg.norm(np.einsum("nij,nj->ni", R_grid - R_exact, x) + p_grid - p_exact, axis=1)
    assert 0 < err.max() < 1e-5
    np.testing.assert_allclose(traj.pose(t[:3])[0], R_exact[:3], atol=1e-12)  # few points: exact


def test_node_fractions_are_the_searchsorted_formula_in_any_order():
    """The compiled node walk gives each time the node at or before it and its fraction to the next, as
    searchsorted does: uneven nodes, times on nodes, clamped beyond the ends, sorted or shuffled."""
    from ingest.train.trajectory.odometry_kernels import node_fractions

    rng = np.random.default_rng(5)
    nodes = np.unique(rng.integers(0, 10**9, 3000)).astype(np.int64)
    t = np.r_[rng.integers(-(10**8), 11 * 10**8, 200_000), nodes, nodes - 1, nodes + 1]
    for times in (np.sort(t), rng.permutation(t)):
        a, g = node_fractions(times, nodes)
        tc = np.clip(times, nodes[0], nodes[-1])
        want = np.clip(np.searchsorted(nodes, tc, side="right") - 1, 0, len(nodes) - 2)
        assert np.array_equal(a, want)
        assert np.array_equal(g, (tc - nodes[want]) / (nodes[want + 1] - nodes[want]))
        assert g.min() == 0.0 and g.max() == 1.0  # on a node; at the last node (the last interval's end)


def test_points_moved_to_a_frame_time_match_the_exact_poses():
    """`to_frame` folds the reference pose into the grid's nodes: a point lands where the exact poses put it."""
    rng = np.random.default_rng(6)
    K = 21
    stamps, R, p = _random_knots(rng, K)
    traj = RigTrajectory(stamps, R, p, np.zeros(K))
    t = rng.integers(0, stamps[-1], 100_000)
    x = rng.normal(size=(len(t), 3)) * 10.0
    t_ref = 512_345_678
    R_ref, p_ref = traj._pose_exact(np.array([t_ref]))
    for n in (len(t), 5):  # the node grid, and the exact poses of a few points
        R_t, p_t = traj._pose_exact(t[:n])
        want = (np.einsum("nij,nj->ni", R_t, x[:n]) + p_t - p_ref[0]) @ R_ref[0]
        err = np.linalg.norm(traj.to_frame(x[:n], t[:n], t_ref) - want, axis=1)
        assert err.max() < 1e-5
    np.testing.assert_allclose(traj.to_frame(x[:5], np.full(5, t_ref), t_ref), x[:5], atol=1e-12)


def test_measured_span_is_the_stretch_of_registered_knots_around_a_time():
    """Knots 3 and 4 are gaps (NaN): the stretches are knots 0..2 and 5..7; a time beside a gap knot, or
    outside the knots, has none; a time exactly on knot 2 belongs to the stretch before it."""
    stamps = np.arange(8, dtype=np.int64) * 50
    residual = np.array([0.0, 1e-3, 1e-3, np.nan, np.nan, 1e-3, 1e-3, 1e-3])
    traj = RigTrajectory(stamps, np.tile(np.eye(3), (8, 1, 1)), np.zeros((8, 3)), residual)
    assert [traj.measured_span(t) for t in (0, 60, 100)] == [(0, 100)] * 3
    assert [traj.measured_span(t) for t in (101, 150, 200, 249)] == [None] * 4
    assert [traj.measured_span(t) for t in (250, 300, 350)] == [(250, 350)] * 3
    assert traj.measured_span(-1) is None and traj.measured_span(351) is None


def test_motion_from_is_the_largest_turn_and_shift_over_the_interval():
    """A 2 rad/s yaw and 1 m/s along x: from t = 0.2 s, the interval [0.1, 0.5] s holds a 0.6 rad turn and
    a 0.3 m shift (at 0.5 s); a yaw that turns back within a knot interval still counts its peak."""
    track = _constant_rate_gyro([0.0, 0.0, 2.0])
    stamps = np.arange(0, 1_000_000_001, 50_000_000, dtype=np.int64)
    R = rotvec_to_matrix(np.outer(stamps / 1e9, [0.0, 0.0, 2.0]))
    p = np.c_[stamps / 1e9, np.zeros((len(stamps), 2))]
    traj = RigTrajectory(stamps, R, p, np.zeros(len(stamps)), track)
    turn, shift = traj.motion_from(200_000_000, 100_000_000, 500_000_000)
    assert turn == pytest.approx(0.6, abs=1e-9) and shift == pytest.approx(0.3, abs=1e-12)
    # knots 0 and 100 ms both at yaw 0, the gyro turning +1 rad/s and back in between: a 0.05 rad peak
    t = np.arange(0, 100_000_001, 1_000_000, dtype=np.int64)
    rate = np.where(t < 50_000_000, 1.0, -1.0)
    wobble = integrate_gyro(t, np.c_[np.zeros((len(t), 2)), rate], np.eye(3))
    flat = RigTrajectory(t[[0, -1]], np.tile(np.eye(3), (2, 1, 1)), np.zeros((2, 3)), np.zeros(2), wobble)
    turn, shift = flat.motion_from(0, 0, 100_000_000)
    assert turn == pytest.approx(0.05, abs=2e-3) and shift == 0.0


def test_the_surveys_imu_readings_integrate_to_the_gyro_read_from_the_bags():
    """The run's first pass keeps the IMU's readings, so the trajectory pass need not read every chunk again."""
    from calibration.rig import read_rig
    from ingest.bags.reader import open_bags
    from ingest.train.bad_messages import BadMessages
    from ingest.train.run.plan import survey
    from ingest.train.run.settings import resolve_topics
    from tests.paths import FIXTURES_DIR

    bag = FIXTURES_DIR / "outdoor_walk_mcap"
    rig = read_rig(FIXTURES_DIR / "outdoor_walk_mcap.truth" / "rig.yaml")
    with open_bags([bag]) as bags:
        topics = resolve_topics(rig, bags.topics(), str(bag))
        bad = BadMessages()
        kept = survey(bags, topics, 50_000_000, bad).gyro
        assert kept is not None and len(kept.stamps_ns) > 100
        read = trajectory.read_gyro(bags, topics.imu, topics.R_cam0_imu, bad)
        given = trajectory.read_gyro(bags, topics.imu, topics.R_cam0_imu, bad, readings=kept)
    assert read is not None and given is not None
    np.testing.assert_array_equal(given.stamps_ns, read.stamps_ns)
    np.testing.assert_array_equal(given.rotations, read.rotations)
