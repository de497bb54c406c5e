"""Livox Mid-360 protocol: CRC check values, hand-built frames, data packet decoding, per-point time."""

from __future__ import annotations

import binascii
import struct
import zlib

import numpy as np
import pytest

from sensorbox.errors import ProtocolError
from sensorbox.livox import packets
from sensorbox.livox import protocol as proto
from sensorbox.livox.protocol import ControlFrame
from sensorbox.livox.tracking import SeqTracker, extrinsic_rotation, to_metres

# --------------------------------------------------------------------------- CRCs


def test_crc_check_values():
    """The published check values of both CRCs over "123456789"."""
    assert proto.crc16_ccitt_false(b"123456789") == 0x29B1
    assert proto.crc32(b"123456789") == 0xCBF43926
    assert proto.crc16_ccitt_false(b"") == 0xFFFF  # init, no xorout


def test_crc16_matches_an_independent_implementation():
    """binascii.crc_hqx with init 0xFFFF is CRC-16/CCITT-FALSE (same poly, no reflection, no xorout)."""
    rng = np.random.default_rng(1)
    for n in (1, 2, 17, 18, 64, 1400):
        data = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        assert proto.crc16_ccitt_false(data) == binascii.crc_hqx(data, 0xFFFF)


# --------------------------------------------------------------------------- control frames


def test_discovery_request_bytes():
    """Empty payload: length 24, CRC-16 over bytes 0..17, CRC-32 field 0 (as the SDK writes it)."""
    raw = proto.build_control_frame(ControlFrame(proto.CMD_DISCOVERY, proto.REQ, proto.SENDER_HOST, 0))
    assert raw == bytes.fromhex("aa0018000000000000000000000000000000c86400000000")
    assert binascii.crc_hqx(raw[:18], 0xFFFF) == 0x64C8


def test_set_work_mode_frame_bytes():
    """0x0100 with one key (0x001A = 0x01), seq 5, built by hand."""
    payload = struct.pack("<HHHHB", 1, 0, 0x001A, 1, 0x01)
    assert proto.encode_kv_list([(proto.KEY_WORK_MODE, b"\x01")]) == payload
    raw = proto.build_control_frame(
        ControlFrame(proto.CMD_SET_PARAMS, proto.REQ, proto.SENDER_HOST, 5, payload)
    )
    assert raw == bytes.fromhex("aa002100050000000001000000000000000090d56fd5e7ad010000001a00010001")
    assert struct.unpack_from("<H", raw, 18)[0] == binascii.crc_hqx(raw[:18], 0xFFFF) == 0xD590
    assert struct.unpack_from("<I", raw, 20)[0] == zlib.crc32(payload) == 0xADE7D56F
    frame = proto.parse_control_frame(raw)
    assert frame == ControlFrame(0x0100, 0, 0, 5, payload)
    assert proto.decode_kv_list(frame.payload) == [(0x001A, b"\x01")]


def test_seq_is_masked_to_16_bits():
    raw = proto.build_control_frame(ControlFrame(proto.CMD_QUERY_PARAMS, proto.REQ, 0, 0x12345))
    assert struct.unpack_from("<I", raw, 4)[0] == 0x2345


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda b: b[:20], "shorter than its 24-byte header"),
        (lambda b: b"\xab" + b[1:], "expected 0xaa"),
        (lambda b: b[:1] + b"\x01" + b[2:], "version 1"),
        (lambda b: b + b"\0", "length field 33 != datagram size 34"),
        (lambda b: b[:8] + b"\x02" + b[9:], "CRC-16"),
        (lambda b: b[:-1] + b"\x02", "CRC-32"),
    ],
)
def test_bad_control_frames_are_rejected(mutate, message):
    raw = bytes.fromhex("aa002100050000000001000000000000000090d56fd5e7ad010000001a00010001")
    with pytest.raises(ProtocolError, match=message):
        proto.parse_control_frame(mutate(raw))


def test_empty_payload_with_nonzero_crc32_is_rejected():
    raw = bytearray(bytes.fromhex("aa0018000000000000000000000000000000c86400000000"))
    raw[20] = 1
    with pytest.raises(ProtocolError, match="CRC-32"):
        proto.parse_control_frame(bytes(raw))


