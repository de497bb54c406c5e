"""ROS 1 interop, checked with ROS 1's own `rosbag` (Debian's python3-rosbag, run by the system python).

Both ways: every ROS 1 bag SensorBox writes (lz4 and uncompressed chunks, every
message kind, and the simulator's bundled fixture) is read message by message
by `rosbag`, which deserialises each message from the bag's embedded
definitions; and a bag that `rosbag`'s writer made (Livox CustomMsg from its
`.msg` text, PointCloud2, Image, CompressedImage, Imu) is read by `open_bags`
+ `decode` (what `sensorbox ingest` uses) and by `sensorbox inspect`.
`make test` installs python3-rosbag (tools/ensure_ros1.sh); without it these skip.
"""

from __future__ import annotations

import base64
import hashlib
import json
import subprocess
import textwrap
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from ingest.bags.decode import Frame, ImuSample, Sweep, decode_pointcloud2
from ingest.bags.livox_msg import POINT_DTYPE, Points, decode_custom_msg
from ingest.bags.reader import open_bags
from ingest.bags.rostypes import (
    COMPRESSED_IMAGE_TYPE,
    CUSTOM_MSG_TYPE,
    IMAGE_TYPE,
    IMU_TYPE,
    POINTCLOUD2_TYPE,
    ROS1_CUSTOM_MSG_MD5,
)
from ingest.inspect import inspect_bags
from sensorbox import messages
from sensorbox.cli.main import app as main_app
from sensorbox.live.bagwriter import BagWriter
from sensorbox.sim.fixtures import fixture_bag
from tests.paths import FIXTURES_DIR

SYSTEM_PYTHON = Path("/usr/bin/python3")


def _has_ros1() -> bool:
    """Whether the system python finds rosbag, roslz4, genpy and sensor_msgs (without importing them)."""
    if not SYSTEM_PYTHON.is_file():
        return False
    probe = "import importlib.util as u; raise SystemExit(not all(map(u.find_spec, %r)))"
    cmd = [str(SYSTEM_PYTHON), "-c", probe % (["rosbag", "roslz4", "genpy", "sensor_msgs"],)]
    return subprocess.run(cmd, capture_output=True, check=False).returncode == 0


pytestmark = [
    pytest.mark.skipif(
        not _has_ros1(),
        reason="ROS 1's rosbag is absent: `apt-get install python3-rosbag python3-sensor-msgs` (make test does)",
    ),
    pytest.mark.xdist_group("ros1"),  # the module fixtures below run ROS 1 once per worker: keep one worker
]

READ_SCRIPT = textwrap.dedent(
    """
    import hashlib, json, struct, sys
    import rosbag

    def summary(msg):
        if msg._type.endswith("/CustomMsg"):  # points packed back as ROS 1 lays them out (19 bytes each)
            values = [v for p in msg.points for v in (p.offset_time, p.x, p.y, p.z, p.reflectivity, p.tag, p.line)]
            packed = struct.pack("<" + "IfffBBB" * len(msg.points), *values)
            return {"timebase": msg.timebase, "point_num": msg.point_num, "lidar_id": msg.lidar_id,
                    "points": len(msg.points), "sha256": hashlib.sha256(packed).hexdigest()}
        if msg._type == "sensor_msgs/PointCloud2":
            return {"fields": [[f.name, f.offset, f.datatype, f.count] for f in msg.fields],
                    "shape": [msg.height, msg.width, msg.point_step, msg.row_step],
                    "sha256": hashlib.sha256(msg.data).hexdigest()}
        if msg._type == "sensor_msgs/Image":
            return {"shape": [msg.height, msg.width, msg.step], "encoding": msg.encoding,
                    "sha256": hashlib.sha256(msg.data).hexdigest()}
        if msg._type == "sensor_msgs/CompressedImage":
            return {"format": msg.format, "sha256": hashlib.sha256(msg.data).hexdigest()}
        if msg._type == "sensor_msgs/Imu":
            v, a = msg.angular_velocity, msg.linear_acceleration
            return {"imu": [v.x, v.y, v.z, a.x, a.y, a.z]}
        raise SystemExit("unexpected type " + msg._type)

    def record(topic, msg, t):
        return {"topic": topic, "type": msg._type, "md5": msg._md5sum, "log_ns": t.to_nsec(),
                "stamp_ns": msg.header.stamp.to_nsec(), "frame_id": msg.header.frame_id, **summary(msg)}

    out = {}
    for target in sys.argv[1:]:  # full=PATH: deserialise every message; raw=PATH: the first of each topic
        mode, path = target.split("=", 1)
        with rosbag.Bag(path) as bag:
            messages, seen = [], set()
            for topic, (datatype, data, md5, _, pytype), t in bag.read_messages(raw=True):
                rec = {"topic": topic, "type": datatype, "md5": md5, "log_ns": t.to_nsec(),
                       "raw_sha256": hashlib.sha256(data).hexdigest()}
                if mode == "full" or topic not in seen:
                    seen.add(topic)
                    rec.update(record(topic, pytype().deserialize(data), t))
                messages.append(rec)
            out[path] = {"compression": bag.get_compression_info().compression, "messages": messages}
    json.dump(out, sys.stdout)
    """
)

