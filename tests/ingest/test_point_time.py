"""PointCloud2 per-point time from each driver's layout, unit and base found from the values.

Every cloud is built as bytes on the wire (ROS 2 CDR and ROS 1) with a header
stamp; the decoded int64 ns times must equal the written values exactly
(for float fields: the float's exact value rounded to the nearest ns).
"""

import struct
from fractions import Fraction

import numpy as np
import pytest
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter

from ingest.bags.decode import NO_POINT_TIME, Sweep, decode
from ingest.bags.message import RawMessage
from ingest.bags.point_time import MAX_OFFSET_NS, point_times_ns
from ingest.bags.rostypes import POINTCLOUD2_TYPE, typestore
from ingest.errors import MessageDecodeError
from ingest.inspect import inspect_bags

I8, U8, I16, U16, I32, U32, F32, F64 = range(1, 9)
CODES = {I8: "b", U8: "B", I16: "h", U16: "H", I32: "i", U32: "I", F32: "f", F64: "d"}
H_NS = 1_700_000_000_123_456_789
N = 40


def cloud_raw(v, fields, point_step, rows, stamp_ns=H_NS):
    """A 1 x len(rows) PointCloud2; `fields` = [(name, offset, datatype)], rows = value tuples in field order."""
    data = bytearray(point_step * len(rows))
    for i, row in enumerate(rows):
        for (_, offset, datatype), value in zip(fields, row, strict=True):
            struct.pack_into("<" + CODES[datatype], data, i * point_step + offset, value)
    ts = typestore(v)
    sec, nsec = divmod(stamp_ns, 1_000_000_000)
    stamp = ts.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
    extra = {"seq": 0} if v == 1 else {}
    pf = ts.types["sensor_msgs/msg/PointField"]
    msg = ts.types[POINTCLOUD2_TYPE](
        header=ts.types["std_msgs/msg/Header"](**extra, stamp=stamp, frame_id="lidar"),
        height=1, width=len(rows), fields=[pf(name=n, offset=o, datatype=d, count=1) for n, o, d in fields],
        is_bigendian=False, point_step=point_step, row_step=point_step * len(rows),
        data=np.frombuffer(bytes(data), np.uint8), is_dense=True,
    )  # fmt: skip
    return bytes(
        ts.serialize_ros1(msg, POINTCLOUD2_TYPE) if v == 1 else ts.serialize_cdr(msg, POINTCLOUD2_TYPE)
    )


def sweep_of(raw, v) -> Sweep:
    out = decode(POINTCLOUD2_TYPE, raw, v)
    assert isinstance(out, Sweep)
    return out


def ns_of_seconds(value) -> int:
    """The exact value of a float (seconds) in ns, rounded to nearest."""
    return round(Fraction(float(value)) * 10**9)


XYZ = [(float(np.float32(0.5 * i)), float(np.float32(-0.25 * i)), float(np.float32(1 + i))) for i in range(N)]


def livox_cloud(v):
    """livox_ros_driver2 PointXYZRTLT: timestamp float64, absolute ns; header = first point."""
    fields = [("x", 0, F32), ("y", 4, F32), ("z", 8, F32), ("intensity", 12, F32), ("tag", 16, U8),
              ("line", 17, U8), ("timestamp", 18, F64)]  # fmt: skip
    base = 1_700_000_000_000_000_000  # float64 holds base + k * 4096 exactly
    times = [base + 4096 * 610 * i for i in range(N)]
    rows = [(*XYZ[i], 7.0, 0, i % 4, float(times[i])) for i in range(N)]
    return cloud_raw(v, fields, 26, rows, stamp_ns=base), times


def offset_time_cloud(v):
    """Livox-style offset_time: uint32 ns after the header stamp."""
    fields = [("x", 0, F32), ("y", 4, F32), ("z", 8, F32), ("offset_time", 12, U32)]
    offsets = [2_500_123 * i for i in range(N)]
    return cloud_raw(v, fields, 16, [(*XYZ[i], offsets[i]) for i in range(N)]), [H_NS + o for o in offsets]


def velodyne_cloud(v, stamp_ns=H_NS):
    """velodyne_pointcloud PointXYZIRT: time float32, seconds after the header stamp."""
    fields = [("x", 0, F32), ("y", 4, F32), ("z", 8, F32), ("intensity", 16, F32), ("ring", 20, U16),
              ("time", 24, F32)]  # fmt: skip
    rel_s = [np.float32(0.0025 * i + 1e-6 * (i % 3)) for i in range(N)]
    rows = [(*XYZ[i], 3.0, i % 16, float(rel_s[i])) for i in range(N)]
    return cloud_raw(v, fields, 32, rows, stamp_ns), [stamp_ns + ns_of_seconds(t) for t in rel_s]