def test_host_address_value_and_kv_round_trip():
    value = proto.host_address_value("192.168.1.50", 56301, 56300)
    assert value == bytes([192, 168, 1, 50]) + struct.pack("<HH", 56301, 56300)
    assert proto.decode_host_address(value) == ("192.168.1.50", 56301, 56300)
    items = [(proto.KEY_STATE_HOST, value), (proto.KEY_PCL_DATA_TYPE, b"\x01"), (0x8001, b"x" * 64)]
    assert proto.decode_kv_list(proto.encode_kv_list(items)) == items
    with pytest.raises(ProtocolError, match="says 8 bytes"):
        proto.decode_kv_list(proto.encode_kv_list(items[:1])[:-2])
    with pytest.raises(ProtocolError, match="left after"):
        proto.decode_kv_list(proto.encode_kv_list(items) + b"\0")


def test_install_attitude_value_layout():
    raw = proto.install_attitude_value((1.5, -2.0, 180.0, 10.0, -20.0, 300.0))
    assert len(raw) == 24
    assert struct.unpack("<3f3i", raw) == (1.5, -2.0, 180.0, 10, -20, 300)


def test_acks_and_queries():
    assert proto.encode_set_ack(0x03, 0x001A) == b"\x03\x1a\x00"
    assert proto.decode_set_ack(b"\x00\x00\x00") == (0, 0)
    with pytest.raises(ProtocolError):
        proto.decode_set_ack(b"\x00")
    assert proto.encode_query([0x8000, 0x001A]) == struct.pack("<HHHH", 2, 0, 0x8000, 0x001A)
    assert proto.decode_query(proto.encode_query([0x8000, 0x001A])) == [0x8000, 0x001A]
    ack = proto.encode_query_ack(0, [(0x001A, b"\x01")])
    assert ack == struct.pack("<BHHHB", 0, 1, 0x001A, 1, 1)
    assert proto.decode_query_ack(ack) == (0, [(0x001A, b"\x01")])


def test_discovery_ack_layout():
    info = proto.DeviceInfo("192.168.1.112", "47MDL9A0010012", 9, 56100)
    raw = proto.encode_discovery_ack(info)
    assert raw == b"\x00\x09" + b"47MDL9A0010012\0\0" + bytes([192, 168, 1, 112]) + struct.pack("<H", 56100)
    assert proto.decode_discovery_ack(raw) == info


# --------------------------------------------------------------------------- data packets


def _hand_packet(
    data_type: int, points: bytes, dot_num: int, stamp: int, cnt: int, time_type: int = 1
) -> bytes:
    """A point datagram built field by field from the notes' offsets."""
    body = struct.pack("<Q", stamp) + points
    head = struct.pack("<BHHHHBBB12s", 0, 36 + len(points), 4750, dot_num, cnt, 0, data_type, time_type, b"")
    return head + struct.pack("<I", zlib.crc32(body)) + body


def test_point_packet_builder_matches_hand_built_bytes():
    rng = np.random.default_rng(2)
    pts = np.zeros((2, 96), packets.POINT_DTYPES[1])
    for name in ("x", "y", "z"):
        pts[name] = rng.integers(-70_000, 70_000, (2, 96))
    pts["reflectivity"] = rng.integers(0, 256, (2, 96))
    pts["tag"] = rng.integers(0, 256, (2, 96))
    stamps = np.array([1_700_000_000_000_480_000, 1_700_000_000_000_960_000])
    built = packets.build_point_packets(1, 1, stamps, np.array([65535, 65536]), pts)
    assert built.shape == (2, 1380)
    for k in range(2):
        raw = b"".join(
            struct.pack("<iiiBB", *(int(pts[n][k, i]) for n in ("x", "y", "z", "reflectivity", "tag")))
            for i in range(96)
        )
        assert built[k].tobytes() == _hand_packet(1, raw, 96, int(stamps[k]), (65535 + k) & 0xFFFF)


