"""Numpy decoders on raw bytes: values written by rosbags' serialisers come back exactly."""

import struct
from typing import Any

import cv2
import numpy as np
import pytest

from ingest.bags.decode import (
    DECODED_TYPES,
    Frame,
    ImuSample,
    Sweep,
    decode,
    decode_compressed_image,
    decode_image,
    decode_imu,
    decode_pointcloud2,
    sweep_from_pointcloud,
)
from ingest.bags.rostypes import (
    COMPRESSED_IMAGE_TYPE,
    IMAGE_TYPE,
    IMU_TYPE,
    POINTCLOUD2_TYPE,
    typestore,
)
from ingest.errors import MessageDecodeError

RNG = np.random.default_rng(7)
STAMP_NS = 1_700_000_000_000_000_000 + 123_456_789
VERSIONS = [1, 2]
F32, F64, U8 = 7, 8, 2


def header(v, stamp_ns=STAMP_NS, frame_id="livox_frame"):
    ts = typestore(v)
    sec, nsec = divmod(stamp_ns, 1_000_000_000)
    stamp = ts.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec)
    if v == 1:
        return ts.types["std_msgs/msg/Header"](seq=3, stamp=stamp, frame_id=frame_id)
    return ts.types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)


def serialize(v, msg, msgtype):
    ts = typestore(v)
    return bytes(ts.serialize_ros1(msg, msgtype) if v == 1 else ts.serialize_cdr(msg, msgtype))


def cloud_raw(v, fields, point_step, data, height, width, row_step=None, big=False, stamp_ns=STAMP_NS):
    ts = typestore(v)
    pf = ts.types["sensor_msgs/msg/PointField"]
    msg = ts.types[POINTCLOUD2_TYPE](
        header=header(v, stamp_ns),
        height=height,
        width=width,
        fields=[pf(name=n, offset=o, datatype=d, count=1) for n, o, d in fields],
        is_bigendian=big,
        point_step=point_step,
        row_step=width * point_step if row_step is None else row_step,
        data=np.frombuffer(data, np.uint8),
        is_dense=True,
    )
    return serialize(v, msg, POINTCLOUD2_TYPE)


def sweep_of(msgtype, raw, v) -> Sweep:
    out = decode(msgtype, raw, v)
    assert isinstance(out, Sweep)
    return out


def frame_of(msgtype, raw, v) -> Frame:
    out = decode(msgtype, raw, v)
    assert isinstance(out, Frame)
    return out


def random_points(n):
    return RNG.uniform(-50, 50, (n, 3)).astype(np.float32), RNG.uniform(0, 255, n).astype(np.float32)


# ---------------------------------------------------------------- PointCloud2

LIVOX_FIELDS = [
    ("x", 0, F32),
    ("y", 4, F32),
    ("z", 8, F32),
    ("intensity", 12, F32),
    ("tag", 16, U8),
    ("line", 17, U8),
    ("timestamp", 18, F64),
]
LEGACY_FIELDS = [
    ("x", 0, F32),
    ("y", 4, F32),
    ("z", 8, F32),
    ("intensity", 12, F32),
    ("tag", 16, U8),
    ("line", 17, U8),
]


