"""Ingest end to end against the simulator's exact truth, plus resume, Dask and bad input."""

from __future__ import annotations

import errno
import filecmp
import hashlib
import json
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from calibration.stereo import rotate_for_stereo
from ingest.bags.reader import open_bags
from ingest.dataset.identity import bag_identity
from ingest.dataset.layout import DEPTH_SCALE, DISP_SCALE, read_png_u16
from ingest.dataset.meta import read_meta
from ingest.errors import BagError, DatasetError, MessageDecodeError, SettingError
from ingest.train.gt.dense import DenseParams
from ingest.train.run.pipeline import ingest
from ingest.train.run.sample_job import SampleParams
from ingest.train.run.settings import IngestConfig
from sensorbox.live.bagwriter import BagWriter
from sensorbox.sim.config import SimConfig
from sensorbox.sim.run import simulate
from sensorbox.sim.score import score_dataset
from sensorbox.sim.truth import Truth, truth_dir
from tests.paths import FIXTURES_DIR

INDOOR = FIXTURES_DIR / "indoor_static_mcap"


def _rig(bag: Path) -> Path:
    return truth_dir(bag) / "rig.yaml"


@pytest.fixture(scope="module")
def full_res_static(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """Full-resolution, noise-free, static indoor: 0.12 s, ingested."""
    root = tmp_path_factory.mktemp("full")
    cfg = SimConfig(scene="indoor", duration_s=0.12, scale=1.0, image="jpeg", range_noise_m=0.0, seed=1)
    bag = simulate(cfg, root / "bag").bag
    out = root / "ds"
    summary = ingest([bag], IngestConfig(rig=_rig(bag), out=out, workers=1))
    assert summary.written >= 2
    return bag, out


def test_static_indoor_depth_and_disparity_match_the_truth(full_res_static: tuple[Path, Path]) -> None:
    bag, out = full_res_static
    truth = Truth.load(bag)
    for score in score_dataset(out, truth):
        assert score.depth_pixels > 5_000
        assert score.depth_median_abs_m <= 0.002
        assert score.depth_outlier_rate <= 0.005, score
        assert score.disp_median_abs_px <= 0.05 and score.disp_over_1px_rate <= 0.005, score
        # the pair as written lies where its disparity GT lays one image onto the other
        dx_px, dy_px, pixels = read_meta(out, score.sid).stereo_offset or [np.nan] * 3
        assert abs(dx_px) < 0.05 and abs(dy_px) < 0.05 and pixels == 5000, (dx_px, dy_px)


def test_walk_outdoor_with_motion_compensation(tmp_path: Path) -> None:
    """1.2 m/s and up to 60 deg/s: IMU rotation + estimated velocity; off for contrast."""
    cfg = SimConfig(
        scene="outdoor", trajectory="walk", duration_s=0.2, scale=0.5, image="jpeg", range_noise_m=0.0, seed=2
    )
    bag = simulate(cfg, tmp_path / "walk").bag
    truth = Truth.load(bag)
    medians: dict[str, list[float]] = {}
    for name, params in (("on", SampleParams()), ("off", SampleParams(min_motion_px=1e9))):
        out = tmp_path / name
        summary = ingest([bag], IngestConfig(rig=_rig(bag), out=out, workers=1, sample=params))
        assert summary.written >= 4
        applied = 0
        for score in score_dataset(out, truth):
            medians.setdefault(name, []).append(score.depth_median_abs_m)
            motion = read_meta(out, score.sid).motion
            applied += motion.applied
            if name == "on":
                assert motion.applied and motion.speed_mps == pytest.approx(1.24, abs=0.1)
                assert score.depth_outlier_rate <= 0.005, score
                assert score.disp_median_abs_px <= 0.05 and score.disp_over_1px_rate <= 0.005, score
        # the CLI's "motion compensation applied" row: every sample when on, none when off
        assert summary.motion_applied == applied == (summary.written if name == "on" else 0)
    assert max(medians["on"]) <= 0.002
    assert min(medians["off"]) > 0.02  # uncompensated: centimetres


def test_range_noise_of_2cm_gives_median_error_below_15mm(tmp_path: Path) -> None:
    bag = FIXTURES_DIR / "outdoor_static_bag.bag"
    out = tmp_path / "ds"
    ingest([bag], IngestConfig(rig=_rig(bag), out=out, workers=1, every=7))
    truth = Truth.load(bag)
    for score in score_dataset(out, truth):
        assert 0.008 < score.depth_median_abs_m <= 0.015, score
        assert abs(score.depth_bias_m) < 0.003, score  # no bias
    meta = read_meta(out, "000000")
    assert meta.points.noise_tag > 0  # the simulator's dust echoes were dropped by their tag


def _sgbm(up: np.ndarray, down: np.ndarray) -> np.ndarray:
    left = cv2.cvtColor(rotate_for_stereo(up), cv2.COLOR_BGR2GRAY)
    right = cv2.cvtColor(rotate_for_stereo(down), cv2.COLOR_BGR2GRAY)
    matcher = cv2.StereoSGBM_create(  # type: ignore[attr-defined]
        minDisparity=0, numDisparities=64, blockSize=5, P1=200, P2=800, uniquenessRatio=5,
        mode=cv2.STEREO_SGBM_MODE_HH,
    )  # fmt: skip
    out: np.ndarray = matcher.compute(left, right).astype(np.float32) / 16.0
    return out


def test_rectified_pair_agrees_with_disparity_gt_under_sgbm(tmp_path: Path) -> None:
    out = tmp_path / "ds"
    ingest([INDOOR], IngestConfig(rig=_rig(INDOOR), out=out, workers=1, every=10))
    up = np.asarray(cv2.imread(str(out / "equirect_up" / "000001.png")))
    down = np.asarray(cv2.imread(str(out / "equirect_down_virt" / "000001.png")))
    gt = rotate_for_stereo(read_png_u16(out / "disp_equirect" / "000001.png", DISP_SCALE))

    def stats(disp: np.ndarray, ref: np.ndarray) -> tuple[float, float]:
        m = (ref != 0) & (disp > 0)
        e = np.abs(disp[m] - ref[m])
        return float(np.median(e)), float((e > 3).mean())

    median, bad3 = stats(_sgbm(up, down), gt)
    assert median < 0.4 and bad3 < 0.1, (median, bad3)
    # what the test guards against: a one-row offset of the pair, or a flipped disparity sign
    assert stats(_sgbm(up, np.roll(down, 1, axis=0)), gt)[0] > 0.8
    assert stats(_sgbm(up, down), -gt)[1] > 0.9


def test_rerun_resumes_and_output_is_deterministic(tmp_path: Path) -> None:
    a, b = tmp_path / "a", tmp_path / "b"
    cfg = IngestConfig(rig=_rig(INDOOR), out=a, workers=2, every=5)
    first = ingest([INDOOR], cfg)
    assert first.written == 5 and first.resumed == 0
    ingest([INDOOR], IngestConfig(rig=_rig(INDOOR), out=b, workers=1, every=5))
    cmp = filecmp.dircmp(a, b)
    for sub in (
        "depth_fisheye",
        "disp_equirect",
        "equirect_up",
        "equirect_down_virt",
        "left_fisheye",
        "right_fisheye",
        "meta",
    ):
        match, mismatch, errs = filecmp.cmpfiles(
            a / sub, b / sub, sorted(p.name for p in (a / sub).iterdir()), False
        )
        assert not mismatch and not errs and len(match) == 5, (sub, mismatch)
    assert cmp.left_only == [] and cmp.right_only == []
    # an interrupted run: one sample's metadata missing, a half-written temp file left behind
    (a / "meta" / "000002.json").unlink()
    (a / "depth_fisheye" / ".000002.png.xyz.tmp").write_bytes(b"partial")
    again = ingest([INDOOR], cfg)
    assert (again.written, again.resumed) == (1, 4)
    assert filecmp.cmp(a / "meta" / "000002.json", b / "meta" / "000002.json", shallow=False)


def test_a_second_recording_is_appended_and_each_resumes_its_own_ids(tmp_path: Path) -> None:
    """Sample ids are keyed by recording (issue 20, class 1): a second bag no longer 'resumes' the first's."""
    walk = FIXTURES_DIR / "indoor_walk_db3"
    out = tmp_path / "ds"
    first = ingest([INDOOR], IngestConfig(rig=_rig(INDOOR), out=out, workers=1, every=10))
    second = ingest([walk], IngestConfig(rig=_rig(INDOOR), out=out, workers=1, every=10))
    assert (first.written, second.resumed) == (first.planned, 0)
    assert second.written + sum(second.skipped.values()) == second.planned
    doc = yaml.safe_load((out / "dataset.yaml").read_text())
    assert [(s["bags"], s["first_id"], s["samples"]) for s in doc["sources"]] == [
        (["indoor_static_mcap"], 0, first.planned),
        (["indoor_walk_db3"], first.planned, second.planned),
    ]
    metas = sorted((out / "meta").glob("*.json"))
    assert len(metas) == first.written + second.written
    assert {json.loads(m.read_text())["source_bag"] for m in metas} == {
        "indoor_static_mcap",
        "indoor_walk_db3",
    }
    again = ingest([walk], IngestConfig(rig=_rig(INDOOR), out=out, workers=1, every=10))
    assert (again.written, again.resumed, again.skipped) == (0, second.written, second.skipped)
    with pytest.raises(
        DatasetError,
        match=r"dataset.yaml: an existing dataset was made with a different 'params' \(every: 10 -> 5\)",
    ):
        ingest([walk], IngestConfig(rig=_rig(INDOOR), out=out, workers=1, every=5))


def test_bag_identity_is_the_data_files_size_and_head_hash_without_metadata_yaml(tmp_path: Path) -> None:
    """A rosbag2 folder is identified by its data files only: bytes = their total size, sha256 over each
    file's "name:size:" and first MiB in name order; metadata.yaml, which `ros2 bag reindex` rewrites,
    changes neither."""
    bag = tmp_path / "rec"
    bag.mkdir()
    (bag / "rec_0.mcap").write_bytes(b"a" * 10)
    (bag / "rec_1.mcap").write_bytes(b"bc" * 3)
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    digest = hashlib.sha256(b"rec_0.mcap:10:" + b"a" * 10 + b"rec_1.mcap:6:" + b"bc" * 3).hexdigest()
    assert bag_identity(bag) == {"bytes": 16, "sha256_head": digest}
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: {version: 8}\n")
    assert bag_identity(bag) == {"bytes": 16, "sha256_head": digest}


def test_a_recording_is_known_by_its_content_and_a_dataset_by_its_rig(tmp_path: Path) -> None:
    """Another recording under the same name, or the same one with another rig, cannot resume into a dataset."""
    out = tmp_path / "ds"
    first = ingest([INDOOR], IngestConfig(rig=_rig(INDOOR), out=out, workers=1, every=10))
    stored = {name: (out / "rig" / name).read_bytes() for name in ("rig.yaml", "camchain.yaml")}
    impostor = tmp_path / "other" / INDOOR.name  # other data, the same folder name
    shutil.copytree(FIXTURES_DIR / "indoor_walk_db3", impostor)
    with pytest.raises(
        DatasetError, match=r"a recording named indoor_static_mcap was ingested here before, from other data"
    ):
        ingest([impostor], IngestConfig(rig=_rig(INDOOR), out=out, workers=1, every=10))
    shifted = yaml.safe_load(_rig(INDOOR).read_text())
    shifted["lidars"]["lidar_top"]["T_cam0_lidar"][0][3] += 0.01  # 1 cm
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(shifted))
    shutil.copy(truth_dir(INDOOR) / "camchain.yaml", tmp_path / "camchain.yaml")
    with pytest.raises(DatasetError, match=r"another rig \(rig.yaml \(lidars.lidar_top.T_cam0_lidar: "):
        ingest([INDOOR], IngestConfig(rig=tmp_path / "rig.yaml", out=out, workers=1, every=10))
    chain = yaml.safe_load((truth_dir(INDOOR) / "camchain.yaml").read_text())
    chain["cam0"]["intrinsics"][-2] += 1.0  # cx, 1 px
    (tmp_path / "camchain.yaml").write_text(yaml.safe_dump(chain))
    (tmp_path / "rig.yaml").write_text(_rig(INDOOR).read_text())
    with pytest.raises(DatasetError, match=r"another rig \(camchain.yaml \(cam0.intrinsics: "):
        ingest([INDOOR], IngestConfig(rig=tmp_path / "rig.yaml", out=out, workers=1, every=10))
    assert {name: (out / "rig" / name).read_bytes() for name in stored} == stored  # left as it was
    again = ingest([INDOOR], IngestConfig(rig=_rig(INDOOR), out=out, workers=1, every=10))
    assert (again.written, again.resumed) == (0, first.written)
    with pytest.raises(BagError, match=r"indoor_static_mcap: the same recording is given twice"):
        ingest([INDOOR, INDOOR], IngestConfig(rig=_rig(INDOOR), out=tmp_path / "twice", workers=1))
    assert not (tmp_path / "twice").exists()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"workers": 0}, r"^workers 0: expected >= 1$"),
        ({"every": 0}, r"^every 0: expected >= 1$"),
        ({"lidar_window_ns": 0}, r"^lidar_window_ns 0: expected > 0$"),
        ({"lidar_window_ns": -5_000_000}, r"^lidar_window_ns -5000000: expected > 0$"),
        ({"dask": "notanaddress"}, r"^dask 'notanaddress': expected a scheduler address tcp://HOST:PORT"),
        ({"sample": SampleParams(png_level=9)}, r"^sample\.png_level 9: expected 0\.\.3$"),
        (
            {"sample": SampleParams(min_range_m=-1.0)},
            r"^sample\.min_range_m -1: expected a finite number >= 0 \(m\)$",
        ),
        (
            {"sample": SampleParams(min_range_m=float("inf"))},
            r"^sample\.min_range_m inf: expected a finite number >= 0 \(m\)$",
        ),
        (
            {
                "gt": "auto",
                "lidar_window_ns": 80_000_000,
                "sample": SampleParams(dense=DenseParams(window_ns=40_000_000)),
            },
            r"^sample\.dense\.window_ns 40000000: expected at least lidar_window_ns with gt 'auto': the sparse GT "
            r"it gives frames in trajectory gaps reads lidar_window_ns of points from the dense window$",
        ),
    ],
)
def test_a_bad_setting_is_one_line_naming_it(tmp_path: Path, change: dict[str, object], message: str) -> None:
    """The library names its settings (the fields of `IngestConfig`); `sensorbox ingest` names its
    options instead (`tests/sensorbox/test_cli.py`)."""
    cfg = IngestConfig(rig=_rig(INDOOR), out=tmp_path / "ds", **change)  # type: ignore[arg-type]
    with pytest.raises(SettingError, match=message):
        ingest([INDOOR], cfg)
    assert not (tmp_path / "ds").exists()