def ouster_cloud(v):
    """ouster-ros PointOS: t uint32 ns after the header stamp, 48-byte points."""
    fields = [("x", 0, F32), ("y", 4, F32), ("z", 8, F32), ("intensity", 16, F32), ("t", 20, U32),
              ("reflectivity", 24, U16), ("ring", 26, U16), ("ambient", 28, U16), ("range", 32, U32)]  # fmt: skip
    t_ns = [2_441_406 * i + 17 for i in range(N)]
    rows = [(*XYZ[i], 1.0, t_ns[i], 9, i % 64, 0, 5000) for i in range(N)]
    return cloud_raw(v, fields, 48, rows), [H_NS + t for t in t_ns]


def absolute_seconds_cloud(v, step, pad):
    """Hesai (packed, header = last point) / RoboSense (aligned, header = first point): float64 s, absolute."""
    fields = [("x", 0, F32), ("y", 4, F32), ("z", 8, F32), ("intensity", 12, F32), ("ring", 16, U16),
              ("timestamp", 16 + pad, F64)]  # fmt: skip
    first_s = 1_700_000_000.25
    abs_s = [first_s + 0.0025 * i for i in range(N)]
    stamp = ns_of_seconds(abs_s[-1] if pad == 2 else abs_s[0])
    rows = [(*XYZ[i], 2.0, i % 32, abs_s[i]) for i in range(N)]
    return cloud_raw(v, fields, step, rows, stamp), [ns_of_seconds(t) for t in abs_s]


LAYOUTS = {
    "livox": (livox_cloud, "timestamp float64 ns absolute (Livox livox_ros_driver2)"),
    "offset_time": (
        offset_time_cloud,
        "offset_time uint32 ns from the header stamp (Livox-style offset_time)",
    ),
    "velodyne": (velodyne_cloud, "time float32 s from the header stamp (Velodyne)"),
    "ouster": (ouster_cloud, "t uint32 ns from the header stamp (Ouster)"),
    "hesai": (lambda v: absolute_seconds_cloud(v, 26, 2), "timestamp float64 s absolute (Hesai / RoboSense)"),
    "robosense": (
        lambda v: absolute_seconds_cloud(v, 32, 8),
        "timestamp float64 s absolute (Hesai / RoboSense)",
    ),
}


@pytest.mark.parametrize("v", [1, 2])
@pytest.mark.parametrize("name", list(LAYOUTS))
def test_point_times_of_each_driver_layout(name, v):
    make, layout = LAYOUTS[name]
    raw, times_ns = make(v)
    sweep = sweep_of(raw, v)
    assert sweep.stamps_ns.dtype == np.int64
    assert sweep.stamps_ns.tolist() == times_ns
    assert sweep.time_layout == layout
    np.testing.assert_array_equal(sweep.xyz_m, np.array(XYZ, np.float32))
    assert 90e6 < times_ns[-1] - times_ns[0] < 110e6  # a 10 Hz sweep: the skew is there to deskew


def test_relative_time_near_a_zero_clock_is_still_relative():
    """Simulation clocks start near 0, where seconds after the header also pass for absolute seconds."""
    raw, times_ns = velodyne_cloud(2, stamp_ns=500_000_000)
    sweep = sweep_of(raw, 2)
    assert sweep.stamps_ns.tolist() == times_ns
    assert "from the header stamp" in sweep.time_layout


def test_absolute_seconds_near_a_zero_clock_stay_absolute():
    fields = [("x", 0, F32), ("y", 4, F32), ("z", 8, F32), ("timestamp", 12, F64)]
    abs_s = [1.0 + 0.001 * i for i in range(N)]
    raw = cloud_raw(2, fields, 20, [(*XYZ[i], abs_s[i]) for i in range(N)], stamp_ns=1_000_000_000)
    sweep = sweep_of(raw, 2)
    assert sweep.stamps_ns.tolist() == [ns_of_seconds(t) for t in abs_s]
    assert sweep.time_layout == "timestamp float64 s absolute (Hesai / RoboSense)"


def test_without_a_time_field_every_point_has_the_header_stamp_and_says_so():
    raw = cloud_raw(2, [("x", 0, F32), ("y", 4, F32), ("z", 8, F32)], 12, XYZ[:3])
    sweep = sweep_of(raw, 2)
    assert sweep.stamps_ns.tolist() == [H_NS] * 3
    assert sweep.time_layout == NO_POINT_TIME


BAD_TIME = [50.25 + 0.25 * i for i in range(N)]
"""Seconds-like values 50 s away from a header stamp of 1.7e9 s: neither absolute nor a sweep's offsets."""