@pytest.mark.parametrize("v", VERSIONS)
@pytest.mark.parametrize("big", [False, True])
def test_livox_26_byte_pointcloud2(v, big):
    n = 9
    xyz, inten = random_points(n)
    tags, lines = RNG.integers(0, 256, n), RNG.integers(0, 4, n)
    base = 1_700_000_000_000_000_000  # a multiple of 256: float64 holds it and the offsets below exactly
    point_ns = base + 1024 * np.arange(n) * 97
    order = ">" if big else "<"
    data = b"".join(
        struct.pack(order + "ffffBBd", *xyz[i], inten[i], tags[i], lines[i], float(point_ns[i]))
        for i in range(n)
    )
    assert len(data) == 26 * n
    raw = cloud_raw(v, LIVOX_FIELDS, 26, data, 1, n, big=big, stamp_ns=base)

    cloud = decode_pointcloud2(raw, v)
    assert (cloud.stamp_ns, cloud.frame_id, cloud.height, cloud.width) == (base, "livox_frame", 1, n)
    assert cloud.points.dtype.itemsize == 26
    np.testing.assert_array_equal(cloud.points["x"], xyz[:, 0])
    np.testing.assert_array_equal(cloud.points["timestamp"], point_ns.astype(np.float64))

    sweep = sweep_of(POINTCLOUD2_TYPE, raw, v)
    assert sweep.xyz_m.dtype == np.float32 and sweep.xyz_m.shape == (n, 3)
    np.testing.assert_array_equal(sweep.xyz_m, xyz)
    assert sweep.stamps_ns.dtype == np.int64
    np.testing.assert_array_equal(sweep.stamps_ns, point_ns)
    np.testing.assert_array_equal(sweep.reflectivity, inten)
    np.testing.assert_array_equal(sweep.tag, tags)
    np.testing.assert_array_equal(sweep.line, lines)
    assert sweep.tag is not None and sweep.tag.dtype == np.uint8


@pytest.mark.parametrize("v", VERSIONS)
def test_legacy_18_byte_pointcloud2_uses_header_stamp(v):
    n = 6
    xyz, inten = random_points(n)
    data = b"".join(struct.pack("<ffffBB", *xyz[i], inten[i], i, i % 4) for i in range(n))
    sweep = sweep_of(POINTCLOUD2_TYPE, cloud_raw(v, LEGACY_FIELDS, 18, data, 1, n), v)
    np.testing.assert_array_equal(sweep.xyz_m, xyz)
    np.testing.assert_array_equal(sweep.stamps_ns, np.full(n, STAMP_NS))
    np.testing.assert_array_equal(sweep.reflectivity, inten)
    np.testing.assert_array_equal(sweep.tag, np.arange(n))
    np.testing.assert_array_equal(sweep.line, np.arange(n) % 4)


@pytest.mark.parametrize("v", VERSIONS)
def test_padded_point_step_pcl_xyzi(v):
    """PCL's PointXYZI: x, y, z at 0/4/8, intensity at 16, point_step 32; padding is garbage."""
    n = 5
    xyz, inten = random_points(n)
    data = bytearray(b"".join(struct.pack("<fff4xf12x", *xyz[i], inten[i]) for i in range(n)))
    for i in range(n):  # fill the padding with garbage that must be ignored
        data[32 * i + 12 : 32 * i + 16] = b"\xab" * 4
        data[32 * i + 20 : 32 * i + 32] = b"\xcd" * 12
    sweep = sweep_of(
        POINTCLOUD2_TYPE,
        cloud_raw(
            v, [("x", 0, F32), ("y", 4, F32), ("z", 8, F32), ("intensity", 16, F32)], 32, bytes(data), 1, n
        ),
        v,
    )
    np.testing.assert_array_equal(sweep.xyz_m, xyz)
    np.testing.assert_array_equal(sweep.reflectivity, inten)
    assert sweep.tag is None and sweep.line is None


@pytest.mark.parametrize("v", VERSIONS)
@pytest.mark.parametrize("given_row_step", [64, 0])
def test_row_step_padding_and_zero(v, given_row_step):
    """An organised 2x3 cloud whose rows carry 16 bytes of padding (row_step 64 > 3 x 16); 0 means packed."""
    height, width = 2, 3
    xyz, _ = random_points(height * width)
    pad = 16 if given_row_step else 0
    rows = [
        b"".join(struct.pack("<fff4x", *xyz[r * width + c]) for c in range(width)) + b"\xee" * pad
        for r in range(height)
    ]
    raw = cloud_raw(
        v,
        [("x", 0, F32), ("y", 4, F32), ("z", 8, F32)],
        16,
        b"".join(rows),
        height,
        width,
        row_step=given_row_step,
    )
    cloud = decode_pointcloud2(raw, v)
    assert cloud.points.shape == (6,)
    np.testing.assert_array_equal(sweep_from_pointcloud(cloud).xyz_m, xyz)