def test_a_rig_without_lidars_or_a_bag_without_messages_is_one_line(tmp_path: Path) -> None:
    rig = yaml.safe_load(_rig(INDOOR).read_text())
    rig["lidars"] = {}
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(rig))
    shutil.copy(truth_dir(INDOOR) / "camchain.yaml", tmp_path / "camchain.yaml")
    with pytest.raises(DatasetError, match=r"rig.yaml: the rig has no LiDAR under 'lidars'"):
        ingest([INDOOR], IngestConfig(rig=tmp_path / "rig.yaml", out=tmp_path / "ds"))
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    with pytest.raises(BagError, match=r"empty.mcap: no messages at all"):
        ingest([empty], IngestConfig(rig=_rig(INDOOR), out=tmp_path / "ds", salvage=True))
    assert not (tmp_path / "ds").exists()


def test_dask_local_cluster_writes_the_same_files(tmp_path: Path) -> None:
    from distributed import LocalCluster

    local = tmp_path / "local"
    ingest([INDOOR], IngestConfig(rig=_rig(INDOOR), out=local, workers=1, every=10))
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        out = tmp_path / "dask"
        summary = ingest(
            [INDOOR], IngestConfig(rig=_rig(INDOOR), out=out, dask=cluster.scheduler_address, every=10)
        )
    assert summary.written == 3
    for sub in ("depth_fisheye", "disp_equirect", "meta"):
        for f in (local / sub).iterdir():
            assert filecmp.cmp(f, out / sub / f.name, shallow=False)


