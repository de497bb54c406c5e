"""Issue 49 (F16): IMU readings that repeat a header stamp are named as repeated stamps, not a wrong rate.

A driver that stamps its 200 Hz readings in batches (20 readings under one
stamp) was refused as "IMU readings at 10 Hz ... the rig says rate_hz 200":
the distinct stamps came at 10 Hz, the readings at the rig's rate. The error
must count the repeated stamps and name the topic; a few repeats are counted
in the summary as repeated stamps.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from ingest.bags.decode import decode_imu
from ingest.errors import BagError
from ingest.train.run.pipeline import ingest
from ingest.train.run.settings import IngestConfig
from sensorbox.messages import imu_msg
from tests.faults.bags import Keep, rewrite
from tests.faults.cli import sensorbox

IMU = "/livox/imu_192_168_1_12"  # the rig's first IMU: 140 readings at 200 Hz in the fixture
FAST = {"workers": 1, "every": 3, "height_full": 64, "gt": "sparse"}


def _stamped_in_batches(batch: int, first: int = 0, last: int = 1 << 30) -> Keep:
    """Readings `first`..`last` of the IMU carry the stamp of the first reading of their batch."""
    stamp: dict[str, int] = {}

    def keep(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        if topic != IMU or not first <= k <= last:
            return [(topic, raw)]
        s = decode_imu(raw)
        if (k - first) % batch == 0:
            stamp["batch"] = s.stamp_ns
        return [(topic, imu_msg(stamp["batch"], s.gyro_rad_s, s.acc))]

    return keep


@pytest.mark.parametrize(
    ("batch", "numbers"),
    [(20, "133 of 140 IMU readings repeat an earlier reading's header stamp: 7 distinct stamps, at 10 Hz"),
     (2, "70 of 140 IMU readings repeat an earlier reading's header stamp: 70 distinct stamps, at 100 Hz")],
)  # fmt: skip
def test_readings_stamped_in_batches_are_refused_as_repeated_stamps_not_another_rate(
    tmp_path: Path, batch: int, numbers: str
) -> None:
    bag, rig = rewrite(tmp_path / "batched", _stamped_in_batches(batch))
    with pytest.raises(BagError) as err:
        ingest([bag], IngestConfig(rig=rig, out=tmp_path / "ds", **FAST))  # type: ignore[arg-type]
    assert str(err.value) == (
        f"{bag}: {IMU}: {numbers}, for readings at 200 Hz (the rig's imu_top says rate_hz 200); readings "
        "stamped in batches cannot be placed in time (a driver or clock that repeats stamps: fix the IMU's "
        "header stamps)"
    )
    assert "rate_hz 200; more than" not in str(err.value)  # not the rate message
    assert not (tmp_path / "ds").exists()


def test_a_few_repeated_imu_stamps_are_counted_as_repeated_stamps_in_the_summary(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag, rig = rewrite(tmp_path / "few", _stamped_in_batches(5, first=40, last=49))  # 2 batches of 5
    summary = ingest([bag], IngestConfig(rig=rig, out=tmp_path / "ds", **FAST))  # type: ignore[arg-type]
    assert summary.written == 7 and summary.duplicates == {IMU: 8}
    args = ["ingest", str(bag), "--rig", str(rig), "--out", str(tmp_path / "cli"), "--workers", "1"]
    code, out, _ = sensorbox(capsys, *args, "--every", "3", "--height-full", "64", "--no-preview")
    rows = [line.split("│")[1:3] for line in out.splitlines() if "repeating a stamp" in line]
    assert code == 0
    assert [[c.strip() for c in row] for row in rows] == [
        [f"messages repeating a stamp, first read: {IMU}", "8"]
    ]
