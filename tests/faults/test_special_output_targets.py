"""Issue 49: writers that renamed a file into place by themselves refuse device and FIFO targets too.

`calibration.warp.save_maps` (the remap map cache), `calibration.rig.write_rig`
(a rig file and its camchain: the simulated camera's `write_rig`, a dataset's
`rig/` copy) wrote or renamed without the project's atomic-write helper: a
FIFO in the cache was replaced by the maps, a rig path linked to /dev/null
swallowed the rig with no error (and a FIFO one waited forever), a dataset's
`rig/camchain.yaml` that was a FIFO was replaced. Each now goes through
`calibration.files.write_atomic(_set)`: one line naming the file and what it
is, nothing written, the node left as it was.
"""

from __future__ import annotations

import logging
import os
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from calibration.errors import WriteError
from calibration.rig import read_rig, write_rig
from calibration.spherical import Equirectangular
from calibration.warp import RemapMaps, load_maps, save_maps
from ingest.errors import OutputError
from ingest.train.run.pipeline import ingest
from ingest.train.run.settings import IngestConfig
from sensorbox.sim.camera_source import SimCameras
from sensorbox.sim.fixtures import FIXTURES
from tests.faults.bags import INDOOR
from tests.faults.cli import sensorbox
from tests.paths import ROOT

RIG = INDOOR.parent / "indoor_static_mcap.truth" / "rig.yaml"
NULL = "a character device"
FIFO = "a FIFO (named pipe)"


def _null_link(path: Path) -> Path:
    path.symlink_to("/dev/null")
    return path


def _fifo(path: Path) -> Path:
    os.mkfifo(path)
    return path


def _is_fifo(path: Path) -> bool:
    return stat.S_ISFIFO(path.lstat().st_mode)