def test_an_unreachable_dask_scheduler_fails_before_anything_is_written(tmp_path: Path) -> None:
    import socket

    import dask

    with socket.socket() as sock:  # a port nobody listens on
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    out = tmp_path / "ds"
    with (
        dask.config.set({"distributed.comm.timeouts.connect": "1s"}),
        pytest.raises(
            SettingError, match=rf"^dask 'tcp://127\.0\.0\.1:{port}': expected a scheduler that answers \("
        ),
    ):
        ingest([INDOOR], IngestConfig(rig=_rig(INDOOR), out=out, dask=f"tcp://127.0.0.1:{port}"))
    assert not out.exists()


def _rig_renaming(tmp_path: Path, topic: str, new: str) -> Path:
    """The fixture's rig with one topic renamed (so the bag lacks it), written into `tmp_path`."""
    (tmp_path / "rig.yaml").write_text(_rig(INDOOR).read_text().replace(topic, new))
    shutil.copy(truth_dir(INDOOR) / "camchain.yaml", tmp_path / "camchain.yaml")
    return tmp_path / "rig.yaml"


def test_missing_topic_lists_the_bag_topics(tmp_path: Path) -> None:
    rig = _rig_renaming(tmp_path, "/livox/lidar_192_168_1_13", "/livox/lidar_10_0_0_9")
    with pytest.raises(
        BagError, match=r"lidar_10_0_0_9.* the bag has: [^\n]*/livox/imu_192_168_1_12, [^\n]*$"
    ):
        ingest([INDOOR], IngestConfig(rig=rig, out=tmp_path / "ds", workers=1))


