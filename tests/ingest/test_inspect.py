"""`inspect_bags` on the simulator's fixtures (known truth) and on a hand-made bag with known faults."""

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2

from calibration.rig import Lidar, Rig, read_rig
from ingest.bag_report import BagReport, RigProblem, StereoReport
from ingest.bags.livox_msg import POINT_DTYPE, encode_custom_msg
from ingest.bags.reader import BagError, open_bags
from ingest.bags.rostypes import IMAGE_TYPE, IMU_TYPE, typestore
from ingest.errors import MessageDecodeError
from ingest.inspect import EL_RANGE_DEG, header_stamp_ns, inspect_bags
from sensorbox.sim.fixtures import FIXTURES, fixture_bag
from sensorbox.sim.lidar import PACKET_PERIOD_NS, POINT_SPACING_NS, POINTS_PER_PACKET, SWEEP_PERIOD_NS
from sensorbox.sim.run import CAMERA_LATENCY_NS, IMU_LATENCY_NS, LIDAR_LATENCY_NS
from tests.paths import FIXTURES_DIR

ROOT = Path(__file__).resolve().parents[2]
REF_RIG = ROOT / "calibration" / "sensorbox.yaml"
NAMES = sorted(FIXTURES)
CAMS = ("/zed_upper/zed_node/rgb/color/rect/image", "/zed_lower/zed_node/rgb/color/rect/image")
LIDARS = ("/livox/lidar_192_168_1_12", "/livox/lidar_192_168_1_13")
IMUS = ("/livox/imu_192_168_1_12", "/livox/imu_192_168_1_13")


def sim_params(name):
    bag = fixture_bag(name, FIXTURES_DIR)
    return yaml.safe_load((bag.parent / f"{bag.name}.truth" / "sim.yaml").read_text())


def cam_topics(name):
    suffix = "/compressed" if FIXTURES[name].image == "jpeg" else ""
    return tuple(t + suffix for t in CAMS)


def stereo_of(report: BagReport) -> StereoReport:
    assert report.stereo is not None
    return report.stereo


def problems_of(report: BagReport) -> tuple[RigProblem, ...]:
    assert report.rig_problems is not None
    return report.rig_problems


@pytest.fixture(scope="module", params=NAMES)
def fixture_report(request):
    return request.param, inspect_bags(fixture_bag(request.param, FIXTURES_DIR))


# ---------------------------------------------------------------- fixtures: per topic


def test_counts_are_what_the_bag_holds(fixture_report):
    name, report = fixture_report
    with open_bags([fixture_bag(name, FIXTURES_DIR)]) as bag:
        held = {t: s.count for t, s in bag.topics().items()}
    assert {t.topic: t.count for t in report.topics} == held
    expected = dict.fromkeys(cam_topics(name), 21) | dict.fromkeys(LIDARS, 7) | dict.fromkeys(IMUS, 140)
    assert held == expected
    assert report.message_count == sum(expected.values()) == 336


def test_rates_within_one_percent_and_no_gaps(fixture_report):
    name, report = fixture_report
    for topics, hz in ((cam_topics(name), 30.0), (LIDARS, 10.0), (IMUS, 200.0)):
        for topic in topics:
            t = report.topic(topic)
            assert t.stamped
            assert t.rate_hz == pytest.approx(hz, rel=0.01), topic
            assert t.median_period_ms == pytest.approx(1000 / t.rate_hz)
            assert (t.gaps, t.largest_gap_ms, t.duplicates, t.out_of_order) == (0, None, 0, 0), topic
            assert t.max_interval_ms < 1.5 * t.median_period_ms
            assert t.undecodable == 0 and t.error is None
    assert report.topic(IMUS[0]).rate_hz == pytest.approx(200.0, abs=1e-9)  # exactly 5 ms apart


def test_log_offsets_match_the_simulated_latencies(fixture_report):
    name, report = fixture_report
    sim = sim_params(name)
    for topic in cam_topics(name):  # log = stamp + CAMERA_LATENCY_NS for every frame
        t = report.topic(topic)
        assert t.log_offset_median_ms == t.log_offset_min_ms == t.log_offset_max_ms == CAMERA_LATENCY_NS / 1e6
    for lidar, imu in zip(sim["lidars"], IMUS, strict=True):
        offset_ns = lidar["clock_offset_ns"]
        # IMU: stamp = true time + clock offset, log = true time + IMU latency
        t = report.topic(imu)
        assert t.log_offset_min_ms == t.log_offset_max_ms == pytest.approx((IMU_LATENCY_NS - offset_ns) / 1e6)
        # LiDAR: log = end of the 100 ms sensor-clock window + latency - offset; stamp = its first
        # packet, at most one packet period after the window start
        t = report.topic(lidar["topic"])
        hi = (SWEEP_PERIOD_NS + LIDAR_LATENCY_NS - offset_ns) / 1e6
        assert hi - PACKET_PERIOD_NS / 1e6 < t.log_offset_min_ms <= t.log_offset_max_ms <= hi