# The real driver's .msg files (livox_ros_driver), as rosbag stores them: main text, then each dependency.
LIVOX_MSG_TEXT = "\n".join(
    [
        "Header header\nuint64 timebase\nuint32 point_num\nuint8 lidar_id\nuint8[3] rsvd\nCustomPoint[] points",
        "=" * 80,
        "MSG: std_msgs/Header\nuint32 seq\ntime stamp\nstring frame_id",
        "=" * 80,
        "MSG: livox_ros_driver/CustomPoint",
        "uint32 offset_time\nfloat32 x\nfloat32 y\nfloat32 z\nuint8 reflectivity\nuint8 tag\nuint8 line",
    ]
)

WRITE_SCRIPT = textwrap.dedent(
    """
    import base64, json, sys
    import genpy, rosbag
    from genpy.dynamic import generate_dynamic
    from sensor_msgs.msg import CompressedImage, Image, Imu, PointCloud2, PointField

    livox = generate_dynamic("livox_ros_driver/CustomMsg", json.loads(sys.argv[2]))
    CustomMsg, CustomPoint = livox["livox_ros_driver/CustomMsg"], livox["livox_ros_driver/CustomPoint"]

    def build(m):
        data = base64.b64decode(m.get("data", ""))
        if m["kind"] == "custom":
            pts = [CustomPoint(*p) for p in m["points"]]
            msg = CustomMsg(timebase=m["stamp_ns"], point_num=len(pts), lidar_id=3, rsvd=[0, 0, 0], points=pts)
        elif m["kind"] == "cloud":
            fields = [PointField(name=n, offset=o, datatype=d, count=1) for n, o, d in m["fields"]]
            msg = PointCloud2(height=1, width=m["width"], fields=fields, is_bigendian=False,
                              point_step=m["point_step"], row_step=m["point_step"] * m["width"],
                              data=data, is_dense=True)
        elif m["kind"] == "image":
            msg = Image(height=m["height"], width=m["width"], encoding="bgr8", step=m["step"], data=data)
        elif m["kind"] == "jpeg":
            msg = CompressedImage(format="jpeg", data=data)
        else:
            msg = Imu()
            msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z = m["gyro"]
            msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z = m["acc"]
        msg.header.stamp = genpy.Time(*divmod(m["stamp_ns"], 10**9))
        msg.header.frame_id = m["frame_id"]
        return msg

    spec = json.load(open(sys.argv[1]))
    for target in sys.argv[3:]:  # COMPRESSION=PATH
        compression, path = target.split("=", 1)
        with rosbag.Bag(path, "w", compression=compression) as bag:
            for m in spec:
                bag.write(m["topic"], build(m), genpy.Time(*divmod(m["log_ns"], 10**9)))
    print(CustomMsg._md5sum)
    """
)


def ros1_read(full: list[Path], raw: list[Path]) -> dict[Path, Any]:
    """ROS 1's rosbag's reading of each bag (READ_SCRIPT), in one process.

    Every message of every bag is decompressed and its bytes hashed; those of
    `full` are all deserialised, those of `raw` the first of each topic.
    """
    targets = [f"full={p}" for p in full] + [f"raw={p}" for p in raw]
    cmd = [str(SYSTEM_PYTHON), "-c", READ_SCRIPT, *targets]
    done = subprocess.run(cmd, capture_output=True, text=True, check=False, timeout=120)
    assert done.returncode == 0, done.stderr
    return {Path(path): result for path, result in json.loads(done.stdout).items()}


def sha256(data: bytes | memoryview | np.ndarray[Any, Any]) -> str:
    return hashlib.sha256(bytes(data)).hexdigest()