def test_float64_xyz_stays_float64():
    xyz = RNG.uniform(-5, 5, (4, 3))
    data = b"".join(struct.pack("<ddd", *p) for p in xyz)
    sweep = sweep_of(
        POINTCLOUD2_TYPE, cloud_raw(2, [("x", 0, F64), ("y", 8, F64), ("z", 16, F64)], 24, data, 1, 4), 2
    )
    assert sweep.xyz_m.dtype == np.float64
    np.testing.assert_array_equal(sweep.xyz_m, xyz)


def test_empty_pointcloud2():
    sweep = sweep_of(POINTCLOUD2_TYPE, cloud_raw(2, LIVOX_FIELDS, 26, b"", 1, 0), 2)
    assert sweep.xyz_m.shape == (0, 3) and sweep.stamps_ns.shape == (0,)


@pytest.mark.parametrize(
    ("fields", "point_step", "data", "width", "message"),
    [
        ([("x", 0, F32), ("y", 4, F32), ("z", 8, F32)], 12, b"\0" * 20, 2, "needs 24 data bytes, has 20"),
        ([("x", 0, F32), ("y", 4, F32), ("z", 8, F64)], 12, b"\0" * 24, 2, "does not fit in point_step 12"),
        ([("x", 0, 9), ("y", 4, F32), ("z", 8, F32)], 12, b"\0" * 24, 2, "datatype 9"),
        ([("x", 0, F32), ("x", 4, F32), ("z", 8, F32)], 12, b"\0" * 24, 2, "empty or repeated"),
    ],
)
def test_malformed_pointcloud2(fields, point_step, data, width, message):
    with pytest.raises(MessageDecodeError, match=message):
        decode_pointcloud2(cloud_raw(2, fields, point_step, data, 1, width), 2)


def test_pointcloud2_without_xyz_is_not_a_sweep():
    raw = cloud_raw(2, [("range", 0, F32)], 4, b"\0" * 8, 1, 2)
    assert decode_pointcloud2(raw, 2).points["range"].tolist() == [0.0, 0.0]
    with pytest.raises(MessageDecodeError, match=r"no x/y/z field; fields are \['range'\]"):
        sweep_of(POINTCLOUD2_TYPE, raw, 2)


# ---------------------------------------------------------------- Image

H, W, PAD = 5, 7, 5
BGR = RNG.integers(0, 256, (H, W, 3), dtype=np.uint8)
GREY = RNG.integers(0, 256, (H, W), dtype=np.uint8)
GREY16 = RNG.integers(0, 65536, (H, W), dtype=np.uint16)


def image_raw(v, encoding, pixels, big=False, pad=PAD, frame_id="cam0"):
    """Serialise `pixels` (H, W[, C]) with `pad` garbage bytes after every row."""
    h, w = pixels.shape[:2]
    rows = pixels.reshape(h, -1)
    if pixels.dtype == np.uint16:
        rows = rows.astype(">u2" if big else "<u2").view(np.uint8).reshape(h, -1)
    data = np.concatenate([rows, np.full((h, pad), 0x5A, np.uint8)], axis=1)
    msg = typestore(v).types[IMAGE_TYPE](
        header=header(v, frame_id=frame_id), height=h, width=w, encoding=encoding,
        is_bigendian=big, step=data.shape[1], data=data.reshape(-1),
    )  # fmt: skip
    return serialize(v, msg, IMAGE_TYPE)


