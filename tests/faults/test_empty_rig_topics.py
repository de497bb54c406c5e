"""Issue 49 (F14): `inspect --rig` names a rig topic the bag declares without a message, never "fine".

A bag whose bottom LiDAR (or lower camera) topic is declared but empty was
reported as "every topic is in the bag with the expected type", exit 0,
while ingest refuses it. The rig check must name the topic, say it is
empty, and fail like a missing topic (exit 2).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from ingest.bags.rostypes import COMPRESSED_IMAGE_TYPE
from tests.faults.bags import LIDAR_BOTTOM, LOWER, rewrite
from tests.faults.cli import sensorbox

CUSTOM_MSG = "livox_ros_driver2/msg/CustomMsg"


@pytest.mark.parametrize(
    ("topic", "msgtype", "sensor"),
    [(LIDAR_BOTTOM, CUSTOM_MSG, "lidar lidar_bottom"), (LOWER, COMPRESSED_IMAGE_TYPE, "camera cam1 (lower)")],
)
def test_a_rig_topic_declared_without_a_message_is_named_empty_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], topic: str, msgtype: str, sensor: str
) -> None:
    def drop(t: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        return [] if t == topic else [(t, raw)]

    bag, rig = rewrite(tmp_path / "bag", drop, declare={topic: msgtype})
    code, out, err = sensorbox(capsys, "inspect", str(bag), "--rig", str(rig))
    assert code == 2
    assert err == [f"error: {rig}: 1 of its sensors does not match the bag (the table above)"]
    problem = [line.split("│")[1:4] for line in out.splitlines() if "in the bag but empty" in line]
    assert [[cell.strip() for cell in row] for row in problem] == [
        [sensor, topic, "in the bag but empty: 0 messages"]
    ]
    assert "every topic is in the bag" not in out


def test_a_topic_differing_only_by_whitespace_is_named_as_such() -> None:
    """Sweep 7 U6: a channel '/livox/imu_192_168_1_12 ' (a trailing space) was listed unquoted beside the
    line saying '/livox/imu_192_168_1_12' is missing, so the line seemed to list the topic it missed."""
    from ingest.topic_map import missing_topic

    topics = ["/livox/imu_192_168_1_12 ", "/livox/imu_192_168_1_13", "/cam\timage"]
    assert missing_topic("b.mcap", "/livox/imu_192_168_1_12", "imu imu_top", topics) == (
        "b.mcap: no topic '/livox/imu_192_168_1_12' for imu imu_top (from the rig) ('/livox/imu_192_168_1_12 ' "
        "differs from it only by whitespace); the bag has: '/cam\\timage', '/livox/imu_192_168_1_12 ', "
        "/livox/imu_192_168_1_13"
    )