def test_second_lidar_clock_offset_shows_in_its_imu_offset():
    report = inspect_bags(fixture_bag("outdoor_walk_mcap", FIXTURES_DIR))
    assert sim_params("outdoor_walk_mcap")["lidar_clock_offset_ns"] == 1_500_000
    top, bottom = (report.topic(t).log_offset_median_ms for t in IMUS)
    assert top is not None and bottom is not None
    assert top == pytest.approx(1.0) and bottom == pytest.approx(-0.5)
    assert top - bottom == pytest.approx(1.5)


@pytest.mark.parametrize("name", NAMES)
def test_header_stamps_read_from_bytes_equal_rosbags_deserialisation(name):
    with open_bags([fixture_bag(name, FIXTURES_DIR)]) as bag:
        ts = typestore(bag.ros_version)
        for n, msg in enumerate(bag.messages()):  # noqa: B007 (n counts the messages)
            full: Any = (
                ts.deserialize_ros1(msg.raw, msg.msgtype)
                if msg.ros_version == 1
                else ts.deserialize_cdr(msg.raw, msg.msgtype)
            )
            stamp = full.header.stamp.sec * 1_000_000_000 + full.header.stamp.nanosec
            assert header_stamp_ns(msg.raw, msg.ros_version) == stamp
    assert n == 335


def test_header_stamp_big_endian_cdr_and_short_buffers():
    raw = bytes([0, 0, 0, 0]) + (1_700_000_000).to_bytes(4, "big") + (123_456_789).to_bytes(4, "big")
    assert header_stamp_ns(raw, 2) == 1_700_000_000_123_456_789
    with pytest.raises(MessageDecodeError, match="too few"):
        header_stamp_ns(raw[:11], 2)
    with pytest.raises(MessageDecodeError, match="nanoseconds"):
        header_stamp_ns(bytes(4) + (1).to_bytes(4, "little") + (2_000_000_000).to_bytes(4, "little"), 1)


# ---------------------------------------------------------------- fixtures: stereo and LiDAR


def true_stereo_dt_ms(name):
    """lower - upper stamp of every frame pair, recomputed from sim.yaml the simulator's way."""
    sim = sim_params(name)
    period = 1e9 / sim["camera_rate_hz"]
    dts = []
    for k in range(21):
        nominal = sim["cameras"]["first_frame_ns"] + k * period
        jitter = np.random.default_rng([sim["seed"], k, 0x1A]).uniform(-1, 1, 2) * sim["camera_jitter_ns"]
        t = [round(nominal + c * sim["stereo_offset_ns"] + jitter[c]) for c in range(2)]
        dts.append((t[1] - t[0]) / 1e6)
    return np.array(dts)


def test_stereo_pairing_matches_the_simulated_jitter(fixture_report):
    name, report = fixture_report
    s = stereo_of(report)
    assert (s.upper_topic, s.lower_topic) == cam_topics(name)
    assert s.source == "names"
    assert (s.pairs, s.unpaired_upper, s.unpaired_lower) == (21, 0, 0)
    assert s.tolerance_ms == pytest.approx(1000 / 30 / 2, rel=0.01)
    truth = true_stereo_dt_ms(name)
    assert s.median_dt_ms == pytest.approx(np.median(truth), abs=1e-6)
    assert s.median_abs_dt_ms == pytest.approx(np.median(np.abs(truth)), abs=1e-6)
    assert s.max_abs_dt_ms == pytest.approx(np.abs(truth).max(), abs=1e-6)
    # 0.1 ms nominal offset, +-0.5 ms uniform jitter on each camera
    assert s.max_abs_dt_ms is not None and s.median_dt_ms is not None
    assert s.max_abs_dt_ms <= 1.1
    assert abs(s.median_dt_ms - 0.1) < 0.3


