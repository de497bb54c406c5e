"""Real recordings repeat messages and run sensors on other clocks: read once, or refused in one line.

- The same messages twice (a file given under two names, split bags that
  overlap, a recorder that wrote them twice) are read once and counted per
  topic: each sample's points and GT are those of the recording read once.
- A LiDAR or IMU on a clock other than the cameras' (a CustomMsg timebase
  from the sensor's boot, IMU header stamps of zero) is refused naming the
  topic and both time ranges, instead of planning no sample or silently
  turning motion compensation off.
"""

from __future__ import annotations

import filecmp
import json
import re
import shutil
import struct
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml
from rich.console import Console

from ingest.bags.livox_msg import decode_custom_msg, encode_custom_msg
from ingest.bags.reader import open_bags
from ingest.dataset.layout import GT_DIRS
from ingest.dataset.meta import read_meta
from ingest.errors import BagError, DatasetError
from ingest.inspect import inspect_bags
from ingest.train.run.pipeline import ingest
from ingest.train.run.sample_dense import GAP_FALLBACK, GAP_REASON
from ingest.train.run.settings import IngestConfig
from ingest.train.trajectory import cache as trajectory_cache
from ingest.train.trajectory import estimate as trajectory_module
from sensorbox.cli.ingest import summary_table
from sensorbox.sim.truth import truth_dir
from tests.faults.bags import INDOOR, LIDAR_BOTTOM, LIDAR_TOP, LOWER, rewrite

IMU = "/livox/imu_192_168_1_12"
UPPER_STORED = "/zed_upper/zed_node/rgb/color/rect/image/compressed"
COUNTS = {UPPER_STORED: 21, LOWER: 21, LIDAR_TOP: 7, LIDAR_BOTTOM: 7, IMU: 140}  # the fixture's messages


def _config(out: Path, rig: Path | None = None) -> IngestConfig:
    return IngestConfig(rig=rig or truth_dir(INDOOR) / "rig.yaml", out=out, workers=1, every=5)


def _stamped(raw: bytes, stamp_ns: int) -> bytes:
    """A ROS 2 message (CDR) whose std_msgs/Header stamp, its first field, is `stamp_ns`."""
    return raw[:4] + struct.pack("<iI", *divmod(stamp_ns, 1_000_000_000)) + raw[12:]


@pytest.mark.parametrize("gt", ["sparse", "dense"])
def test_the_same_messages_twice_are_read_once_and_counted(tmp_path: Path, gt: str) -> None:
    """Every pass (plan, gyro, trajectory, samples) reads each message once: the same files, bit for bit."""
    once = ingest([INDOOR], replace(_config(tmp_path / "once"), gt=gt))
    (data,) = INDOOR.glob("*.mcap")
    copy = tmp_path / "copy.mcap"  # the same data under another name
    shutil.copy(data, copy)
    twice = ingest([INDOOR, copy], replace(_config(tmp_path / "twice"), gt=gt))
    assert (twice.written, twice.planned) == (once.written, once.planned)
    assert twice.written >= 4
    assert twice.duplicates == COUNTS and once.duplicates == {}
    folders = ["depth_fisheye", "disp_equirect", "left_fisheye", *(["trajectories"] if gt == "dense" else [])]
    for folder in folders:
        files = sorted((tmp_path / "once" / folder).iterdir())
        assert files
        for f in files:
            other = tmp_path / "twice" / folder / f.name
            if f.suffix == ".npz":  # the kept trajectory pass: the same arrays, under a key naming two bags
                with np.load(f) as a, np.load(other) as b:
                    assert a.files == b.files and str(a["key"]) != str(b["key"])
                    assert all(np.array_equal(a[k], b[k]) for k in a.files if k != "key"), f
                continue
            assert filecmp.cmp(f, other, shallow=False), f


def test_the_same_messages_three_times_are_not_a_stopped_clock(tmp_path: Path) -> None:
    """Two extra copies per message are repeats, counted twice; a clock that is not running is told by
    one stamp for every message, not by how many copies there are."""
    (data,) = INDOOR.glob("*.mcap")
    copies = [tmp_path / "a.mcap", tmp_path / "b.mcap"]
    for c in copies:
        shutil.copy(data, c)
    thrice = ingest([INDOOR, *copies], _config(tmp_path / "thrice"))
    assert thrice.duplicates == {t: 2 * n for t, n in COUNTS.items()} and thrice.written >= 4


