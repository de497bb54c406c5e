"""Simulator self-consistency: its LiDAR, cameras, IMU and truth agree exactly with each other."""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from calibration.errors import SensorboxError
from calibration.rig import REFERENCE_RIG, read_rig
from calibration.transforms import invert
from ingest.bags.livox_msg import decode_custom_msg
from sensorbox.messages import PC2_DTYPE
from sensorbox.sim.appearance import Texture
from sensorbox.sim.camera import CameraSim, render
from sensorbox.sim.config import SimConfig
from sensorbox.sim.lidar import POINT_SPACING_NS, POINTS_PER_PACKET
from sensorbox.sim.run import CAMERA_LATENCY_NS, IMU_LATENCY_NS, simulate
from sensorbox.sim.scenes import build_scene
from sensorbox.sim.trajectory import (
    GRAVITY_MPS2,
    R_BODY_CAM,
    Handheld,
    Sinusoid,
    TumSpline,
    imu_readings,
    static,
    walk,
)
from sensorbox.sim.truth import Truth
from tests.faults.cli import sensorbox


@pytest.fixture(scope="module")
def walk_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """0.35 s of noise-free outdoor walking, with a 3 ms clock offset on the second LiDAR."""
    out = tmp_path_factory.mktemp("sim") / "walk"
    cfg = SimConfig(
        scene="outdoor", trajectory="walk", duration_s=0.35, scale=0.1, range_noise_m=0.0,
        lidar_clock_offset_ns=3_000_000, seed=3,
    )  # fmt: skip
    simulate(cfg, out)
    return out