ALPHA = np.full((H, W, 1), 77, np.uint8)
IMAGE_CASES: dict[str, tuple[np.ndarray, np.ndarray]] = {
    "bgr8": (BGR, BGR),
    "rgb8": (BGR[:, :, ::-1], BGR),
    "bgra8": (np.concatenate([BGR, ALPHA], axis=2), BGR),
    "rgba8": (np.concatenate([BGR[:, :, ::-1], ALPHA], axis=2), BGR),
    "mono8": (GREY, GREY),
    "mono16": (GREY16, GREY16),
}


@pytest.mark.parametrize("v", VERSIONS)
@pytest.mark.parametrize("encoding", sorted(IMAGE_CASES))
@pytest.mark.parametrize("pad", [0, PAD])
def test_image_encodings_with_step_padding(v, encoding, pad):
    pixels, expected = IMAGE_CASES[encoding]
    frame = frame_of(IMAGE_TYPE, image_raw(v, encoding, pixels, pad=pad), v)
    assert (frame.stamp_ns, frame.frame_id) == (STAMP_NS, "cam0")
    assert frame.image.dtype == expected.dtype and frame.image.shape == expected.shape
    assert frame.image.flags.c_contiguous
    np.testing.assert_array_equal(frame.image, expected)


@pytest.mark.parametrize("encoding", sorted(IMAGE_CASES))
@pytest.mark.parametrize("pad", [0, PAD])
def test_keep_bgra_gives_a_bgra8_image_as_recorded_and_the_others_as_before(encoding, pad):
    pixels, expected = IMAGE_CASES[encoding]
    if encoding == "bgra8":
        expected = pixels
    frame = decode(IMAGE_TYPE, image_raw(2, encoding, pixels, pad=pad), 2, keep_bgra=True)
    assert isinstance(frame, Frame) and frame.image.flags.c_contiguous
    assert frame.image.dtype == expected.dtype and frame.image.shape == expected.shape
    np.testing.assert_array_equal(frame.image, expected)


def test_mono16_big_endian():
    frame = decode_image(image_raw(2, "mono16", GREY16, big=True), 2)
    assert frame.image.dtype == np.uint16 and frame.image.dtype.isnative
    np.testing.assert_array_equal(frame.image, GREY16)


BAYER = {  # ROS pattern -> OpenCV's pattern-named conversion (OpenCV >= 4.10 spells the top-left quad)
    "rggb": cv2.COLOR_BayerRGGB2BGR,
    "bggr": cv2.COLOR_BayerBGGR2BGR,
    "gbrg": cv2.COLOR_BayerGBRG2BGR,
    "grbg": cv2.COLOR_BayerGRBG2BGR,
}


def mosaic_of(bgr, pattern):
    """Sample a BGR image through a Bayer filter whose top-left 2x2 quad is `pattern`."""
    channel = {"b": 0, "g": 1, "r": 2}
    out = np.empty(bgr.shape[:2], bgr.dtype)
    for k, (dy, dx) in enumerate([(0, 0), (0, 1), (1, 0), (1, 1)]):
        out[dy::2, dx::2] = bgr[dy::2, dx::2, channel[pattern[k]]]
    return out


@pytest.mark.parametrize("v", VERSIONS)
@pytest.mark.parametrize("pattern", sorted(BAYER))
def test_bayer8_matches_cvtcolor_and_recovers_a_flat_colour(v, pattern):
    mosaic = RNG.integers(0, 256, (8, 10), dtype=np.uint8)
    frame = frame_of(IMAGE_TYPE, image_raw(v, f"bayer_{pattern}8", mosaic), v)
    np.testing.assert_array_equal(frame.image, cv2.cvtColor(mosaic, BAYER[pattern]))

    flat = np.empty((8, 10, 3), np.uint8)
    flat[:] = (10, 100, 200)  # B, G, R
    frame = frame_of(IMAGE_TYPE, image_raw(v, f"bayer_{pattern}8", mosaic_of(flat, pattern)), v)
    np.testing.assert_array_equal(frame.image[2:-2, 2:-2], flat[2:-2, 2:-2])


