"""Issue 49 (F10): points the Livox tags as noise are counted by topic in the summary and `dataset.yaml`.

Each sample's meta counted them (`points.noise_tag`), but the summary and
`dataset.yaml` did not: a run whose LiDAR tagged a third of its points as
dust said nothing of them. The bag is the fixture with every third point of
the top LiDAR tagged "other" (medium confidence); the counts must be exactly
the tagged points of its messages, and the GT that of the points left.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from ingest.bags.livox_msg import decode_custom_msg, encode_custom_msg
from ingest.dataset.meta import read_meta
from ingest.train.plausible import NOISE_TAG
from ingest.train.run.pipeline import ingest
from ingest.train.run.settings import IngestConfig
from tests.faults.bags import LIDAR_TOP, Keep, rewrite
from tests.faults.cli import sensorbox

FAST = {"workers": 1, "every": 3, "height_full": 64}
OTHER_NOISE = 0b0001_0000  # the tag's "other" field: medium confidence


def _tag_every_third(tagged: list[int]) -> Keep:
    def keep(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        if topic != LIDAR_TOP:
            return [(topic, raw)]
        msg = decode_custom_msg(raw)
        pts = msg.points.copy()
        pts["tag"][::3] = OTHER_NOISE
        tagged.append(int(np.count_nonzero(pts["tag"] == OTHER_NOISE)))
        return [(topic, encode_custom_msg(msg.stamp_ns, msg.frame_id, msg.timebase_ns, pts, msg.lidar_id))]

    return keep


def test_noise_tagged_points_are_counted_by_topic_in_the_summary_and_dataset_yaml(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    tagged: list[int] = []
    bag, rig = rewrite(tmp_path / "bag", _tag_every_third(tagged))
    out = tmp_path / "ds"
    summary = ingest([bag], IngestConfig(rig=rig, out=out, **FAST))  # type: ignore[arg-type]
    assert summary.written == 7 and sum(tagged) > 40_000
    assert summary.dropped == {LIDAR_TOP: {NOISE_TAG: sum(tagged)}}
    source = yaml.safe_load((out / "dataset.yaml").read_text())["sources"][0]
    assert source["dropped_implausible"] == {LIDAR_TOP: {NOISE_TAG: sum(tagged)}}
    assert all(read_meta(out, p.stem).points.noise_tag > 0 for p in (out / "meta").glob("*.json"))
    assert not any("noise" in w for w in summary.warnings)  # counted, not a warning: a Livox tags some

    args = ["ingest", str(bag), "--rig", str(rig), "--out", str(tmp_path / "cli"), "--workers", "1"]
    code, printed, _ = sensorbox(capsys, *args, "--every", "3", "--height-full", "64", "--no-preview")
    assert code == 0
    rows = [line for line in printed.splitlines() if "dropped," in line]
    assert len(rows) == 1 and NOISE_TAG in rows[0] and rows[0].split()[-2] == f"{sum(tagged):,}"
