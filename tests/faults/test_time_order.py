"""Issue 49: stamps that run backwards in the bag's log order, and a topic carrying two kinds of messages,
are refused, naming the topic and the stamps or types.

The passes read a bag in log order and take it for time order: with the log
order reversed (every stamp unchanged) a sparse run kept 11,808 of 21,809
points of a window with every drop counter at 0; a camera whose header stamps
run backwards paired each image with another time's points without a word.
One message delivered late is still taken (`tests/ingest/test_pipeline.py`).
"""

from __future__ import annotations

import shutil
import struct
from pathlib import Path

import pytest

from ingest.bags.reader import open_bags
from ingest.errors import BagError
from ingest.train.run.pipeline import ingest
from ingest.train.run.settings import IngestConfig
from sensorbox.live.bagwriter import BagWriter
from sensorbox.sim.truth import truth_dir
from tests.faults.bags import INDOOR, LIDAR_TOP, LOWER, UPPER, rewrite

FAST = {"workers": 1, "every": 3, "height_full": 96}  # 96 rows keep disparity GT
IMU = "/livox/imu_192_168_1_12"


def _at(ns: int) -> str:
    return f"{ns / 1e9:.3f} s"


def test_a_bag_in_reversed_log_order_is_refused_naming_the_first_topic_and_stamps(tmp_path: Path) -> None:
    with open_bags([INDOOR]) as bags:
        messages = [(m.topic, m.msgtype, m.log_ns, bytes(m.raw)) for m in bags.messages()]
    first, last = messages[0][2], messages[-1][2]
    dst = tmp_path / "reversed"
    with BagWriter(dst, "mcap") as out:
        for topic, msgtype in dict((t, ty) for t, ty, _, _ in messages).items():
            out.add(topic, msgtype)
        for topic, _, log_ns, raw in reversed(messages):
            out.write(topic, first + last - log_ns, raw)
    shutil.copytree(truth_dir(INDOOR), truth_dir(dst))
    upper = [m for m in messages if m[0].startswith("/zed_upper")]
    stamps = [struct.unpack_from("<iI", raw, 4) for _, _, _, raw in upper]
    stamps_ns = [s * 1_000_000_000 + n for s, n in stamps]
    with pytest.raises(BagError) as err:
        ingest([dst], IngestConfig(rig=truth_dir(dst) / "rig.yaml", out=tmp_path / "ds", **FAST))  # type: ignore[arg-type]
    topic = upper[0][0]
    assert str(err.value) == (
        f"{dst}: {topic}: header stamps run backwards in 20 of 20 steps of the bag's log order (the first: "
        f"{_at(stamps_ns[-2])} logged at {_at(first + last - upper[-2][2])}, after {_at(stamps_ns[-1])}); "
        "expected stamps that rise with log time (a sensor clock running backwards, or a bag rewritten out "
        "of order)"
    )
    assert not (tmp_path / "ds").exists()