@pytest.mark.parametrize("pattern", sorted(BAYER))
def test_bayer16_is_scaled_to_uint8(pattern):
    flat = np.empty((8, 10, 3), np.uint16)
    flat[:] = (10 * 257, 100 * 257, 200 * 257)
    frame = decode_image(image_raw(2, f"bayer_{pattern}16", mosaic_of(flat, pattern)), 2)
    assert frame.image.dtype == np.uint8
    np.testing.assert_array_equal(
        frame.image[2:-2, 2:-2], np.broadcast_to(np.array([10, 100, 200], np.uint8), (4, 6, 3))
    )


def test_bad_images():
    with pytest.raises(MessageDecodeError, match="encoding 'yuv422' is not supported"):
        decode_image(image_raw(2, "yuv422", GREY), 2)
    msg: Any = typestore(2).types[IMAGE_TYPE](
        header=header(2),
        height=4,
        width=4,
        encoding="bgr8",
        is_bigendian=0,
        step=10,
        data=np.zeros(40, np.uint8),
    )
    with pytest.raises(MessageDecodeError, match="step 10 < 12 bytes per row"):
        decode_image(serialize(2, msg, IMAGE_TYPE), 2)
    msg.step = 12
    with pytest.raises(MessageDecodeError, match="needs 48 data bytes, has 40"):
        decode_image(serialize(2, msg, IMAGE_TYPE), 2)
    msg.data = np.zeros(96, np.uint8)  # twice too long: another size or encoding than the header says
    with pytest.raises(MessageDecodeError, match="needs 48 data bytes, has 96"):
        decode_image(serialize(2, msg, IMAGE_TYPE), 2)
    msg.step = 16  # padded rows: the last row's padding may be left out, nothing more
    for size in (60, 64):
        msg.data = np.zeros(size, np.uint8)
        assert decode_image(serialize(2, msg, IMAGE_TYPE), 2).image.shape == (4, 4, 3)
    msg.data = np.zeros(65, np.uint8)
    with pytest.raises(MessageDecodeError, match=r"Image bgr8 4x4 step 16 needs 60\.\.64 data bytes, has 65"):
        decode_image(serialize(2, msg, IMAGE_TYPE), 2)
    with pytest.raises(MessageDecodeError, match="not a valid ROS 2 sensor_msgs/msg/Image"):
        decode_image(b"\x00\x01\x00\x00\x01", 2)


# ---------------------------------------------------------------- CompressedImage


def compressed_raw(v, fmt, data):
    msg = typestore(v).types[COMPRESSED_IMAGE_TYPE](
        header=header(v, frame_id="cam1"), format=fmt, data=np.frombuffer(data, np.uint8)
    )
    return serialize(v, msg, COMPRESSED_IMAGE_TYPE)


_U, _V = np.meshgrid(np.linspace(0, 200, 64), np.linspace(20, 220, 48))
SMOOTH = np.dstack([_U, _V, np.full((48, 64), 128.0)]).astype(np.uint8)


@pytest.mark.parametrize("v", VERSIONS)
def test_compressed_png_round_trip_is_exact(v):
    _, png = cv2.imencode(".png", SMOOTH)
    frame = frame_of(COMPRESSED_IMAGE_TYPE, compressed_raw(v, "png", png.tobytes()), v)
    assert (frame.stamp_ns, frame.frame_id) == (STAMP_NS, "cam1")
    np.testing.assert_array_equal(frame.image, SMOOTH)


@pytest.mark.parametrize("v", VERSIONS)
def test_compressed_jpeg_round_trip(v):
    _, jpg = cv2.imencode(".jpg", SMOOTH, [cv2.IMWRITE_JPEG_QUALITY, 95])
    frame = decode_compressed_image(compressed_raw(v, "bgr8; jpeg compressed bgr8", jpg.tobytes()), v)
    assert frame.image.shape == SMOOTH.shape and frame.image.dtype == np.uint8
    assert np.abs(frame.image.astype(int) - SMOOTH).mean() < 2.0
    assert np.abs(frame.image.astype(int) - SMOOTH[:, :, ::-1]).mean() > 20  # BGR, not RGB


