"""Issue 49: a dataset knows its frames by their content, and a rerun checks what it calls done.

A frame is written once whatever the bags are named or however they are
split and combined over runs; a finished sample whose files were damaged
is written again (and said so), never kept as done.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from ingest.bags.decode import decode_compressed_image
from ingest.bags.reader import open_bags
from ingest.dataset.meta import read_meta
from ingest.errors import DatasetError
from ingest.train.run.pipeline import ingest
from ingest.train.run.settings import IngestConfig
from sensorbox.live.bagwriter import BagWriter
from sensorbox.messages import image_msg
from sensorbox.sim.truth import truth_dir
from tests.faults.bags import INDOOR, UPPER, rewrite
from tests.faults.cli import sensorbox

RIG = truth_dir(INDOOR) / "rig.yaml"


def _cfg(out: Path, every: int = 1) -> IngestConfig:
    return IngestConfig(rig=RIG, out=out, workers=1, every=every, height_full=64)


def _stamps(out: Path) -> list[int]:
    """The upper stamps of every sample in `out`, one per sample (duplicates kept)."""
    return sorted(read_meta(out, p.stem).stamp_ns for p in (out / "meta").glob("*.json"))


def _split(tmp: Path, overlap_s: float) -> tuple[Path, Path]:
    """The fixture cut at the middle of its log time into two mcap bags that share +-`overlap_s`."""
    with open_bags([INDOOR]) as bags:
        messages = [(m.topic, m.msgtype, m.log_ns, bytes(m.raw)) for m in bags.messages()]
    mid = (messages[0][2] + messages[-1][2]) // 2
    halves = []
    for name, keep in (
        ("first", lambda t: t < mid + overlap_s * 1e9),
        ("second", lambda t: t >= mid - overlap_s * 1e9),
    ):
        with BagWriter(tmp / name, "mcap") as out:
            for topic, msgtype in {m[0]: m[1] for m in messages}.items():
                out.add(topic, msgtype)
            for topic, _, log_ns, raw in messages:
                if keep(log_ns):
                    out.write(topic, log_ns, raw)
        halves.append(tmp / name)
    return halves[0], halves[1]


def test_the_same_recording_under_another_name_is_not_written_twice(tmp_path: Path) -> None:
    """The rosbag2 folder, then its .mcap file: 21 frames, 21 samples (it was 42)."""
    out = tmp_path / "ds"
    first = ingest([INDOOR], _cfg(out))
    again = ingest([INDOOR / f"{INDOOR.name}.mcap"], _cfg(out))
    assert len(_stamps(out)) == len(set(_stamps(out))) == 21
    assert (first.written, again.written, again.resumed, again.held_elsewhere) == (21, 0, 21, 21)


def test_bags_ingested_apart_then_together_or_overlapping_hold_each_frame_once(tmp_path: Path) -> None:
    """Bag A, bag B (sharing 0.15 s of frames with A), then both together: every frame once (it was 2x)."""
    a, b = _split(tmp_path, 0.15)
    out = tmp_path / "ds"
    ingest([a], _cfg(out))
    after_a = set(_stamps(out))
    second = ingest([b], _cfg(out))
    assert second.held_elsewhere > 0  # the overlap, written by A's run
    assert len(_stamps(out)) == len(set(_stamps(out)))  # (it wrote the overlap's frames twice)
    both = ingest([a, b], _cfg(out))
    assert both.written + both.resumed + sum(both.skipped.values()) == both.planned
    stamps = _stamps(out)
    assert len(stamps) == len(set(stamps))  # no frame twice
    assert after_a < set(stamps)
    whole = tmp_path / "whole"
    ingest([INDOOR], _cfg(whole))
    assert set(stamps) <= set(_stamps(whole)) | after_a


def _as_raw(tmp: Path, name: str, brighter: int) -> Path:
    """The fixture with its upper images as raw bgra8 `Image`s, `brighter` added to every pixel."""

    def keep(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        if topic != UPPER + "/compressed":
            return [(topic, raw)]
        frame = decode_compressed_image(raw)
        image = np.ascontiguousarray(frame.image.astype(np.int16) + brighter).clip(0, 255).astype(np.uint8)
        return [(UPPER, image_msg(frame.stamp_ns, frame.frame_id, image))]

    return rewrite(tmp / name, keep)[0]


def test_a_frame_with_the_stamps_of_another_but_other_images_is_written(tmp_path: Path) -> None:
    """Stamps alone do not identify a frame: simulated recordings share them, with other images."""
    out = tmp_path / "ds"
    first = ingest([_as_raw(tmp_path, "plain", 0)], _cfg(out, every=10))
    other = ingest([_as_raw(tmp_path, "brighter", 9)], _cfg(out, every=10))
    assert (other.written, other.held_elsewhere) == (first.written, 0)
    stamps = _stamps(out)
    assert len(stamps) == 2 * len(set(stamps)) == 2 * first.written
    again = ingest([_as_raw(tmp_path, "plain_again", 0)], _cfg(out, every=10))
    assert (again.written, again.held_elsewhere) == (0, first.written)


def test_frame_digest_covers_shape_and_every_pixel() -> None:
    from ingest.dataset.identity import frame_digest

    up, lo = np.zeros((4, 6, 3), np.uint8), np.zeros((4, 6, 3), np.uint8)
    base = frame_digest(up, lo)
    changed = lo.copy()
    changed[3, 5, 2] = 1
    assert frame_digest(up, changed) != base
    assert frame_digest(up.reshape(6, 4, 3), lo) != base
    assert frame_digest(up, lo) == base


def _row(table: str, item: str) -> str:
    """The value of the summary table's row `item`."""
    line = next(line for line in table.splitlines() if f"│ {item} " in line)
    return line.split("│")[2].strip()


