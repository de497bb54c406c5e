"""Issue 49 (F11): a LiDAR thin in every sweep is measured against what a Mid-360 sends, and said.

The thin-window rule took its expected rate from the sweeps themselves, so a
LiDAR whose driver published one point a sweep (or a fifth of its points)
was never thin: ingest wrote samples at 0.00 % GT density without a word.
The bottom LiDAR of the fixture is thinned in every sweep; every window of it
must be flagged thin and one warning line must name its topic and numbers.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from ingest.bags.livox_msg import decode_custom_msg, encode_custom_msg
from ingest.train.run.lidar_rate import THIN_FRACTION
from ingest.train.run.pipeline import ingest
from ingest.train.run.settings import IngestConfig
from tests.faults.bags import INDOOR, LIDAR_BOTTOM, Keep, rewrite

FAST = {"workers": 1, "every": 3, "height_full": 96, "gt": "sparse"}  # 96 rows keep disparity GT


def _thinned(step: int, count: int) -> Keep:
    """The bottom LiDAR's sweeps with every `step`-th point, at most `count` of them."""

    def keep(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        if topic != LIDAR_BOTTOM:
            return [(topic, raw)]
        msg = decode_custom_msg(raw)
        pts = msg.points[::step][:count]
        return [(topic, encode_custom_msg(msg.stamp_ns, msg.frame_id, msg.timebase_ns, pts, msg.lidar_id))]

    return keep


@pytest.mark.parametrize(
    ("step", "count", "numbers"),
    [
        (1, 1, "7 points in 7 sweeps (1 a sweep, 10 points/s)"),
        (5, 2000, "14,000 points in 7 sweeps (2,000 a sweep, 21,538 points/s)"),
    ],
)
def test_a_lidar_thin_in_every_sweep_is_flagged_in_every_sample_and_one_warning(
    tmp_path: Path, step: int, count: int, numbers: str
) -> None:
    bag, rig = rewrite(tmp_path / "thin", _thinned(step, count))
    summary = ingest([bag], IngestConfig(rig=rig, out=tmp_path / "ds", **FAST))  # type: ignore[arg-type]
    assert summary.written == 7
    assert summary.flagged == {f"lidar_bottom thin in the window (< {THIN_FRACTION:.0%} of its rate)": 7}
    thin = [w for w in summary.warnings if LIDAR_BOTTOM in w]
    assert thin == [
        f"{LIDAR_BOTTOM} (the rig's lidar lidar_bottom): {numbers} but a Mid-360 sends 200,000 points/s; "
        "every window of it is thin and its GT sparse (a driver set to drop points, or lost packets?)"
    ]


def test_the_fixtures_full_sweeps_are_neither_thin_nor_warned_about(tmp_path: Path) -> None:
    summary = ingest([INDOOR], IngestConfig(rig=INDOOR.parent / "indoor_static_mcap.truth" / "rig.yaml",
                                            out=tmp_path / "ds", **FAST))  # type: ignore[arg-type]  # fmt: skip
    assert summary.written == 7 and summary.flagged == {} and summary.warnings == []


def test_two_stretches_an_hour_apart_are_rated_over_the_time_they_cover() -> None:
    """Sweep 6 U3: two recordings an hour apart in one call blamed the LiDARs (78 points/s, 'a driver set
    to drop points'): the rate was taken over the hour between. Full sweeps an hour apart rate at a
    Mid-360's 200,000 points/s, and a stretch thin in every sweep still is thin."""
    import numpy as np

    from ingest.train.run.lidar_rate import LidarRates

    def sweeps(rates: LidarRates, start_ns: int, count: int, points: int) -> None:
        for k in range(count):  # 100 ms sweeps, points evenly over each
            t0 = start_ns + k * 100_000_000
            rates.add("/lidar", t0 + np.linspace(0, 100_000_000, points, endpoint=False).astype(np.int64))

    full = LidarRates()
    sweeps(full, 0, 7, 20_000)
    sweeps(full, 3_600_000_000_000, 7, 20_000)
    got = full.recorded_per_s("/lidar")
    assert got is not None and abs(got - 200_000) < 1_000
    assert full.thin_lines({"/lidar": "lidar_top"}) == []
    thin = LidarRates()
    sweeps(thin, 0, 7, 2_000)
    sweeps(thin, 3_600_000_000_000, 7, 2_000)
    (line,) = thin.thin_lines({"/lidar": "lidar_top"})
    assert line.startswith(
        "/lidar (the rig's lidar lidar_top): 28,000 points in 14 sweeps (2,000 a sweep, 20,0"
    )