def test_lidar_sweeps_have_the_mid360_timing_and_field_of_view(fixture_report):
    name, report = fixture_report
    assert [li.topic for li in report.lidars] == list(LIDARS)
    for li in report.lidars:
        assert li.sweeps == 7 and li.undecodable == 0
        packets = li.points_median / POINTS_PER_PACKET
        assert packets in (208, 209)  # 100 ms / 480 us
        duration_ns = (packets - 1) * PACKET_PERIOD_NS + (POINTS_PER_PACKET - 1) * POINT_SPACING_NS
        # PointCloud2 point times are float64 absolute ns: 256 ns steps near 1.7e18 ns
        tol_ms = 1e-6 if FIXTURES[name].lidar_msg == "custom" else 2 * 256e-6
        assert li.duration_ms_median == pytest.approx(duration_ns / 1e6, abs=tol_ms)
        lo, hi = EL_RANGE_DEG
        assert lo - 1e-4 <= li.elevation_min_deg < lo + 0.1
        assert hi - 0.1 < li.elevation_max_deg <= hi + 1e-4
        assert 0.3 < li.coverage_median < 0.7
    top, bottom = report.lidars
    if FIXTURES[name].scene == "indoor":  # closed room: every ray returns
        assert top.zero_fraction == bottom.zero_fraction == 0.0
        assert top.coverage_median > 0.55 and bottom.coverage_median > 0.55
    else:  # the upright LiDAR sees the sky, the upside-down one the ground
        assert top.zero_fraction > 0.2 and bottom.zero_fraction < 0.1
        assert top.coverage_median < bottom.coverage_median


def test_suggested_mapping_reproduces_the_fixture_rig(fixture_report):
    name, report = fixture_report
    rig = yaml.safe_load(
        (
            fixture_bag(name, FIXTURES_DIR).parent
            / f"{fixture_bag(name, FIXTURES_DIR).name}.truth"
            / "rig.yaml"
        ).read_text()
    )
    got = yaml.safe_load(report.mapping.yaml())
    up, low = cam_topics(name)
    assert got["cameras"] == {"cam0": {"role": "upper", "topic": up}, "cam1": {"role": "lower", "topic": low}}
    assert got["lidars"] == {n: {"topic": b["topic"], "ip": b["ip"]} for n, b in rig["lidars"].items()}
    assert got["imus"] == {n: {"topic": b["topic"], "rate_hz": 200.0} for n, b in rig["imus"].items()}
    assert report.mapping.notes == ()


def test_rig_check_on_fixtures():
    raw_rig = read_rig(
        fixture_bag("outdoor_walk_mcap", FIXTURES_DIR).parent / "outdoor_walk_mcap.truth" / "rig.yaml"
    )
    report = inspect_bags(fixture_bag("outdoor_walk_mcap", FIXTURES_DIR), rig=raw_rig)
    assert report.rig_problems == ()
    assert report.stereo is not None and report.stereo.source == "rig"

    # the rig names raw image topics; the jpeg fixtures carry image_transport's /compressed ones
    bag = fixture_bag("indoor_static_mcap", FIXTURES_DIR)
    report = inspect_bags(bag, rig=read_rig(bag.parent / "indoor_static_mcap.truth" / "rig.yaml"))
    assert problems_of(report) == ()  # ingest reads the /compressed variant: no problem to report
    assert (
        stereo_of(report).source == "rig" and stereo_of(report).pairs == 21
    )  # paired on the /compressed topics


# ---------------------------------------------------------------- a bag with known faults

T0 = 1_700_000_000_000_000_000
P = 33_333_333  # ns, 30 Hz
RIGHT_DT = 200_000  # ns, lower camera after the upper


def image_raw(stamp_ns):
    ts = typestore(2)
    sec, nsec = divmod(stamp_ns, 1_000_000_000)
    header = ts.types["std_msgs/msg/Header"](
        stamp=ts.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id="cam"
    )
    msg = ts.types[IMAGE_TYPE](
        header=header,
        height=2,
        width=2,
        encoding="mono8",
        is_bigendian=0,
        step=2,
        data=np.arange(4, dtype=np.uint8),
    )
    return bytes(ts.serialize_cdr(msg, IMAGE_TYPE))


