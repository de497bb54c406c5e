"""Issue 20, class 3: a sample with far fewer LiDAR points than the LiDAR's rate promises is flagged.

The bottom LiDAR stops half way through the fixture: its sweep 3 (0.3-0.4 s)
is cut after its first 80 ms and nothing follows. With every third frame
planned, frame 12 (sample 4, +-50 ms around 0.405 s) holds 25 ms of its
points: thin. Frames 15 and 18 (samples 5 and 6) hold none: silent. All are
written (the top LiDAR still sees), flagged in meta and counted.
"""

from __future__ import annotations

import json
from pathlib import Path

from ingest.bags.livox_msg import decode_custom_msg, encode_custom_msg
from ingest.train.run.lidar_rate import THIN_FRACTION
from ingest.train.run.pipeline import ingest
from ingest.train.run.settings import IngestConfig
from tests.faults.bags import LIDAR_BOTTOM, rewrite

STOP_NS = 80_000_000  # into sweep 3


def _stops_half_way(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
    if topic != LIDAR_BOTTOM or k < 3:
        return [(topic, raw)]
    if k > 3:
        return []
    msg = decode_custom_msg(raw)
    pts = msg.points[msg.points["offset_time"] < STOP_NS]
    return [(topic, encode_custom_msg(msg.stamp_ns, msg.frame_id, msg.timebase_ns, pts, msg.lidar_id))]


def test_a_lidar_that_stops_half_way_flags_the_thin_sample_and_the_silent_ones(tmp_path: Path) -> None:
    bag, rig = rewrite(tmp_path / "stops", _stops_half_way)
    out = tmp_path / "ds"
    summary = ingest([bag], IngestConfig(rig=rig, out=out, workers=1, every=3, height_full=64))
    assert (summary.planned, summary.written) == (7, 7)
    assert summary.flagged == {
        f"lidar_bottom thin in the window (< {THIN_FRACTION:.0%} of its rate)": 1,
        "lidar_bottom silent in the window": 2,
    }
    points = {p.stem: json.loads(p.read_text())["points"] for p in sorted((out / "meta").glob("*.json"))}
    thin = {sid: p["thin_lidars"] for sid, p in points.items() if p["thin_lidars"]}
    silent = {sid: p["silent_lidars"] for sid, p in points.items() if p["silent_lidars"]}
    assert thin == {"000004": ["lidar_bottom"]}
    assert silent == {sid: ["lidar_bottom"] for sid in ("000005", "000006")}
    # the thin one holds the top LiDAR's window plus a quarter of the bottom's: ~62 % of a whole window's
    assert 0.55 < points["000004"]["total"] / points["000002"]["total"] < 0.7