def test_a_lidar_on_its_own_clock_is_refused_naming_it(tmp_path: Path) -> None:
    def boot_clock(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        if topic != LIDAR_BOTTOM:
            return [(topic, raw)]
        msg = decode_custom_msg(raw)  # the timebase counted from the sensor's boot, 123 s ago
        boot = msg.timebase_ns % 1_000_000_000 + 123_000_000_000
        return [(topic, encode_custom_msg(msg.stamp_ns, msg.frame_id, boot, msg.points, msg.lidar_id))]

    bag, rig = rewrite(tmp_path / "bag.mcap", boot_clock)
    pattern = (
        rf"^{bag}: {LIDAR_BOTTOM}: point times 123\.\d+ s\.\.123\.\d+ s do not overlap the upper camera's stamps "
        r"\d+\.\d+ s\.\.\d+\.\d+ s; the sensor's clock is not the cameras' \(sync it: PTP/gPTP or the host's time\)$"
    )
    with pytest.raises(BagError, match=pattern):
        ingest([bag], _config(tmp_path / "ds", rig))
    assert not (tmp_path / "ds").exists()
    (line,) = inspect_bags(bag).clock_problems()  # inspect says so too, for this LiDAR only
    assert line.startswith(f"{LIDAR_BOTTOM}: point times 123.") and "do not overlap" in line
    assert inspect_bags(INDOOR).clock_problems() == []


def test_imu_stamps_of_zero_are_refused_naming_the_topic(tmp_path: Path) -> None:
    def zero(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        return [(topic, _stamped(raw, 0) if topic == IMU else raw)]

    bag, rig = rewrite(tmp_path / "bag.mcap", zero)
    with pytest.raises(BagError, match=rf"^{bag}: {IMU}: header stamps 0\.000 s\.\.0\.000 s do not overlap"):
        ingest([bag], _config(tmp_path / "ds", rig))
    assert not (tmp_path / "ds").exists()


def test_camera_stamps_that_do_not_change_are_named(tmp_path: Path) -> None:
    def constant(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        return [(topic, _stamped(raw, 5_000_000_000) if topic == UPPER_STORED else raw)]

    bag, rig = rewrite(tmp_path / "bag.mcap", constant)
    message = (
        f"{bag}: 21 frame(s) on {UPPER_STORED} but 1 distinct header stamp(s) (header stamps: 5.000 s for all); "
        "need at least 2"
    )
    with pytest.raises(BagError) as err:
        ingest([bag], _config(tmp_path / "ds", rig))
    assert str(err.value) == message


def test_pairs_without_lidar_in_their_window_are_counted(tmp_path: Path) -> None:
    """Both LiDARs lose their last two sweeps: the last frames have no point within +-50 ms, are not
    planned, and the summary says how many, so that planned + uncovered = pairs."""

    def drop_last(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        return [] if topic in (LIDAR_TOP, LIDAR_BOTTOM) and k >= COUNTS[topic] - 2 else [(topic, raw)]

    bag, rig = rewrite(tmp_path / "bag.mcap", drop_last)
    full = ingest([INDOOR], IngestConfig(rig=rig, out=tmp_path / "full", workers=1, every=1))
    cut = ingest([bag], IngestConfig(rig=rig, out=tmp_path / "cut", workers=1, every=1))
    assert full.uncovered == 0 and full.planned == full.pairs == 21
    assert cut.pairs == 21 and cut.uncovered > 0
    assert cut.planned + cut.uncovered == cut.pairs and cut.written == cut.planned


def test_a_constant_stereo_offset_is_shown(tmp_path: Path) -> None:
    """Cameras that are not hardware-synced pair within half a period; the summary shows the offset."""

    def late(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        if topic != LOWER:
            return [(topic, raw)]
        sec, nsec = struct.unpack_from("<iI", raw, 4)
        return [(topic, _stamped(raw, sec * 1_000_000_000 + nsec + 12_000_000))]

    bag, rig = rewrite(tmp_path / "bag.mcap", late)
    summary = ingest([bag], _config(tmp_path / "ds", rig))
    synced = ingest([INDOOR], _config(tmp_path / "synced"))
    assert summary.written == synced.written == 5
    assert summary.stereo_dt_ms == pytest.approx([dt + 12.0 for dt in synced.stereo_dt_ms], abs=1e-6)
    assert max(abs(dt) for dt in synced.stereo_dt_ms) < 1.0  # the simulated cameras' own jitter


def test_a_rerun_with_other_settings_is_refused_before_any_pass(tmp_path: Path) -> None:
    """The dataset's settings are compared before the passes over the bags: a dense rerun with another
    --every is refused without running the trajectory pass again (its file stays as it was)."""
    out = tmp_path / "ds"
    ingest([INDOOR], replace(_config(out), gt="dense"))
    (tum,) = (out / "trajectories").glob("*.tum")
    before = tum.stat()
    with pytest.raises(
        DatasetError, match=r"an existing dataset was made with a different 'params' \(every: 5 -> 7\)"
    ):
        ingest([INDOOR], replace(_config(out), gt="dense", every=7))
    after = tum.stat()
    assert (after.st_ino, after.st_mtime_ns) == (before.st_ino, before.st_mtime_ns)


def test_a_resumed_dense_run_reuses_the_trajectory_pass(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A rerun after a killed run reads the pass the first run kept (`trajectories/<bag>.npz`) instead
    of repeating the odometry, and writes the same bytes; a kept file that cannot be read is computed
    again."""
    out = tmp_path / "ds"
    first = ingest([INDOOR], replace(_config(out), gt="dense"))
    assert first.trajectory is not None and not first.trajectory.reused and first.written >= 3
    (kept,) = (out / "trajectories").glob("*.npz")
    sid = "000001"
    files = [out / folder / f"{sid}.png" for folder in GT_DIRS]
    before = [f.read_bytes() for f in files]

    def killed_before_the_sample() -> None:  # what a run stopped before it finished the sample leaves
        for f in [*files, out / "meta" / f"{sid}.json"]:
            f.unlink()

    def no_odometry(*args: object, **kwargs: object) -> None:
        raise AssertionError("the odometry ran again")

    killed_before_the_sample()
    with monkeypatch.context() as patch:
        patch.setattr(trajectory_module, "trajectory_pass", no_odometry)
        again = ingest([INDOOR], replace(_config(out), gt="dense"))
    assert again.trajectory is not None and again.trajectory.reused
    assert (again.written, again.resumed) == (1, first.written - 1)
    assert [f.read_bytes() for f in files] == before
    with np.load(kept) as z:
        key = str(z["key"])
    assert json.loads(key)["code"] == trajectory_cache.code_digest()  # a new version computes it again
    assert trajectory_cache.load(kept, key) is not None and trajectory_cache.load(kept, key + " ") is None
    kept.write_bytes(kept.read_bytes()[:200])  # damaged
    killed_before_the_sample()
    third = ingest([INDOOR], replace(_config(out), gt="dense"))
    assert third.trajectory is not None and not third.trajectory.reused and third.written == 1
    assert [f.read_bytes() for f in files] == before


def test_a_lidar_gap_skips_the_dense_samples_it_touches(tmp_path: Path) -> None:
    """Both LiDARs lose two sweeps: those knots are carried by prediction (residual NaN), a frame inside
    the gap is skipped by reason, and no sample accumulates points across it."""

    def gap(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        return [] if topic in (LIDAR_TOP, LIDAR_BOTTOM) and k in (3, 4) else [(topic, raw)]

    bag, rig = rewrite(tmp_path / "bag.mcap", gap)
    dense = ingest(
        [bag], IngestConfig(rig=rig, out=tmp_path / "dense", workers=1, every=1, gt="dense", height_full=96)
    )
    assert dense.trajectory is not None and dense.trajectory.gaps >= 1
    assert dense.skipped.get(GAP_REASON, 0) >= 1
    assert dense.written + sum(dense.skipped.values()) == dense.planned
    metas = [read_meta(tmp_path / "dense", f.stem) for f in sorted((tmp_path / "dense" / "meta").iterdir())]
    assert len(metas) == dense.written >= 5
    assert all(m.points.kept + m.points.off_trajectory <= m.points.total for m in metas)
    # a frame after the gap: its +-500 ms window holds the three sweeps before the gap too, which were
    # placed on another stretch of the trajectory, so they are left out (the ends alone are a few points)
    with open_bags([bag]) as bags:
        sweep = [m for m in bags.messages(topics=[LIDAR_TOP])][3]  # the first after the gap
        gap_end_ns = decode_custom_msg(bytes(sweep.raw)).stamp_ns
    after = [m for m in metas if m.stamp_ns > gap_end_ns + 50_000_000]
    assert after and all(m.points.off_trajectory > 0.4 * m.points.total for m in after)
    assert dense.dense_points == {  # the summary's totals are the metadata's
        "accumulated": sum(m.gt.accumulated_points for m in metas),
        "removed as movers": sum(m.gt.removed_moving for m in metas),
        "left out: no registered pose near the frame": sum(m.points.off_trajectory for m in metas),
    }

    # --gt auto keeps dense GT and gives the frames in the gap the sparse GT a sparse run gives them
    auto = ingest(
        [bag], IngestConfig(rig=rig, out=tmp_path / "auto", workers=1, every=1, gt="auto", height_full=96)
    )
    sparse = ingest(
        [bag], IngestConfig(rig=rig, out=tmp_path / "sparse", workers=1, every=1, gt="sparse", height_full=96)
    )
    assert auto.method == "dense" and "in LiDAR gaps: frames there get sparse GT" in auto.decision
    # frames with no LiDAR point within +-50 ms are skipped, as a sparse run leaves them unplanned; the
    # frames past the trajectory's ends are skipped as in a dense run
    ends = dense.skipped.get("outside the trajectory", 0)
    assert auto.skipped == {**dense.skipped, GAP_REASON: sparse.uncovered}
    assert (
        sparse.uncovered > 0 and auto.written == dense.written + dense.skipped[GAP_REASON] - sparse.uncovered
    )

    def by_stamp(name: str) -> dict[int, str]:
        folder = tmp_path / name
        return {read_meta(folder, f.stem).stamp_ns: f.stem for f in (folder / "meta").iterdir()}

    runs = {name: by_stamp(name) for name in ("auto", "dense", "sparse")}
    in_gap = runs["auto"].keys() - runs["dense"].keys()
    assert auto.flagged["sparse GT (frame in a trajectory gap)"] == len(in_gap) > 0
    assert {m: len(d) for m, d in auto.density_by_method.items()} == {
        "dense": auto.written - len(in_gap), "sparse": len(in_gap)
    }  # fmt: skip
    console = Console(width=200, record=True)
    console.print(summary_table(auto, tmp_path / "auto"))
    text = console.export_text()
    for method, n in (("dense", auto.written - len(in_gap)), ("sparse", len(in_gap))):
        assert re.search(
            rf"GT density of the {method} GT samples \(median, samples\) +│ +[0-9.]+ %, {n} ", text
        )
    assert len(runs["sparse"]) == auto.written + ends  # sparse GT at the ends too
    for stamp, sid in runs["auto"].items():
        like = "dense" if stamp in runs["dense"] else "sparse"
        meta = read_meta(tmp_path / "auto", sid)
        assert (meta.gt.method, meta.gt.decision == GAP_FALLBACK) == (like, like == "sparse")
        for folder in GT_DIRS:
            got = (tmp_path / "auto" / folder / f"{sid}.png").read_bytes()
            assert got == (tmp_path / like / folder / f"{runs[like][stamp]}.png").read_bytes(), (sid, folder)
        if like == "sparse":  # and the same metadata, thin LiDARs over the same window included
            want = read_meta(tmp_path / "sparse", runs["sparse"][stamp])
            # its files are named by its id, its settings are the run's (--gt auto, sparse)
            assert replace(meta, id="", files={}, settings={}, gt=replace(meta.gt, decision="")) == replace(
                want, id="", files={}, settings={}, gt=replace(want.gt, decision="")
            )

    # a dataset whose auto run chose sparse GT for this recording (as an earlier version did for any gap)
    # is not resumed with dense samples
    doc_path = tmp_path / "auto" / "dataset.yaml"
    doc = yaml.safe_load(doc_path.read_text())
    doc["sources"][0]["ground_truth"].update(method="sparse", window_ms=50.0)
    doc_path.write_text(yaml.safe_dump(doc, sort_keys=False))
    with pytest.raises(
        DatasetError, match=r"before with sparse GT over \+-50 ms, now dense GT over \+-1000 ms \(auto: "
    ):
        ingest(
            [bag], IngestConfig(rig=rig, out=tmp_path / "auto", workers=1, every=1, gt="auto", height_full=96)
        )


@pytest.mark.parametrize("gt", ["dense", "auto"])
def test_clocks_are_checked_before_the_trajectory_pass(tmp_path: Path, gt: str) -> None:
    """A LiDAR on its own clock is refused before the odometry, which would step knot by knot across
    the years between the clocks, and before anything is written."""

    def boot_clock(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        if topic != LIDAR_BOTTOM:
            return [(topic, raw)]
        msg = decode_custom_msg(raw)
        boot = msg.timebase_ns % 1_000_000_000 + 123_000_000_000
        return [(topic, encode_custom_msg(msg.stamp_ns, msg.frame_id, boot, msg.points, msg.lidar_id))]

    bag, rig = rewrite(tmp_path / "bag.mcap", boot_clock)
    with pytest.raises(BagError, match="the sensor's clock is not the cameras'"):
        ingest([bag], replace(_config(tmp_path / "ds", rig), gt=gt))
    assert not (tmp_path / "ds").exists()


def test_an_imu_topic_without_readings_is_refused(tmp_path: Path) -> None:
    """The rig names an IMU whose topic is in the bag but holds no message: refused like a missing topic
    (motion compensation and the odometry would otherwise run without it, unsaid)."""

    def no_imu(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        return [] if topic == IMU else [(topic, raw)]

    bag, rig = rewrite(tmp_path / "bag.mcap", no_imu, declare={IMU: "sensor_msgs/msg/Imu"})
    with open_bags([bag]) as bags:
        assert IMU in bags.topics()
    for gt in ("sparse", "auto"):
        with pytest.raises(BagError) as err:
            ingest([bag], replace(_config(tmp_path / "ds", rig), gt=gt))
        assert str(err.value) == f"{bag}: no readings on {IMU} (the rig's IMU) in the whole bag"
        assert not (tmp_path / "ds").exists()


def test_a_camera_topic_without_frames_is_refused(tmp_path: Path) -> None:
    """The lower camera's topic in the bag with no message: a dataset of 0 samples was written with
    exit 0 and nothing said, where an empty LiDAR or IMU topic is refused."""

    def no_lower(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        return [] if topic == LOWER else [(topic, raw)]

    bag, rig = rewrite(tmp_path / "bag.mcap", no_lower, declare={LOWER: "sensor_msgs/msg/CompressedImage"})
    with open_bags([bag]) as bags:
        assert LOWER in bags.topics()
    with pytest.raises(BagError) as err:
        ingest([bag], _config(tmp_path / "ds", rig))
    assert str(err.value) == f"{bag}: no frames on {LOWER} (the rig's lower camera) in the whole bag"
    assert not (tmp_path / "ds").exists()


def test_an_imu_gap_is_shown_in_the_summary(tmp_path: Path) -> None:
    """40 IMU readings (200 ms at 200 Hz) missing: one gap, its length measured on the stamps."""

    def gap(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        return [] if topic == IMU and 40 <= k < 80 else [(topic, raw)]

    bag, rig = rewrite(tmp_path / "bag.mcap", gap)
    summary = ingest([bag], _config(tmp_path / "ds", rig))
    assert len(summary.imu_gaps_ms) == 1 and summary.imu_gaps_ms[0] == pytest.approx(205.0, abs=1.0)
    assert ingest([INDOOR], _config(tmp_path / "whole")).imu_gaps_ms == []


def test_a_clock_offset_between_the_lidars_is_named(tmp_path: Path) -> None:
    """The bottom LiDAR's clock 30 ms ahead (no PTP between the two): ingest and inspect say so in one
    line; it used to show only as a drop in dense GT's density (48 % -> 22 %)."""

    def ahead(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        if topic != LIDAR_BOTTOM:
            return [(topic, raw)]
        msg = decode_custom_msg(raw)
        shift = 30_000_000
        return [(topic, encode_custom_msg(msg.stamp_ns + shift, msg.frame_id, msg.timebase_ns + shift, msg.points,
                                          msg.lidar_id))]  # fmt: skip

    bag, rig = rewrite(tmp_path / "bag.mcap", ahead)
    line = (
        rf"^{LIDAR_TOP} and {LIDAR_BOTTOM}: bag time minus stamp differs by 30\.\d ms \(median\); their "
        r"clocks may disagree by that much \(sync the LiDARs: PTP/gPTP\)$"
    )
    summary = ingest([bag], _config(tmp_path / "ds", rig))
    assert len([w for w in summary.warnings if re.match(line, w)]) == 1
    assert [p for p in inspect_bags(bag).clock_problems() if re.match(line, p)]
    assert ingest([INDOOR], _config(tmp_path / "synced")).warnings == []
    # calib refine lays each LiDAR's points onto cam0's images by their times: sweep 9 found it turning
    # the walk's lidar_top by 0.98 deg to absorb a 35 ms clock error; it refuses instead, nothing written
    from calibration.errors import CalibrationError
    from calibration.rig import read_rig
    from ingest.train.run.pipeline import refine_rig

    with pytest.raises(CalibrationError) as refused:
        refine_rig([bag], read_rig(rig), workers=1)
    assert re.match(line[:-1] + "; refine lays each LiDAR's points onto cam0's images by their times, so a pose "
                    "refined from them would take the clock error in: sync the LiDARs and record again, then "
                    "refine$", str(refused.value))  # fmt: skip