def imu_raw(stamp_ns, acc):
    ts = typestore(2)
    sec, nsec = divmod(stamp_ns, 1_000_000_000)
    vec = ts.types["geometry_msgs/msg/Vector3"]
    msg = ts.types[IMU_TYPE](
        header=ts.types["std_msgs/msg/Header"](
            stamp=ts.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id="livox_frame"
        ),
        orientation=ts.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=0.0),
        orientation_covariance=np.zeros(9),
        angular_velocity=vec(x=0.0, y=0.0, z=0.0),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=vec(x=acc[0], y=acc[1], z=acc[2]),
        linear_acceleration_covariance=np.zeros(9),
    )
    return bytes(ts.serialize_cdr(msg, IMU_TYPE))


def sweep_points(el_deg, n_zero, span_ns):
    """One point per 1 deg azimuth cell centre at elevation `el_deg`, two outside the band, `n_zero` zeros."""
    az = np.radians(np.arange(360) - 179.5)
    el = np.radians(np.full(360, el_deg))
    dirs = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
    outside = np.radians([[0.0, -10.0], [0.0, 60.0]])  # (az, el): below and above [-7, 52]
    extra = np.stack([np.cos(outside[:, 1]), np.zeros(2), np.sin(outside[:, 1])], axis=1)
    xyz = np.concatenate([dirs * 5.0, dirs * 7.0, extra * 3.0, np.zeros((n_zero, 3))])  # each cell hit twice
    pts = np.zeros(len(xyz), POINT_DTYPE)
    pts["x"], pts["y"], pts["z"] = xyz.T
    pts["offset_time"] = np.linspace(0, span_ns, len(xyz)).astype(np.uint32)
    return pts


def lidar_raw(stamp_ns, el_deg, n_zero=40, span_ns=99_000_000):
    return encode_custom_msg(stamp_ns, "livox_frame", stamp_ns, sweep_points(el_deg, n_zero, span_ns))


