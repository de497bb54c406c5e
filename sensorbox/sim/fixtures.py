"""The small recorded-bag fixtures in tests/fixtures/, defined once for `make fixtures` and the tests.

About 0.7 s each (7 LiDAR sweeps, 21 stereo pairs) at reduced image scale; both
scenes, all three bag formats and both LiDAR message kinds among them; each
under 8 MB with its truth folder (two Mid-360s alone make 8 MB/s of points).
"""

from __future__ import annotations

import shutil
from pathlib import Path

from sensorbox.live.bagwriter import bag_path
from sensorbox.sim.config import SimConfig
from sensorbox.sim.run import SimSummary, simulate
from sensorbox.sim.truth import truth_dir

FIXTURES_DIR = Path("tests") / "fixtures"
"""The fixtures, relative to the checkout root (`make fixtures` runs there; tests pass their own root)."""
FIXTURES: dict[str, SimConfig] = {
    "indoor_static_mcap": SimConfig(
        scene="indoor", trajectory="static", duration_s=0.7, format="mcap", lidar_msg="custom",
        image="jpeg", jpeg_quality=80, scale=0.25, range_noise_m=0.0, seed=1,
    ),
    "outdoor_walk_mcap": SimConfig(
        scene="outdoor", trajectory="walk", duration_s=0.7, format="mcap", lidar_msg="custom",
        image="raw", scale=0.125, range_noise_m=0.0, lidar_clock_offset_ns=1_500_000, seed=2,
    ),
    "indoor_walk_db3": SimConfig(
        scene="indoor", trajectory="walk", duration_s=0.7, format="db3", lidar_msg="pointcloud2",
        image="jpeg", jpeg_quality=80, scale=0.25, range_noise_m=0.02, seed=3,
    ),
    "outdoor_static_bag": SimConfig(
        scene="outdoor", trajectory="static", duration_s=0.7, format="bag", lidar_msg="custom",
        image="jpeg", jpeg_quality=80, scale=0.25, range_noise_m=0.02, seed=4,
    ),
}  # fmt: skip


def fixture_bag(name: str, root: Path = FIXTURES_DIR) -> Path:
    """Path of the bag (rosbag2 folder or .bag file) of fixture `name` under `root`."""
    return bag_path(root / name, FIXTURES[name].format)


def make_fixture(name: str, root: Path = FIXTURES_DIR) -> SimSummary:
    """(Re)generate fixture `name` under `root`, replacing an existing one."""
    bag = fixture_bag(name, root)
    for old in (bag, truth_dir(bag)):
        if old.is_dir():
            shutil.rmtree(old)
        elif old.exists():
            old.unlink()
    return simulate(FIXTURES[name], root / name)


def main() -> None:
    """`make fixtures`: regenerate every fixture and print its size."""
    for name in FIXTURES:
        summary = make_fixture(name)
        total = summary.size_bytes + sum(f.stat().st_size for f in summary.truth.iterdir())
        print(f"{fixture_bag(name)}: {total / 1e6:.2f} MB with truth")


if __name__ == "__main__":
    main()