def test_an_imu_the_rig_names_must_be_in_the_bag(tmp_path: Path) -> None:
    """No silent fallback to motion compensation without the IMU (issue 20, class 3)."""
    rig = _rig_renaming(tmp_path, "/livox/imu_192_168_1_12", "/livox/imu_10_0_0_9")
    with pytest.raises(BagError, match=r"no topic '/livox/imu_10_0_0_9' for imu .* \(from the rig\)"):
        ingest([INDOOR], IngestConfig(rig=rig, out=tmp_path / "ds", workers=1))
    assert not (tmp_path / "ds").exists()


def test_rig_that_does_not_match_the_bag(tmp_path: Path) -> None:
    """The reference rig is full resolution, the fixture images 480x300: the run stops at the first images.
    The output it leaves holds no sample, so the same --out takes the right rig afterwards."""
    from calibration.rig import REFERENCE_RIG

    passes: list[str] = []
    with pytest.raises(BagError, match=r"the image is 480x300 but the rig's cam0 is 1920x1200"):
        ingest(
            [INDOOR], IngestConfig(rig=REFERENCE_RIG, out=tmp_path / "ds", workers=1, every=10, gt="dense"),
            passes=lambda what, done, total: passes.append(what),
        )  # fmt: skip
    assert passes == []  # before the first pass over the bags (a dense run's trajectory pass takes minutes)
    assert not (tmp_path / "ds").exists()
    summary = ingest([INDOOR], IngestConfig(rig=_rig(INDOOR), out=tmp_path / "ds", workers=1, every=10))
    assert summary.written == summary.planned > 0
    doc = yaml.safe_load((tmp_path / "ds" / "dataset.yaml").read_text())
    assert doc["fisheye_size"] == [300, 480] and len(doc["sources"]) == 1  # rows, columns