def faulty_bag(path):
    """Two cameras (left/right names), two Livox LiDARs with IMUs, a headerless topic, known faults."""
    left, right = [], []
    for k in range(30):
        stamp = T0 + k * P
        if k != 5:  # the right camera drops frame 5
            right.append((stamp + RIGHT_DT + 5_000_000, image_raw(stamp + RIGHT_DT)))
        if k == 10:
            continue  # the left camera drops frame 10: a 2-period gap
        log = stamp + 5_000_000
        if k == 20:
            log += 40_000_000  # arrives after frame 21: one out-of-order stamp
        left.append((log, image_raw(stamp)))
        if k == 15:
            left.append((log + 1_000_000, image_raw(stamp)))  # duplicated stamp
    lidar_down = [
        (T0 + k * 100_000_000 + 102_000_000, lidar_raw(T0 + k * 100_000_000, 10.5)) for k in range(3)
    ]
    lidar_down.append((T0 + 402_000_000, lidar_raw(T0 + 300_000_000, 10.5)[:60]))  # truncated points
    lidar_up = [
        (T0 + k * 100_000_000 + 102_000_000, lidar_raw(T0 + k * 100_000_000, -0.5, n_zero=0))
        for k in range(3)
    ]
    imu_down = [
        (T0 + k * 5_000_000 + 1_000_000, imu_raw(T0 + k * 5_000_000, (0.01, 0.0, -1.0))) for k in range(50)
    ]
    imu_up = [
        (T0 + k * 5_000_000 + 1_000_000, imu_raw(T0 + k * 5_000_000, (0.1, 0.0, 9.81))) for k in range(50)
    ]
    string = bytes(
        typestore(2).serialize_cdr(
            typestore(2).types["std_msgs/msg/String"](data="hi"), "std_msgs/msg/String"
        )
    )
    topics = {
        "/stereo/left/image_raw": (IMAGE_TYPE, left),
        "/stereo/right/image_raw": (IMAGE_TYPE, right),
        "/livox/lidar_10_0_0_7": ("livox_ros_driver2/msg/CustomMsg", lidar_down),
        "/livox/imu_10_0_0_7": (IMU_TYPE, imu_down),
        "/livox/lidar_10_0_0_8": ("livox_ros_driver2/msg/CustomMsg", lidar_up),
        "/livox/imu_10_0_0_8": (IMU_TYPE, imu_up),
        "/status": ("std_msgs/msg/String", [(T0 + 7, string), (T0 + 9, string)]),
    }
    with Writer2(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        for topic, (msgtype, msgs) in topics.items():
            conn = writer.add_connection(topic, msgtype, typestore=typestore(2))
            for log_ns, raw in msgs:
                writer.write(conn, log_ns, raw)
    return path


@pytest.fixture(scope="module")
def faulty(tmp_path_factory):
    return faulty_bag(tmp_path_factory.mktemp("faulty") / "bag")


def test_gap_duplicate_and_out_of_order_are_counted(faulty):
    t = inspect_bags(faulty).topic("/stereo/left/image_raw")
    assert t.count == 30  # 30 frames - 1 dropped + 1 duplicate
    assert t.rate_hz == pytest.approx(1e9 / P)
    assert (t.gaps, t.largest_gap_ms, t.max_interval_ms) == (1, 2 * P / 1e6, 2 * P / 1e6)
    assert (t.duplicates, t.out_of_order) == (1, 1)
    assert (t.log_offset_min_ms, t.log_offset_median_ms, t.log_offset_max_ms) == (5.0, 5.0, 45.0)
    assert (t.first_stamp_ns, t.last_stamp_ns) == (T0, T0 + 29 * P)
    right = inspect_bags(faulty).topic("/stereo/right/image_raw")
    assert (right.count, right.gaps, right.largest_gap_ms, right.duplicates, right.out_of_order) == (
        29,
        1,
        2 * P / 1e6,
        0,
        0,
    )


def test_stereo_pairs_and_unpaired_frames(faulty):
    s = stereo_of(inspect_bags(faulty))
    assert (s.upper_topic, s.lower_topic, s.source) == (
        "/stereo/left/image_raw",
        "/stereo/right/image_raw",
        "names",
    )
    # left lacks frame 10, right lacks frame 5; the duplicated left stamp is one frame
    assert (s.pairs, s.unpaired_upper, s.unpaired_lower) == (28, 1, 1)
    assert s.median_dt_ms == s.median_abs_dt_ms == s.max_abs_dt_ms == RIGHT_DT / 1e6


def test_lidar_coverage_of_a_known_sweep(faulty):
    report = inspect_bags(faulty)
    down, up = report.lidars
    assert down.topic == "/livox/lidar_10_0_0_7" and up.topic == "/livox/lidar_10_0_0_8"
    n = 2 * 360 + 2 + 40
    assert (down.sweeps, down.undecodable, down.points_median) == (3, 1, n)
    assert down.zero_fraction == pytest.approx(40 / n)
    assert down.duration_ms_median == pytest.approx(99.0, abs=1e-6)
    assert down.coverage_median == pytest.approx(360 / (360 * 59))  # one elevation row, every azimuth
    assert down.elevation_min_deg == pytest.approx(-10.0) and down.elevation_max_deg == pytest.approx(60.0)
    assert up.zero_fraction == 0.0 and up.coverage_median == pytest.approx(1 / 59)
    t = report.topic("/livox/lidar_10_0_0_7")
    assert (
        t.count == 4 and t.undecodable == 0 and "CustomMsg" in str(t.error)
    )  # header fine, points cut short


def test_headerless_topic_is_counted_not_timed(faulty):
    t = inspect_bags(faulty).topic("/status")
    assert (t.msgtype, t.count, t.stamped, t.rate_hz, t.log_offset_median_ms) == (
        "std_msgs/msg/String",
        2,
        False,
        None,
        None,
    )


def test_mapping_from_names_livox_ips_and_imu_gravity(faulty):
    mapping = inspect_bags(faulty).mapping
    assert yaml.safe_load(mapping.yaml()) == {
        "cameras": {
            "cam0": {"role": "upper", "topic": "/stereo/left/image_raw"},
            "cam1": {"role": "lower", "topic": "/stereo/right/image_raw"},
        },
        "lidars": {
            "lidar_bottom": {"topic": "/livox/lidar_10_0_0_7", "ip": "10.0.0.7"},  # IMU reads -1 g on z
            "lidar_top": {
                "topic": "/livox/lidar_10_0_0_8",
                "ip": "10.0.0.8",
            },  # +9.81 m/s^2: units do not matter
        },
        "imus": {
            "imu_bottom": {"topic": "/livox/imu_10_0_0_7", "rate_hz": 200.0},
            "imu_top": {"topic": "/livox/imu_10_0_0_8", "rate_hz": 200.0},
        },
    }


def test_rig_topics_missing_or_of_the_wrong_type(faulty):
    ref = read_rig(REF_RIG)
    report = inspect_bags(faulty, rig=ref)
    assert {p.topic for p in problems_of(report)} == {c.topic for c in ref.cameras} | {
        li.topic for li in ref.lidars
    } | {i.topic for i in ref.imus}
    assert all(p.problem == "not in the bag" for p in problems_of(report))
    assert stereo_of(report).source == "names"  # the rig's cameras are not there

    cams = tuple(
        dataclasses.replace(c, topic=t)
        for c, t in zip(ref.cameras, ("/stereo/left/image_raw", "/status"), strict=True)
    )
    rig = Rig(cams, lidars=(Lidar("lidar_top", "/livox/imu_10_0_0_8", np.eye(4)),), name="mixed")
    problems = problems_of(inspect_bags(faulty, rig=rig))
    assert [(p.sensor, p.topic) for p in problems] == [
        ("camera cam1 (lower)", "/status"),
        ("lidar lidar_top", "/livox/imu_10_0_0_8"),
    ]
    assert "has type std_msgs/msg/String; expected an image type" in problems[0].problem
    assert "has type sensor_msgs/msg/Imu; expected a LiDAR type" in problems[1].problem


def test_progress_reports_every_message(faulty):
    calls = []
    report = inspect_bags([faulty], progress=lambda done, total: calls.append((done, total)))
    assert calls[-1] == (report.message_count, report.message_count)
    assert [d for d, _ in calls] == sorted(d for d, _ in calls)


def test_truncated_mcap_needs_salvage(tmp_path):
    src = fixture_bag("outdoor_walk_mcap", FIXTURES_DIR) / "outdoor_walk_mcap.mcap"
    cut = tmp_path / "cut.mcap"
    data = src.read_bytes()
    cut.write_bytes(data[: len(data) * 2 // 3])
    with pytest.raises(BagError, match="--salvage"):
        inspect_bags(cut)
    report = inspect_bags(cut, salvage=True)
    assert report.salvaged == (cut,)
    assert 0 < report.message_count < 336
    assert report.topic(IMUS[0]).rate_hz == pytest.approx(200.0)


def test_missing_bag_is_a_bag_error(tmp_path):
    with pytest.raises(BagError, match="no such file"):
        inspect_bags(tmp_path / "nothing.mcap")


def test_the_duration_counts_topics_inspect_cannot_decode(tmp_path: Path) -> None:
    """A bag whose only topic has an unknown type and no embedded definition: inspect refuses the topic
    but counts its messages; its log time span was 0.00 s (from the decoded topics alone)."""
    from mcap.writer import Writer

    from ingest.inspect import inspect_bags

    path = tmp_path / "unknown.mcap"
    with path.open("wb") as f:
        writer = Writer(f)
        writer.start(profile="ros2")
        schema = writer.register_schema(name="foo_msgs/msg/Bar", encoding="ros2msg", data=b"")
        channel = writer.register_channel(topic="/foo", message_encoding="cdr", schema_id=schema)
        for k, log_ns in enumerate((1_000_000_000, 2_000_000_000, 3_500_000_000)):
            writer.add_message(
                channel, log_time=log_ns, data=b"\x00\x01\x00\x00", publish_time=log_ns, sequence=k
            )
        writer.finish()
    report = inspect_bags([path])
    assert report.message_count == 3
    (foo,) = report.topics
    assert foo.error is not None and "refusing to guess its layout" in foo.error
    assert report.duration_s == 2.5


def test_a_rig_topic_whose_type_is_named_the_ros1_way_says_so_not_missing() -> None:
    """Sweep 5: a ROS 2 mcap whose schemas are named sensor_msgs/CompressedImage (no /msg/) made ingest
    say the rig's camera was "not in the bag", though its /compressed topic was there."""
    from calibration.rig import REFERENCE_RIG, read_rig
    from ingest.topic_map import check_rig

    rig = read_rig(REFERENCE_RIG)
    upper = f"{rig.upper.topic}/compressed"
    types = {
        upper: "sensor_msgs/CompressedImage",
        f"{rig.lower.topic}/compressed": "sensor_msgs/msg/CompressedImage",
    }
    types |= {li.topic: "livox_ros_driver2/msg/CustomMsg" for li in rig.lidars}
    types |= {i.topic: "sensor_msgs/msg/Imu" for i in rig.imus}
    problems = check_rig(rig, types)
    assert [(p.sensor, p.topic, p.problem) for p in problems] == [
        (
            "camera cam0 (upper)",
            upper,
            "has type sensor_msgs/CompressedImage; expected an image type (sensor_msgs/msg/CompressedImage or "
            "sensor_msgs/msg/Image) (its schema names it the ROS 1 way: a ROS 2 bag names it "
            "sensor_msgs/msg/CompressedImage)",
        )
    ]