def livox_points(n: int, seed: int) -> Points:
    rng = np.random.default_rng(seed)
    pts = np.zeros(n, POINT_DTYPE)
    pts["offset_time"] = np.sort(rng.integers(0, 100_000_000, n))
    for axis in "xyz":
        pts[axis] = rng.normal(0, 5, n).astype(np.float32)
    for name in ("reflectivity", "tag", "line"):
        pts[name] = rng.integers(0, 256 if name == "reflectivity" else 4, n)
    return pts


def gradient_image(height: int, width: int, seed: int) -> np.ndarray[Any, np.dtype[np.uint8]]:
    """A smooth gradient plus noise: lz4 compresses it some, not all (several LZ4 blocks per chunk)."""
    rng = np.random.default_rng(seed)
    ramp = np.add.outer(np.arange(height), np.arange(width)) % 256
    img = np.repeat(ramp[:, :, None], 3, axis=2) + rng.integers(0, 8, (height, width, 3))
    return (img % 256).astype(np.uint8)


# ------------------------------------------------------------ SensorBox -> ROS 1

LOG0_NS = 1_700_000_000_000_000_000
BIG = gradient_image(600, 800, 0)  # 1.9 MB as bgra8: a chunk of more than one 1 MiB LZ4 block
POINTS = livox_points(300, 1)
GYRO, ACC = np.array([0.1, -0.2, 0.3]), np.array([0.01, 0.02, 1.0])
WRITTEN = [  # (topic, msgtype, header stamp ns, raw): every kind of message SensorBox writes
    ("/zed/image", IMAGE_TYPE, 1_000, messages.image_msg(1_000, "cam0", BIG, ros=1)),
    ("/zed/image/compressed", COMPRESSED_IMAGE_TYPE, 2_000,
     messages.compressed_image_msg(2_000, "cam0", BIG[:60, :80], ros=1)),
    ("/livox/lidar", CUSTOM_MSG_TYPE, 3_000, messages.custom_msg(3_000, POINTS, ros=1)),
    ("/livox/points", POINTCLOUD2_TYPE, 4_000, messages.pointcloud2_msg(4_000, POINTS, ros=1)),
    ("/livox/imu", IMU_TYPE, 5_000, messages.imu_msg(5_000, GYRO, ACC, ros=1)),
    ("/zed/image", IMAGE_TYPE, 6_000, messages.image_msg(6_000, "cam0", BIG[::-1].copy(), ros=1)),
]  # fmt: skip
SIM_BAG = fixture_bag("outdoor_static_bag", FIXTURES_DIR)


@pytest.fixture(scope="module")
def ros1_reads(tmp_path_factory: pytest.TempPathFactory) -> dict[Path, Any]:
    """ROS 1's reading of our bag with lz4 chunks, without compression, and of the simulator's fixture."""
    root = tmp_path_factory.mktemp("ours")
    for compress in (True, False):
        with BagWriter(root / f"{compress}.bag", "bag", compress=compress) as bag:
            for topic, msgtype, _, _ in WRITTEN:
                if topic not in bag.counts:
                    bag.add(topic, msgtype)
            for k, (topic, _, _, raw) in enumerate(WRITTEN):
                bag.write(topic, LOG0_NS + k, raw)
    return ros1_read(full=[root / "True.bag", root / "False.bag"], raw=[SIM_BAG])


@pytest.mark.parametrize(("compress", "compression"), [(True, "lz4"), (False, "none")])
def test_rosbag_reads_every_message_we_write(
    ros1_reads: dict[Path, Any], compress: bool, compression: str
) -> None:
    got = next(v for k, v in ros1_reads.items() if k.name == f"{compress}.bag")
    assert got["compression"] == compression
    msgs = got["messages"]
    assert [(m["topic"], m["stamp_ns"], m["log_ns"]) for m in msgs] == [
        (t, s, LOG0_NS + k) for k, (t, _, s, _) in enumerate(WRITTEN)
    ]
    image, jpeg, custom, cloud, imu, flipped = msgs
    assert (image["type"], image["encoding"], image["shape"]) == (
        "sensor_msgs/Image",
        "bgra8",
        [600, 800, 3200],
    )
    assert image["sha256"] == sha256(cv2.cvtColor(BIG, cv2.COLOR_BGR2BGRA))
    assert flipped["sha256"] == sha256(cv2.cvtColor(BIG[::-1], cv2.COLOR_BGR2BGRA))
    ok, buf = cv2.imencode(".jpg", BIG[:60, :80], [cv2.IMWRITE_JPEG_QUALITY, 90])
    assert ok and jpeg["sha256"] == sha256(buf) and jpeg["format"] == "bgra8; jpeg compressed bgr8"
    assert (custom["type"], custom["md5"]) == ("livox_ros_driver2/CustomMsg", ROS1_CUSTOM_MSG_MD5)
    assert (custom["timebase"], custom["point_num"], custom["points"]) == (3_000, 300, 300)
    assert custom["sha256"] == sha256(POINTS.tobytes())  # every point's 7 values, as ROS 1 decoded them
    assert cloud["shape"] == [1, 300, 26, 26 * 300]
    assert [f[0] for f in cloud["fields"]] == ["x", "y", "z", "intensity", "tag", "line", "timestamp"]
    assert cloud["sha256"] == sha256(decode_pointcloud2(WRITTEN[3][3], 1).points.tobytes())
    assert imu["imu"] == [*GYRO, *ACC] and imu["frame_id"] == "livox_frame"


