"""`sensorbox inspect` through typer, with its own app (the main CLI wires the same function)."""

import shutil
from pathlib import Path
from typing import Any

import typer
import yaml
from typer.testing import CliRunner

from calibration.errors import SensorboxError
from ingest.bags.reader import BagError
from sensorbox.cli.inspect import inspect_cmd
from sensorbox.sim.fixtures import fixture_bag
from tests.paths import FIXTURES_DIR

app = typer.Typer(pretty_exceptions_enable=False, add_completion=False)
app.command("inspect")(inspect_cmd)


@app.callback()
def _root() -> None:
    """Test app."""


runner = CliRunner()
TOPICS = (
    "/zed_upper/zed_node/rgb/color/rect/image",
    "/zed_lower/zed_node/rgb/color/rect/image",
    "/livox/lidar_192_168_1_12",
    "/livox/lidar_192_168_1_13",
    "/livox/imu_192_168_1_12",
    "/livox/imu_192_168_1_13",
)


def mapping_yaml(stdout: str) -> Any:
    """The YAML printed after the 'Suggested rig topic mapping' line."""
    tail = stdout.split("Suggested rig topic mapping", 1)[1]
    return yaml.safe_load(tail)


def test_inspect_prints_topics_timing_and_mapping():
    res = runner.invoke(app, ["inspect", str(fixture_bag("outdoor_walk_mcap", FIXTURES_DIR))])
    assert res.exit_code == 0, res.output
    out = res.stdout
    assert "ROS 2, 336 messages" in out
    for topic in TOPICS:
        assert topic in out
    assert "200.00" in out and "10.02" in out  # IMU and LiDAR rates
    assert "18.00 (18.00..18.00)" in out  # camera latency, every frame
    assert "-0.50 (-0.50..-0.50)" in out  # second IMU: 1 ms latency - 1.5 ms clock offset
    assert "0 / 0" in out and "21 (nearest stamps within" in out  # stereo: all frames paired
    assert "19968" in out and "-7.0 .. 52.0" in out  # points per sweep, elevation range
    assert mapping_yaml(out) == {
        "cameras": {
            "cam0": {"role": "upper", "topic": TOPICS[0]},
            "cam1": {"role": "lower", "topic": TOPICS[1]},
        },
        "lidars": {
            "lidar_top": {"topic": TOPICS[2], "ip": "192.168.1.12"},
            "lidar_bottom": {"topic": TOPICS[3], "ip": "192.168.1.13"},
        },
        "imus": {
            "imu_top": {"topic": TOPICS[4], "rate_hz": 200.0},
            "imu_bottom": {"topic": TOPICS[5], "rate_hz": 200.0},
        },
    }
    assert "cam0: {role: upper, topic: /zed_upper/zed_node/rgb/color/rect/image}" in out


def test_inspect_with_rig_reports_missing_topics(tmp_path: Path):
    bag = fixture_bag("indoor_walk_db3", FIXTURES_DIR)
    truth = bag.parent / "indoor_walk_db3.truth"
    shutil.copy(truth / "camchain.yaml", tmp_path)
    rig = tmp_path / "rig.yaml"  # a LiDAR topic the bag lacks; the cameras' /compressed variants count
    rig.write_text(
        (truth / "rig.yaml").read_text().replace("/livox/lidar_192_168_1_13", "/livox/lidar_10_0_0_9")
    )
    res = runner.invoke(app, ["inspect", str(bag), "--rig", str(rig)])
    assert res.exit_code == 2, res.output  # the whole report, then the failed check
    assert res.stderr.strip() == f"error: {rig}: 1 of its sensors does not match the bag (the table above)"
    assert "/livox/lidar_10_0_0_9" in res.stdout and "not in the bag" in res.stdout
    assert "/zed_upper/zed_node/rgb/color/rect/image " not in res.stdout  # found as /compressed
    assert "The bag's topics:" in res.stdout
    assert "/zed_upper/zed_node/rgb/color/rect/image/compressed (CompressedImage)" in res.stdout
    assert "topics from rig" in res.stdout


def test_inspect_matching_rig_says_so():
    bag = fixture_bag("outdoor_walk_mcap", FIXTURES_DIR)
    rig = bag.parent / "outdoor_walk_mcap.truth" / "rig.yaml"
    res = runner.invoke(app, ["inspect", str(bag), "--rig", str(rig)])
    assert res.exit_code == 0, res.output
    assert "every topic is in the bag with the expected type" in res.stdout


def test_errors_are_left_to_the_main_cli(tmp_path: Path):
    res = runner.invoke(app, ["inspect", str(tmp_path / "missing.mcap")])
    assert res.exit_code != 0
    assert isinstance(res.exception, BagError) and isinstance(res.exception, SensorboxError)
    assert "no such file" in str(res.exception)


def test_the_same_bag_twice_is_refused_not_counted_twice():
    bag = fixture_bag("indoor_static_mcap", FIXTURES_DIR)
    again = bag.parent / ".." / bag.parent.name / bag.name
    res = runner.invoke(app, ["inspect", str(bag), str(again)])
    assert isinstance(res.exception, BagError)
    assert str(res.exception) == f"{again}: the same recording is given twice"
    (data,) = bag.glob("*.mcap")  # the rosbag2 folder and its own data file
    res = runner.invoke(app, ["inspect", str(bag), str(data)])
    assert isinstance(res.exception, BagError)
    assert str(res.exception) == f"{data}: the same recording is given twice (as {bag})"


def test_help_describes_the_command_and_options():
    res = runner.invoke(app, ["inspect", "--help"])
    assert res.exit_code == 0
    for text in ("stereo pairing", "LiDAR coverage", "--rig", "--salvage", "Rig file", "truncated"):
        assert text in res.stdout


def test_the_lidar_table_never_folds_a_topic_on_a_narrow_terminal():
    """Both LiDAR topics were folded after '/livox/lidar_192_168_1' on an 80-column terminal, so the two
    rows began the same; each topic now stays on one line and the other columns wrap."""
    import io

    from rich.console import Console

    from ingest.inspect import inspect_bags
    from sensorbox.cli.inspect import _lidar_table

    report = inspect_bags([fixture_bag("indoor_static_mcap", FIXTURES_DIR)])
    out = io.StringIO()
    Console(file=out, width=80).print(_lidar_table(report.lidars))
    lines = out.getvalue().splitlines()
    for topic in ("/livox/lidar_192_168_1_12", "/livox/lidar_192_168_1_13"):
        assert any(topic in line for line in lines), (topic, out.getvalue())
