"""Capture end to end: the emulated rig (launch/sim.launch.yaml) recorded and ingested into a dataset,
`sensorbox capture` as the rig-file form of launch/sensorbox.launch.yaml, and the two commands' CLI."""

from __future__ import annotations

import itertools
import json
import os
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import yaml

from calibration.errors import SensorboxError
from ingest.bags.decode import header_stamp_ns
from ingest.bags.livox_msg import decode_custom_msg
from ingest.bags.reader import open_bags
from ingest.train.run.pipeline import ingest
from ingest.train.run.settings import IngestConfig
from sensorbox.live.capture import CaptureConfig, capture_plan, check_config
from sensorbox.live.launch import parse_launch
from sensorbox.live.launch_run import run_launch
from tests.faults.cli import run_here
from tests.live import HANG_S, NO_DISK_GUARD

ROOT = Path(__file__).resolve().parents[2]
REF = ROOT / "calibration" / "sensorbox.yaml"
SIM_LAUNCH = ROOT / "launch" / "sim.launch.yaml"
UPPER = "/zed_upper/zed_node/rgb/color/rect/image/compressed"
LOWER = "/zed_lower/zed_node/rgb/color/rect/image/compressed"
LIDARS = ("/livox/lidar_192_168_1_12", "/livox/lidar_192_168_1_13")
IMUS = ("/livox/imu_192_168_1_12", "/livox/imu_192_168_1_13")
_blocks = itertools.count()