def test_imu_packet_bytes_and_decode():
    raw = packets.build_imu_packet(1, 123_456_789, 7, np.array([0.1, -0.2, 0.3]), np.array([0.0, 0.0, 1.0]))
    assert len(raw) == 60
    body = struct.pack("<Q6f", 123_456_789, 0.1, -0.2, 0.3, 0.0, 0.0, 1.0)
    assert raw[:24] == struct.pack("<BHHHHBBB12s", 0, 60, 0, 1, 7, 0, 0, 1, b"")
    assert raw[24:] == struct.pack("<I", zlib.crc32(body)) + body
    pkt = packets.decode_imu_packet(raw)
    assert (pkt.udp_cnt, pkt.time_type, pkt.timestamp_ns) == (7, 1, 123_456_789)
    np.testing.assert_array_equal(pkt.gyro_rad_s, np.array([0.1, -0.2, 0.3], np.float32))
    np.testing.assert_array_equal(pkt.acc_g, [0.0, 0.0, 1.0])
    for bad in (raw[:59], raw[:10] + b"\x01" + raw[11:], raw[:-1] + b"\x00"):
        with pytest.raises(ProtocolError):
            packets.decode_imu_packet(bad)


def test_point_times_follow_the_driver_rule():
    """4750 * 100 // 96 = 4947 ns (integer division by dot_num, not dot_num - 1)."""
    t = packets.point_times_ns(np.array([1000, 2000]), np.array([4750, 100]), np.array([96, 3]), 96)
    assert t[0, 1] - t[0, 0] == 4947
    assert t[0, 95] == 1000 + 95 * 4947
    assert t[1, 2] == 2000 + 2 * (10_000 // 3)


def _slots(datagrams: list[bytes], slot: int = 2048) -> tuple[bytearray, np.ndarray]:
    buf = bytearray(slot * len(datagrams))
    for k, d in enumerate(datagrams):
        n = min(len(d), slot)  # recvfrom_into truncates to the slot
        buf[k * slot : k * slot + n] = d[:n]
    return buf, np.array([min(len(d), slot) for d in datagrams])


def test_decode_batch_groups_data_types_and_names_each_reject():
    p1 = _hand_packet(1, struct.pack("<iiiBB", 1000, -2000, 3000, 10, 0b0100) * 96, 96, 5_000, 1)
    p2 = _hand_packet(2, struct.pack("<hhhBB", 100, -200, 300, 20, 0) * 96, 96, 6_000, 2)
    p3 = _hand_packet(3, struct.pack("<IHHBB", 5000, 9000, 4500, 30, 1) * 96, 96, 7_000, 3)
    bad = {
        "short": p1[:35],
        "oversized": p1 * 2,
        "version": b"\x01" + p1[1:],
        "length": p1[:1] + struct.pack("<H", 1381) + p1[3:],
        "data_type": p1[:10] + b"\x07" + p1[11:],
        "dot_num": p1[:5] + struct.pack("<H", 95) + p1[7:],
        "crc32": p1[:-1] + b"\xff",
    }
    imu = packets.build_imu_packet(1, 1, 1, np.zeros(3), np.zeros(3))
    datagrams = [p1, *bad.values(), p2, p3, imu]
    buf, sizes = _slots(datagrams)
    groups, rejects = packets.decode_point_batch(buf, 2048, sizes)
    assert {r: rows.tolist() for r, rows in rejects.items()} == {
        "short": [1], "oversized": [2], "version": [3], "length": [4], "data_type": [5, 10], "dot_num": [6],
        "crc32": [7],
    }  # fmt: skip
    by_type = {g.data_type: g for g in groups}
    assert sorted(by_type) == [1, 2, 3]
    g1 = by_type[1]
    assert g1.rows.tolist() == [0] and g1.points.shape == (1, 96)
    assert g1.header["timestamp"][0] == 5_000 and g1.header["udp_cnt"][0] == 1
    np.testing.assert_array_equal(packets.native_xyz(1, g1.points)[0, 5], [1000, -2000, 3000])
    np.testing.assert_allclose(to_metres(1, packets.native_xyz(1, g1.points))[0, 0], [1.0, -2.0, 3.0])
    np.testing.assert_allclose(to_metres(2, packets.native_xyz(2, by_type[2].points))[0, 0], [1.0, -2.0, 3.0])
    # spherical: r = 5 m, theta 90 deg (horizon), phi 45 deg
    xyz = to_metres(3, packets.native_xyz(3, by_type[3].points))[0, 0]
    np.testing.assert_allclose(xyz, [5 / np.sqrt(2), 5 / np.sqrt(2), 0.0], atol=1e-12)
    assert by_type[3].points["reflectivity"][0, 0] == 30 and g1.points["tag"][0, 0] == 0b0100
    # without the CRC check the bit-flipped packet is accepted
    _, rejects = packets.decode_point_batch(buf, 2048, sizes, check_crc=False)
    assert "crc32" not in rejects


def test_decode_batch_never_raises_on_garbage():
    rng = np.random.default_rng(3)
    datagrams = [rng.integers(0, 256, int(n), dtype=np.uint8).tobytes() for n in rng.integers(0, 3000, 200)]
    # garbage with a plausible header too
    good = _hand_packet(1, b"\0" * 14 * 96, 96, 0, 0)
    datagrams += [good[:36] + rng.integers(0, 256, 1344, dtype=np.uint8).tobytes() for _ in range(20)]
    buf, sizes = _slots(datagrams)
    groups, rejects = packets.decode_point_batch(buf, 2048, sizes)
    n_ok = sum(len(g.rows) for g in groups)
    assert n_ok + sum(len(r) for r in rejects.values()) == len(datagrams)
    assert n_ok == 0  # random bytes never pass the CRC


@pytest.mark.parametrize("data_type", [1, 2, 3])
def test_quantise_then_decode_is_within_one_unit(data_type):
    rng = np.random.default_rng(4)
    xyz = rng.uniform(-60, 60, (500, 3))
    xyz[:10] = 0.0  # no-return points stay all zero
    q = packets.quantise_points(data_type, xyz, np.zeros(500, np.uint8), np.zeros(500, np.uint8))
    back = to_metres(data_type, packets.native_xyz(data_type, q))
    assert (back[:10] == 0).all()
    r = np.linalg.norm(xyz, axis=1)
    tol = {1: 0.5e-3 * np.sqrt(3), 2: 5e-3 * np.sqrt(3), 3: 0.5e-3 + r * np.radians(0.01)}[data_type]
    assert (np.linalg.norm(back - xyz, axis=1) <= tol + 1e-9).all()


def test_spherical_azimuth_just_below_360_degrees_wraps_to_0():
    """Spherical phi is 0.01-degree steps in [0, 36000): an azimuth of -0.001 deg (359.999) rounds to
    36000, which is 0 on the wire; theta is the zenith angle, 90 deg (9000) in the x-y plane."""
    xyz = np.array([[10.0, -10.0 * np.tan(np.radians(0.001)), 0.0], [0.0, 10.0, 0.0]])
    q = packets.quantise_points(3, xyz, np.zeros(2, np.uint8), np.zeros(2, np.uint8))
    assert q["phi"].tolist() == [0, 9000] and q["theta"].tolist() == [9000, 9000]
    assert q["depth"].tolist() == [10000, 10000]


def test_cartesian_coordinates_beyond_the_field_saturate_instead_of_wrapping():
    """Data type 2 stores 10 mm units in int16: 400 m (40000) saturates at 32767 (327.67 m) and -400 m at
    -32768, never wraps to the other side; data type 1 (mm, int32) holds 400 m exactly."""
    xyz = np.array([[400.0, -400.0, 1.0]])
    zero = np.zeros(1, np.uint8)
    q2 = packets.quantise_points(2, xyz, zero, zero)
    assert (int(q2["x"][0]), int(q2["y"][0]), int(q2["z"][0])) == (32767, -32768, 100)
    q1 = packets.quantise_points(1, xyz, zero, zero)
    assert (int(q1["x"][0]), int(q1["y"][0]), int(q1["z"][0])) == (400000, -400000, 1000)


def test_extrinsic_rotation_convention():
    """R = Rz(yaw) Ry(pitch) Rx(roll): yaw 90 deg maps x to y; roll 90 deg maps y to z."""
    np.testing.assert_allclose(extrinsic_rotation(0, 0, 90) @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(extrinsic_rotation(90, 0, 0) @ [0, 1, 0], [0, 0, 1], atol=1e-15)
    np.testing.assert_allclose(extrinsic_rotation(0, 90, 0) @ [0, 0, 1], [1, 0, 0], atol=1e-15)
    r, p, y = np.radians([10.0, -20.0, 30.0])
    Rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    Ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    Rz = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
    np.testing.assert_allclose(extrinsic_rotation(10, -20, 30), Rz @ Ry @ Rx, atol=1e-15)
    # translation in mm, applied before the division to metres; data type 2 uses t // 10 (10 mm units)
    ext = (0.0, 0.0, 90.0, 100.0, 200.0, 305.0)
    np.testing.assert_allclose(to_metres(1, np.array([[1000.0, 0, 0]]), ext), [[0.1, 1.2, 0.305]], atol=1e-12)
    np.testing.assert_allclose(to_metres(2, np.array([[100.0, 0, 0]]), ext), [[0.1, 1.2, 0.30]], atol=1e-12)
    np.testing.assert_allclose(to_metres(3, np.array([[1.0, 0, 0]]), ext), [[0.1, 1.2, 0.305]], atol=1e-12)
    # data type 2 (cm): the driver's C++ integer division truncates the mm translation toward zero
    ext = (0.0, 0.0, 0.0, 17.0, -17.0, -9.0)
    np.testing.assert_allclose(to_metres(2, np.array([[100.0, 0, 0]]), ext), [[1.01, -0.01, 0.0]], atol=1e-12)


# --------------------------------------------------------------------------- udp_cnt accounting


def _track(cnts: list[int]) -> SeqTracker:
    t = SeqTracker()
    for c in cnts:
        t.add(c & 0xFFFF)
    return t


def test_seq_tracker_counts_loss_across_the_16_bit_wrap():
    t = _track([65533, 65534, 65535, 0, 2, 5])  # 1, 3, 4 missing
    assert (t.lost, t.duplicates, t.reordered) == (3, 0, 0)
    t = _track(list(range(65000, 65000 + 3 * 65536, 1)))  # three full wraps, nothing lost
    assert t.lost == 0 and t.unique == 3 * 65536


def test_seq_tracker_reorder_and_duplicates():
    t = _track([10, 12, 11, 13, 13, 12, 15])
    assert (t.lost, t.duplicates, t.reordered, t.unique) == (1, 2, 1, 5)
    t = _track([5, 4, 6])  # the first packet seen was itself late
    assert (t.lost, t.reordered) == (0, 1)


def test_seq_tracker_restarts_after_a_counter_reset():
    t = _track([*range(30_000, 30_100), *range(0, 50)])
    assert (t.jumps, t.lost, t.duplicates, t.unique) == (1, 0, 0, 150)  # every packet kept


def test_seq_tracker_tells_a_counter_jump_from_loss_by_the_time_that_passed():
    """480 us between packets: 27,546 missing counters 480 us later is a jump (kept, not lost). The
    packet clock decides: a gap it covers is loss, even when the packets arrived in a burst; a gap it
    does not cover is a counter jump, and a packet clock that leapt against the arrival clock as well
    is a time jump (`last_leapt`). Past half the counter range a gap is unwrapped."""
    t = SeqTracker()
    for k in range(10):
        t.add(k, 480_000 * k, 480_000 * k + 7)
    t.add(9 + 27_546, 480_000 * 10, 480_000 * 10 + 7)  # a spoofed or corrupted counter
    t.add(10, 480_000 * 11, 480_000 * 11 + 7)  # the stream goes on: a jump back
    assert t.highest is not None and t.lowest is not None
    assert (t.jumps, t.lost, t.unique, t.highest - t.lowest) == (2, 0, 12, 11)
    for clocks, jumps, lost, leapt in (
        ((13_222_080_000, 13_222_080_000 + 7), 0, 27_546, False),  # 13.2 s without packets
        ((13_222_080_000, 480_000), 0, 27_546, False),  # the same gap in a burst (a sender catching up)
        ((480_000, 13_222_080_000), 1, 0, False),  # the packet clock saw 480 us pass: the counter leapt
        ((1000 * 10**9, 480_000), 1, 0, True),  # both leapt
    ):
        t = SeqTracker()
        t.add(0, 0, 0)
        t.add(27_547, *clocks)
        assert (t.jumps, t.lost, t.last_leapt) == (jumps, lost, leapt), clocks
    t = SeqTracker()
    t.add(0, 0, 7)
    t.add(1, 1000 * 10**9, 480_007)  # the packet clock alone leapt: a time jump, no counter jump
    assert (t.jumps, t.lost, t.last_leapt) == (0, 0, True)
    t = SeqTracker()
    t.add(0, 0, 7)
    t.add(40_000 & 0xFFFF, 480_000 * 40_000, 480_000 * 40_000 + 7)  # 19.2 s: past half the counter range
    t.add((40_000 + 65_536 + 5) & 0xFFFF, 480_000 * (40_005 + 65_536), 480_000 * (40_005 + 65_536) + 7)
    assert (t.jumps, t.lost, t.highest) == (0, 39_999 + 65_536 + 4, 40_005 + 65_536)
