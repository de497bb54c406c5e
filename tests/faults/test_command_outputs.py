"""Every command's outputs under faults, as a user meets them: one line, and what is left behind.

Bags on a full disk (simulate), output paths that are files, sets of files
written whole or not at all (bench, stats), capture's options checked before
anything is written, --image-type where it has no meaning, damaged GT PNGs.

Full disks are injected as in test_output_errors (`_fill_disk_at`: half the
bytes land, then ENOSPC); sqlite3's "database or disk is full" by the
writer's own exception. Nothing here needs root.
"""

from __future__ import annotations

import errno
import json
import os
import sqlite3
from pathlib import Path

import cv2
import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2.storage_sqlite3 import Sqlite3Writer

from ingest.errors import OutputError
from tests.faults.bags import INDOOR
from tests.faults.cli import sensorbox
from tests.faults.test_output_errors import ENOSPC, RIG, _files, _fill_disk_at
from tests.ingest.test_evaluate import make_benchmark, write_predictions

SIM = ["--duration", "0.2", "--scale", "0.1"]


@pytest.mark.parametrize(
    ("fmt", "where"), [("mcap", "open"), ("bag", "open"), ("db3", "write"), ("bag", "write")]
)
def test_a_full_disk_while_simulating_names_the_bag_and_leaves_nothing(
    fmt: str, where: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """db3 was a sqlite3 traceback, bag `error: No space left on device` without a path."""
    why = ENOSPC
    if where == "open":
        _fill_disk_at(monkeypatch, ".partial")  # the hidden bag: its header does not fit
        doing, lost = "create", ""
    else:
        doing, lost = "write", "; no bag written"
        if fmt == "db3":
            why = "database or disk is full"

            def full(*args: object) -> None:
                raise sqlite3.OperationalError(why)

            monkeypatch.setattr(Sqlite3Writer, "write", full)
        else:

            def nospace(*args: object) -> None:
                raise OSError(errno.ENOSPC, ENOSPC)

            monkeypatch.setattr(Writer1, "write", nospace)
    out = tmp_path / ("a.bag" if fmt == "bag" else "a")
    code, _, err = sensorbox(capsys, "simulate", "--out", str(out), *SIM, "--format", fmt)
    assert (code, err) == (3, [f"error: {out}: cannot {doing} the bag: {why}{lost}"])
    assert list(tmp_path.iterdir()) == []  # no bag, no hidden partial bag, no truth


@pytest.mark.parametrize("fails", ["scene.ply", "sim.yaml"])
def test_a_full_disk_while_writing_the_truth_leaves_neither_bag_nor_truth(
    fails: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The truth folder is written after the bag; a bag whose truth did not fit is not a fixture, so
    neither stays (and no staging folder), and a stale truth of an earlier bag is replaced only whole."""
    out = tmp_path / "a"
    _fill_disk_at(monkeypatch, fails)
    code, _, err = sensorbox(capsys, "simulate", "--out", str(out), *SIM)
    truth = tmp_path / "a.truth"
    assert (code, err) == (3, [f"error: cannot write {truth}: {ENOSPC}; no bag written"])
    assert list(tmp_path.iterdir()) == []
    monkeypatch.undo()
    code, _, err = sensorbox(capsys, "simulate", "--out", str(out), *SIM)
    assert (code, err) == (0, [])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "a.truth"]
    assert (truth / "sim.yaml").is_file() and (truth / "scene.ply").is_file()


def test_a_refused_simulation_prints_no_blank_line_before_its_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """rich's Progress left an empty line on stderr when it is not a terminal."""
    code, _, err = sensorbox(capsys, "simulate", "--out", str(tmp_path / "x"), "--duration", "0")
    assert code == 2 and len(err) == 1 and err[0].startswith("error: "), err


def test_a_simulation_prints_nothing_on_stderr(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = sensorbox(capsys, "simulate", "--out", str(tmp_path / "x"), *SIM)
    assert (code, err) == (0, []) and "Truth" in out


def _afile(tmp: Path) -> Path:
    f = tmp / "afile"
    f.write_text("mine\n")
    return f


def test_output_paths_that_are_files_are_refused_before_the_work(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Each used to fail after the work (`File exists`, `Not a directory`) or blame the wrong thing."""
    f = _afile(tmp_path)
    bench = make_benchmark(tmp_path / "bench")
    pred = tmp_path / "pred"
    write_predictions(bench, pred, "stereo")
    eval_args = ["eval", "--dataset", str(bench), "--pred", str(pred), "--task", "stereo"]
    cases = [
        (
            ["bench", "--bag", str(tmp_path / "none"), "--only", "default", "--out", str(f)],
            f"error: --out {f}: is a file; give a folder for the CSVs and charts",
        ),
        (
            ["bench", "--dense", "--out", str(f)],
            f"error: --out {f}: is a file; give a folder for dense.png",
        ),
        (
            ["render-benchmark", str(tmp_path / "scans"), "--rig", str(RIG), "--out", str(f)],
            f"error: --out {f}: is a file; give a folder for the benchmark layout",
        ),
        (
            ["calib", "check", str(RIG), "--plot", str(f / "p.png")],
            f"error: --plot {f / 'p.png'}: {f} is a file, not a folder",
        ),
        (
            [*eval_args, "--json", str(f / "x.json")],
            f"error: --json {f / 'x.json'}: {f} is a file, not a folder",
        ),
        (
            [*eval_args, "--heatmap", str(f / "h.png")],
            f"error: --heatmap {f / 'h.png'}: {f} is a file, not a folder",
        ),
        (
            ["eval", "--dataset", str(bench), "--pred", str(f), "--task", "stereo"],
            f"error: --pred {f}: is a file; expected a folder of predictions",
        ),
        (
            ["stats", str(bench), "--out", str(f / "s")],
            f"error: --out {f / 's'}: {f} is a file, not a folder",
        ),
    ]
    for args, message in cases:
        code, out, err = sensorbox(capsys, *args)
        assert (code, err) == (2, [message]), args
        assert out == ""  # refused before any work printed anything
    assert f.read_text() == "mine\n" and sorted(p.name for p in tmp_path.iterdir()) == [
        "afile",
        "bench",
        "pred",
    ]


def test_output_files_that_are_a_device_or_fifo_are_refused_before_the_work(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """eval --json and --heatmap renamed their file over a FIFO or a link to /dev/null (calib check --plot
    /dev/full replaced the device node with a PNG): exit 3 naming it, before any work printed anything."""
    bench = make_benchmark(tmp_path / "bench")
    pred = tmp_path / "pred"
    write_predictions(bench, pred, "stereo")
    fifo, link = tmp_path / "e.json", tmp_path / "h.png"
    os.mkfifo(fifo)
    link.symlink_to("/dev/null")
    eval_args = ["eval", "--dataset", str(bench), "--pred", str(pred), "--task", "stereo"]
    cases = [
        ([*eval_args, "--json", str(fifo)], f"error: {fifo}: is not a regular file (a FIFO (named pipe)); give a file path"),
        ([*eval_args, "--heatmap", str(link)], f"error: {link}: is not a regular file (a character device); give a file path"),
        (["calib", "check", str(RIG), "--plot", str(link)], f"error: {link}: is not a regular file (a character device); give a file path"),
    ]  # fmt: skip
    for args, message in cases:
        code, out, err = sensorbox(capsys, *args)
        assert (code, out, err) == (3, "", [message]), args
    assert fifo.lstat().st_mode & 0o170000 == 0o010000 and link.readlink() == Path("/dev/null")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bench", "e.json", "h.png", "pred"]


def test_an_eval_report_onto_a_file_eval_reads_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Sweep 7 S1: `eval --json PRED/.../000000.png` wrote the JSON report over that prediction, exit 0.
    A report path in the dataset, among the predictions or in a mask folder is refused (exit 2), and
    every input is left as it was; the top level of the prediction folder (the default report's) is fine."""
    bench = make_benchmark(tmp_path / "bench")
    pred = tmp_path / "pred"
    write_predictions(bench, pred, "stereo")
    one = sorted(pred.rglob("*.png"))[0]
    gt = sorted(bench.rglob("*.png"))[0]
    before = {p: p.read_bytes() for p in [*pred.rglob("*"), *bench.rglob("*")] if p.is_file()}
    eval_args = ["eval", "--dataset", str(bench), "--pred", str(pred), "--task", "stereo"]
    cases = [
        (["--json", str(one)], f"error: --json {one}: among the predictions ({pred}), whose files eval reads; "
                               f"give a path outside {pred} or at its top level"),
        (["--heatmap", str(gt)], f"error: --heatmap {gt}: inside the dataset ({bench}), whose files eval reads; "
                                 "give a path outside it"),
    ]  # fmt: skip
    for args, message in cases:
        assert sensorbox(capsys, *eval_args, *args) == (2, "", [message]), args
    assert {p: p.read_bytes() for p in [*pred.rglob("*"), *bench.rglob("*")] if p.is_file()} == before
    code, _, _ = sensorbox(
        capsys, *eval_args, "--image-type", "pano_crop", "--json", str(pred / "report.json")
    )
    assert code == 0 and json.loads((pred / "report.json").read_text())


def test_refine_and_view_refuse_to_write_over_what_they_read(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Sweep 7 S1: `calib refine --out` onto the input rig's camchain replaced it with the refined rig (the
    input rig no longer loaded), and `view --save` onto a GT depth PNG made it a Rerun recording; exit 0."""
    rig = tmp_path / "rig" / "rig.yaml"
    rig.parent.mkdir()
    for name in ("rig.yaml", "camchain.yaml"):
        (rig.parent / name).write_bytes((RIG.parent / name).read_bytes())
    chain = rig.parent / "camchain.yaml"
    kept = chain.read_bytes()
    code, _, err = sensorbox(capsys, "calib", "refine", str(INDOOR), "--rig", str(rig), "--out", str(chain))
    assert (code, err) == (2, [
        f"error: --out {chain}: is {chain}, which refine reads (the rig, its camchain or a bag); give another path"
    ])  # fmt: skip
    assert chain.read_bytes() == kept
    inside = INDOOR / "refined.yaml"
    code, _, err = sensorbox(capsys, "calib", "refine", str(INDOOR), "--rig", str(rig), "--out", str(inside))
    assert (code, err) == (2, [
        f"error: --out {inside}: lies in {INDOOR}, which refine reads (the rig, its camchain or a bag); give a path "
        "outside it"
    ])  # fmt: skip
    dataset = tmp_path / "ds"
    (dataset / "depth_fisheye").mkdir(parents=True)
    png = dataset / "depth_fisheye" / "000000.png"
    png.write_bytes(b"a depth map")
    code, _, err = sensorbox(capsys, "view", str(dataset), "--save", str(png))
    assert (code, err) == (2, [
        f"error: --save {png}: lies in {dataset}, the dataset the viewer reads; give a path outside it"
    ])  # fmt: skip
    assert png.read_bytes() == b"a depth map"


@pytest.mark.parametrize(
    "kind", ["file", "under a file", "symlink loop", "under a symlink loop", "/dev/null"]
)
def test_an_out_that_cannot_be_a_folder_is_exit_2_for_ingest_as_for_stats(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], kind: str
) -> None:
    """ingest said "cannot open X: Not a directory" with exit code 3 (a refused write) where stats said
    "is a file" with 2; a symbolic link loop passed stats' check and ingest's read the bags first."""
    f = _afile(tmp_path)
    (tmp_path / "loop").symlink_to(tmp_path / "loop")
    out, why = {
        "file": (f, "is a file; give a folder for {holds}"),
        "under a file": (f / "sub", f"{f} is a file, not a folder"),
        "symlink loop": (
            tmp_path / "loop",
            "is a symbolic link that leads nowhere (Too many levels of symbolic links); give a folder",
        ),
        "under a symlink loop": (
            tmp_path / "loop" / "sub",
            f"{tmp_path / 'loop'} is a symbolic link that leads nowhere (Too many levels of symbolic links); "
            "give a folder",
        ),
        "/dev/null": (Path("/dev/null"), "is a file; give a folder for {holds}"),
    }[kind]
    bench = make_benchmark(tmp_path / "bench")
    for args, holds in (
        (["ingest", str(INDOOR), "--rig", str(RIG), "--out", str(out)], "the dataset"),
        (["stats", str(bench), "--out", str(out)], "stats.json and stats.png"),
    ):
        code, stdout, err = sensorbox(capsys, *args)
        assert (code, stdout, err) == (2, "", [f"error: --out {out}: {why.format(holds=holds)}"]), args
    assert f.read_text() == "mine\n" and sorted(p.name for p in tmp_path.iterdir()) == [
        "afile",
        "bench",
        "loop",
    ]


def test_a_set_of_files_is_written_whole_or_not_at_all(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """bench wrote bench_tradeoff.csv and then failed on the chart; stats likewise with stats.json."""
    from ingest.dataset.layout import write_atomic_set

    out = tmp_path / "out"
    out.mkdir()
    (out / "a.csv").write_text("old\n")
    _fill_disk_at(monkeypatch, "b.png")
    with pytest.raises(OutputError) as err:
        write_atomic_set([(out / "a.csv", b"new\n"), (out / "b.png", b"x" * 1000)])
    assert str(err.value) == f"cannot write {out / 'b.png'}: {ENOSPC}"
    assert _files(out) == ["a.csv"] and (out / "a.csv").read_text() == "old\n"  # the old set, no temporaries
    with pytest.raises(OutputError):  # a folder it made for the set goes again
        write_atomic_set([(tmp_path / "new" / "sub" / "a.csv", b"1"), (tmp_path / "new" / "b.png", b"2")])
    assert not (tmp_path / "new").exists()
    with pytest.raises(OutputError, match=r"out: Is a directory$"):  # checked before any rename
        write_atomic_set([(out / "c.csv", b"1"), (out, b"2")])
    assert _files(out) == ["a.csv"]


def test_stats_on_a_full_disk_leaves_neither_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    bench = make_benchmark(tmp_path / "bench")
    out = tmp_path / "s"
    _fill_disk_at(monkeypatch, "stats.png")
    code, _, err = sensorbox(capsys, "stats", str(bench), "--out", str(out))
    assert (code, err) == (3, [f"error: cannot write {out / 'stats.png'}: {ENOSPC}"])
    assert not out.exists()  # no stats.json without its chart, and not the folder made for them


@pytest.mark.parametrize("fails", ["heat.png", "eval.json"])
def test_eval_on_a_full_disk_leaves_neither_the_json_nor_the_heatmap(
    fails: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """--json and --heatmap are one output set: whichever file the disk refuses, neither is left."""
    bench = make_benchmark(tmp_path / "bench")
    pred = tmp_path / "pred"
    write_predictions(bench, pred, "stereo")
    out = tmp_path / "out"
    args = ["eval", "--dataset", str(bench), "--pred", str(pred), "--task", "stereo", "--image-type", "pano_crop"]  # fmt: skip
    files = ["--json", str(out / "eval.json"), "--heatmap", str(out / "heat.png")]
    _fill_disk_at(monkeypatch, fails)
    code, _, err = sensorbox(capsys, *args, *files)
    assert (code, err) == (3, [f"error: cannot write {out / fails}: {ENOSPC}"])
    assert not out.exists()
    monkeypatch.undo()
    code, stdout, _ = sensorbox(capsys, *args, *files)
    assert code == 0 and sorted(p.name for p in out.iterdir()) == ["eval.json", "heat.png"]
    assert f"JSON report: {out / 'eval.json'}" in stdout


CAPTURE = ["capture", "--rig", str(RIG), "--emulate", "--scale", "0.25"]


@pytest.mark.parametrize(
    ("option", "message"),
    [
        (["--jpeg-quality", "0"], "--jpeg-quality 0: expected 1..100"),
        (["--duration", "-1"], "--duration -1: expected a finite number >= 0, in seconds (0 = until Ctrl-C)"),
        (["--split-size", "-5"], "--split-size -5: expected a finite number >= 0, in MiB (0 = never split)"),
        (["--min-free", "nan"], "--min-free nan: expected a finite number >= 0, in MiB"),
        (["--min-free", "1e300"], "--min-free 1e+300: expected at most 1e+09 MiB (about a petabyte)"),
        (["--duration", "1e9"], "--duration 1e+09: expected at most 1e+08 s (about three years)"),
        (["--name", "a/b"], "--name 'a/b': use letters, digits and _ . + - only (a folder name)"),
        (["--scale", "0"], "--scale 0: expected a number > 0 (0.25 -> 480x300)"),
    ],
)
def test_capture_options_are_checked_before_anything_is_written(
    option: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The rig was copied into --out first, and the error blamed the rig file or named split_bytes."""
    out = tmp_path / "c2"
    code, _, err = sensorbox(capsys, *CAPTURE, "--out", str(out), *option)
    assert (code, err) == (2, [f"error: {message}"])
    assert not out.exists()


def _train_dataset(root: Path) -> Path:
    for folder in ("depth_fisheye", "disp_equirect"):
        (root / folder).mkdir(parents=True)
        cv2.imwrite(str(root / folder / "000000.png"), np.full((6, 10), 500, np.uint16))
    return root


@pytest.mark.parametrize("cmd", ["eval", "stats"])
def test_image_type_on_a_train_dataset_is_refused(
    cmd: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """It was silently ignored (rc 0) on the train layout; it selects benchmark views only."""
    ds = _train_dataset(tmp_path / "ds")
    pred = tmp_path / "pred"
    (pred / "disp_equirect").mkdir(parents=True)
    np.save(pred / "disp_equirect" / "000000.npy", np.full((6, 10), 5.0, np.float32))
    args = (
        ["eval", "--dataset", str(ds), "--pred", str(pred), "--task", "stereo"]
        if cmd == "eval"
        else ["stats", str(ds)]
    )
    code, _, err = sensorbox(capsys, *args, "--image-type", "foo")
    message = (
        f"error: --image-type 'foo': {ds} is a train-layout dataset, which has one view per sample; "
        "--image-type selects benchmark views only (leave it out)"
    )
    assert (code, err) == (2, [message])
    assert sorted(p.name for p in ds.iterdir()) == ["depth_fisheye", "disp_equirect"]


@pytest.mark.parametrize("damage", ["cut", "flip"])
def test_a_damaged_ground_truth_png_is_our_one_line_only(
    damage: str, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """OpenCV's `[ WARN:0@0.8] ... PNG input buffer is incomplete` or `libpng error: ...` came first."""
    bench = make_benchmark(tmp_path / "bench")
    gt = sorted(bench.rglob("depth/*.png"))[0]
    data = bytearray(gt.read_bytes())
    if damage == "cut":
        data = data[: len(data) // 2]
    else:
        idat = data.index(b"IDAT") + 4
        data[idat + 2] ^= 0x10  # inside the zlib stream: libpng reads bad rows before it checks the CRC
    pred = tmp_path / "pred"
    write_predictions(bench, pred, "mono", view="fisheye")  # from the GT while it is whole
    gt.write_bytes(bytes(data))
    capfd.readouterr()
    scoring = ["eval", "--dataset", str(bench), "--pred", str(pred), "--task", "mono", "--json", str(tmp_path / "e.json")]  # fmt: skip
    for args in (["stats", str(bench), "--out", str(tmp_path / "s")], scoring):
        code, _, err = sensorbox(capfd, *args)  # file descriptors captured: what C libraries print too
        assert (code, err) == (
            2,
            [
                f"error: {gt}: cannot be decoded ({len(data)} bytes: empty, cut short or not an image)"
                + "; ground truth must be a 16-bit single-channel PNG"
            ],
        ), err


def test_a_window_of_1e300_ms_is_one_line_naming_the_option(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`--window-ms 1e300` ended in an OverflowError traceback (nanoseconds as a C long), 1e12 in 'Cannot
    allocate memory' naming no option."""
    from tests.faults.cli import sensorbox
    from tests.paths import FIXTURES_DIR

    bag = FIXTURES_DIR / "indoor_static_mcap"
    for value in ("1e300", "1e12"):
        code, _, err = sensorbox(
            capsys, "ingest", str(bag), "--rig", str(bag.with_name(bag.name + ".truth") / "rig.yaml"),
            "--out", str(tmp_path / "o"), "--window-ms", value,
        )  # fmt: skip
        assert code == 2
        assert err == [f"error: --window-ms {float(value):g}: expected at most 3.6e+06 ms (an hour)"]
        assert not (tmp_path / "o").exists()


def test_a_window_under_1_ns_is_named_as_given(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Sweep 3: `--window-ms 1e-9` was '--window-ms must be > 0, got 0' (1 ps rounded to 0 ns), naming a value
    the user did not give."""
    from tests.faults.cli import sensorbox
    from tests.paths import FIXTURES_DIR

    bag = FIXTURES_DIR / "indoor_static_mcap"
    rig = bag.with_name(bag.name + ".truth") / "rig.yaml"
    for option, extra in (("--window-ms", []), ("--gt-window-ms", ["--gt", "dense"])):
        code, _, err = sensorbox(
            capsys,
            "ingest",
            str(bag),
            "--rig",
            str(rig),
            "--out",
            str(tmp_path / "o"),
            option,
            "1e-9",
            *extra,
        )
        assert (code, err) == (
            2,
            [f"error: {option} 1e-09: under 1 ns, the resolution of the stamps; expected > 0"],
        )
        assert not (tmp_path / "o").exists()


def test_refine_names_the_bag_topic_and_time_of_an_imu_message_it_cannot_decode(tmp_path: Path) -> None:
    """`calib refine` said only '162 bytes are not a valid ROS 2 sensor_msgs/msg/Imu'; ingest named all three."""
    from calibration.rig import read_rig
    from ingest.errors import MessageDecodeError
    from ingest.train.run.refine import refine
    from tests.faults.bags import rewrite

    def keep(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        return [(topic, raw[: len(raw) // 2] if "imu" in topic and k == 3 else raw)]

    bag, rig = rewrite(tmp_path / "bag", keep)
    with pytest.raises(
        MessageDecodeError, match=rf"^{bag}: /livox/imu_192_168_1_1[23] at log time \d+\.\d{{9}} s: "
    ):
        refine([bag], read_rig(rig))


@pytest.mark.parametrize(
    ("source", "what"), [("indoor_walk_db3", "a SQLite database"), ("outdoor_static_bag.bag", "a ROS 1 bag")]
)
def test_another_bag_format_named_mcap_is_called_by_its_name(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], source: str, what: str
) -> None:
    """A .db3 or ROS 1 bag renamed x.mcap was 'MCAP file is truncated or still being written; rerun with
    --salvage': the wrong cause and advice."""
    import shutil

    from tests.faults.cli import sensorbox
    from tests.paths import FIXTURES_DIR

    src = FIXTURES_DIR / source
    data = next(src.glob("*.db3")) if src.is_dir() else src
    shutil.copyfile(data, tmp_path / "x.mcap")
    code, _, err = sensorbox(capsys, "inspect", str(tmp_path / "x.mcap"))
    assert code == 2
    assert len(err) == 1 and err[0].startswith(
        f"error: {tmp_path / 'x.mcap'}: not an MCAP file: it starts like {what}"
    )


def test_a_depth_map_of_another_size_than_its_image_or_dataset_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """stats counted a 7x5 depth map beside 10x6 images (density and depth shares of another picture)."""
    bench = make_benchmark(tmp_path / "bench")
    cfg = bench / "001_057_000" / "120FOV" / "65mm" / "CENTER"
    gt = cfg / "depth" / "pano_crop.png"
    cv2.imwrite(str(gt), np.full((5, 7), 2000, np.uint16))
    code, out, err = sensorbox(capsys, "stats", str(bench), "--image-type", "pano_crop")
    line = f"error: {gt}: depth map 7x5 px, expected 10x6 (the size of its image {cfg / 'pano_crop.png'})"
    assert (code, out, err) == (2, "", [line])
    ds = _train_dataset(tmp_path / "ds")  # 10x6 depth maps, no image: dataset.yaml gives the size
    (ds / "dataset.yaml").write_text("fisheye_size: [300, 480]\n")  # no 'format': not cut short, a part
    code, out, err = sensorbox(capsys, "stats", str(ds))
    line = (
        f"error: {ds / 'depth_fisheye' / '000000.png'}: depth map 10x6 px, expected 480x300 (the size of "
        f"{ds / 'dataset.yaml'}'s fisheye_size)"
    )
    assert (code, out, err) == (2, "", [line])
    assert not (ds / "stats.json").exists() and not (bench / "stats.json").exists()


@pytest.mark.parametrize(
    ("args", "line"),
    [
        (
            ["ingest", str(INDOOR), "--rig", str(RIG), "--height-full", "7"],
            "--height-full 7: expected >= 64 rows (a pixel of 2.8 degrees; fewer leave no image a network can "
            "downsample, nor disparity)",
        ),
        (
            ["render-benchmark", "scan.ply", "--rig", str(RIG), "--height-full", "7"],
            "--height-full must be >= 64 rows (a pixel of 2.8 degrees; fewer leave no image a network can "
            "downsample, nor disparity), got 7",
        ),
        (
            ["render-benchmark", "scan.ply", "--rig", str(RIG), "--yaw", "1e300"],
            "--yaw [1e+300]: each yaw must be within -360..360 degrees",
        ),
        (
            ["render-benchmark", "scan.ply", "--rig", str(RIG), "--yaw", "90", "--yaw", "-361"],
            "--yaw [90.0, -361.0]: each yaw must be within -360..360 degrees",
        ),
        (
            ["render-benchmark", "scan.ply", "--rig", str(RIG), "--baseline", "1e300"],
            "--baseline [1e+300]: each baseline must be at most 2000 mm",
        ),
        (
            ["render-benchmark", "scan.ply", "--rig", str(RIG), "--height", "1.5", "--height", "1e300"],
            "--height [1.5, 1e+300]: each height must be within -100..100 m",
        ),
        (  # sweep 3: the line named the DoubleSphere's fx, not the option
            [
                "render-benchmark",
                "scan.ply",
                "--rig",
                str(RIG),
                "--fov",
                "120",
                "--fov",
                "0.001",
                "--size",
                "128x72",
            ],
            "--fov 0.001: no 128x72 fisheye of that FOV (DoubleSphere: fx must be within 0.128..128000 px "
            "(0.001..1000 times the image's 128 px) for a useful field of view, got 7503470.999999999)",
        ),
    ],
)
def test_a_sphere_of_7_rows_or_a_yaw_of_1e300_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], line: str
) -> None:
    """ingest --height-full 7 wrote 7x14 equirects with no disparity pixel; --yaw 1e300 rendered some
    arbitrary heading and recorded 1e300 degrees; --baseline and --height 1e300 rendered with overflow
    warnings (a `1e+300mm` folder)."""
    code, out, err = sensorbox(capsys, *args, "--out", str(tmp_path / "o"))
    assert (code, out, err) == (2, "", [f"error: {line}"])
    assert not (tmp_path / "o").exists()


def test_render_benchmark_into_a_training_set_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Sweep 3: render-benchmark --out a training set wrote its scene beside the samples, exit 0; stats then
    took the folder for the training set alone (5 depth maps), the benchmark out of sight."""
    from tests.faults.cli import sensorbox

    out = tmp_path / "ds"
    (out / "meta").mkdir(parents=True)
    (out / "dataset.yaml").write_text("format: widedepth-train\n")
    code, stdout, err = sensorbox(
        capsys, "render-benchmark", "scan.ply", "--rig", str(RIG), "--out", str(out)
    )
    assert (code, stdout, err) == (
        2,
        "",
        [
            f"error: {out}: holds a training set (dataset.yaml: the ingest layout); render-benchmark would mix "
            "a benchmark into it: choose another --out"
        ],
    )
    assert sorted(p.name for p in out.iterdir()) == ["dataset.yaml", "meta"]