def test_a_damaged_finished_sample_is_written_again_and_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A deleted, cut, overwritten image or an invalid meta JSON: written again, one line each (was '0 / 5')."""
    out = tmp_path / "ds"
    args = ["ingest", str(INDOOR), "--rig", str(RIG), "--out", str(out), "--workers", "1", "--every", "5"]
    args += ["--height-full", "64", "--gt", "sparse", "--no-preview"]
    assert sensorbox(capsys, *args)[0] == 0
    kept = {p.relative_to(out): p.read_bytes() for p in out.rglob("*.png")}
    (out / "left_fisheye" / "000000.png").unlink()
    cut = out / "depth_fisheye" / "000001.png"
    cut.write_bytes(cut.read_bytes()[:100])
    over = out / "equirect_up" / "000002.png"
    data = bytearray(over.read_bytes())
    data[len(data) // 2] ^= 0xFF  # overwritten in place: the same size, other content
    over.write_bytes(bytes(data))
    (out / "meta" / "000003.json").write_text("{not json")
    code, stdout, err = sensorbox(capsys, *args)
    assert code == 0
    assert _row(stdout, "written / already done (resumed)") == "4 / 1"
    assert _row(stdout, "finished samples found damaged, written again") == "4"
    size = len(kept[Path("depth_fisheye/000001.png")])
    assert [line for line in err if "damaged" in line] == [
        f"warning: damaged sample written again: {out}/left_fisheye/000000.png: missing",
        f"warning: damaged sample written again: {out}/depth_fisheye/000001.png: 100 bytes, {size} were written",
        f"warning: damaged sample written again: {out}/equirect_up/000002.png: not the file written "
        "(its SHA-256 differs)",
        f"warning: damaged sample written again: {out}/meta/000003.json: not SensorBox sample metadata "
        "(JSONDecodeError: Expecting property name enclosed in double quotes: line 1 column 2 (char 1))",
    ]
    assert {p.relative_to(out): p.read_bytes() for p in out.rglob("*.png")} == kept  # the damage is gone
    assert json.loads((out / "meta" / "000003.json").read_text())["id"] == "000003"
    code, stdout, err = sensorbox(capsys, *args)
    assert (code, [line for line in err if "damaged" in line]) == (0, [])
    assert _row(stdout, "written / already done (resumed)") == "0 / 5"


@pytest.mark.parametrize("kind", ["link to /dev/zero", "fifo"])
def test_a_sample_file_that_is_a_device_or_fifo_is_refused_not_read(
    kind: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A sample's file a symlink to /dev/zero was read until memory ran out (MemoryError traceback); a
    FIFO would wait forever: one line naming it, exit 2, the node left as it is."""
    out = tmp_path / "ds"
    args = ["ingest", str(INDOOR), "--rig", str(RIG), "--out", str(out), "--workers", "1", "--every", "5"]
    args += ["--height-full", "64", "--gt", "sparse", "--no-preview"]
    assert sensorbox(capsys, *args)[0] == 0
    odd = out / "depth_fisheye" / "000001.png"
    odd.unlink()
    if kind == "fifo":
        os.mkfifo(odd)
        what = "a FIFO (named pipe)"
    else:
        odd.symlink_to("/dev/zero")
        what = "a character device"
    code, _, err = sensorbox(capsys, *args)
    assert (code, err) == (
        2,
        [f"error: {odd}: is {what}, not a file of the dataset; remove it, or give another --out"],
    )
    assert odd.is_symlink() == (kind != "fifo") and not odd.is_file()