def _rewrite(src: Path, dst: Path, keep: object) -> Path:
    """Copy a fixture bag message by message through `keep(topic, index, raw) -> list[raw]`."""
    with open_bags([src]) as bags, BagWriter(dst, "mcap") as out:
        for topic, info in bags.topics().items():
            out.add(topic, info.msgtype)
        seen: dict[str, int] = {}
        for msg in bags.messages():
            k = seen[msg.topic] = seen.get(msg.topic, -1) + 1
            for raw in keep(msg.topic, k, bytes(msg.raw)):  # type: ignore[operator]
                out.write(msg.topic, msg.log_ns, raw)
    return dst


def test_lidar_that_stops_and_duplicated_or_reordered_frames(tmp_path: Path) -> None:
    held: list[bytes] = []

    def keep(topic: str, k: int, raw: bytes) -> list[bytes]:
        if topic.endswith("lidar_192_168_1_13") and k >= 3:
            return []  # the bottom LiDAR dies after 0.3 s
        if topic.startswith("/zed_upper") and k == 4:
            return [raw, raw]  # a duplicated frame
        if topic.startswith("/zed_lower") and k == 6:
            held.append(raw)  # delivered after frame 7: out of order
            return []
        if topic.startswith("/zed_lower") and k == 7:
            return [raw, held.pop()]
        return [raw]

    bag = _rewrite(INDOOR, tmp_path / "broken", keep)
    shutil.copytree(truth_dir(INDOOR), truth_dir(bag))
    out = tmp_path / "ds"
    summary = ingest([bag], IngestConfig(rig=_rig(bag), out=out, workers=1))
    assert summary.frames == 21 and summary.pairs == 21 and summary.written == 21
    early, late = read_meta(out, "000001"), read_meta(out, "000020")
    assert set(early.lidar_skew_ms) == {"lidar_top", "lidar_bottom"}
    assert late.points.total < 0.75 * early.points.total  # only the top LiDAR left
    assert early.points.silent_lidars == [] and late.points.silent_lidars == ["lidar_bottom"]
    silent = sum(read_meta(out, f"{k:06d}").points.silent_lidars == ["lidar_bottom"] for k in range(21))
    thin = sum(read_meta(out, f"{k:06d}").points.thin_lidars == ["lidar_bottom"] for k in range(21))
    assert summary.flagged == {
        "lidar_bottom silent in the window": silent,
        "lidar_bottom thin in the window (< 50% of its rate)": thin,
    }
    assert silent >= 10 and thin == 2  # the two frames whose window the bottom LiDAR's end cuts