def test_rosbag_reads_the_simulators_bag(ros1_reads: dict[Path, Any]) -> None:
    """The bundled fixture is `sensorbox simulate --format bag` output (lz4, CustomMsg, jpeg, Imu).

    ROS 1 decompresses every chunk and sees our exact message bytes; the first
    message of each topic is deserialised (the synthetic bags above cover every
    message) and its header stamp and (for sweeps) every point match ours.
    """
    got = ros1_reads[SIM_BAG]
    assert got["compression"] == "lz4"
    with open_bags(SIM_BAG) as ours:
        msgs = list(ours.messages())
    assert [(m["topic"], m["log_ns"], m["raw_sha256"]) for m in got["messages"]] == [
        (m.topic, m.log_ns, sha256(m.raw)) for m in msgs
    ]
    firsts = {m.topic: m for m in reversed(msgs)}
    decoded = [m for m in got["messages"] if "stamp_ns" in m]
    assert [m["topic"] for m in decoded] == list(dict.fromkeys(m.topic for m in msgs))  # 6 topics
    for m in decoded:
        assert m["stamp_ns"] == firsts[m["topic"]].stamp(str(SIM_BAG)), m["topic"]
    sweeps = [m for m in decoded if m["type"] == "livox_ros_driver2/CustomMsg"]
    assert len(sweeps) == 2
    for m in sweeps:
        assert m["sha256"] == sha256(decode_custom_msg(firsts[m["topic"]].raw, 1).points.tobytes())
        assert m["points"] == m["point_num"] > 19_000


# ------------------------------------------------------------ ROS 1 -> SensorBox


def _foreign_spec(pts: Points, img: np.ndarray[Any, Any], jpeg: bytes) -> list[dict[str, Any]]:
    """What the ROS 1 writer script builds: a Velodyne-style padded PointCloud2 and a padded bgr8 Image."""
    h, w = img.shape[:2]
    padded = np.zeros((h, w * 3 + 4), np.uint8)  # step = 3 w + 4: the decoder must honour step
    padded[:, : w * 3] = img.reshape(h, -1)
    cloud = np.zeros(len(pts), {"names": ["x", "y", "z", "intensity"], "formats": ["<f4"] * 4,
                                "offsets": [0, 4, 8, 16], "itemsize": 32})  # fmt: skip
    for axis in "xyz":
        cloud[axis] = pts[axis]
    cloud["intensity"] = pts["reflectivity"]
    points = [[int(p["offset_time"]), *(float(p[a]) for a in "xyz"),
               int(p["reflectivity"]), int(p["tag"]), int(p["line"])] for p in pts]  # fmt: skip
    b64 = lambda data: base64.b64encode(bytes(data)).decode()  # noqa: E731
    base = 1_600_000_000_000_000_000
    spec = [
        {"kind": "custom", "topic": "/livox/lidar", "stamp_ns": base + 1, "points": points},
        {"kind": "cloud", "topic": "/velodyne_points", "stamp_ns": base + 2, "width": len(pts), "point_step": 32,
         "fields": [["x", 0, 7], ["y", 4, 7], ["z", 8, 7], ["intensity", 16, 7]], "data": b64(cloud.tobytes())},
        {"kind": "image", "topic": "/cam/image_raw", "stamp_ns": base + 3, "height": h, "width": w,
         "step": w * 3 + 4, "data": b64(padded)},
        {"kind": "jpeg", "topic": "/cam/image_raw/compressed", "stamp_ns": base + 4, "data": b64(jpeg)},
        {"kind": "imu", "topic": "/imu", "stamp_ns": base + 5, "gyro": [0.5, 0.25, -1.0], "acc": [0.0, 9.75, 0.125]},
    ]  # fmt: skip
    for k, m in enumerate(spec):
        m.update(frame_id=f"frame{k}", log_ns=m["stamp_ns"] + 1_000_000)
    return spec