def test_a_finished_sample_whose_meta_records_no_files_is_written_again(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Meta without `files` was taken as done when its PNGs decoded: a zeroed depth PNG stayed ('0 / 5')."""
    out = tmp_path / "ds"
    args = ["ingest", str(INDOOR), "--rig", str(RIG), "--out", str(out), "--workers", "1", "--every", "5"]
    args += ["--height-full", "64", "--gt", "sparse", "--no-preview"]
    assert sensorbox(capsys, *args)[0] == 0
    depth = out / "depth_fisheye" / "000001.png"
    kept = depth.read_bytes()
    image = cv2.imread(str(depth), cv2.IMREAD_UNCHANGED)
    assert image is not None and image.dtype == np.uint16
    assert cv2.imwrite(str(depth), np.zeros_like(image))
    meta_path = out / "meta" / "000001.json"
    meta = json.loads(meta_path.read_text())
    del meta["files"]
    meta_path.write_text(json.dumps(meta))
    code, stdout, err = sensorbox(capsys, *args)
    assert code == 0
    assert _row(stdout, "written / already done (resumed)") == "1 / 4"
    assert [line for line in err if "damaged" in line] == [
        f"warning: damaged sample written again: {meta_path}: records no files (size and SHA-256) "
        "to check the sample by"
    ]
    assert depth.read_bytes() == kept
    assert "files" in json.loads(meta_path.read_text())


def test_a_lost_dataset_yaml_is_not_rewritten_to_describe_samples_made_otherwise(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """dataset.yaml deleted, a rerun with --window-ms 20 over samples made with 50 ms: refused, naming the
    setting and both values (it wrote a dataset.yaml claiming 20 ms)."""
    out = tmp_path / "ds"
    args = ["ingest", str(INDOOR), "--rig", str(RIG), "--out", str(out), "--workers", "1", "--every", "5"]
    args += ["--height-full", "64", "--gt", "sparse", "--no-preview"]
    assert sensorbox(capsys, *args)[0] == 0
    check = yaml.safe_load((out / "dataset.yaml").read_text())["sources"][0]["calibration_check"]
    (out / "dataset.yaml").unlink()
    code, _, err = sensorbox(capsys, *args, "--window-ms", "20")
    assert (code, err) == (
        2,
        [
            f"error: {out}/meta/000000.json: the folder's samples were made with a different 'params' "
            f"(lidar_window_ns: 50000000 -> 20000000) and {out}/dataset.yaml is missing; choose a new --out "
            "or the settings they were made with"
        ],
    )
    assert not (out / "dataset.yaml").exists()
    code, stdout, _ = sensorbox(capsys, *args)  # the settings they were made with: described again
    assert code == 0 and _row(stdout, "written / already done (resumed)") == "0 / 5"
    assert len(list((out / "meta").glob("*.json"))) == 5
    doc = yaml.safe_load((out / "dataset.yaml").read_text())
    assert doc["params"]["lidar_window_ns"] == 50_000_000
    # the recording keeps the ids its samples were written under (sweep 5: it was given 5..9, which hold
    # no files, and a second recording 10..14)
    assert [(s["first_id"], s["samples"]) for s in doc["sources"]] == [(0, 5)]
    # the calibration check covers the samples resumed, not only those this run wrote (none: it was gone)
    assert doc["sources"][0]["calibration_check"] == check and check["samples"] == 5
    assert sorted(p.stem for p in (out / "meta").glob("*.json")) == [f"{i:06d}" for i in range(5)]


def test_a_sample_id_holding_another_frame_is_never_overwritten(tmp_path: Path) -> None:
    """dataset.yaml's ranges that do not describe the folder: refused, the other frame's files kept."""
    out = tmp_path / "ds"
    ingest([INDOOR], _cfg(out, every=5))
    meta = out / "meta" / "000001.json"
    doc = json.loads(meta.read_text())
    doc["stamp_ns"] += 1
    meta.write_text(json.dumps(doc))
    with pytest.raises(
        DatasetError, match=r"000001.json: sample 000001 is the frame at 1700000000\.\d{9} s, but "
    ):
        ingest([INDOOR], _cfg(out, every=5))
    assert json.loads(meta.read_text()) == doc


def test_a_damaged_frame_found_under_another_name_is_written_again_under_its_id(tmp_path: Path) -> None:
    """The frame is the folder's sample 000003, whose image was cut: the run under another name writes it
    again there, not a second copy under a new id."""
    out = tmp_path / "ds"
    ingest([INDOOR], _cfg(out, every=5))
    cut = out / "right_fisheye" / "000003.png"
    whole = cut.read_bytes()
    cut.write_bytes(whole[:10])
    again = ingest([INDOOR / f"{INDOOR.name}.mcap"], _cfg(out, every=5))
    assert (again.written, again.held_elsewhere) == (1, 4)
    assert again.damaged == [f"{cut}: 10 bytes, {len(whole)} were written"]
    assert sorted(p.stem for p in (out / "meta").glob("*.json")) == [f"00000{k}" for k in range(5)]
    assert cut.read_bytes() == whole


@pytest.mark.parametrize(
    ("doc", "found"),
    [
        (
            "format: widedepth-benchmark\nsensorbox_version: 0.1.0\n",
            "format 'widedepth-benchmark' (SensorBox 0.1.0)",
        ),
        ("name: another tool's dataset\nsplits: [train, val]\n", "no 'format'"),
    ],
)
def test_a_dataset_yaml_of_another_format_is_refused_not_overwritten(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], doc: str, found: str
) -> None:
    """With no sample beside it, ingest replaced another format's dataset.yaml with its own, silently."""
    out = tmp_path / "ds"
    out.mkdir()
    (out / "dataset.yaml").write_text(doc)
    args = ["ingest", str(INDOOR), "--rig", str(RIG), "--out", str(out), "--workers", "1", "--every", "5"]
    code, stdout, err = sensorbox(capsys, *args, "--height-full", "64", "--gt", "sparse", "--no-preview")
    assert (code, stdout, err) == (
        2,
        "",
        [
            f"error: {out}/dataset.yaml: {found}, expected format 'widedepth-train' (a SensorBox training "
            "set); ingest would overwrite it: choose another --out"
        ],
    )
    assert [p.name for p in out.iterdir()] == ["dataset.yaml"] and (out / "dataset.yaml").read_text() == doc


def test_stats_says_which_finished_samples_have_no_depth_map(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A training set whose depth_fisheye/000001.png is gone: stats described the other samples as the
    whole dataset without a word ('4 depth maps', exit 0); it still does, and one warning names it."""
    out = tmp_path / "ds"
    args = ["ingest", str(INDOOR), "--rig", str(RIG), "--out", str(out), "--workers", "1", "--every", "5"]
    assert sensorbox(capsys, *args, "--height-full", "64", "--gt", "sparse", "--no-preview")[0] == 0
    held = len(list((out / "meta").glob("*.json")))
    (out / "depth_fisheye" / "000001.png").unlink()
    code, stdout, err = sensorbox(capsys, "stats", str(out), "--out", str(tmp_path / "stats"))
    assert code == 0
    assert f"{held - 1} depth maps" in stdout
    assert err == [
        f"warning: {out}: 1 finished sample(s) (meta/<id>.json) have no depth map (depth_fisheye/<id>.png), "
        "left out of these statistics: 000001"
    ]
    doc = json.loads(next((tmp_path / "stats").glob("*.json")).read_text())
    assert doc["missing_gt"] == ["000001"]


def test_a_dataset_folder_linked_to_another_is_refused_not_rewritten(tmp_path: Path) -> None:
    """Sweep 3: with left_fisheye a link to right_fisheye, a rerun found the 5 left images damaged, wrote
    them again (each right image then over it) and exited 0 with every left image a right one."""
    out = tmp_path / "ds"
    ingest([INDOOR], _cfg(out, every=7))
    right = {p.name: p.read_bytes() for p in sorted((out / "right_fisheye").glob("*.png"))}
    for p in (out / "left_fisheye").iterdir():
        p.unlink()
    (out / "left_fisheye").rmdir()
    (out / "left_fisheye").symlink_to("right_fisheye")
    with pytest.raises(DatasetError) as err:
        ingest([INDOOR], _cfg(out, every=7))
    assert str(err.value) == (
        f"{out}: left_fisheye and right_fisheye are one folder (left_fisheye is a link to right_fisheye); "
        "each of a dataset's folders must be its own"
    )
    assert {p.name: p.read_bytes() for p in sorted((out / "right_fisheye").glob("*.png"))} == right


def test_a_dataset_without_its_rig_copy_is_not_resumed_with_another_rig(tmp_path: Path) -> None:
    """Sweep 3: after rig/ was deleted, a rerun with the top LiDAR moved 1 mm said '0 written / 5 already
    done', exit 0, and wrote rig/ and dataset.yaml describing a rig the 5 samples were not made with."""
    out = tmp_path / "ds"
    ingest([INDOOR], _cfg(out, every=7))
    yaml_before = (out / "dataset.yaml").read_bytes()
    for p in (out / "rig").iterdir():
        p.unlink()
    (out / "rig").rmdir()
    moved = tmp_path / "rig" / "rig.yaml"
    moved.parent.mkdir()
    (moved.parent / "camchain.yaml").write_bytes((RIG.parent / "camchain.yaml").read_bytes())
    text = RIG.read_text()
    assert "0.0043]" in text
    moved.write_text(text.replace("0.0043]", "0.0053]", 1))
    with pytest.raises(DatasetError) as err:
        ingest([INDOOR], IngestConfig(rig=moved, out=out, workers=1, every=7, height_full=64))
    assert str(err.value) == (
        f"{out / 'rig' / 'rig.yaml'}: missing, so the rig the dataset's samples were made with cannot be "
        "compared with this run's; put the dataset's rig/ back or choose a new --out"
    )
    assert (out / "dataset.yaml").read_bytes() == yaml_before
    assert not (out / "rig").exists()


def test_a_sample_copied_under_another_id_is_named(tmp_path: Path) -> None:
    """Sweep 9: a finished dataset with sample 000004's files copied as 000005 (its meta's id changed): a
    rerun said 'written 0 / already done 5', exit 0, and the folder kept the frame twice."""
    out = tmp_path / "ds"
    ingest([INDOOR], _cfg(out, every=7))
    done = sorted(p.stem for p in (out / "meta").glob("*.json"))
    last, extra = done[-1], f"{int(done[-1]) + 1:06d}"
    for folder in out.iterdir():
        for f in folder.glob(f"{last}.*") if folder.is_dir() else ():
            (folder / f"{extra}{f.suffix}").write_bytes(f.read_bytes())
    meta = json.loads((out / "meta" / f"{extra}.json").read_text())
    meta["id"] = extra
    (out / "meta" / f"{extra}.json").write_text(json.dumps(meta))
    yaml_before = (out / "dataset.yaml").read_bytes()
    with pytest.raises(DatasetError) as err:
        ingest([INDOOR], _cfg(out, every=7))
    stamp = meta["stamp_ns"]
    assert str(err.value) == (
        f"{out / 'meta' / f'{extra}.json'}: sample {extra} holds the same frames as sample {last} (the frame "
        f"at {stamp // 10**9}.{stamp % 10**9:09d} s, frames_sha256 {meta['frames_sha256'][:12]}...): the "
        f"frame twice in the dataset, a sample copied within it; delete sample {extra}'s files or choose a "
        "new --out"
    )
    assert (out / "dataset.yaml").read_bytes() == yaml_before


def test_a_fifo_as_the_datasets_camchain_is_named_not_read(tmp_path: Path) -> None:
    """A FIFO in place of the dataset's rig/camchain.yaml: a rerun would block reading it to compare the
    rig; it is one line naming the file, and nothing is written."""
    out = tmp_path / "ds"
    ingest([INDOOR], _cfg(out, every=7))
    yaml_before = (out / "dataset.yaml").read_bytes()
    (out / "rig" / "camchain.yaml").unlink()
    os.mkfifo(out / "rig" / "camchain.yaml")
    with pytest.raises(DatasetError) as err:
        ingest([INDOOR], _cfg(out, every=7))
    assert (
        str(err.value) == f"{out / 'rig' / 'camchain.yaml'}: is a FIFO (named pipe), not a dataset rig file"
    )
    assert (out / "dataset.yaml").read_bytes() == yaml_before


def test_a_benchmark_folder_is_not_ingested_into(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Sweep 3: ingest --out a render-benchmark folder wrote 5 samples beside its scene, exit 0; stats then
    described the folder as a 'train layout' of 5 depth maps, the benchmark's views out of sight."""
    out = tmp_path / "bench"
    (out / "000_000_000" / "120FOV").mkdir(parents=True)
    (out / "000_000_000" / "scene.yaml").write_text("scene: 000_000_000\n")
    code, _, err = sensorbox(
        capsys, "ingest", str(INDOOR), "--rig", str(RIG), "--out", str(out), "--workers", "1"
    )
    assert (code, err) == (
        2,
        [
            f"error: {out}: holds a benchmark (000_000_000/scene.yaml: the render-benchmark layout); "
            "ingest would mix a training set into it: choose another --out"
        ],
    )
    assert sorted(p.name for p in out.iterdir()) == ["000_000_000"]


WALK = INDOOR.parent / "outdoor_walk_mcap"


@pytest.mark.parametrize("command", ["inspect", "ingest"])
def test_two_recordings_given_together_are_refused_naming_both(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str
) -> None:
    """Sweep 6 S6/U3: two recordings over the same 0.7 s of stamps on the same topics, given together,
    were read as one: `inspect` suggested IMU rates of 4385.7 and 543.9 Hz (both run at 200), ingest
    interleaved them. One line names both bags, their spans and a shared topic."""
    extra = ["--rig", str(RIG), "--out", str(tmp_path / "ds")] if command == "ingest" else []
    code, _, err = sensorbox(capsys, command, str(INDOOR), str(WALK), *extra)
    assert (code, err) == (2, [
        f"error: {INDOOR} and {WALK} overlap in time (1700000000.001-1700000000.702 s and "
        "1700000000.001-1700000000.800 s) on 4 topics such as /livox/imu_192_168_1_12 with other messages: two "
        "recordings, not the files of one (a split recording's files follow each other); give them in two calls"
    ])  # fmt: skip
    assert not (tmp_path / "ds").exists()


def test_recorders_of_other_topics_at_the_same_time_are_one_recording(tmp_path: Path) -> None:
    """Bags recorded side by side, one with the cameras and one with the LiDARs and IMUs, overlap in time
    but share no topic: read together, they are the recording whole."""
    with open_bags([INDOOR]) as whole:
        every = {t: s.msgtype for t, s in whole.topics().items()}  # each file declares every channel
    cameras, _ = rewrite(
        tmp_path / "cameras.mcap", lambda t, k, raw: [(t, raw)] if "zed" in t else [], declare=every
    )
    livox, _ = rewrite(
        tmp_path / "livox.mcap", lambda t, k, raw: [] if "zed" in t else [(t, raw)], declare=every
    )
    with open_bags([cameras, livox]) as both, open_bags([INDOOR]) as whole:
        assert both.topics() == whole.topics()
        assert sorted((m.topic, m.log_ns) for m in both.messages()) == sorted(
            (m.topic, m.log_ns) for m in whole.messages()
        )


def test_a_sample_of_other_settings_copied_in_is_refused_naming_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Sweep 11: sample 000001's files and meta replaced by the same frame's sample of a --window-ms 20 run
    (its meta records 20 ms): the rerun took it as done ("0 / 5") in a dataset whose dataset.yaml says
    50 ms. Every sample's recorded settings are compared with the run's, dataset.yaml present or not."""
    out, other = tmp_path / "ds", tmp_path / "other"
    args = ["ingest", str(INDOOR), "--rig", str(RIG), "--workers", "1", "--every", "5", "--height-full", "64"]
    args += ["--gt", "sparse", "--no-preview"]
    assert sensorbox(capsys, *args, "--out", str(out))[0] == 0
    assert sensorbox(capsys, *args, "--out", str(other), "--window-ms", "20")[0] == 0
    copied = [p for p in other.rglob("000001.*") if p.is_file()]
    assert len(copied) >= 5
    for p in copied:
        (out / p.relative_to(other)).write_bytes(p.read_bytes())
    code, _, err = sensorbox(capsys, *args, "--out", str(out))
    assert (code, err) == (
        2,
        [
            f"error: {out}/meta/000001.json: this sample was made with a different 'params' (lidar_window_ns: "
            f"20000000 -> 50000000) than {out}/dataset.yaml describes and this run asks (a sample copied in "
            "from another dataset?); delete its files (the run writes it again) or choose a new --out"
        ],
    )
    for p in copied:
        (out / p.relative_to(other)).unlink()
    code, stdout, _ = sensorbox(capsys, *args, "--out", str(out))
    assert code == 0 and _row(stdout, "written / already done (resumed)") == "1 / 4"
