"""Issue 49: a command line click cannot parse is one line, `error: ...`, exit code 2, like every other
user mistake; `--help` and a bare group still print the help."""

from __future__ import annotations

from pathlib import Path

import pytest

from calibration.rig import REFERENCE_RIG
from tests.faults.cli import sensorbox
from tests.paths import ROOT


@pytest.mark.parametrize(
    ("args", "line"),
    [
        (
            ["stats", "--every", "abc"],
            "error: No such option: --every (see 'sensorbox stats --help')",
        ),
        (
            ["ingest", "--workers", "abc"],
            "error: Invalid value for '--workers': Input should be a valid integer, unable to parse string "
            "as an integer (see 'sensorbox ingest --help')",
        ),
        (["stats"], "error: Missing argument 'dataset'. (see 'sensorbox stats --help')"),
        (["nosuch"], "error: No such command 'nosuch'. (see 'sensorbox --help')"),
        (
            ["calib", "chek"],
            "error: No such command 'chek'. Did you mean 'check'? (see 'sensorbox calib --help')",
        ),
    ],
)
def test_a_command_line_click_refuses_is_one_line_and_exit_2(
    args: list[str], line: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """Typer printed the usage, a hint and the message in a box: seven lines on stderr."""
    code, out, err = sensorbox(capsys, *args)
    assert (code, out, err) == (2, "", [line])


@pytest.mark.parametrize("group", [[], ["calib"]])
def test_help_and_a_bare_group_still_print_the_help(
    group: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    code, out, err = sensorbox(capsys, *group, "--help")
    assert (code, err) == (0, []) and "Usage: sensorbox" in out
    code, out, err = sensorbox(capsys, *group)  # no_args_is_help: the help, and click's exit code 2
    assert (code, err) == (2, []) and "Usage: sensorbox" in out


def test_a_launch_number_in_exponent_form_is_a_number(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Sweep 3: `loop_s:=1e-9` was "parameter 'loop_s' = '1e-9': expected a finite number" (YAML 1.1 reads
    1e-9, without a dot, as text); text that is no number still names its value. Sweep 11: a loop too short
    for a sweep failed only in the run, naming `--duration`, which launch has not."""
    launch = ROOT / "launch" / "sim.launch.yaml"
    node_line = 1 + launch.read_text().splitlines().index("  - node:")  # the first emulator's
    out = f"out:={tmp_path / 'bags'}"
    code, _, err = sensorbox(capsys, "launch", "--dry-run", str(launch), out, "loop_s:=5e-1")
    assert (code, err) == (0, [])
    code, _, err = sensorbox(capsys, "launch", "--dry-run", str(launch), out, "loop_s:=1e-3")  # sweep 11
    assert (code, err) == (
        2,
        [
            "error: node 'lidar_top_emulator' (sensorbox/mid360_emulator) at "
            f"{ROOT}/sensorbox/share/launch/sim.launch.yaml:{node_line}: loop_s 0.001: expected 0 (simulate "
            "live) or at least 0.2 s (two 10 Hz sweeps: a shorter loop may hold no whole sweep to replay)"
        ],
    )
    code, _, err = sensorbox(capsys, "launch", "--dry-run", str(launch), out, "loop_s:=1e-9s")
    assert (code, err) == (
        2,
        [
            "error: node 'lidar_top_emulator' (sensorbox/mid360_emulator) at "
            f"{ROOT}/sensorbox/share/launch/sim.launch.yaml:{node_line}: parameter 'loop_s' = '1e-9s': "
            "expected a finite number"
        ],
    )


def test_a_simulation_shorter_than_a_camera_frame_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Sweep 3: `simulate --duration 1e-9` wrote a bag of no image and no IMU reading (one LiDAR message
    a topic, 'rate 1000000000.0 Hz'), exit 0."""
    out = tmp_path / "s.mcap"
    code, _, err = sensorbox(capsys, "simulate", "--duration", "1e-9", "--scale", "0.1", "--out", str(out))
    assert (code, err) == (
        2,
        [
            "error: --duration 1e-09: shorter than one camera frame period (33.3 ms at 30 Hz), so the bag may "
            "hold no image; expected at least 0.03333 s"
        ],
    )
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("compare", [",", "195FOV,", ",65mm"])
def test_a_compare_without_both_configurations_names_the_option(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], compare: str
) -> None:
    """Sweep 3: `eval --compare ,` was "configuration '': expected <FOV>FOV ... or <B>mm", naming no option."""
    code, out, err = sensorbox(
        capsys,
        "eval",
        "--dataset",
        str(tmp_path),
        "--pred",
        str(tmp_path),
        "--task",
        "stereo",
        "--compare",
        compare,
    )
    assert (code, out, err) == (2, "", [f"error: --compare {compare!r}: expected A,B (e.g. 195FOV,120FOV)"])


def test_a_launch_remap_to_an_empty_topic_names_its_file_and_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Sweep 3: `remap: [{from: /a, to: ""}]` was "invalid topic name ''", naming neither file nor line."""
    launch = tmp_path / "x.launch.yaml"
    launch.write_text(
        'launch:\n- node: {pkg: sensorbox, exec: recorder, name: n1, remap: [{from: /a, to: ""}]}\n'
    )
    code, _, err = sensorbox(capsys, "launch", "--dry-run", str(launch))
    assert (code, err) == (
        2,
        [
            f"error: {launch}:2: remap to: invalid topic name '': expected e.g. '/livox/imu', 'imu' or '~/image'"
        ],
    )


def test_two_launch_nodes_of_one_name_are_refused_by_the_dry_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Sweep 3: `launch --dry-run` passed two nodes named rec, which the run refuses when it starts."""
    launch = tmp_path / "x.launch.yaml"
    launch.write_text(
        "launch:\n- node: {pkg: sensorbox, exec: recorder, name: rec}\n- node: {pkg: sensorbox, exec: recorder, name: rec}\n"
    )
    code, _, err = sensorbox(capsys, "launch", "--dry-run", str(launch))
    assert (code, err) == (
        2,
        [
            f"error: {launch}:3: a second node named 'rec' (the first at {launch}:2); give each node its own name"
        ],
    )


def test_two_nodes_publishing_one_topic_are_refused_by_the_dry_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Sweep 7: a second camera node on the same topics, or a Livox driver with multi_topic 0 and two
    LiDARs, recorded two sensors interleaved on one topic, exit 0."""
    launch = tmp_path / "x.launch.yaml"
    camera = (
        "{pkg: sensorbox, exec: camera, name: %s, param: [{name: source, value: opencv}, {name: device, value: '0'}, "
        "{name: topic, value: /zed_upper/image}]}"
    )
    launch.write_text(f"launch:\n- node: {camera % 'cam_a'}\n- node: {camera % 'cam_b'}\n")
    code, _, err = sensorbox(capsys, "launch", "--dry-run", str(launch))
    topic = "/zed_upper/image/compressed"
    assert (code, err) == (2, [
        f"error: {launch}:3: node 'cam_b' publishes {topic}, as does node 'cam_a' at {launch}:2; their messages "
        "would be recorded as one topic: give each its own (a remap or its topic parameter)"
    ])  # fmt: skip
    driver = tmp_path / "d.launch.yaml"
    driver.write_text(
        "launch:\n- node: {pkg: sensorbox, exec: livox_driver, name: drv, param: [{name: host_ip, value: 127.0.0.1}, "
        "{name: lidar_ips, value: [127.0.0.12, 127.0.0.13]}, {name: multi_topic, value: false}]}\n"
    )
    code, _, err = sensorbox(capsys, "launch", "--dry-run", str(driver))
    assert (code, err) == (2, [
        f"error: node 'drv' (sensorbox/livox_driver) at {driver}:2: multi_topic 0 with 2 lidars (127.0.0.12, "
        "127.0.0.13) publishes every lidar on /livox/lidar and every IMU on /livox/imu, one stream no rig can "
        "tell apart; set multi_topic 1 (/livox/lidar_<ip>)"
    ])  # fmt: skip


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["camera:=opencv", "upper_device:=/dev/video0", "lower_device:=/dev/video0"],
            ":49: node 'v4l2_stereo' opens the camera device /dev/video0 for both its cameras; one device cannot "
            "be two sources: give each its own",
        ),
        (
            ["upper_serial:=301234", "lower_serial:=301234"],
            ":37: node 'zed_stereo' opens the ZED camera serial 301234 for both its cameras; one device cannot be "
            "two sources: give each its own",
        ),
        (
            ["upper_serial:=-5"],
            ":37: parameter 'upper_serial' = -5: expected a ZED serial number (0: the first camera found)",
        ),
    ],
)
def test_one_camera_as_both_sources_is_refused_by_the_dry_run(
    capsys: pytest.CaptureFixture[str], args: list[str], message: str
) -> None:
    """Sweep 6 U5: the dry run accepted one camera device or ZED serial as both cameras, and a serial of -5."""
    code, _, err = sensorbox(capsys, "launch", "--dry-run", "launch/sensorbox.launch.yaml", "out:=x", *args)
    assert code == 2 and len(err) == 1 and err[0].startswith("error: ") and err[0].endswith(message), err


def test_two_emulators_on_one_address_are_refused_by_the_dry_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    launch = tmp_path / "x.launch.yaml"
    node = "{pkg: sensorbox, exec: mid360_emulator, name: %s, param: [{name: ip, value: 127.0.0.12}]}"
    launch.write_text(f"launch:\n- node: {node % 'a'}\n- node: {node % 'b'}\n")
    code, _, err = sensorbox(capsys, "launch", "--dry-run", str(launch))
    assert (code, err) == (2, [
        f"error: {launch}:3: node 'b' opens the Mid-360 address 127.0.0.12, as does node 'a' at {launch}:2; one "
        "device cannot be two sources: give each its own"
    ])  # fmt: skip


def test_an_emulator_whose_rig_lacks_its_lidar_is_refused_by_the_dry_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Sweep 7: the dry run passed an emulator of a LiDAR its rig lacks, or whose rig file is missing;
    the run refused each only once started."""
    launch = tmp_path / "x.launch.yaml"
    node = "{pkg: sensorbox, exec: mid360_emulator, name: e, param: [{name: ip, value: 127.0.0.12}, %s]}"
    launch.write_text(f"launch:\n- node: {node % '{name: lidar, value: lidar_middle}'}\n")
    code, _, err = sensorbox(capsys, "launch", "--dry-run", str(launch))
    assert code == 2 and len(err) == 1
    assert err[0].startswith("error: node 'e' (sensorbox/mid360_emulator) at ") and err[0].endswith(
        ": lidar 'lidar_middle': the rig " + str(REFERENCE_RIG) + " has lidar_top, lidar_bottom"
    ), err
    missing = tmp_path / "nothere.yaml"
    launch.write_text(f"launch:\n- node: {node % ('{name: rig, value: ' + repr(str(missing)) + '}')}\n")
    code, _, err = sensorbox(capsys, "launch", "--dry-run", str(launch))
    assert code == 2 and err[0].endswith(f": {missing}: rig file not found"), err


def test_a_launch_argument_given_twice_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Sweep 3: `out:=a out:=b` ran into b without a word about a."""
    launch = ROOT / "launch" / "sim.launch.yaml"
    code, _, err = sensorbox(capsys, "launch", "--dry-run", str(launch), "out:=a", "out:=b")
    assert (code, err) == (2, ["error: launch argument out given twice (out:=a, out:=b); give it once"])


def test_capture_refuses_a_host_ip_that_is_no_address(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Sweep 3: `capture --emulate --host-ip 999.1.1.1` recorded a bag, exit 0, the address taken without a word."""
    out = tmp_path / "bags"
    rig = ROOT / "tests" / "fixtures" / "indoor_static_mcap.truth" / "rig.yaml"
    args = [
        "capture",
        "--emulate",
        "--rig",
        str(rig),
        "--out",
        str(out),
        "--host-ip",
        "999.1.1.1",
        "--duration",
        "1",
    ]
    code, _, err = sensorbox(capsys, *args)
    assert (code, err) == (
        2,
        ["error: --host-ip '999.1.1.1': expected a dotted IPv4 address such as 192.168.1.5"],
    )
    assert not out.exists()