def _lidar_points_world(bag: Path, truth: Truth) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per LiDAR topic: non-zero points mapped to the world at their own (true) time, and their tags."""
    offsets = {li["topic"]: li["clock_offset_ns"] for li in truth.params["lidars"]}
    lidars = {li.topic: li for li in truth.rig.lidars}
    out: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {t: [] for t in lidars}
    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if c.topic in lidars]
        for conn, _, raw in reader.messages(connections=conns):
            msg = decode_custom_msg(raw, 2)
            p = msg.points
            hit = (p["x"] != 0) | (p["y"] != 0) | (p["z"] != 0)
            true_ns = msg.point_stamps_ns[hit] - offsets[conn.topic]
            xyz = np.stack([p["x"][hit], p["y"][hit], p["z"][hit]], axis=1).astype(np.float64)
            T = truth.T_world_cam0(true_ns) @ lidars[conn.topic].T_cam0_lidar
            world = np.einsum("nij,nj->ni", T[:, :3, :3], xyz) + T[:, :3, 3]
            out[conn.topic].append((world, p["tag"][hit]))
    return {t: (np.concatenate([w for w, _ in v]), np.concatenate([g for _, g in v])) for t, v in out.items()}


def test_noise_free_lidar_points_lie_on_the_mesh_at_their_own_time(walk_bag: Path) -> None:
    truth = Truth.load(walk_bag)
    for topic, (world, tags) in _lidar_points_world(walk_bag, truth).items():
        d = truth.mesh.distance(world)
        assert len(d) > 10_000, topic
        assert np.median(d) < 1e-4, (topic, np.median(d))
        assert d.max() < 1e-3, (topic, d.max())
        assert not tags.any()  # noise off: no dust echoes, no low-confidence tags


def test_motion_skew_is_real(walk_bag: Path) -> None:
    """The same points mapped with one pose per sweep (no deskew) are off the mesh by centimetres."""
    truth = Truth.load(walk_bag)
    lidar = truth.rig.lidars[0]
    with AnyReader([walk_bag]) as reader:
        conn = next(c for c in reader.connections if c.topic == lidar.topic)
        _, _, raw = next(iter(reader.messages(connections=[conn])))
    msg = decode_custom_msg(raw, 2)
    p = msg.points[(msg.points["x"] != 0)]
    xyz = np.stack([p["x"], p["y"], p["z"]], axis=1).astype(np.float64)
    T = truth.T_world_cam0(np.array([msg.timebase_ns]))[0] @ lidar.T_cam0_lidar
    d = truth.mesh.distance(xyz @ T[:3, :3].T + T[:3, 3])
    assert np.percentile(d, 90) > 0.02


def test_range_noise_statistics(tmp_path: Path) -> None:
    out = tmp_path / "noisy"
    simulate(SimConfig(duration_s=0.1, scale=0.05, range_noise_m=0.02, dust_fraction=0.01, seed=5), out)
    truth = Truth.load(out)
    for world, tags in _lidar_points_world(out, truth).values():
        clean = tags == 0
        d = truth.mesh.distance(world[clean])
        # |N(0, 2 cm)| along the ray projects onto the surface normal: median below 0.674 sigma
        assert 0.004 < np.median(d) < 0.0135
        assert 0.006 < (~clean).mean() < 0.014  # dust echoes: 1 % of returns, tagged


def test_exact_range_matches_the_floor_below_the_static_rig(tmp_path: Path) -> None:
    out = tmp_path / "static"
    simulate(SimConfig(duration_s=0.05, scale=0.05, range_noise_m=0.0), out)
    truth = Truth.load(out)
    # the static rig looks along world +x: cam0 +y is world down, the floor is 1.5 m below cam0
    a = np.radians([0.0, 5.0, 10.0, -8.0])
    rays = np.stack([np.zeros_like(a), np.cos(a), np.sin(a)], axis=1)
    got = truth.range_along(rays, truth.start_ns + 10_000_000)
    np.testing.assert_allclose(got, 1.5 / np.cos(a), atol=2e-5)
    # arbitrary pixels: the returned range lands on the mesh
    model = truth.rig.upper.model
    px = np.random.default_rng(0).uniform([0, 0], [model.width - 1, model.height - 1], (500, 2))
    r = truth.range_at(model, px, truth.start_ns)
    rays, ok = model.unproject(px)
    T = truth.T_world_cam0(np.array([truth.start_ns]))[0]
    hit = ok & np.isfinite(r)
    pts = (rays[hit] * r[hit, None]) @ T[:3, :3].T + T[:3, 3]
    assert hit.sum() > 400
    assert truth.mesh.distance(pts).max() < 1e-4


def test_checker_corners_appear_where_the_double_sphere_model_projects_them() -> None:
    rig = read_rig(REFERENCE_RIG)
    scene = build_scene("indoor", 0)
    board = scene.checkerboards[0]
    cam = rig.upper.model.scaled(0.5)
    T_world_cam0 = static(scene.start_world).T_world_cam0(np.array([0.0]))[0]
    image = render(CameraSim("cam0", cam, np.eye(4)), scene, Texture(0), T_world_cam0, supersample=4)
    corners_cam0 = board.inner_corners_world() @ invert(T_world_cam0)[:3, :3].T + invert(T_world_cam0)[:3, 3]
    uv, ok = cam.project(corners_cam0)
    assert ok.all()
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    start = (uv + np.array([0.6, -0.5])).astype(np.float32).reshape(-1, 1, 2)  # start off the corner
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
    found = cv2.cornerSubPix(gray, start, (3, 3), (-1, -1), crit).reshape(-1, 2)
    err = found - uv
    # no bias (a half-pixel convention slip would show as 0.5 px), and sampling noise only
    assert np.abs(err.mean(axis=0)).max() < 0.05, err.mean(axis=0)
    assert np.median(np.linalg.norm(err, axis=1)) < 0.15 and np.abs(err).max() < 0.3, err


def test_imu_matches_closed_form_motion() -> None:
    t = np.linspace(0.0, 2.0, 401)
    T_cam0_imu = read_rig(REFERENCE_RIG).imus[0].T_cam0_imu
    R_imu_cam0 = T_cam0_imu[:3, :3].T
    # static: no rotation, +1 g along the IMU axis that points up (world z)
    traj = static(np.array([0.0, 0.0, 1.5]))
    gyro, acc = imu_readings(traj, t, T_cam0_imu)
    np.testing.assert_allclose(gyro, 0.0, atol=1e-12)
    up_imu = R_imu_cam0 @ R_BODY_CAM.T @ np.array([0.0, 0.0, 1.0])
    np.testing.assert_allclose(acc, np.broadcast_to(up_imu, acc.shape), atol=1e-6)
    # pure yaw: rate = yaw' about body z (= cam0 -y); the IMU's lever arm adds centripetal force
    yaw = Sinusoid(0.4, 0.5, 0.3)
    traj = Handheld((0.0, 0.0, 1.5), yaw=(yaw,))
    gyro, _ = imu_readings(traj, t, T_cam0_imu)
    rate = 0.4 * 2 * np.pi * 0.5 * np.cos(2 * np.pi * 0.5 * t + 0.3)
    np.testing.assert_allclose(gyro, rate[:, None] * (R_imu_cam0 @ np.array([0.0, -1.0, 0.0])), atol=1e-6)
    # lateral sway: a_y = -A w^2 sin(w t + phi) in the world, gravity on z
    sway = Sinusoid(0.05, 1.0, 0.0)
    traj = Handheld((0.0, 0.0, 1.5), sway=(sway,))
    _, acc = imu_readings(traj, t, np.eye(4))
    w = 2 * np.pi
    expected_world = np.stack([0 * t, -0.05 * w**2 * np.sin(w * t), 0 * t + GRAVITY_MPS2], axis=1)
    np.testing.assert_allclose(acc * GRAVITY_MPS2, expected_world @ R_BODY_CAM, atol=1e-5)


def test_walk_has_the_promised_motion_budget() -> None:
    traj = walk(np.zeros(3), seed=1)
    t = np.linspace(0, 10, 20001)
    gyro, _ = imu_readings(traj, t, np.eye(4))
    body = gyro @ R_BODY_CAM.T  # rates about body x (roll), y (pitch), z (yaw)
    peak_deg = np.degrees(np.abs(body).max(axis=0))
    assert 30 < peak_deg[2] <= 62 and 20 < peak_deg[1] <= 62
    _, p = traj.pose(t)
    assert np.diff(p[:, 0]).sum() / 10 == pytest.approx(1.2, rel=1e-9)


def test_custom_tum_trajectory_follows_the_file(walk_bag: Path) -> None:
    truth = Truth.load(walk_bag)
    spline = TumSpline(truth.path / "trajectory.tum")
    t = np.linspace(0.0, 0.3, 37)
    R_ref, p_ref = truth.trajectory.pose(t)
    R, p = spline.pose(t)
    np.testing.assert_allclose(p, p_ref, atol=1e-6)
    np.testing.assert_allclose(R, R_ref, atol=1e-6)


def test_bag_rates_counts_and_stamps(walk_bag: Path) -> None:
    truth = Truth.load(walk_bag)
    start = truth.start_ns
    stamps: dict[str, list[int]] = {}
    with AnyReader([walk_bag]) as reader:  # no types registered: the bag embeds its definitions
        for conn, log_ns, raw in reader.messages():
            msg: Any = reader.deserialize(raw, conn.msgtype) if "lidar" not in conn.topic else None
            if msg is None:
                stamp = decode_custom_msg(raw).stamp_ns
            else:
                stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            stamps.setdefault(conn.topic, []).append(stamp)
            # log time = host arrival (true time + latency); the stamp runs on the sensor's clock
            offset = 3_000_000 if conn.topic.endswith("_13") else 0
            if "zed" in conn.topic:
                assert log_ns - stamp == CAMERA_LATENCY_NS
            elif "imu" in conn.topic:
                assert log_ns - stamp == IMU_LATENCY_NS - offset
    rel = {t: (np.array(v) - start) / 1e9 for t, v in stamps.items()}
    cams = [t for t in rel if "zed" in t]
    assert len(cams) == 2 and all(len(rel[t]) in (10, 11) for t in cams)
    for t in cams:
        assert np.all(np.abs(np.diff(rel[t]) - 1 / 30) <= 1.01e-3)  # +-0.5 ms jitter on each frame
    np.testing.assert_allclose(rel[cams[1]] - rel[cams[0]], 100e-6, atol=1.01e-3)
    lidar_top, lidar_bottom = (li.topic for li in truth.rig.lidars)
    for topic, offset_ns in ((lidar_top, 0), (lidar_bottom, 3_000_000)):
        s = np.array(stamps[topic])
        assert len(s) in (3, 4)
        # sweeps start at the first packet after each 100 ms boundary of the sensor's own clock
        assert np.all((s % 100_000_000) < 480_000)
        assert offset_ns == truth.params["lidars"][1 if offset_ns else 0]["clock_offset_ns"]
    imu = [t for t in rel if "imu" in t]
    for t in imu:
        np.testing.assert_allclose(np.diff(rel[t]), 0.005, atol=1e-9)
        assert len(rel[t]) == pytest.approx(0.35 * 200, abs=1)


def test_sweep_timing_matches_the_driver(walk_bag: Path) -> None:
    truth = Truth.load(walk_bag)
    topic = truth.rig.lidars[0].topic
    with AnyReader([walk_bag]) as reader:
        conn = next(c for c in reader.connections if c.topic == topic)
        _, _, raw = next(iter(reader.messages(connections=[conn])))
    msg = decode_custom_msg(raw)
    off = msg.points["offset_time"].astype(np.int64).reshape(-1, POINTS_PER_PACKET)
    assert msg.stamp_ns == msg.timebase_ns and off[0, 0] == 0
    np.testing.assert_array_equal(np.diff(off, axis=1), POINT_SPACING_NS)
    np.testing.assert_array_equal(np.diff(off[:, 0]), 480_000)
    assert off.shape[0] in (208, 209)
    np.testing.assert_array_equal(msg.points["line"], np.tile(np.arange(POINTS_PER_PACKET) % 4, off.shape[0]))


@pytest.mark.parametrize("fmt", ["mcap", "db3", "bag"])
def test_every_format_reads_back_without_registering_types(tmp_path: Path, fmt: str) -> None:
    cfg = SimConfig(duration_s=0.1, scale=0.05, format=fmt, lidar_msg="pointcloud2", image="jpeg")  # type: ignore[arg-type]
    summary = simulate(cfg, tmp_path / "x")
    with AnyReader([summary.bag]) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        assert set(types.values()) == {
            "sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/PointCloud2", "sensor_msgs/msg/Imu"
        }  # fmt: skip
        n = 0
        for conn, _, raw in reader.messages():
            n += 1
            msg: Any = reader.deserialize(raw, conn.msgtype)
            if conn.msgtype.endswith("PointCloud2"):
                assert (msg.point_step, msg.height, msg.is_bigendian) == (26, 1, False)
                assert [f.name for f in msg.fields] == list(PC2_DTYPE.names or ())
                cloud = np.frombuffer(msg.data, PC2_DTYPE)
                assert cloud["timestamp"][0] == msg.header.stamp.sec * 1e9 + msg.header.stamp.nanosec
            if conn.msgtype.endswith("CompressedImage"):
                decoded = cv2.imdecode(msg.data, cv2.IMREAD_COLOR)
                assert decoded is not None and decoded.shape == (60, 96, 3)
    assert n == sum(summary.counts.values()) > 0


def test_mcap_library_decodes_the_bag(walk_bag: Path) -> None:
    from mcap.reader import make_reader

    mcap_file = next(walk_bag.glob("*.mcap"))
    with mcap_file.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        schemas = {s.name: s for s in summary.schemas.values()}
        assert "livox_ros_driver2/msg/CustomMsg" in schemas
        assert b"CustomPoint[] points" in schemas["livox_ros_driver2/msg/CustomMsg"].data
        counts: dict[str, int] = {}
        for _, channel, message in reader.iter_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            if "lidar" in channel.topic:
                assert decode_custom_msg(message.data).point_stamps_ns.size > 0
    with AnyReader([walk_bag]) as any_reader:
        assert counts == {c.topic: c.msgcount for c in any_reader.connections}


def test_same_seed_same_bytes(tmp_path: Path) -> None:
    cfg = SimConfig(duration_s=0.1, scale=0.05, seed=11, trajectory="walk")
    a, b = simulate(cfg, tmp_path / "a"), simulate(cfg, tmp_path / "b")
    with AnyReader([a.bag]) as ra, AnyReader([b.bag]) as rb:
        left = [(c.topic, t, bytes(raw)) for c, t, raw in ra.messages()]
        right = [(c.topic, t, bytes(raw)) for c, t, raw in rb.messages()]
    assert left == right


def test_movers_are_where_their_truth_says_at_each_points_own_time(tmp_path: Path) -> None:
    """LiDAR points on movers lie on the mover's mesh at the point's own time (and not at another)."""
    from sensorbox.sim.movers import MovingCaster, read_movers

    cfg = SimConfig(
        scene="outdoor", trajectory="walk", duration_s=0.3, scale=0.1, range_noise_m=0.0, movers=True, seed=2
    )  # fmt: skip
    simulate(cfg, tmp_path / "m")
    truth = Truth.load(tmp_path / "m")
    movers = read_movers(truth.path)
    assert [m.name for m in movers] == ["person_crossing", "person_oncoming", "door", "car"]
    assert [m.name for m in truth.movers] == [m.name for m in movers]
    offsets = {li["topic"]: li["clock_offset_ns"] for li in truth.params["lidars"]}
    lidars = {li.topic: li for li in truth.rig.lidars}
    on_mover = 0
    with AnyReader([tmp_path / "m"]) as reader:
        conns = [c for c in reader.connections if c.topic in lidars]
        for conn, _, raw in reader.messages(connections=conns):
            msg = decode_custom_msg(raw, 2)
            p = msg.points
            hit = ((p["x"] != 0) | (p["y"] != 0) | (p["z"] != 0)) & (p["tag"] == 0)
            true_ns = msg.point_stamps_ns[hit] - offsets[conn.topic]
            xyz = np.stack([p["x"][hit], p["y"][hit], p["z"][hit]], axis=1).astype(np.float64)
            T = truth.T_world_cam0(true_ns) @ lidars[conn.topic].T_cam0_lidar
            origin = T[:, :3, 3]
            world = np.einsum("nij,nj->ni", T[:, :3, :3], xyz) + origin
            d = world - origin
            r = np.linalg.norm(d, axis=1)
            t_s = (true_ns - truth.start_ns) / 1e9
            caster = MovingCaster(truth.mesh, movers)
            mover_only = caster.cast(origin, d / r[:, None], t_s, static=False).range_m
            mine = np.abs(mover_only - r) < 1e-3  # the point is on a mover at its own time
            on_mover += int(mine.sum())
            if mine.any():  # 50 ms later the mover has moved on: the same ray no longer meets it there
                later = caster.cast(
                    origin[mine], d[mine] / r[mine, None], t_s[mine] + 0.05, static=False
                ).range_m
                assert np.median(np.abs(later - r[mine])) > 5e-3
            static_r = truth.mesh.cast(origin, d / r[:, None]).range_m
            np.testing.assert_allclose(
                np.minimum(static_r, mover_only), r, atol=1e-3
            )  # every hit is explained
    assert on_mover > 100


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"duration_s": math.inf}, r"--duration must be a finite number > 0.0, got inf"),
        ({"scale": math.nan}, r"--scale must be a finite number > 0.0, got nan"),
        (
            {"scale": 0.001},
            r"--scale 0.001 makes camera cam0 2x1 px; expected >= 8 px on each side \(--scale >= 0.007\)$",
        ),
        (
            {"scale": 1e-6},  # the focal lengths out of range too: the size is said first
            r"--scale 1e-06 makes camera cam0 1x1 px; expected >= 8 px on each side \(--scale >= 0.007\)$",
        ),
        ({"range_noise_m": math.nan}, r"--range-noise must be a finite number >= 0 m, got nan"),
        (
            {"range_noise_m": 1e300},
            r"--range-noise 1e\+300: expected at most 10 m \(1-sigma\)$",
        ),  # points at 0
        ({"duration_s": 1e300}, r"--duration 1e\+300: expected at most 1e\+08 s"),  # was an OverflowError
        ({"lidar_clock_offset_ns": 2_000_000_000}, r"--lidar-offset-ms 2000: expected within \+-1000 ms"),
        ({"tum": Path("t.tum")}, r"--tum is read only with --trajectory custom \(got --trajectory static\)"),
    ],
)
def test_a_bad_simulation_setting_is_one_line_before_anything_is_written(
    tmp_path: Path, change: dict[str, object], message: str
) -> None:
    """Non-finite values reached int() (a traceback) or the bag (NaN noise); --tum alone left a partial bag;
    --scale 0.001 wrote 2x1 px cameras."""
    cfg = SimConfig(**{"duration_s": 0.1, "scale": 0.1, **change})  # type: ignore[arg-type]
    with pytest.raises(SensorboxError, match=message):
        simulate(cfg, tmp_path / "bag")
    assert list(tmp_path.iterdir()) == []


def _write_tum(path: Path, rows: int, dt_s: float, replace: dict[int, str] | None = None) -> Path:
    """A TUM file of `rows` poses `dt_s` apart at epoch stamps (line 1 a comment; row k on line k + 2)."""
    lines = ["# t tx ty tz qx qy qz qw"]
    for k in range(rows):
        lines.append(f"{1_700_000_000 + k * dt_s:.6f} {0.1 * k:.3f} 0 1.4 0.5 -0.5 0.5 -0.5")
    for line_no, text in (replace or {}).items():
        lines[line_no - 1] = text
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize(
    ("line", "message"),
    [
        ("1700000000.100000 nan 0 1.4 0.5 -0.5 0.5 -0.5", "line 4: tx is nan; expected a finite number"),
        (
            "1700000000.100000 0.2 0 1.4 0 0 0 0",
            "line 4: the quaternion qx qy qz qw is all zeros; expected a rotation",
        ),
        (
            "1700000000.100000 0.2 0 1.4 0.5 -0.5 0.5",
            "line 4: 7 columns; expected 8, 't tx ty tz qx qy qz qw'",
        ),
        ("1700000000.100000 0.2 0 x 0.5 -0.5 0.5 -0.5", "line 4: tz is 'x'; expected a number"),
        (
            "1700000000.000000 0.2 0 1.4 0.5 -0.5 0.5 -0.5",
            "line 4: t is 1700000000.000000, not after the previous row's 1700000000.050000; "
            "expected strictly increasing timestamps",
        ),
    ],
)
def test_a_bad_tum_row_is_named_by_its_line(tmp_path: Path, line: str, message: str) -> None:
    """NaN reached scipy's CubicSpline and a zero quaternion RotationSpline: tracebacks without a line."""
    path = _write_tum(tmp_path / "t.tum", 20, 0.05, {4: line})
    with pytest.raises(SensorboxError) as err:
        TumSpline(path)
    assert str(err.value) == f"{path}: {message}"