def test_a_jpeg_exif_orientation_is_not_applied():
    """Sweep 7 U7: an APP1 Exif segment with Orientation 3 turned cam0's images 180 deg while the depth GT
    stayed the sensor's (blamed on a LiDAR pose). The camchain describes the sensor's pixels: the tag is
    left unapplied, and the frame is the JPEG without it, pixel for pixel."""
    _, jpg = cv2.imencode(".jpg", SMOOTH, [cv2.IMWRITE_JPEG_QUALITY, 95])
    plain = jpg.tobytes()
    tiff = b"II*\x00" + struct.pack("<I", 8) + struct.pack("<H", 1) + struct.pack("<HHII", 0x0112, 3, 1, 3)
    tiff += struct.pack("<I", 0)  # one IFD entry (Orientation = 3: turned 180 deg), no next IFD
    exif = b"Exif\x00\x00" + tiff
    tagged = plain[:2] + b"\xff\xe1" + struct.pack(">H", len(exif) + 2) + exif + plain[2:]
    turned = cv2.imdecode(np.frombuffer(tagged, np.uint8), cv2.IMREAD_COLOR)  # OpenCV applies the tag
    assert turned is not None and np.abs(turned.astype(int) - SMOOTH[::-1, ::-1]).mean() < 2
    frame = decode_compressed_image(compressed_raw(2, "jpeg", tagged), 2)
    expected = decode_compressed_image(compressed_raw(2, "jpeg", plain), 2)
    np.testing.assert_array_equal(frame.image, expected.image)


def test_compressed_grey_png_is_mono():
    _, png = cv2.imencode(".png", GREY)
    frame = decode_compressed_image(compressed_raw(2, "mono8; png compressed", png.tobytes()), 2)
    np.testing.assert_array_equal(frame.image, GREY)


@pytest.mark.parametrize("data", [b"", b"not a jpeg at all"])
def test_compressed_garbage(data):
    with pytest.raises(MessageDecodeError, match=r"format 'jpeg'.*could not be decoded"):
        decode_compressed_image(compressed_raw(2, "jpeg", data), 2)


# ---------------------------------------------------------------- Imu