def test_an_undecodable_message_names_bag_topic_and_time(tmp_path: Path) -> None:
    """A CustomMsg cut short used to abort with a message naming no bag, topic or time (issue 20, class 4)."""

    def keep(topic: str, k: int, raw: bytes) -> list[bytes]:
        return [raw[: len(raw) // 2]] if topic.endswith("lidar_192_168_1_12") and k == 2 else [raw]

    bag = _rewrite(INDOOR, tmp_path / "cut", keep)
    shutil.copytree(truth_dir(INDOOR), truth_dir(bag))
    with pytest.raises(
        MessageDecodeError, match=rf"{bag}: /livox/lidar_192_168_1_12 at log time \d+\.\d{{9}} s: "
    ):
        ingest([bag], IngestConfig(rig=_rig(bag), out=tmp_path / "ds", workers=1))


def test_a_lidar_with_no_message_at_all_is_an_error(tmp_path: Path) -> None:
    bag = _rewrite(
        INDOOR, tmp_path / "no_bottom", lambda topic, k, raw: [] if topic.endswith("1_13") else [raw]
    )
    shutil.copytree(truth_dir(INDOOR), truth_dir(bag))
    with pytest.raises(
        BagError, match=r"no points on /livox/lidar_192_168_1_13 \(the rig's lidar lidar_bottom\)"
    ):
        ingest([bag], IngestConfig(rig=_rig(bag), out=tmp_path / "ds", workers=1))


def test_nan_points_are_counted_not_fatal(tmp_path: Path) -> None:
    from ingest.bags.livox_msg import decode_custom_msg, encode_custom_msg

    def keep(topic: str, k: int, raw: bytes) -> list[bytes]:
        if "lidar" in topic:
            msg = decode_custom_msg(raw)
            pts = msg.points.copy()
            pts["x"][::50] = np.nan
            return [encode_custom_msg(msg.stamp_ns, msg.frame_id, msg.timebase_ns, pts, msg.lidar_id)]
        return [raw]

    bag = _rewrite(INDOOR, tmp_path / "nan", keep)
    shutil.copytree(truth_dir(INDOOR), truth_dir(bag))
    out = tmp_path / "ds"
    ingest([bag], IngestConfig(rig=_rig(bag), out=out, workers=1, every=10))
    meta = read_meta(out, "000000")
    assert meta.points.non_finite == pytest.approx(meta.points.total / 50, rel=0.05)


def test_disk_full_is_a_clear_error_and_leaves_no_partial_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls = {"n": 0}
    real = Path.replace

    def full_disk(self: Path, target: Path) -> Path:
        calls["n"] += 1
        if calls["n"] > 11:  # dataset.yaml, rig/camchain.yaml, rig/rig.yaml, sample 0's 7 files, 1 more
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, target)

    monkeypatch.setattr(Path, "replace", full_disk)
    out = tmp_path / "ds"
    with pytest.raises(DatasetError, match="No space left on device"):
        ingest([INDOOR], IngestConfig(rig=_rig(INDOOR), out=out, workers=1))
    monkeypatch.undo()
    assert not list(out.rglob("*.tmp"))
    assert len(list((out / "meta").glob("*.json"))) == 1  # the finished sample; the broken one has no meta
    resumed = ingest([INDOOR], IngestConfig(rig=_rig(INDOOR), out=out, workers=1))
    assert (resumed.resumed, resumed.written) == (1, 20)


def test_exr_copies_hold_the_unquantised_values(tmp_path: Path) -> None:
    import OpenEXR

    out = tmp_path / "ds"
    ingest(
        [INDOOR], IngestConfig(rig=_rig(INDOOR), out=out, workers=1, every=20, sample=SampleParams(exr=True))
    )
    depth_png = read_png_u16(out / "depth_fisheye" / "000000.png", DEPTH_SCALE)
    disp_png = read_png_u16(out / "disp_equirect" / "000000.png", DISP_SCALE)
    depth = OpenEXR.File(str(out / "depth_fisheye_exr" / "000000.exr")).channels()["Y"].pixels
    disp = OpenEXR.File(str(out / "disp_equirect_exr" / "000000.exr")).channels()["Y"].pixels
    assert depth.dtype == np.float32 and depth.shape == depth_png.shape
    np.testing.assert_array_equal(depth > 0, depth_png > 0)
    np.testing.assert_allclose(depth, depth_png, atol=0.5e-3 + 1e-6)  # PNG: mm, rounded
    np.testing.assert_allclose(disp, disp_png, atol=0.005 + 1e-6)  # PNG: 1/100 px, rounded
    assert np.abs(depth - depth_png).max() > 0  # the EXR is not the quantised copy
    doc = yaml.safe_load((out / "dataset.yaml").read_text())
    assert doc["crop_offset"] == [0, 0] and doc["equirect_size"] == [
        doc["height_full"],
        2 * doc["height_full"],
    ]
    assert np.allclose(np.array(doc["R_cam0_rect"]) @ np.array(doc["R_cam0_rect"]).T, np.eye(3))


def test_pool_workers_get_their_images_and_points_through_the_shared_slots(
    tmp_path: Path, monkeypatch
) -> None:
    from ingest.runtime.transport import ArraySlots

    used = []
    put = ArraySlots.put

    def counting_put(self, arrays):
        ref = put(self, arrays)
        used.append(ref is not None)
        return ref

    monkeypatch.setattr(ArraySlots, "put", counting_put)
    summary = ingest([INDOOR], IngestConfig(rig=_rig(INDOOR), out=tmp_path / "ds", workers=2, every=10))
    assert summary.written == len(used) > 0 and all(used)


def test_a_dense_block_that_fails_on_a_worker_stops_the_run_with_its_one_line_and_no_partial_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Dense GT's blocks run as tasks on the pool's workers: a block whose fit raises stops the run with that
    error's line, before any sample that needs the block is written, and leaves neither a temporary file
    nor the folder the blocks' values were kept in."""
    from ingest.train.run import block_jobs

    def failing(*args: object) -> None:
        raise DatasetError("block fit failed on purpose")

    monkeypatch.setattr(block_jobs, "world_normals", failing)  # the workers fork after this
    out = tmp_path / "ds"
    with pytest.raises(DatasetError, match=r"^block fit failed on purpose$"):
        ingest([INDOOR], IngestConfig(rig=_rig(INDOOR), out=out, workers=2, every=10, gt="dense"))
    assert not [p for p in out.rglob("*") if p.name.startswith(".")]  # no temporary, no .kept folder
    assert not list((out / "meta").glob("*.json"))  # every sample needs the first block


@pytest.mark.parametrize(("cores", "helper"), [(2, False), (8, True)])
def test_workers_use_a_helper_thread_only_when_a_core_is_free(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, cores: int, helper: bool
) -> None:
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(cores)))
    summary = ingest([INDOOR], IngestConfig(rig=_rig(INDOOR), out=tmp_path / "ds", workers=2, every=20))
    assert summary.written >= 2
    assert bool(summary.overlapped_ms) is helper and "images" in summary.stage_ms
    assert "overlap_images" not in yaml.safe_load((tmp_path / "ds" / "dataset.yaml").read_text())["params"]