def test_the_remap_cache_neither_reads_nor_replaces_a_fifo(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = _fifo(tmp_path / "maps.npz")
    maps = RemapMaps(np.zeros((2, 3), np.float32), np.zeros((2, 3), np.float32), np.ones((2, 3), bool), ())
    with caplog.at_level(logging.WARNING, logger="calibration.warp"):
        save_maps(path, maps)
        assert load_maps(path, Equirectangular(8)) is None  # not read: a FIFO would wait forever
    assert _is_fifo(path)  # not replaced by the maps
    assert [r.getMessage() for r in caplog.records] == [
        f"{path}: cannot store the remap maps ({path}: is not a regular file ({FIFO}); give a file path); "
        "they will be built again next time",
        f"{path}: unreadable remap map cache file ({path}: is {FIFO}, not a remap map cache file); "
        "building the maps again",
    ]


@pytest.mark.parametrize(("make", "what"), [(_null_link, NULL), (_fifo, FIFO)])
def test_write_rig_refuses_a_device_or_fifo_and_writes_neither_file(
    tmp_path: Path, make: object, what: str
) -> None:
    rig = read_rig(RIG)
    target = make(tmp_path / "rig.yaml")  # type: ignore[operator]
    with pytest.raises(WriteError) as err:
        write_rig(rig, target)
    assert str(err.value) == f"{target}: is not a regular file ({what}); give a file path"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rig.yaml"]  # no camchain, no temporary file
    chain = make(tmp_path / "other-camchain.yaml")  # type: ignore[operator]
    with pytest.raises(WriteError) as err:
        write_rig(rig, tmp_path / "other.yaml")
    assert str(err.value) == f"{chain}: is not a regular file ({what}); give a file path"
    assert not (tmp_path / "other.yaml").exists()


def test_the_simulated_cameras_rig_refuses_a_device(tmp_path: Path) -> None:
    sim = SimCameras(FIXTURES["indoor_static_mcap"])
    target = _null_link(tmp_path / "rig.yaml")
    with pytest.raises(OutputError) as err:
        sim.write_rig(target)
    assert str(err.value) == f"{target}: is not a regular file ({NULL}); give a file path"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rig.yaml"] and target.is_symlink()


def test_a_dataset_rig_copy_that_is_a_fifo_is_refused_exit_3(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "ds"
    (out / "rig").mkdir(parents=True)
    chain = _fifo(out / "rig" / "camchain.yaml")
    line = f"{chain}: is not a regular file ({FIFO}); give a file path"
    fast = {"workers": 1, "every": 3, "height_full": 64, "gt": "sparse"}
    with pytest.raises(OutputError) as err:
        ingest([INDOOR], IngestConfig(rig=RIG, out=out, **fast))  # type: ignore[arg-type]
    assert str(err.value) == line and _is_fifo(chain) and not (out / "rig" / "rig.yaml").exists()
    args = ["ingest", str(INDOOR), "--rig", str(RIG), "--out", str(out), "--workers", "1", "--every", "3"]
    code, _, stderr = sensorbox(capsys, *args, "--height-full", "64", "--gt", "sparse", "--no-preview")
    assert (code, stderr) == (3, [f"error: {line}"])


def test_a_launch_out_that_is_a_file_is_named_as_such(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Sweep 3: `launch sim.launch.yaml out:=/dev/null` was 'error: /dev/null: File exists' (exit 3)."""
    out = tmp_path / "bags"
    out.write_text("mine\n")
    launch = ROOT / "launch" / "sim.launch.yaml"
    code, _, err = sensorbox(capsys, "launch", str(launch), f"out:={out}", "duration:=1", "scale:=0.1")
    assert (code, err) == (2, [f"error: {out}: is a file, not a folder; give out a folder for the bags"])
    assert out.read_text() == "mine\n"


def test_eval_json_onto_a_folder_is_refused_before_the_scoring(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Sweep 3: `eval --json FOLDER` scored every sample, printed its tables, then said 'cannot write
    FOLDER: Is a directory' (exit 3), naming no option."""
    from tests.ingest.test_evaluate import make_benchmark, write_predictions

    bench = make_benchmark(tmp_path / "bench")
    pred = tmp_path / "pred"
    write_predictions(bench, pred, "stereo")
    folder = tmp_path / "reports"
    folder.mkdir()
    code, out, err = sensorbox(
        capsys,
        "eval",
        "--dataset",
        str(bench),
        "--pred",
        str(pred),
        "--task",
        "stereo",
        "--json",
        str(folder),
    )
    assert (code, out, err) == (2, "", [f"error: --json {folder}: is a folder; give a file path"])
    assert list(folder.iterdir()) == []


def test_view_save_onto_a_full_disk_is_one_line_and_leaves_no_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Sweep 3: `view --save` onto a full disk (a 2 MiB tmpfs) ended in a traceback, RuntimeError: Failed to
    encode LogMsg: Failed to write: No space left on device (os error 28), and left its .v.rrd.tmp."""
    import rerun

    full = "Failed to encode LogMsg: Failed to write: No space left on device (os error 28)"

    def save(self: object, path: Path, *args: object, **kwargs: object) -> None:
        Path(path).write_bytes(b"RRF2")  # the binding creates the file, then fails writing to it
        raise RuntimeError(full)

    monkeypatch.setattr(rerun.RecordingStream, "save", save)
    (tmp_path / "ds" / "depth_fisheye").mkdir(parents=True)
    out = tmp_path / "v.rrd"
    code, _, err = sensorbox(capsys, "view", str(tmp_path / "ds"), "--save", str(out))
    assert (code, err) == (3, [f"error: cannot write {out}: {full}"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]


def test_a_closed_standard_output_is_one_line_and_a_closed_standard_error_is_silent(tmp_path: Path) -> None:
    """Sweep 6: `sensorbox ingest ... >&-` ended in a traceback (Python leaves a closed stream None)."""
    python = f"{sys.executable} -m sensorbox.cli"
    closed = subprocess.run(
        ["bash", "-c", f"{python} ingest {INDOOR} --rig {RIG} --out {tmp_path / 'ds'} >&-"],
        capture_output=True, text=True, cwd=ROOT,
    )  # fmt: skip
    assert closed.returncode == 2
    assert closed.stderr == "error: standard output is closed; give it a file, or >/dev/null to discard it\n"
    assert not (tmp_path / "ds").exists()
    quiet = subprocess.run(
        ["bash", "-c", f"{python} calib check {tmp_path / 'missing.yaml'} 2>&-"],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert quiet.returncode == 2 and quiet.stderr == ""  # the error went nowhere; the exit code still tells


def test_a_full_standard_output_is_named_and_a_full_standard_error_keeps_the_exit_code(
    tmp_path: Path,
) -> None:
    """Sweep 7: `inspect ... > /dev/full` said only "No space left on device" (naming neither stdout nor
    a file), and `calib check MISSING 2> /dev/full` exited 1 instead of the documented 2."""
    python = f"{sys.executable} -m sensorbox.cli"
    full = subprocess.run(
        ["bash", "-c", f"{python} inspect {INDOOR} --rig {RIG} > /dev/full"],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert (full.returncode, full.stderr) == (3, "error: standard output: No space left on device\n")
    quiet = subprocess.run(
        ["bash", "-c", f"{python} calib check {tmp_path / 'missing.yaml'} 2> /dev/full"],
        capture_output=True, text=True, cwd=ROOT,
    )  # fmt: skip
    assert (quiet.returncode, quiet.stdout) == (2, "")


def test_a_deleted_working_directory_is_one_line(tmp_path: Path) -> None:
    """Sweep 6 U6: run from a directory deleted meanwhile, ingest died in Open3D's oneMKL ("Cannot load
    libOpen3D.so"), naming no cause."""
    gone = tmp_path / "gone"
    gone.mkdir()
    python = f"{sys.executable} -m sensorbox.cli"
    res = subprocess.run(
        ["bash", "-c", f"cd {gone} && rmdir {gone} && PYTHONPATH={ROOT} {python} inspect {INDOOR}"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert (res.returncode, res.stderr) == (
        2,
        "error: the current directory no longer exists (deleted since the shell entered it); cd to a folder that "
        "exists\n",
    )


@pytest.mark.parametrize("which", ["--json", "--dataset", "--pred"])
def test_a_symbolic_link_loop_given_to_eval_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], which: str
) -> None:
    """Sweep 8: `eval --json LOOP` or `--dataset LOOP` (a link to a link to the first) ended in pathlib's
    `RuntimeError: Symlink loop` traceback, exit 1."""
    loop = tmp_path / "loop"
    (tmp_path / "loop2").symlink_to(loop)
    loop.symlink_to(tmp_path / "loop2")
    (tmp_path / "pred").mkdir()
    paths = {"--dataset": str(INDOOR), "--pred": str(tmp_path / "pred"), "--json": str(tmp_path / "r.json")}
    paths[which] = str(loop)
    args = [a for flag, path in paths.items() for a in (flag, path)]
    code, out, err = sensorbox(capsys, "eval", *args, "--task", "completion")
    line = f"error: {loop}: is a symbolic link that leads nowhere (a loop of links)"
    if which == "--json":  # an output: refused naming its option before anything is read
        line = f"error: --json {loop}: is a symbolic link that leads nowhere (Too many levels of symbolic links); "
        line += "give a file path"
    assert (code, out, err) == (2, "", [line])


@pytest.mark.parametrize(
    ("command", "flag", "expected"),
    [
        (["calib", "check", "{rig}", "--plot"], "--plot", "a file path"),
        (
            ["calib", "refine", "{bag}", "--rig", "{rig}", "--out", "{tmp}/r.yaml", "--plot"],
            "--plot",
            "a file path",
        ),
        (["simulate", "--duration", "0.1", "--scale", "0.1", "--out"], "--out", "a bag path"),
        (["capture", "--rig", "{rig}", "--emulate", "--duration", "1", "--out"], "--out", "a folder"),
        (
            ["eval", "--dataset", "{bag}", "--pred", "{tmp}", "--task", "completion", "--heatmap"],
            "--heatmap",
            "a file path",
        ),
    ],
)
def test_an_output_that_is_a_symbolic_link_loop_is_refused_before_the_work(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], command: list[str], flag: str, expected: str
) -> None:
    """Sweep 8: `calib refine --plot LOOP` ended in pathlib's RuntimeError traceback after the whole refine;
    `simulate --out LOOP` and `capture --out LOOP` said 'Not a directory' of a temporary or 'File exists',
    exit 3."""
    loop = tmp_path / "loop.png"
    (tmp_path / "loop2.png").symlink_to(loop)
    loop.symlink_to(tmp_path / "loop2.png")
    rig = INDOOR.parent / "indoor_static_mcap.truth" / "rig.yaml"
    args = [a.format(rig=rig, bag=INDOOR, tmp=tmp_path) for a in command]
    code, _, err = sensorbox(capsys, *args, str(loop))
    assert code == 2 and err == [
        f"error: {flag} {loop}: is a symbolic link that leads nowhere (Too many levels of symbolic links); "
        f"give {expected}"
    ]
    assert not (tmp_path / "r.yaml").exists()


def test_a_launch_file_or_view_save_that_is_a_symbolic_link_loop_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Sweep 8: `launch --dry-run LOOP` and `view DATASET --save LOOP` ended in pathlib's RuntimeError
    traceback, exit 1."""
    loop = tmp_path / "loop.yaml"
    (tmp_path / "loop2.yaml").symlink_to(loop)
    loop.symlink_to(tmp_path / "loop2.yaml")
    code, _, err = sensorbox(capsys, "launch", "--dry-run", str(loop))
    assert (code, err) == (
        2,
        [f"error: {loop}: is a symbolic link that leads nowhere (a loop of links); give a launch file"],
    )
    for layout in ("disp_equirect", "depth_fisheye"):
        (tmp_path / "ds" / layout).mkdir(parents=True)
    code, _, err = sensorbox(capsys, "view", str(tmp_path / "ds"), "--save", str(loop))
    assert (
        code == 2
        and len(err) == 1
        and str(loop) in err[0]
        and "is a symbolic link that leads nowhere" in err[0]
    )