@pytest.mark.parametrize("v", VERSIONS)
def test_imu(v):
    ts = typestore(v).types
    vec, quat = ts["geometry_msgs/msg/Vector3"], ts["geometry_msgs/msg/Quaternion"]
    msg = ts[IMU_TYPE](
        header=header(v, frame_id="livox_imu"),
        orientation=quat(x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=np.zeros(9),
        angular_velocity=vec(x=0.01, y=-0.02, z=0.5),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=vec(x=0.02, y=-0.01, z=1.0),  # g, as the Livox driver stores it
        linear_acceleration_covariance=np.zeros(9),
    )
    sample = decode(IMU_TYPE, serialize(v, msg, IMU_TYPE), v)
    assert isinstance(sample, ImuSample)
    assert (sample.stamp_ns, sample.frame_id) == (STAMP_NS, "livox_imu")
    np.testing.assert_array_equal(sample.gyro_rad_s, [0.01, -0.02, 0.5])
    np.testing.assert_array_equal(sample.acc, [0.02, -0.01, 1.0])
    direct = decode_imu(serialize(v, msg, IMU_TYPE), v)
    np.testing.assert_array_equal(direct.acc, sample.acc)


# ---------------------------------------------------------------- Livox CustomMsg and dispatch


def custom_msg_raw(v, pkg, n, frame_id="livox_frame", timebase=STAMP_NS - 5000):
    ts = typestore(v)
    point = ts.types[f"{pkg}/msg/CustomPoint"]
    pts = [
        point(offset_time=int(1000 * i + 7), x=float(np.float32(0.5 * i)), y=float(np.float32(-1.25 * i)),
              z=float(np.float32(0.1 + i)), reflectivity=i % 256, tag=(3 * i) % 256, line=i % 4)
        for i in range(n)
    ]  # fmt: skip
    msg = ts.types[f"{pkg}/msg/CustomMsg"](
        header=header(v, frame_id=frame_id), timebase=timebase, point_num=n, lidar_id=192,
        rsvd=np.zeros(3, np.uint8), points=pts,
    )  # fmt: skip
    return serialize(v, msg, f"{pkg}/msg/CustomMsg")


@pytest.mark.parametrize("v", VERSIONS)
@pytest.mark.parametrize("pkg", ["livox_ros_driver", "livox_ros_driver2"])
@pytest.mark.parametrize("frame_id", ["", "abc", "livox_frame"])
def test_custom_msg_sweep(v, pkg, frame_id):
    n = 11
    timebase = STAMP_NS - 5000
    sweep = sweep_of(f"{pkg}/msg/CustomMsg", custom_msg_raw(v, pkg, n, frame_id, timebase), v)
    i = np.arange(n)
    assert (sweep.stamp_ns, sweep.frame_id) == (STAMP_NS, frame_id)
    assert sweep.xyz_m.dtype == np.float32
    np.testing.assert_array_equal(
        sweep.xyz_m, np.stack([0.5 * i, -1.25 * i, 0.1 + i], axis=1).astype(np.float32)
    )
    np.testing.assert_array_equal(sweep.stamps_ns, timebase + 1000 * i + 7)
    np.testing.assert_array_equal(sweep.reflectivity, i)
    np.testing.assert_array_equal(sweep.tag, 3 * i)
    np.testing.assert_array_equal(sweep.line, i % 4)


def test_dispatch_accepts_ros1_style_names_and_refuses_unknown_types():
    raw = custom_msg_raw(1, "livox_ros_driver", 2)
    assert sweep_of("livox_ros_driver/CustomMsg", raw, 1).stamps_ns.tolist() == [
        STAMP_NS - 5000 + 7,
        STAMP_NS - 5000 + 1007,
    ]
    assert {"livox_ros_driver/msg/CustomMsg", "livox_ros_driver2/msg/CustomMsg", IMAGE_TYPE} <= DECODED_TYPES
    with pytest.raises(MessageDecodeError, match="no decoder for message type 'std_msgs/msg/String'"):
        decode("std_msgs/msg/String", b"", 2)
    with pytest.raises(ValueError, match="ros_version must be 1 or 2"):
        decode(IMAGE_TYPE, b"", 3)  # type: ignore[arg-type]


def test_a_sweeps_span_is_its_earliest_and_latest_point_whatever_their_order():
    from ingest.bags.decode import Sweep

    sweep = Sweep(100, "lidar", np.zeros((3, 3)), np.array([150, 90, 120], np.int64))
    assert sweep.span_ns == (90, 150)
    assert Sweep(100, "lidar", np.zeros((0, 3)), np.zeros(0, np.int64)).span_ns == (100, 100)


def test_a_compressed_message_in_a_bag_that_says_none_is_named_so() -> None:
    """Sweep 8: a rosbag2 whose metadata.yaml says no compression while every blob is zstd: the line said
    only 'Invalid or unsupported CDR encapsulation', as of a damaged message."""
    import zstandard

    from ingest.bags.decode import decode
    from ingest.bags.rostypes import IMU_TYPE

    raw = zstandard.ZstdCompressor().compress(b"\x00\x01\x00\x00" + bytes(300))
    with pytest.raises(MessageDecodeError) as err:
        decode(IMU_TYPE, raw)
    assert str(err.value).endswith(
        "(they begin with zstd's magic number: the message is zstd-compressed, which the bag's metadata does not "
        "say: check its compression_format and compression_mode)"
    )