def fresh_port_base() -> int:
    """A block of nine UDP ports no other test or xdist worker uses (the driver tests use 20000+)."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw")
    return 30000 + 1000 * int(worker or 0) + 10 * next(_blocks)


def run_cli(*args: str, timeout: float = HANG_S) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "sensorbox.cli", *args], capture_output=True, text=True, cwd=ROOT,
        check=False, timeout=timeout,
    )  # fmt: skip


@pytest.mark.realtime
def test_sim_launch_records_a_bag_that_ingests_into_a_dataset(tmp_path):
    out = tmp_path / "bags"
    args = {
        "out": str(out),
        "duration": "2.5",
        "scale": "0.25",
        "name": "sim",
        "port_base": str(fresh_port_base()),
        "min_free_mb": str(NO_DISK_GUARD),
    }
    result = run_launch(parse_launch(SIM_LAUNCH, args), tick_s=0.1)
    assert result.error is None and result.reason == "recorder: recorded 2.5 s"
    assert result.files == (out / "sim_000",)
    snap = result.snapshot
    c = {f"{node}.{key}": v for node, st in snap.nodes.items() for key, v in st.counters.items()}
    # conservation, however busy the machine: what the bus carried is in the bag or counted as a
    # recorder drop; every camera frame read was published, or counted by reason
    rec_drops = sum(v for k, v in snap.drops.items() if k.startswith("recorder."))
    assert sum(snap.published.values()) == sum(snap.written.values()) + rec_drops
    frames = c["zed_sim.upper.frames"] + c["zed_sim.lower.frames"]
    published = c["zed_sim.upper.published"] + c["zed_sim.lower.published"]
    assert (
        frames
        == published
        + snap.drops["zed_sim.encode"]
        + snap.drops["zed_sim.pair"]
        + c["zed_sim.unpaired_at_stop"]
    )
    assert c["zed_sim.upper.published"] == c["zed_sim.lower.published"] == c["zed_sim.pairs"] > 0

    with open_bags(out / "sim_000") as bags:
        counts = {t: s.count for t, s in bags.topics().items()}
        stamps = {
            t: [header_stamp_ns(m.raw, 2) for m in bags.messages([t])] for t in (UPPER, LOWER, *LIDARS, *IMUS)
        }
        sweeps = {t: [decode_custom_msg(m.raw, 2) for m in bags.messages([t])] for t in LIDARS}
    assert set(counts) == {UPPER, LOWER, *LIDARS, *IMUS}
    assert sum(counts.values()) == sum(snap.written.values())
    if not rec_drops:  # every pair the cameras published is in the bag, as a pair
        assert counts[UPPER] == counts[LOWER] == c["zed_sim.pairs"]
        dt = np.array(stamps[LOWER]) - np.array(stamps[UPPER])
        assert np.abs(dt).max() < 2_000_000  # the simulator's 0.1 ms stereo offset +- 0.5 ms jitter each
    # 30 Hz frame times: a frame the camera missed leaves a gap of whole periods
    period = 1e9 / 30
    gaps = np.diff(stamps[UPPER]) / period
    assert (np.abs(gaps - np.rint(gaps)) < 0.1).all() and (np.rint(gaps) >= 1).all()
    for k, topic in enumerate(LIDARS):
        ip = ("127.0.0.12", "127.0.0.13")[k]
        # every sweep holds whole packets of one 100 ms window of device time, windows in order
        keys = []
        for sw in sweeps[topic]:
            first_of_packet = sw.point_stamps_ns.reshape(-1, 96)[:, 0] // 100_000_000
            assert (first_of_packet == first_of_packet[0]).all()
            keys.append(int(first_of_packet[0]))
        assert keys == sorted(set(keys))
        if not rec_drops:  # the driver's books: sweeps and points published are the ones recorded
            assert len(sweeps[topic]) == c[f"livox_lidar_publisher.{ip}.sweeps"]
            assert sum(len(sw.points) for sw in sweeps[topic]) == c[f"livox_lidar_publisher.{ip}.points"]
        # nothing invented: the driver kept no more packets than the emulator sent
        emulator = ("lidar_top_emulator", "lidar_bottom_emulator")[k]
        assert c[f"livox_lidar_publisher.{ip}.packets"] <= c[f"{emulator}.packets_sent"]
    # the emulators' scan and the cameras share the simulator's clock: sweeps span the frames
    assert stamps[LIDARS[0]][0] < stamps[UPPER][len(stamps[UPPER]) // 2] < stamps[LIDARS[0]][-1]

    rig = out / "rig.yaml"
    assert rig.is_file()
    ds = tmp_path / "dataset"
    summary = ingest([out / "sim_000"], IngestConfig(rig=rig, out=ds, workers=1, every=20))
    assert summary.written >= 2 and summary.pairs <= min(counts[UPPER], counts[LOWER])
    if not rec_drops:
        assert summary.pairs == counts[UPPER]
    ids = sorted(p.stem for p in (ds / "meta").glob("*.json"))
    assert len(ids) == summary.written
    for folder in ("left_fisheye", "right_fisheye", "equirect_up", "equirect_down_virt", "disp_equirect",
                   "depth_fisheye"):  # fmt: skip
        assert sorted(p.stem for p in (ds / folder).glob("*.png")) == ids, folder
    depth = cv2.imread(str(ds / "depth_fisheye" / f"{ids[0]}.png"), cv2.IMREAD_UNCHANGED)
    assert depth is not None
    assert depth.dtype == np.uint16 and depth.shape == (300, 480)
    valid = depth[depth > 0]
    assert valid.size > 1000 and 300 <= np.median(valid) <= 20_000  # indoor ranges, mm
    meta = json.loads((ds / "meta" / f"{ids[0]}.json").read_text())
    assert meta["stamp_ns"] in stamps[UPPER]
    assert yaml.safe_load((ds / "dataset.yaml").read_text())


def test_capture_is_the_rig_file_form_of_the_real_launch_file():
    launch = parse_launch(ROOT / "launch" / "sensorbox.launch.yaml")
    direct = capture_plan(CaptureConfig(rig=REF, out=Path("bags"), split_size_mb=4096, min_free_mb=2048))
    assert [(n.pkg, n.exec) for n in direct.nodes] == [(n.pkg, n.exec) for n in launch.nodes]
    drv_l, cam_l, rec_l = launch.nodes
    drv_d, cam_d, rec_d = direct.nodes
    assert dict(drv_d.params) == dict(drv_l.params) and drv_d.remaps == drv_l.remaps == ()
    assert cam_d.params["source"] == cam_l.params["source"] == "zed"
    assert (cam_d.params["upper_topic"], cam_d.params["lower_topic"]) == (
        "/zed_upper/zed_node/rgb/color/rect/image", "/zed_lower/zed_node/rgb/color/rect/image",
    )  # fmt: skip
    for key in ("out", "duration_s", "split_size_mb", "min_free_mb"):
        assert rec_d.params[key] == rec_l.params[key], key


def test_capture_emulated_remaps_loopback_lidars_to_the_rig_topics(tmp_path):
    plan = capture_plan(CaptureConfig(rig=REF, out=tmp_path, emulate=True, port_base=31999))
    emu_top, emu_bottom, driver, camera, _ = plan.nodes
    assert (emu_top.params["ip"], emu_top.params["lidar"]) == ("127.0.0.12", "lidar_top")
    assert (emu_bottom.params["ip"], emu_bottom.params["lidar"]) == ("127.0.0.13", "lidar_bottom")
    assert driver.params["host_ip"] == "127.0.0.1" and driver.params["port_base"] == 31999
    assert driver.params["lidar_ips"] == ["127.0.0.12", "127.0.0.13"]
    assert set(driver.remaps) == {
        ("/livox/lidar_127_0_0_12", LIDARS[0]), ("/livox/imu_127_0_0_12", IMUS[0]),
        ("/livox/lidar_127_0_0_13", LIDARS[1]), ("/livox/imu_127_0_0_13", IMUS[1]),
    }  # fmt: skip
    assert camera.params["source"] == "sim" and camera.params["write_rig"] == str(tmp_path / "rig.yaml")


def test_capture_needs_lidar_ips(tmp_path):
    text = REF.read_text().replace("    ip: 192.168.1.13\n", "")
    rig = tmp_path / "rig.yaml"
    rig.write_text(text)
    (tmp_path / "sensorbox-camchain.yaml").write_text((REF.parent / "sensorbox-camchain.yaml").read_text())
    with pytest.raises(SensorboxError, match=r"lidars\.lidar_bottom: no 'ip'"):
        capture_plan(CaptureConfig(rig=rig, out=tmp_path))


def test_port_base_and_jpeg_quality_limits(tmp_path):
    """The driver takes nine consecutive UDP ports from --port-base (`Ports.block`): 65527 + 8 = 65535
    is the last that fits, 65528 is refused; JPEG quality runs 1..100, so 0 is refused."""
    check_config(CaptureConfig(rig=REF, out=tmp_path, port_base=65527))
    check_config(CaptureConfig(rig=REF, out=tmp_path, jpeg_quality=1))
    with pytest.raises(
        SensorboxError, match=r"^--port-base 65528: expected 1\.\.65527 \(the first of nine UDP ports\)$"
    ):
        check_config(CaptureConfig(rig=REF, out=tmp_path, port_base=65528))
    with pytest.raises(SensorboxError, match=r"^--jpeg-quality 0: expected 1\.\.100$"):
        check_config(CaptureConfig(rig=REF, out=tmp_path, jpeg_quality=0))


def test_cli_launch_dry_run_show_args_and_errors(capsys: pytest.CaptureFixture[str]) -> None:
    """`launch --dry-run`, `--show-args`, a bad argument and `--help`, in this process (`run_here`)."""
    res = run_here(capsys, "launch", str(SIM_LAUNCH), "--dry-run", "scale:=0.5")
    assert res.returncode == 0, res.stderr
    assert "- livox_lidar_publisher (livox_ros_driver2/livox_ros_driver2_node), namespace /" in res.stdout
    assert "    remap /livox/lidar_127_0_0_12 -> /livox/lidar_192_168_1_12\n" in res.stdout
    assert "    param scale = 0.5\n" in res.stdout
    res = run_here(capsys, "launch", str(SIM_LAUNCH), "--show-args")
    assert res.returncode == 0
    assert (
        "  duration:='0' (default '0')\n      seconds to record; 0 = until interrupted (Ctrl-C)\n"
        in res.stdout
    )
    assert "  scene:='indoor' (default 'indoor', one of indoor, outdoor)\n" in res.stdout
    res = run_here(capsys, "launch", str(SIM_LAUNCH), "scene:=moon")
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode == 2 and len(lines) == 1
    assert "scene:='moon' is not one of indoor, outdoor" in lines[0] and "sim.launch.yaml" in lines[0]
    res = run_here(capsys, "capture", "--rig", str(REF), "--out", "x", "--camera", "usb")
    assert res.returncode == 2 and "--camera 'usb': expected one of zed, opencv" in res.stderr
    for args in (["launch", "--help"], ["capture", "--help"]):
        res = run_here(capsys, *args)
        assert res.returncode == 0 and "Usage" in res.stdout


@pytest.mark.realtime
def test_cli_capture_emulated_rig(tmp_path):
    out = tmp_path / "cap"
    res = run_cli(
        "capture", "--rig", str(REF), "--out", str(out), "--emulate", "--duration", "1", "--scale", "0.25",
        "--name", "c", "--port-base", str(fresh_port_base()), "--min-free", str(NO_DISK_GUARD),
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    flat = " ".join(res.stdout.split())
    assert "stopped: recorder: recorded 1 s" in flat and f"Bag: {out / 'c_000'}" in flat
    with open_bags(out / "c_000") as bags:
        assert set(bags.topics()) == {UPPER, LOWER, *LIDARS, *IMUS}
    assert "drops" in res.stderr  # the status line


def test_status_line_rates_drops_and_disk():
    from sensorbox.cli.capture import status_line
    from sensorbox.live.bus import GraphSnapshot, NodeStatus

    imu, cam = "/livox/imu_192_168_1_12", UPPER
    prev = GraphSnapshot(1.0, {imu: 200, cam: 30}, {imu: 200, cam: 30}, {}, {}, {})
    rec = NodeStatus({"bytes_written": 3 * 2**20, "disk_free_bytes": 5 * 2**30})
    now = GraphSnapshot(3.0, {imu: 600, cam: 92}, {imu: 600, cam: 90}, {}, {"rec.queue": 2, "drv.udp_lost": 0},
                        {"rec": rec})  # fmt: skip
    assert status_line(prev, now) == (
        "   3.0 s  imu_192_168_1_12 200.0 | zed_upper 30.0 msg/s  drops queue 2  3.0 MiB written  5.0 GiB free"
    )
    assert status_line(None, GraphSnapshot(0.5, {}, {}, {}, {}, {})) == "   0.5 s  no messages yet  drops 0"


def test_a_lidar_that_sent_nothing_is_a_warning_after_the_recording():
    """Issue 49: `loop_s:=0` recorded a bag with no LiDAR or IMU message and every counter 0, silently."""
    from sensorbox.live.bus import NodeStatus
    from sensorbox.live.livox_node import silent_lidars

    driver = NodeStatus({"127.0.0.12.packets": 0.0, "127.0.0.12.imu_packets": 0.0, "127.0.0.13.packets": 0.0,
                         "127.0.0.13.imu_packets": 40.0, "foreign": 0.0})  # fmt: skip
    heard = NodeStatus({"127.0.0.14.packets": 5.0, "127.0.0.14.imu_packets": 40.0})
    assert silent_lidars({"livox": driver, "other": heard, "rec": NodeStatus()}, 19.54) == [
        "livox: lidar 127.0.0.12 sent no point and no IMU packet in 19.5 s; the recording holds no LiDAR or IMU "
        "message from it",
        "livox: lidar 127.0.0.13 sent no point packet in 19.5 s; the recording holds no LiDAR message from it",
    ]


@pytest.mark.realtime
def test_a_live_emulator_sweeps_without_listing_its_run_first():
    """`loop_s:=0` simulates live over a 1e7 s run: its first sweep comes at once (it listed 1e8 windows
    first, and the emulator never sent)."""
    from sensorbox.sim.config import SimConfig
    from sensorbox.sim.lidar import iter_sweep_windows, sweep_windows
    from sensorbox.sim.run import setup_sim
    from sensorbox.sim.scan_source import SimScan

    setup = setup_sim(SimConfig(scene="indoor", duration_s=0.35, scale=0.1))
    lidar = setup.lidars[0]
    assert list(iter_sweep_windows(lidar, setup.cfg.start_ns, setup.duration_ns)) == sweep_windows(
        lidar, setup.cfg.start_ns, setup.duration_ns
    )
    live = setup_sim(SimConfig(scene="indoor", duration_s=1e7, scale=0.1))
    first: list[Any] = []
    sweeping = threading.Thread(target=lambda: first.append(next(SimScan(live, 0).sweeps())), daemon=True)
    sweeping.start()
    sweeping.join(60.0)  # it takes a second; listing the windows first took minutes and gigabytes
    assert first and first[0].timebase_ns == next(SimScan(setup, 0).sweeps()).timebase_ns


@pytest.mark.realtime
def test_a_launch_that_publishes_nothing_says_so(tmp_path: Path) -> None:
    """Sweep 7: a launch file with a recorder alone 'recorded 2 s', an empty table, no bag and no line."""
    launch = tmp_path / "rec.launch.yaml"
    launch.write_text(
        "launch:\n- node: {pkg: sensorbox, exec: recorder, name: rec, param: ["
        f"{{name: out, value: '{tmp_path / 'bags'}'}}, {{name: duration_s, value: 1.0}}]}}\n"
    )
    res = run_cli("launch", str(launch))
    assert res.returncode == 0, res.stderr
    assert "warning: no message was published in " in res.stderr
    assert res.stderr.rstrip().endswith(
        "s: no node of the run publishes a topic (a recorder alone records nothing), so no bag was written"
    )
    assert not list(tmp_path.rglob("*.mcap"))


def test_a_camera_that_published_nothing_is_a_warning_after_the_recording() -> None:
    """Sweep 8: capture --emulate stopped by SIGINT after 1.1 s wrote a bag with both LiDARs and IMUs and not
    one camera frame, exit 0 and no line (the LiDARs had one, `silent_lidars`)."""
    from sensorbox.cli.capture import silent_lines
    from sensorbox.live.bus import GraphSnapshot, NodeStatus

    upper, lower = "/zed_upper/zed_node/rgb/color/rect/image", "/zed_lower/zed_node/rgb/color/rect/image"
    snap = GraphSnapshot(
        1.13, {"/livox/lidar_192_168_1_12": 9, lower: 0}, {}, {}, {},
        {"cameras": NodeStatus(), "livox": NodeStatus({"192.168.1.12.packets": 90.0, "192.168.1.12.imu_packets": 200.0})},
        {upper: "cameras", lower: "cameras", "/livox/lidar_192_168_1_12": "livox"},
    )  # fmt: skip
    assert silent_lines(snap, recorded=True) == [
        f"cameras: published nothing on {lower}, {upper} in 1.1 s; the recording holds no message of it (a camera "
        "that had not started, or was unplugged)"
    ]
    assert silent_lines(snap, recorded=False) == []


def test_a_rig_sensor_the_recording_lacks_is_a_warning() -> None:
    """Sweep 8: a launch whose driver lists lidar_ips [127.0.0.12] only, while the rig its camera node
    wrote beside the bag names both LiDARs: a bag without lidar_bottom or imu_bottom, exit 0 and no line
    (inspect then refused the pair)."""
    from sensorbox.cli.capture import silent_lines
    from sensorbox.live.bus import GraphSnapshot

    bottom = "/livox/lidar_192_168_1_13"
    snap = GraphSnapshot(
        3.3, {"/livox/lidar_192_168_1_12": 30}, {}, {}, {}, {}, {"/livox/lidar_192_168_1_12": "driver"},
        {bottom: "out/rig.yaml names it for lidar_bottom", "/livox/lidar_192_168_1_12": "out/rig.yaml names it for lidar_top"},
    )  # fmt: skip
    assert silent_lines(snap, recorded=True) == [
        f"{bottom}: out/rig.yaml names it for lidar_bottom, yet nothing was published on it in 3.3 s; the "
        "recording holds none of it (a driver that does not list that sensor's address, or a remap that sends it "
        "elsewhere)"
    ]
