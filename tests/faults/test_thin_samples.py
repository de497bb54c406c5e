"""Issue 20, class 3: a sample with far fewer LiDAR points than the LiDAR's rate promises is flagged.

The bottom LiDAR stops half way through the fixture: its sweep 4 (0.4-0.5 s)
is cut after its first 30 ms and nothing follows. With every other frame
planned, frame 14 (sample 7, +-50 ms around 0.471 s) holds 9 ms of its
points: thin. Frames 16-20 (samples 8-10) hold none: silent. Both are
written (the top LiDAR still sees), flagged in meta and counted.
"""

from __future__ import annotations

import json
from pathlib import Path

from ingest.bags.livox_msg import decode_custom_msg, encode_custom_msg
from ingest.train.lidar_rate import THIN_FRACTION
from ingest.train.pipeline import IngestConfig, ingest
from tests.faults.bags import LIDAR_BOTTOM, rewrite

STOP_NS = 30_000_000  # into sweep 4


def _stops_half_way(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
    if topic != LIDAR_BOTTOM or k < 4:
        return [(topic, raw)]
    if k > 4:
        return []
    msg = decode_custom_msg(raw)
    pts = msg.points[msg.points["offset_time"] < STOP_NS]
    return [(topic, encode_custom_msg(msg.stamp_ns, msg.frame_id, msg.timebase_ns, pts, msg.lidar_id))]


def test_a_lidar_that_stops_half_way_flags_the_thin_sample_and_the_silent_ones(tmp_path: Path) -> None:
    bag, rig = rewrite(tmp_path / "stops", _stops_half_way)
    out = tmp_path / "ds"
    summary = ingest([bag], IngestConfig(rig=rig, out=out, workers=1, every=2, height_full=64))
    assert (summary.planned, summary.written) == (11, 11)
    assert summary.flagged == {
        f"lidar_bottom thin in the window (< {THIN_FRACTION:.0%} of its rate)": 1,
        "lidar_bottom silent in the window": 3,
    }
    points = {p.stem: json.loads(p.read_text())["points"] for p in sorted((out / "meta").glob("*.json"))}
    thin = {sid: p["thin_lidars"] for sid, p in points.items() if p["thin_lidars"]}
    silent = {sid: p["silent_lidars"] for sid, p in points.items() if p["silent_lidars"]}
    assert thin == {"000007": ["lidar_bottom"]}
    assert silent == {sid: ["lidar_bottom"] for sid in ("000008", "000009", "000010")}
    # the thin one holds the top LiDAR's window plus a sliver of the bottom's: ~55 % of a whole window's
    assert 0.5 < points["000007"]["total"] / points["000004"]["total"] < 0.6