FOREIGN_POINTS, FOREIGN_IMAGE = livox_points(200, 2), gradient_image(30, 40, 3)
FOREIGN_JPEG = cv2.imencode(".jpg", FOREIGN_IMAGE)[1]
FOREIGN = _foreign_spec(FOREIGN_POINTS, FOREIGN_IMAGE, FOREIGN_JPEG.tobytes())


@pytest.fixture(scope="module")
def ros1_bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """`FOREIGN` written by ROS 1's rosbag writer with each of its chunk compressions."""
    root = tmp_path_factory.mktemp("ros1")
    (root / "spec.json").write_text(json.dumps(FOREIGN))
    bags = {c: root / f"{c}.bag" for c in ("lz4", "bz2", "none")}
    cmd = [str(SYSTEM_PYTHON), "-c", WRITE_SCRIPT, str(root / "spec.json"), json.dumps(LIVOX_MSG_TEXT),
           *(f"{c}={p}" for c, p in bags.items())]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, check=False, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == ROS1_CUSTOM_MSG_MD5  # genpy's MD5 of the driver's text = ours
    return bags


@pytest.mark.parametrize("compression", ["lz4", "bz2", "none"])
def test_bag_written_by_rosbag_is_read_by_ingest(ros1_bags: dict[str, Path], compression: str) -> None:
    bag, spec, pts, img, jpeg = ros1_bags[compression], FOREIGN, FOREIGN_POINTS, FOREIGN_IMAGE, FOREIGN_JPEG
    with open_bags(bag) as bags:
        assert {t: (s.msgtype, s.count) for t, s in bags.topics().items()} == {
            "/livox/lidar": ("livox_ros_driver/msg/CustomMsg", 1),
            "/velodyne_points": (POINTCLOUD2_TYPE, 1),
            "/cam/image_raw": (IMAGE_TYPE, 1),
            "/cam/image_raw/compressed": (COMPRESSED_IMAGE_TYPE, 1),
            "/imu": (IMU_TYPE, 1),
        }
        got = list(bags.messages())
    assert [(m.topic, m.log_ns, m.ros_version) for m in got] == [(s["topic"], s["log_ns"], 1) for s in spec]
    custom, cloud, image, compressed, imu = (m.decoded(str(bag)) for m in got)
    assert isinstance(custom, Sweep) and isinstance(cloud, Sweep)
    assert (custom.stamp_ns, custom.frame_id) == (spec[0]["stamp_ns"], "frame0")
    xyz = np.stack([pts[a] for a in "xyz"], axis=1)
    np.testing.assert_array_equal(custom.xyz_m, xyz)
    np.testing.assert_array_equal(custom.stamps_ns, spec[0]["stamp_ns"] + pts["offset_time"].astype(np.int64))
    for name in ("reflectivity", "tag", "line"):
        np.testing.assert_array_equal(getattr(custom, name), pts[name])
    np.testing.assert_array_equal(cloud.xyz_m, xyz)
    np.testing.assert_array_equal(cloud.reflectivity, pts["reflectivity"].astype(np.float32))
    assert (cloud.stamps_ns == spec[1]["stamp_ns"]).all() and cloud.frame_id == "frame1"
    assert isinstance(image, Frame) and isinstance(compressed, Frame)
    np.testing.assert_array_equal(image.image, img)
    np.testing.assert_array_equal(compressed.image, cv2.imdecode(jpeg, cv2.IMREAD_ANYCOLOR))
    assert (image.stamp_ns, compressed.stamp_ns) == (spec[2]["stamp_ns"], spec[3]["stamp_ns"])
    assert isinstance(imu, ImuSample)
    assert (imu.gyro_rad_s.tolist(), imu.acc.tolist()) == (spec[4]["gyro"], spec[4]["acc"])


def test_bag_written_by_rosbag_is_read_by_inspect(ros1_bags: dict[str, Path]) -> None:
    res = CliRunner().invoke(main_app, ["inspect", str(ros1_bags["lz4"])])
    assert res.exit_code == 0, res.output
    assert "lz4.bag: ROS 1, 5 messages" in res.stdout and "livox_ros_driver/msg/CustomMsg" in res.stdout
    report = inspect_bags(ros1_bags["lz4"])
    assert (report.ros_version, report.message_count) == (1, 5)
    assert {t.topic: (t.count, t.stamped, t.error) for t in report.topics} == {
        s["topic"]: (1, True, None) for s in FOREIGN
    }
    assert {c.topic for c in report.lidars} == {"/livox/lidar", "/velodyne_points"}