def test_a_tum_file_shorter_than_the_duration_is_refused(tmp_path: Path) -> None:
    """Poses past the last row were clamped: the rig froze for the rest of the recording, rc 0."""
    path = _write_tum(tmp_path / "short.tum", 10, 0.01)
    cfg = SimConfig(trajectory="custom", tum=path, duration_s=0.2, scale=0.1)
    with pytest.raises(SensorboxError) as err:
        simulate(cfg, tmp_path / "bag")
    assert str(err.value) == (
        f"{path}: the trajectory spans 0.09 s (first to last row), shorter than --duration 0.2 s; "
        "expected a TUM file covering the whole simulation (which starts at its first row)"
    )
    assert not (tmp_path / "bag").exists()


@pytest.mark.parametrize("kind", ["link to /dev/zero", "fifo"])
def test_a_tum_path_that_is_no_regular_file_is_one_line_before_a_byte_is_read(
    kind: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """--tum /dev/zero was read whole until a MemoryError traceback; a FIFO would wait forever."""
    tum = tmp_path / "t.tum"
    if kind == "fifo":
        os.mkfifo(tum)
        what = "a FIFO (named pipe)"
    else:
        tum.symlink_to("/dev/zero")
        what = f"a character device (a link to {Path('/dev/zero').resolve()})"
    out = tmp_path / "out" / "t.mcap"
    args = ["simulate", "--duration", "0.2", "--scale", "0.25", "--trajectory", "custom", "--tum", str(tum)]
    code, _, err = sensorbox(capsys, *args, "--out", str(out))
    assert (code, err) == (2, [f"error: {tum}: is {what}, not a TUM trajectory file"])
    assert not (tmp_path / "out").exists()