def test_dataset_yaml_names_the_rig_by_an_absolute_path(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A rig given relative to the working folder is recorded so that it resolves from anywhere."""
    monkeypatch.chdir(_rig(INDOOR).parent.parent)
    relative = Path(_rig(INDOOR).parent.name) / "rig.yaml"
    ingest([INDOOR], IngestConfig(rig=relative, out=tmp_path / "ds", workers=1, every=10))
    doc = yaml.safe_load((tmp_path / "ds" / "dataset.yaml").read_text())
    assert doc["rig"]["source"] == str(_rig(INDOOR).resolve())


def test_passes_report_every_message_and_sweep_they_read(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The passes before the first sample (minutes on a long recording) report their progress: the
    first over every message of the rig's topics, the trajectory pass over every LiDAR sweep; the
    counts are rosbags' own. (A call every 4 messages here: the fixture is short.)"""
    from rosbags.highlevel import AnyReader

    from calibration.rig import read_rig
    from ingest.bags import reader as bag_reader
    from ingest.train.run.pipeline import PASS_READ, PASS_TRAJECTORY

    every = 4
    monkeypatch.setattr(bag_reader, "PROGRESS_EVERY", every)

    rig = read_rig(_rig(INDOOR))
    with AnyReader([INDOOR]) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
    cameras = [t if t in counts else f"{t}/compressed" for t in (rig.upper.topic, rig.lower.topic)]
    lidars = [li.topic for li in rig.lidars]
    n_lidar = sum(counts[t] for t in lidars)
    n_read = n_lidar + sum(counts[t] for t in cameras) + counts[rig.imus[0].topic]
    calls: list[tuple[str, int, int]] = []
    cfg = IngestConfig(rig=_rig(INDOOR), out=tmp_path / "out", workers=1, every=10, gt="dense")
    summary = ingest([INDOOR], cfg, passes=lambda what, done, total: calls.append((what, done, total)))
    assert summary.written > 0 and summary.method == "dense"
    stages = [what for what, _, _ in calls]
    assert stages == sorted(stages, key=[PASS_READ, PASS_TRAJECTORY].index)  # one pass, then the other
    for what, n in ((PASS_READ, n_read), (PASS_TRAJECTORY, n_lidar)):
        done = [(d, t) for w, d, t in calls if w == what]
        assert done[-1] == (n, n), what
        assert [d for d, _ in done[:-1]] == list(range(every, n, every))
        assert all(t == n for _, t in done)


def test_a_camera_that_maps_no_pixel_to_a_ray_is_one_line(monkeypatch: pytest.MonkeyPatch) -> None:
    """GT density is GT pixels over the pixels with a ray: a model with none would divide by zero."""
    from calibration.errors import CalibrationError
    from calibration.rig import REFERENCE_RIG, read_rig
    from ingest.raster.view import pixel_rays
    from ingest.train.run.sample_job import Geometry

    rig = read_rig(REFERENCE_RIG)
    rays, valid = pixel_rays(rig.upper.model)
    monkeypatch.setattr("ingest.train.run.sample_job.pixel_rays", lambda model: (rays, np.zeros_like(valid)))
    with pytest.raises(CalibrationError, match=r"camera cam0 maps none of its 1920x1200 pixels to a ray"):
        Geometry.from_rig(rig)


QOS = (
    "- history: 3\n  depth: 0\n  reliability: 1\n  durability: 2\n  deadline:\n    sec: 9223372036\n"
    "    nsec: 854775807\n  lifespan:\n    sec: 9223372036\n    nsec: 854775807\n  liveliness: 1\n"
    "  liveliness_lease_duration:\n    sec: 9223372036\n    nsec: 854775807\n  avoid_ros_namespace_conventions: false"
)


def test_a_db3_whose_topic_serialization_differs_from_its_metadata_is_said_so(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Sweep 5: a .db3 whose topics table says 'json' for a camera where metadata.yaml says 'cdr' was
    warned about as "other QoS profiles"."""
    import logging
    import sqlite3

    from tests.paths import FIXTURES_DIR

    folder = tmp_path / "db3"
    shutil.copytree(FIXTURES_DIR / "indoor_walk_db3", folder)
    with sqlite3.connect(folder / "indoor_walk_db3.db3") as db:
        topic = db.execute("SELECT name FROM topics WHERE name LIKE '/zed_upper%'").fetchone()[0]
        db.execute("UPDATE topics SET serialization_format = 'json' WHERE name = ?", (topic,))
    with caplog.at_level(logging.WARNING), open_bags([folder]) as bags:
        assert sum(1 for m in bags.messages() if m.topic == topic) > 0
    assert [r.getMessage() for r in caplog.records if "describes" in r.getMessage()] == [
        f"{folder}: metadata.yaml describes {topic} (serialization format 'cdr', the file's 'json') otherwise "
        "than the storage file; their messages are read all the same"
    ]


def test_a_folder_whose_metadata_qos_differs_from_its_file_loses_no_message(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """rosbags pairs a rosbag2 folder's metadata topics with its file's channels by QoS too: a QoS that
    differs (rosbag2's own mcap/talker and sqlite3/talker test bags) read the topic as 0 messages, without
    a word, in inspect and ingest. Here the upper camera's 21 frames: now read, with one warning."""
    import logging

    folder = tmp_path / "qos"
    shutil.copytree(INDOOR, folder)
    meta = folder / "metadata.yaml"
    meta.write_text(
        meta.read_text().replace("offered_qos_profiles: ''", f"offered_qos_profiles: {json.dumps(QOS)}", 1)
    )
    with caplog.at_level(logging.WARNING), open_bags([folder]) as bags:
        read = sum(1 for _ in bags.messages())
    with open_bags([folder / "indoor_static_mcap.mcap"]) as bags:
        assert read == sum(1 for _ in bags.messages()) == 336
    warning = [r.getMessage() for r in caplog.records if "QoS" in r.getMessage()]
    assert warning == [
        f"{folder}: metadata.yaml describes /zed_upper/zed_node/rgb/color/rect/image/compressed (QoS "
        "profiles) otherwise than the storage file; their messages are read all the same"
    ]
    summary = ingest([folder], IngestConfig(rig=_rig(INDOOR), out=tmp_path / "ds", workers=1, every=7))
    clean = ingest([INDOOR], IngestConfig(rig=_rig(INDOOR), out=tmp_path / "clean", workers=1, every=7))
    assert summary.written == clean.written > 0