def bad_velodyne_raw(v=2):
    fields = [("x", 0, F32), ("y", 4, F32), ("z", 8, F32), ("time", 12, F32)]
    return cloud_raw(v, fields, 16, [(*XYZ[i], BAD_TIME[i]) for i in range(N)])


@pytest.mark.parametrize(
    ("datatype", "values", "shown"),
    [
        (F32, BAD_TIME, r"'time' \(float32\) holds 50\.25\.\.60"),
        (U32, [0, 4_000_000_000], r"'time' \(uint32\) holds 0\.\.4000000000"),  # 4 s: longer than any sweep
        (F64, [1e12, 1e12 + 1], r"'time' \(float64\) holds 1000000000000\.\.1000000000001"),
    ],
)
def test_a_layout_that_fits_nothing_names_the_field_and_its_values(datatype, values, shown):
    fields = [("x", 0, F32), ("y", 4, F32), ("z", 8, F32), ("time", 12, datatype)]
    raw = cloud_raw(2, fields, 20, [(*XYZ[i], value) for i, value in enumerate(values)])
    with pytest.raises(MessageDecodeError, match=shown + r".*fits no known layout.*within 3 s"):
        sweep_of(raw, 2)


def test_the_error_names_bag_topic_and_log_time():
    msg = RawMessage("/velodyne_points", POINTCLOUD2_TYPE, H_NS, bad_velodyne_raw(), 2)
    with pytest.raises(
        MessageDecodeError, match=r"^bag\.mcap: /velodyne_points at log time .*'time' \(float32\)"
    ):
        msg.decoded("bag.mcap")
    assert MAX_OFFSET_NS == 3_000_000_000


def test_inspect_shows_each_lidar_topics_time_layout_and_the_unplaceable_one(tmp_path):
    path = tmp_path / "lidars.mcap"
    schema, _ = typestore(2).generate_msgdef(POINTCLOUD2_TYPE, ros_version=2)
    clouds = {
        "/ouster/points": ouster_cloud(2)[0],
        "/hesai": LAYOUTS["hesai"][0](2)[0],
        "/bad": bad_velodyne_raw(),
    }
    with path.open("wb") as f:
        writer = McapWriter(f, compression=CompressionType.NONE)
        writer.start(profile="ros2", library="test")
        schema_id = writer.register_schema(POINTCLOUD2_TYPE, "ros2msg", schema.encode())
        for k, (topic, raw) in enumerate(clouds.items()):
            channel = writer.register_channel(topic, "cdr", schema_id)
            writer.add_message(channel, log_time=H_NS + k, data=raw, publish_time=H_NS + k)
        writer.finish()
    report = inspect_bags(path)
    lidars = {li.topic: li for li in report.lidars}
    assert lidars["/ouster/points"].time_layout == LAYOUTS["ouster"][1]
    assert lidars["/hesai"].time_layout == LAYOUTS["hesai"][1]
    assert lidars["/ouster/points"].duration_ms_median == pytest.approx((N - 1) * 2.441406, abs=1e-6)
    assert (lidars["/bad"].sweeps, lidars["/bad"].undecodable) == (0, 1)
    error = report.topic("/bad").error
    assert error is not None and "'time' (float32) holds 50.25..60" in error


def test_a_big_endian_time_field_that_reads_wrong_names_the_flag() -> None:
    """Sweep 6 U4: a PointCloud2 flagged is_bigendian on little-endian data said only "has 7 non-finite
    values": the byte order it was read in, from the message's flag, is named."""
    from ingest.bags.point_time import BIG_ENDIAN_HINT

    little = np.array([1700000000.1, 1700000000.2, 1700000000.3], "<f8")
    as_flagged = np.frombuffer(
        little.tobytes(), np.dtype([("timestamp", ">f8")])
    )  # the same bytes read big-endian
    try:
        point_times_ns(as_flagged, 1_700_000_000_000_000_000)
    except MessageDecodeError as err:
        assert str(err).endswith(BIG_ENDIAN_HINT), err
        assert BIG_ENDIAN_HINT == (
            " (read big-endian, as the message's is_bigendian says: a driver that sets it on little-endian data?)"
        )
    else:
        raise AssertionError("little-endian times read big-endian were accepted")
    right = np.frombuffer(little.astype(">f8").tobytes(), np.dtype([("timestamp", ">f8")]))
    times, _ = point_times_ns(right, 1_700_000_000_000_000_000)
    assert np.allclose(
        times, [1_700_000_000_100_000_000, 1_700_000_000_200_000_000, 1_700_000_000_300_000_000], atol=1e3
    )