def test_a_camera_whose_stamps_run_backwards_is_refused(tmp_path: Path) -> None:
    with open_bags([INDOOR]) as bags:
        heads = [bytes(m.raw[4:12]) for m in bags.messages(topics=[LOWER])]

    def backwards(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        if topic != LOWER:
            return [(topic, raw)]
        return [(topic, raw[:4] + heads[len(heads) - 1 - k] + raw[12:])]  # frame k stamped as frame 20 - k

    bag, rig = rewrite(tmp_path / "bag", backwards)
    with pytest.raises(BagError, match=rf"^{bag}: {LOWER}: header stamps run backwards in 20 of 20 steps "):
        ingest([bag], IngestConfig(rig=rig, out=tmp_path / "ds", **FAST))  # type: ignore[arg-type]


def _lower_stamps(
    frame: int, head: bytes, tmp_path: Path, other_image: bool = False
) -> tuple[list[int], list[int], Path, Path]:
    """The fixture with the lower camera's `frame` carrying header stamp bytes `head` (and with
    `other_image`, one bit of its JPEG's entropy data flipped: the static fixture's frames are alike): the
    lower stamps (ns) and log times before the change, the bag and its rig."""
    with open_bags([INDOOR]) as bags:
        msgs = list(bags.messages(topics=[LOWER]))
    stamps_ns = [s * 1_000_000_000 + n for s, n in (struct.unpack_from("<iI", m.raw, 4) for m in msgs)]

    def change(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        if topic != LOWER or k != frame:
            return [(topic, raw)]
        data = bytearray(raw[:4] + head + raw[12:])
        data[-100] ^= 1 if other_image else 0
        return [(topic, bytes(data))]

    bag, rig = rewrite(tmp_path / "bag", change)
    return stamps_ns, [m.log_ns for m in msgs], bag, rig


def test_a_camera_frame_stamped_before_the_one_logged_before_it_is_said_and_its_lost_partner_counted(
    tmp_path: Path,
) -> None:
    """One lower frame stamped 1 ms before the frame logged before it: one step back in 20. The run goes
    on (a message delivered late is taken in stamp order), says so in one line naming the topic and
    stamps, and counts the upper frame left without a partner."""
    with open_bags([INDOOR]) as bags:
        stamps_ns = [
            s * 1_000_000_000 + n
            for s, n in (struct.unpack_from("<iI", m.raw, 4) for m in bags.messages([LOWER]))
        ]
    early_ns = stamps_ns[9] - 1_000_000
    stamps_ns, logs, bag, rig = _lower_stamps(
        10, struct.pack("<iI", *divmod(early_ns, 1_000_000_000)), tmp_path
    )
    summary = ingest([bag], IngestConfig(rig=rig, out=tmp_path / "ds", **FAST))  # type: ignore[arg-type]
    assert summary.warnings == [
        f"{LOWER}: header stamps step back in 1 of {len(stamps_ns) - 1} steps of the bag's log order (the "
        f"first: {_at(early_ns)} logged at {_at(logs[10])}, after {_at(stamps_ns[9])}); those messages are "
        "taken in stamp order (a message delivered late, or a sensor clock that jumped)"
    ]
    assert (summary.frames, summary.pairs) == (len(stamps_ns), len(stamps_ns) - 1)


def test_a_camera_frame_carrying_an_earlier_frames_stamp_is_left_out_and_said(tmp_path: Path) -> None:
    """Lower frame 10 carries frame 8's header stamp and another image: not a copy of frame 8, so it is
    not only counted as a repeated message: one line names the topic and stamp. (The same image under
    the same stamp is a copy: `tests/faults/test_clocks_and_repeats.py`.)"""
    with open_bags([INDOOR]) as bags:
        heads = [bytes(m.raw[4:12]) for m in bags.messages(topics=[LOWER])]
    stamps_ns, _, bag, rig = _lower_stamps(10, heads[8], tmp_path, other_image=True)
    summary = ingest([bag], IngestConfig(rig=rig, out=tmp_path / "ds", **FAST))  # type: ignore[arg-type]
    assert summary.warnings == [
        f"{LOWER}: 1 message carries the header stamp of an earlier message with other content (the first: "
        f"{_at(stamps_ns[8])}); left out, as its time is not known (a sensor clock that stalled or stepped "
        "back)"
    ]
    assert summary.duplicates == {LOWER: 1}
    assert (summary.frames, summary.pairs) == (len(stamps_ns), len(stamps_ns) - 1)


def test_an_imu_reading_or_two_delivered_late_are_taken(tmp_path: Path) -> None:
    held: list[bytes] = []

    def late(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        if topic == IMU and k in (40, 90):
            held.append(raw)
            return []
        if topic == IMU and k in (42, 92):
            return [(topic, raw), (topic, held.pop())]
        return [(topic, raw)]

    bag, rig = rewrite(tmp_path / "bag", late)
    summary = ingest([bag], IngestConfig(rig=rig, out=tmp_path / "ds", **FAST))  # type: ignore[arg-type]
    assert summary.written == 7


def test_a_lidar_topic_that_also_carries_imu_messages_is_refused(tmp_path: Path) -> None:
    """Ingest read only the topic's LiDAR messages and skipped the others without a word."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from ingest.bags.rostypes import IMU_TYPE, typestore

    with open_bags([INDOOR]) as bags:
        messages = [(m.topic, m.msgtype, m.log_ns, bytes(m.raw)) for m in bags.messages()]
    dst = tmp_path / "mixed"
    with Writer(dst, version=8, storage_plugin=StoragePlugin.MCAP) as out:
        conns = {
            (t, ty): out.add_connection(t, ty, typestore=typestore(2))
            for t, ty in {(t, ty) for t, ty, _, _ in messages}
        }
        conns[(LIDAR_TOP, IMU_TYPE)] = out.add_connection(LIDAR_TOP, IMU_TYPE, typestore=typestore(2))
        for topic, msgtype, log_ns, raw in messages:
            out.write(conns[(topic, msgtype)], log_ns, raw)
            if topic == IMU:
                out.write(conns[(LIDAR_TOP, IMU_TYPE)], log_ns, raw)
    shutil.copytree(truth_dir(INDOOR), truth_dir(dst))
    with pytest.raises(BagError) as err:
        ingest([dst], IngestConfig(rig=truth_dir(dst) / "rig.yaml", out=tmp_path / "ds", **FAST))  # type: ignore[arg-type]
    assert str(err.value) == (
        f"{dst}: {LIDAR_TOP} (the rig's lidar lidar_top) has type livox_ros_driver2/msg/CustomMsg | "
        "sensor_msgs/msg/Imu; expected a LiDAR type (livox_ros_driver/msg/CustomMsg or "
        "livox_ros_driver2/msg/CustomMsg or sensor_msgs/msg/PointCloud2)"
    )


def test_stereo_pairs_exposed_apart_are_said_with_the_largest(tmp_path: Path) -> None:
    """The lower camera's frame 9 stamped 13 ms late: still its upper frame's partner (within half a
    period), but the lower image shows another moment than the GT: one line says how many and the most."""
    with open_bags([INDOOR]) as bags:
        upper_ns, lower_ns = (
            [
                s * 1_000_000_000 + n
                for s, n in (struct.unpack_from("<iI", m.raw, 4) for m in bags.messages([t]))
            ]
            for t in (UPPER + "/compressed", LOWER)
        )
    late_ns = lower_ns[9] + 13_000_000
    most_ms = (late_ns - upper_ns[9]) / 1e6  # 13 ms and the fixture's own sync jitter (+-0.5 ms a camera)
    _, _, bag, rig = _lower_stamps(9, struct.pack("<iI", *divmod(late_ns, 1_000_000_000)), tmp_path)
    summary = ingest([bag], IngestConfig(rig=rig, out=tmp_path / "ds", **FAST))  # type: ignore[arg-type]
    assert summary.warnings == [
        f"1 of {summary.planned} stereo pairs are exposed more than 2 ms apart (the most: {most_ms:.1f} ms, at "
        f"upper stamp {_at(upper_ns[9])}): with the rig moving, the lower image shows another moment than the "
        "disparity GT (hardware-sync the cameras, or leave out the samples by their meta's stereo_dt_ms)"
    ]
    assert summary.pairs == summary.frames


def test_a_lidar_sweep_stamped_with_the_previous_sweeps_timebase_is_left_out_and_said(tmp_path: Path) -> None:
    """Sweep 5: the top LiDAR's sweep 4 carries sweep 3's header stamp and timebase with its own points.
    Its points then lay over sweep 3's moment (GT pixels there 15029 -> 20831) and its own moment had
    none, without a word. Sweeps of one LiDAR never cover each other's moments: it is left out, said in
    one line, and the GT is that of the bag without the sweep."""
    from ingest.bags.livox_msg import decode_custom_msg, encode_custom_msg
    from ingest.dataset.layout import GT_DIRS

    with open_bags([INDOOR]) as bags:
        sweeps = [decode_custom_msg(bytes(m.raw)) for m in bags.messages(topics=[LIDAR_TOP])]
    prev = sweeps[3]

    def restamped(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        if topic != LIDAR_TOP or k != 4:
            return [(topic, raw)]
        own = decode_custom_msg(raw)
        return [
            (
                topic,
                encode_custom_msg(prev.stamp_ns, own.frame_id, prev.timebase_ns, own.points, own.lidar_id),
            )
        ]

    def without(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        return [] if topic == LIDAR_TOP and k == 4 else [(topic, raw)]

    bag, rig = rewrite(tmp_path / "bag", restamped)
    summary = ingest([bag], IngestConfig(rig=rig, out=tmp_path / "ds", **FAST))  # type: ignore[arg-type]
    first_ns = prev.timebase_ns + int(sweeps[4].points["offset_time"].min())
    assert (
        f"{LIDAR_TOP}: 1 sweep with point times that cover an earlier sweep's (the first: {_at(first_ns)}); "
        "left out, as its time is not known (a driver that repeated a sweep's timebase, or a clock that "
        "stepped back)"
    ) in summary.warnings
    gone, gone_rig = rewrite(tmp_path / "gone", without)
    clean = ingest([gone], IngestConfig(rig=gone_rig, out=tmp_path / "gone-ds", **FAST))  # type: ignore[arg-type]
    assert summary.written == clean.written > 0

    def gt(out: Path) -> dict[str, bytes]:
        return {f"{d}/{p.name}": p.read_bytes() for d in GT_DIRS for p in sorted((out / d).glob("*.png"))}

    assert gt(tmp_path / "ds") == gt(tmp_path / "gone-ds")
