"""Issue 49: rig and calibration files, special files and bounds: refused in one line, never silent wrong GT.

Each case is run as a user would (`sensorbox ...` in this process, or in a
child process with a memory and time limit where the fault, unfixed, would
read without end or wait forever) with its fixture written to tmp_path.
"""

from __future__ import annotations

import errno
import os
import resource
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml

from calibration import CalibrationError, read_kalibr_camchain, read_rig
from tests.faults.bags import INDOOR
from tests.faults.cli import sensorbox
from tests.paths import ROOT

TRUTH = INDOOR.parent / "indoor_static_mcap.truth"


def _rig(tmp: Path, edit: dict[str, object] | None = None, camchain: str = "camchain.yaml") -> Path:
    """The indoor fixture's rig (480x300 cameras) in `tmp`, its top-level keys updated by `edit`
    (None drops a key), its camchain copied beside it and named `camchain`."""
    shutil.copy(TRUTH / "camchain.yaml", tmp / "camchain.yaml")
    doc = yaml.safe_load((TRUTH / "rig.yaml").read_text())
    doc["camchain"] = camchain
    for key, value in (edit or {}).items():
        if value is None:
            del doc[key]
        else:
            doc[key] = value
    path = tmp / "rig.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def test_a_misspelt_rig_key_is_refused_not_ignored(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`imu:` for `imus:` dropped both IMUs without a word (dense GT p95 29.2 mm against 1.7 mm)."""
    imus = yaml.safe_load((TRUTH / "rig.yaml").read_text())["imus"]
    rig = _rig(tmp_path, {"imus": None, "imu": imus})
    code, _, err = sensorbox(capsys, "calib", "check", str(rig))
    assert (code, err) == (
        2,
        [
            f"error: {rig}: unknown key 'imu' (did you mean 'imus'?); "
            "known keys: sensorbox_rig, name, camchain, cameras, lidars, imus"
        ],
    )
    out = tmp_path / "ds"
    code, _, err = sensorbox(capsys, "ingest", str(INDOOR), "--rig", str(rig), "--out", str(out))
    assert code == 2 and err[0].startswith(f"error: {rig}: unknown key 'imu'") and len(err) == 1
    assert not out.exists()


@pytest.mark.parametrize(("scale", "shown"), [(1000.0, "89.5"), (1e12 / 0.0895, "1e+12")])
def test_a_lidar_lever_arm_in_millimetres_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], scale: float, shown: str
) -> None:
    """87 mm written as 87 (or 1e12 m) passed calib check, inspect and ingest; density fell 10.4 -> 4.4 %."""
    lidars = yaml.safe_load((TRUTH / "rig.yaml").read_text())["lidars"]
    T = np.array(lidars["lidar_top"]["T_cam0_lidar"], float)
    T[:3, 3] *= scale
    lidars["lidar_top"]["T_cam0_lidar"] = T.tolist()
    rig = _rig(tmp_path, {"lidars": lidars})
    line = (
        f"error: {rig}: lidars.lidar_top.T_cam0_lidar: translation {shown} m from cam0: expected <= 2 m "
        "on a handheld rig (millimetres written as metres?)"
    )
    for command in (["calib", "check", str(rig)], ["inspect", str(INDOOR), "--rig", str(rig)]):
        code, _, err = sensorbox(capsys, *command)
        assert (code, err) == (2, [line]), command


def test_a_100k_deep_yaml_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A RecursionError traceback in calib check, inspect and ingest."""
    deep = tmp_path / "deep.yaml"
    deep.write_text("cam0: " + "[" * 100_000 + "]" * 100_000 + "\n")
    line = f"error: {deep}: line 1, column 70: malformed YAML: nested more than 64 levels deep"
    out = tmp_path / "ds"
    for command in (
        ["calib", "check", str(deep)],
        ["inspect", str(INDOOR), "--rig", str(deep)],
        ["ingest", str(INDOOR), "--rig", str(deep), "--out", str(out)],
    ):
        code, _, err = sensorbox(capsys, *command)
        assert (code, err) == (2, [line]), command
    assert not out.exists()


def _limited() -> None:
    """In the child: 3 GiB of address space, so reading /dev/zero unbounded ends in a MemoryError."""
    resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))


def _guarded(*args: str) -> tuple[int, list[str]]:
    """(exit code, stderr lines) of `sensorbox ARGS` in a child with a memory limit and a 60 s timeout."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    try:
        res = subprocess.run(
            [sys.executable, "-m", "sensorbox.cli", *args],
            capture_output=True, text=True, timeout=60, env=env, preexec_fn=_limited,
        )  # fmt: skip
    except subprocess.TimeoutExpired:
        return -1, ["timed out: the read blocked"]
    return res.returncode, res.stderr.splitlines()


def _special(kind: str, path: Path) -> str:
    """Make `path` a `kind` of special file; return how the error line names it."""
    if kind == "fifo":
        os.mkfifo(path)
        return "is a FIFO (named pipe)"
    if kind == "folder":
        path.mkdir()
        return "is a folder"
    path.symlink_to(f"/dev/{kind}")
    return f"is a character device (a link to /dev/{kind})"


@pytest.mark.parametrize("kind", ["zero", "urandom", "fifo", "folder"])
def test_a_camchain_that_is_not_a_regular_file_is_refused_before_reading(tmp_path: Path, kind: str) -> None:
    """A camchain linked to /dev/zero or /dev/urandom was read until the OOM killer came (24 GB); a FIFO
    blocked forever."""
    rig = _rig(tmp_path, camchain="chain.yaml")
    chain = tmp_path / "chain.yaml"
    what = _special(kind, chain)
    assert _guarded("calib", "check", str(rig)) == (
        2,
        [f"error: {chain}: {what}, not a Kalibr camchain (referenced by rig.yaml) file"],
    )


def test_a_rig_that_is_a_fifo_is_refused(tmp_path: Path) -> None:
    rig = tmp_path / "rig.yaml"
    os.mkfifo(rig)
    assert _guarded("calib", "check", str(rig)) == (
        2,
        [f"error: {rig}: is a FIFO (named pipe), not a rig file"],
    )


def test_a_yaml_file_over_4_mib_is_refused_unread(tmp_path: Path) -> None:
    rig = _rig(tmp_path)
    with rig.open("a") as f:
        f.write("#" * (4 << 20))
    with pytest.raises(CalibrationError) as err:
        read_rig(rig)
    assert (
        str(err.value)
        == f"{rig}: {rig.stat().st_size} bytes; a rig file is at most 4 MiB (is this the right file?)"
    )


def _camchain_with(tmp: Path, edit: str, to: str) -> Path:
    path = tmp / "camchain.yaml"
    text = (TRUTH / "camchain.yaml").read_text()
    assert edit in text
    path.write_text(text.replace(edit, to, 1))
    return path


def test_a_double_sphere_xi_of_1e9_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Ingest ended in a ZeroDivisionError: the valid image circle of such a camera is a few pixels."""
    chain = _camchain_with(tmp_path, "intrinsics: [-0.18153,", "intrinsics: [1.0e9,")
    code, _, err = sensorbox(capsys, "calib", "check", str(chain))
    assert (code, err) == (
        2,
        [
            f"error: {chain}: cam0: DoubleSphere: xi must be in (-1, 1], got 1000000000.0 (at -1 the optical "
            "axis has no image, beyond 1 the valid image circle shrinks to a few pixels; a fitted fisheye's "
            "xi is about -0.3..0.3)"
        ],
    )


def test_an_integer_of_5000_digits_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A traceback (ValueError: Exceeds the limit (4300 digits) for integer string conversion)
    in calib check and inspect."""
    chain = _camchain_with(tmp_path, "resolution: [480, 300]", "resolution: [480" + "0" * 5000 + ", 300]")
    line = (
        f"error: {chain}: line 6, column 16: malformed YAML: an integer of 5003 digits; at most 4300 are read"
    )
    for command in (["calib", "check", str(chain)], ["inspect", str(INDOOR), "--rig", str(chain)]):
        code, _, err = sensorbox(capsys, *command)
        assert (code, err) == (2, [line]), command


def test_a_focal_length_of_1e300_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """fu = 1e300 passed calib check (HFOV 0.0 deg); ingest then failed in the occlusion filter
    (ValueError: Maximum allowed dimension exceeded), leaving a dataset.yaml and empty folders."""
    chain = _camchain_with(tmp_path, "0.59021, 125.05785,", "0.59021, 1e300,")
    line = (
        f"error: {chain}: cam0: DoubleSphere: fx must be within 0.48..480000 px (0.001..1000 times the "
        "image's 480 px) for a useful field of view, got 1e+300"
    )
    code, _, err = sensorbox(capsys, "calib", "check", str(chain))
    assert (code, err) == (2, [line])
    out = tmp_path / "ds"
    code, _, err = sensorbox(capsys, "ingest", str(INDOOR), "--rig", str(chain), "--out", str(out))
    assert (code, err) == (2, [line])
    assert not out.exists()


def test_a_resolution_of_1e9_is_refused_before_any_map_is_sized(tmp_path: Path) -> None:
    """Ingest asked numpy for 6.94 EiB. Asserted on the reader, which allocates nothing either way."""
    chain = _camchain_with(tmp_path, "resolution: [480, 300]", "resolution: [1000000000, 1000000000]")
    with pytest.raises(CalibrationError) as err:
        read_kalibr_camchain(chain)
    assert str(err.value) == (
        f"{chain}: cam0.resolution: expected [width, height] positive ints of at most 16384, "
        "got [1000000000, 1000000000]"
    )


def test_an_emptied_launch_argument_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`out:=` wrote /rig.yaml and /rig-camchain.yaml at the filesystem root (write_rig = $(var out)/rig.yaml)."""
    launch = ROOT / "sensorbox" / "share" / "launch" / "sim.launch.yaml"
    code, out, err = sensorbox(capsys, "launch", str(launch), "out:=", "--dry-run")
    assert (code, out, err) == (
        2,
        "",
        [
            f"error: {launch}: launch argument out:= is empty (its default is 'bags/sim'); "
            "give a value, or leave it out for the default"
        ],
    )
    code, out, _ = sensorbox(capsys, "launch", str(launch), "name:=", "--dry-run")  # its default is empty
    assert code == 0 and "param name = ''" in out


@pytest.mark.parametrize("option", ["--out", "--rig"])
def test_an_empty_path_option_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, option: str
) -> None:
    """`ingest --out ""` wrote the dataset into the current folder (typer reads "" as ".")."""
    monkeypatch.chdir(tmp_path)
    args = {"--out": str(tmp_path / "ds"), "--rig": str(TRUTH / "rig.yaml"), option: ""}
    code, _, err = sensorbox(capsys, "ingest", str(INDOOR), *(s for kv in args.items() for s in kv))
    assert (code, err) == (2, [f"error: {option} '': empty path (that is the current folder); give a path"])
    assert list(tmp_path.iterdir()) == []


def test_empty_paths_of_other_commands_are_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rig = str(TRUTH / "rig.yaml")
    for command, flag in (
        (["ingest", "", "--rig", rig, "--out", str(tmp_path / "ds")], "BAGS"),
        (["calib", "check", rig, "--plot", ""], "--plot"),
        (["stats", ""], "DATASET"),
        (["simulate", "--out", ""], "--out"),
        (["render-benchmark", "x.ply", "--rig", rig, "--out", ""], "--out"),
        (["bench", "--out", ""], "--out"),
        (["eval", "--dataset", str(tmp_path), "--pred", "", "--task", "stereo"], "--pred"),
    ):
        code, _, err = sensorbox(capsys, *command)
        assert (code, err) == (2, [f"error: {flag} '': empty path (that is the current folder); give a path"])


def test_bad_launch_files_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A binary launch file was a UnicodeDecodeError traceback, 400 nested groups a RecursionError."""
    binary = tmp_path / "bin.launch.yaml"
    binary.write_bytes(b'launch:\n- arg: {name: a, default: "\x89PNG"}\n')
    groups = tmp_path / "groups.launch.yaml"
    groups.write_text(
        "launch:\n" + "".join("  " * i + "- group:\n" for i in range(400)) + "  " * 400 + "- log: {}\n"
    )
    chain = [tmp_path / f"inc{i}.launch.yaml" for i in range(40)]
    for i, path in enumerate(chain[:-1]):
        path.write_text(f"launch:\n- include: {{file: {chain[i + 1].name}}}\n")
    chain[-1].write_text("launch: []\n")
    for path, line in (
        (binary, f"{binary}: not a YAML launch file (byte 35 is 0x89, not UTF-8 text)"),
        (groups, f"{groups}: line 33, column 65: malformed YAML: nested more than 64 levels deep"),
        (chain[0], f"{chain[32]}: included more than 32 files deep (from {chain[0]})"),
    ):
        code, _, err = sensorbox(capsys, "launch", str(path), "--dry-run")
        assert (code, err) == (2, [f"error: {line}"])


def test_a_launch_substitution_growing_to_gigabytes_is_refused(tmp_path: Path) -> None:
    """`let`s that each double the last: a MemoryError traceback (run with a memory limit)."""
    launch = tmp_path / "grow.launch.yaml"
    lets = "".join(f'- let: {{name: a{i}, value: "$(var a{i - 1})$(var a{i - 1})"}}\n' for i in range(1, 40))
    launch.write_text("launch:\n- let: {name: a0, value: " + "x" * 64 + "}\n" + lets)
    assert _guarded("launch", str(launch), "--dry-run") == (
        2,
        [
            f"error: {launch}:13: a substituted value longer than 100000 characters "
            "(a substitution that grows with each use?)"
        ],
    )


def test_a_bag_that_is_a_fifo_is_refused(tmp_path: Path) -> None:
    """A FIFO named x.mcap (or a rosbag2 folder's data file) made inspect and ingest wait forever."""
    fifo = tmp_path / "x.mcap"
    os.mkfifo(fifo)
    line = f"error: {fifo}: is a FIFO (named pipe), not a bag file or rosbag2 folder"
    assert _guarded("inspect", str(fifo)) == (2, [line])
    folder = tmp_path / "rec"
    folder.mkdir()
    shutil.copy(INDOOR / "metadata.yaml", folder)
    os.mkfifo(folder / "rec_0.mcap")
    out = tmp_path / "ds"
    rig = str(TRUTH / "rig.yaml")
    assert _guarded("ingest", str(folder), "--rig", rig, "--out", str(out)) == (
        2,
        [f"error: {folder / 'rec_0.mcap'}: is a FIFO (named pipe), not a bag file or rosbag2 folder"],
    )
    assert not out.exists()


def test_a_bag_that_is_a_loop_of_links_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Sweep 3: a bag path whose links lead round in a loop ended inspect and ingest in a traceback
    (RuntimeError: Symlink loop from ...)."""
    loop = tmp_path / "a.mcap"
    loop.symlink_to(tmp_path / "b.mcap")
    (tmp_path / "b.mcap").symlink_to(loop)
    line = f"error: {loop}: is a symbolic link that leads nowhere (a loop of links); give a bag file or rosbag2 folder"
    out = tmp_path / "ds"
    for command in (
        ["inspect", str(loop)],
        ["ingest", str(loop), "--rig", str(TRUTH / "rig.yaml"), "--out", str(out)],
    ):
        code, _, err = sensorbox(capsys, *command)
        assert (code, err) == (2, [line]), command
    assert not out.exists()


def test_a_rerun_over_a_sample_metadata_fifo_does_not_wait(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Sweep 3: a FIFO in place of a finished sample's meta/<id>.json made the rerun wait forever on its read;
    the sample is damaged, and its rewrite refuses the FIFO (exit 3, one line)."""
    out = tmp_path / "ds"
    args = ["ingest", str(INDOOR), "--rig", str(TRUTH / "rig.yaml"), "--out", str(out), "--every", "7"]
    code, _, _ = sensorbox(
        capsys, *args, "--gt", "sparse", "--workers", "1", "--no-preview", "--height-full", "256"
    )
    assert code == 0
    meta = out / "meta" / "000001.json"
    meta.unlink()
    os.mkfifo(meta)
    assert _guarded(*args, "--gt", "sparse", "--workers", "1", "--no-preview", "--height-full", "256") == (
        3,
        [f"error: {meta}: is not a regular file (a FIFO (named pipe)); give a file path"],
    )


def test_a_npy_header_claiming_1e10_values_is_refused_before_allocation(tmp_path: Path) -> None:
    """`sensorbox eval` asked numpy for 37.3 GiB (run with a memory limit: unfixed, it is a MemoryError)."""
    from tests.ingest.test_evaluate import make_benchmark, write_predictions

    bench = make_benchmark(tmp_path / "bench")
    pred = tmp_path / "pred"
    npy = next(p for p in write_predictions(bench, pred, "stereo") if p.suffix == ".npy")
    with npy.open("wb") as f:  # the magic string and a header, no data
        np.lib.format.write_array_header_1_0(
            f, {"descr": "<f4", "fortran_order": False, "shape": (100000, 100000)}
        )
    assert _guarded("eval", "--dataset", str(bench), "--pred", str(pred), "--task", "stereo") == (
        2,
        [
            f"error: {npy}: the .npy header claims shape (100000, 100000) of float32 (40000000000 bytes), "
            "but the file holds 0 bytes of data"
        ],
    )


@pytest.mark.parametrize(
    ("args", "line"),
    [
        (
            ["--scale", "100"],
            "--scale 100 makes camera cam0 192000x120000 px; expected <= 16,777,216 px (--scale <= 2.698)",
        ),
        (
            ["--supersample", "1000"],
            "--supersample 1000 casts 2,304,000,000,000 rays a frame for camera cam0 (1920x1200 px at --scale 1); "
            "expected <= 16,777,216 (--supersample <= 2)",
        ),
    ],
)
def test_a_simulation_too_big_for_memory_is_refused_before_allocation(
    tmp_path: Path, args: list[str], line: str
) -> None:
    """--scale 100 asked numpy for 172 GiB, --supersample 1000 for more (run with a memory limit)."""
    out = tmp_path / "sim"
    assert _guarded("simulate", "--out", str(out), *args) == (2, [f"error: {line}"])
    assert not out.exists()


def test_a_negative_seed_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A ValueError traceback from numpy's generator."""
    out = tmp_path / "sim"
    assert sensorbox(capsys, "simulate", "--out", str(out), "--seed", "-1")[::2] == (
        2,
        ["error: --seed must be an integer >= 0, got -1"],
    )
    assert not out.exists()


@pytest.fixture
def read_only_folder(tmp_path: Path) -> Iterator[Path]:
    """A folder this process cannot write into: mode 0555, or as root (who ignores modes) a read-only
    tmpfs mounted there; skipped where neither can be had."""
    folder = tmp_path / "ro"
    folder.mkdir()
    if os.geteuid() != 0:
        folder.chmod(0o555)
        yield folder
        folder.chmod(0o755)
        return
    mount = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "ro,size=1m", "tmpfs", str(folder)], capture_output=True
    )
    if mount.returncode != 0:
        pytest.skip(f"cannot mount a read-only tmpfs: {mount.stderr.decode().strip()}")
    try:
        yield folder
    finally:
        subprocess.run(["umount", str(folder)], check=True)


@pytest.mark.parametrize("under", [False, True])
@pytest.mark.parametrize(
    "command",
    [
        ["bench"],
        ["render-benchmark", "site.yaml", "--rig", str(ROOT / "calibration" / "sensorbox.yaml")],
        ["stats", str(TRUTH)],
    ],
)
def test_a_read_only_out_is_refused_before_the_work_with_exit_3(
    read_only_folder: Path, capsys: pytest.CaptureFixture[str], command: list[str], under: bool
) -> None:
    """bench failed only after its whole 25 s run; render-benchmark exited 2 (3 is an OS-refused write)."""
    out = read_only_folder / "b" if under else read_only_folder
    why = os.strerror(errno.EROFS if os.geteuid() == 0 else errno.EACCES)
    where = f" (in {read_only_folder})" if under else ""
    code, _, err = sensorbox(capsys, *command, "--out", str(out))
    assert (code, err) == (3, [f"error: --out {out}: cannot write{where}: {why}"])


@pytest.mark.parametrize(
    ("model", "intrinsics", "name"),
    [
        ("omni", [1000.0, 125.0, 125.0, 240.0, 150.0], "Omni"),
        ("eucm", [0.6, 1000.0, 125.0, 125.0, 240.0, 150.0], "ExtendedUnified"),
    ],
)
def test_a_camera_that_sees_through_no_pixel_is_refused(
    tmp_path: Path, model: str, intrinsics: list[float], name: str
) -> None:
    """Valid numbers that are no lens (the image circle a few pixels wide): ingest divided by its zero
    valid pixels, as with a ds xi of 1e9."""
    chain = tmp_path / "camchain.yaml"
    cam = {"camera_model": model, "intrinsics": intrinsics, "distortion_model": "none", "distortion_coeffs": [],
           "resolution": [480, 300]}  # fmt: skip
    chain.write_text(yaml.safe_dump({"cam0": cam}))
    with pytest.raises(CalibrationError) as err:
        read_kalibr_camchain(chain)
    assert str(err.value) == (
        f"{chain}: cam0: the {name} model maps only 0 of 640 sampled pixels (a 32 x 20 grid) to rays; "
        "a lens sees through most of its image: check the intrinsics"
    )
    cam["intrinsics"] = [0.5, *intrinsics[1:]] if model == "omni" else [0.6, 1.0, *intrinsics[2:]]
    chain.write_text(yaml.safe_dump({"cam0": cam}))
    assert read_kalibr_camchain(chain).cameras[0].model.width == 480  # the same lens with sane parameters


def test_a_site_manifest_or_livox_user_config_that_is_a_fifo_is_refused(tmp_path: Path) -> None:
    """Both were read with a bare read_text: a FIFO waited forever."""
    site = tmp_path / "site.yaml"
    os.mkfifo(site)
    rig = str(ROOT / "calibration" / "sensorbox.yaml")
    assert _guarded("render-benchmark", str(site), "--rig", rig, "--out", str(tmp_path / "b")) == (
        2,
        [f"error: {site}: is a FIFO (named pipe), not a site manifest file"],
    )
    config = tmp_path / "MID360_config.json"
    os.mkfifo(config)
    code = f"from sensorbox.live.livox_node import read_livox_json; read_livox_json({str(config)!r})"
    try:
        res = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
            env={**os.environ, "PYTHONPATH": str(ROOT)},
        )  # fmt: skip
    except subprocess.TimeoutExpired:
        pytest.fail("read_livox_json blocked on a FIFO")
    assert res.stderr.splitlines()[-1] == (
        f"sensorbox.errors.GraphError: {config}: is a FIFO (named pipe), not a Livox user config file"
    )


@pytest.mark.parametrize(("shift", "shown"), [("1000000.0", "1e+06"), ("-4.2", "-4.2")])
def test_a_timeshift_beyond_a_second_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], shift: str, shown: str
) -> None:
    """`timeshift_cam_imu: 1e6` (or 4.2 ms written as 4.2): ingest planned 0 samples and said no why."""
    rig = _rig(tmp_path)
    chain = tmp_path / "camchain.yaml"
    topic = "  rostopic: /zed_lower/zed_node/rgb/color/rect/image\n"
    chain.write_text(chain.read_text().replace(topic, f"{topic}  timeshift_cam_imu: {shift}\n"))
    line = (
        f"error: {chain}: cam1.timeshift_cam_imu: {shown} s; expected within +-1 s (Kalibr's are milliseconds, "
        "0.0042 for 4.2 ms: a value in ms or ns, or an unsynchronised clock?)"
    )
    out = tmp_path / "ds"
    for command in (
        ["calib", "check", str(rig)],
        ["ingest", str(INDOOR), "--rig", str(rig), "--out", str(out), "--height-full", "64"],
    ):
        code, stdout, err = sensorbox(capsys, *command)
        assert (code, stdout, err) == (2, "", [line]), command
    assert not out.exists()


@pytest.mark.parametrize(("scale", "shown"), [(1000.0, "120.3"), (1e6 / 0.120309, "1e+06")])
def test_a_camera_baseline_over_10_m_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], scale: float, shown: str
) -> None:
    """cam1's T_cn_cnm1 at 1e6 m (or 120 mm written as 120) was only warned about; ingest went on."""
    rig = _rig(tmp_path)
    chain = tmp_path / "camchain.yaml"
    doc = yaml.safe_load(chain.read_text())
    T = np.array(doc["cam1"]["T_cn_cnm1"], float)
    T[:3, 3] *= scale
    doc["cam1"]["T_cn_cnm1"] = T.tolist()
    chain.write_text(yaml.safe_dump(doc))
    line = (
        f"error: {chain}: cam1.T_cn_cnm1: translation {shown} m from cam0: expected <= 10 m between two "
        "cameras of a rig (millimetres written as metres?)"
    )
    out = tmp_path / "ds"
    for command in (
        ["calib", "check", str(rig)],
        ["ingest", str(INDOOR), "--rig", str(rig), "--out", str(out), "--height-full", "64"],
    ):
        code, stdout, err = sensorbox(capsys, *command)
        assert (code, stdout, err) == (2, "", [line]), command
    assert not out.exists()


@pytest.mark.parametrize(
    ("args", "line"),
    [
        (
            ["duration:=nan"],
            "node 'recorder' (sensorbox/recorder) at {sim}:85: parameter 'duration_s' = 'nan': expected a "
            "finite number",
        ),
        (
            ["loop_s:=-3"],
            "node 'lidar_top_emulator' (sensorbox/mid360_emulator) at {sim}:27: loop_s must be >= 0 "
            "(0 = simulate live), got -3.0",
        ),
        (
            ["scale:=0"],
            "node 'zed_sim' (sensorbox/sim_camera) at {sim}:72: --scale must be a finite number > 0.0, got 0.0",
        ),
        (
            ["min_free_mb:=1e300"],
            "node 'recorder' (sensorbox/recorder) at {sim}:85: parameter 'min_free_mb' = '1e300': expected at "
            "most 1e+09 MiB (about a petabyte)",
        ),
        (
            ["loop_s:=1e300"],
            "node 'lidar_top_emulator' (sensorbox/mid360_emulator) at {sim}:27: parameter 'loop_s' = '1e300': "
            "expected at most 1e+08 s (the longest simulated recording)",
        ),
        (
            ["port_base:=70000"],
            "node 'lidar_top_emulator' (sensorbox/mid360_emulator) at {sim}:27: parameter 'port_base' = 70000: "
            "expected 1..65527 (the first of nine UDP ports, each <= 65535)",
        ),
        (
            ["--talker"],
            "node 'talker' (sensorbox/talker) at {talker}:2: parameter(s) colour not used by this node (with "
            "these settings); it reads: count, payload_bytes, rate_hz, topic",
        ),
    ],
)
def test_a_dry_run_refuses_what_the_run_refuses(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], line: str
) -> None:
    """`launch --dry-run` printed the nodes of values the run refuses (nan, -3, scale 0, port 70000, a
    parameter no node reads), exit 0; it now builds the nodes as the run does, starting none."""
    sim = ROOT / "sensorbox" / "share" / "launch" / "sim.launch.yaml"
    talker = tmp_path / "talker.launch.yaml"
    talker.write_text(
        "launch:\n- node: {pkg: sensorbox, exec: talker, param: [{name: colour, value: red}]}\n"
    )
    out = tmp_path / "bags"
    command = ["launch", str(talker)] if args == ["--talker"] else ["launch", str(sim), f"out:={out}", *args]
    expected = (2, "", [f"error: {line.format(sim=sim, talker=talker)}"])
    assert sensorbox(capsys, *command, "--dry-run") == expected
    assert sensorbox(capsys, *command) == expected  # the run: refused the same, before any node started
    assert sorted(p.name for p in tmp_path.iterdir()) == ["talker.launch.yaml"]  # nothing written


@pytest.mark.parametrize(
    ("arg", "key", "value"),
    [("host_ip:=bogus", "host_ip", "bogus"), ("lidar_top_ip:=999.1.1.1", "lidar_ips", "999.1.1.1")],
)
def test_a_dry_run_refuses_an_address_that_is_no_ipv4(
    capsys: pytest.CaptureFixture[str], arg: str, key: str, value: str
) -> None:
    """Sweep 5: `launch --dry-run host_ip:=bogus` printed the nodes, exit 0 (`capture --host-ip bogus`
    refused it)."""
    launch = ROOT / "sensorbox" / "share" / "launch" / "sensorbox.launch.yaml"
    code, out, err = sensorbox(capsys, "launch", str(launch), "--dry-run", arg)
    assert (code, out, err) == (
        2,
        "",
        [
            f"error: node 'livox_lidar_publisher' (livox_ros_driver2/livox_ros_driver2_node) at {launch}:25: "
            f"parameter '{key}' = '{value}': expected a dotted IPv4 address such as 192.168.1.5"
        ],
    )


def test_a_dry_run_writes_no_rig(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The simulated camera's `write_rig` is written when the node starts, not when the dry run builds it."""
    sim = ROOT / "sensorbox" / "share" / "launch" / "sim.launch.yaml"
    code, out, err = sensorbox(capsys, "launch", str(sim), f"out:={tmp_path / 'bags'}", "--dry-run")
    assert (code, err) == (0, []) and f"param write_rig = '{tmp_path / 'bags'}/rig.yaml'" in out
    assert list(tmp_path.iterdir()) == []


def test_a_camchain_with_one_rostopic_twice_is_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Both cameras on one rostopic in the camchain (the rig giving no topic): the error named rig.yaml's
    cameras.cam0.topic, a key the rig file does not hold."""
    doc = yaml.safe_load((TRUTH / "rig.yaml").read_text())
    rig = _rig(tmp_path, {"cameras": {n: {"role": c["role"]} for n, c in doc["cameras"].items()}})
    chain = tmp_path / "camchain.yaml"
    upper, lower = "/zed_upper/zed_node/rgb/color/rect/image", "/zed_lower/zed_node/rgb/color/rect/image"
    chain.write_text(chain.read_text().replace(lower, upper))
    for path in (rig, chain):  # the rig, and the camchain given as a rig on its own
        code, stdout, err = sensorbox(capsys, "calib", "check", str(path))
        assert (code, stdout, err) == (
            2,
            "",
            [
                f"error: {chain}: cam0.rostopic and cam1.rostopic are both {upper}: each sensor needs its own topic"
            ],
        )
    cameras = {n: {"role": c["role"]} for n, c in doc["cameras"].items()}
    cameras["cam1"]["topic"] = upper  # one topic from each file
    rig = _rig(tmp_path, {"cameras": cameras})
    chain.write_text(chain.read_text().replace(lower, upper))
    code, _, err = sensorbox(capsys, "calib", "check", str(rig))
    assert (code, err) == (
        2,
        [
            f"error: {chain}: cam0.rostopic and {rig}: cameras.cam1.topic are both {upper}: each sensor needs "
            "its own topic"
        ],
    )


def test_a_double_sphere_xi_of_minus_1_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Sweep 3: xi = -1 passed calib check (VFOV 0.0 deg); ingest then ended in a ValueError traceback
    (default_height_full: the camera does not see along its optical axis)."""
    chain = _camchain_with(tmp_path, "intrinsics: [-0.18153,", "intrinsics: [-1.0,")
    line = (
        f"error: {chain}: cam0: DoubleSphere: xi must be in (-1, 1], got -1.0 (at -1 the optical axis has no "
        "image, beyond 1 the valid image circle shrinks to a few pixels; a fitted fisheye's xi is about -0.3..0.3)"
    )
    out = tmp_path / "out"
    for command in (
        ["calib", "check", str(chain)],
        ["ingest", str(INDOOR), "--rig", str(chain), "--out", str(out), "--workers", "1", "--no-preview"],
    ):
        code, _, err = sensorbox(capsys, *command)
        assert (code, err) == (2, [line]), command
    assert not out.exists()


def test_a_camera_topic_of_null_is_named_by_ingest(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Sweep 3: `topic: null` passed calib check; ingest then said 'no topic None for the lower camera
    (from the rig)', naming neither the rig file nor its key."""
    upper = "/zed_upper/zed_node/rgb/color/rect/image"
    rig = _rig(
        tmp_path,
        {"cameras": {"cam0": {"role": "upper", "topic": upper}, "cam1": {"role": "lower", "topic": None}}},
    )
    out = tmp_path / "out"
    code, _, err = sensorbox(
        capsys, "ingest", str(INDOOR), "--rig", str(rig), "--out", str(out), "--workers", "1"
    )
    assert (code, err) == (
        2,
        [
            f"error: {rig}: cameras.cam1.topic: the lower camera has no topic (null in the rig file and no "
            "rostopic in the camchain); expected the topic of its images in the bag"
        ],
    )
    assert not out.exists()


def test_pixels_ten_times_taller_than_wide_are_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Sweep 3: fv = 10 fu passed calib check (VFOV 11.3 deg) and ingest wrote its 5 samples, exit 0, with
    the LiDAR points 0.70 deg off the images (0.03 deg with the right fv) and the GT density 2.49 % (10.43 %)."""
    chain = _camchain_with(tmp_path, "125.05785, 125.017325", "125.05785, 1250.17325")
    line = (
        f"error: {chain}: cam0: DoubleSphere: fx / fy = 0.1 (fx 125.05785, fy 1250.17325): expected 0.5..2, "
        "as a camera's pixels are square within a few per cent (fx or fy mistyped?)"
    )
    out = tmp_path / "out"
    for command in (
        ["calib", "check", str(chain)],
        ["ingest", str(INDOOR), "--rig", str(chain), "--out", str(out), "--workers", "1", "--no-preview"],
    ):
        code, _, err = sensorbox(capsys, *command)
        assert (code, err) == (2, [line]), command
    assert not out.exists()


def test_a_rig_version_of_true_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Sweep 3: `sensorbox_rig: true` passed calib check and ingest as version 1 (True == 1 in Python)."""
    rig = _rig(tmp_path, {"sensorbox_rig": True})
    code, _, err = sensorbox(capsys, "calib", "check", str(rig))
    assert (code, err) == (
        2,
        [
            f"error: {rig}: sensorbox_rig: expected version 1 (or a Kalibr camchain with cam0, cam1, ...), got True"
        ],
    )


def test_a_rig_name_that_is_no_string_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Sweep 3: `name: !!binary aGVsbG8=` passed calib check as the rig "b'hello'"."""
    rig = _rig(tmp_path)
    rig.write_text(rig.read_text().replace("name: sensorbox-reference", "name: !!binary aGVsbG8="))
    code, _, err = sensorbox(capsys, "calib", "check", str(rig))
    assert (code, err) == (2, [f"error: {rig}: name: expected a string, got b'hello'"])


def test_a_first_camera_with_a_pose_to_a_camera_before_it_is_warned_about(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Sweep 3: cam0's T_cn_cnm1 was dropped without a word (the chain's origin has no camera before it)."""
    chain = _camchain_with(
        tmp_path,
        "  rostopic: /zed_upper/zed_node/rgb/color/rect/image\n",
        "  rostopic: /zed_upper/zed_node/rgb/color/rect/image\n"
        "  T_cn_cnm1: [[1, 0, 0, 0.1], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]\n",
    )
    read_kalibr_camchain(chain)
    assert [r.getMessage() for r in caplog.records if "T_cn_cnm1" in r.getMessage()] == [
        f"{chain}: cam0.T_cn_cnm1 ignored: the first camera of a chain is its origin, with no camera before it "
        "(Kalibr writes none for it; cameras in another order?)"
    ]


def test_a_timeshift_that_pairs_no_frame_is_named(tmp_path: Path) -> None:
    """Sweep 8: cam1's `timeshift_cam_imu: 0.999` (inside the +-1 s limit) left no lower frame within half a
    frame of an upper one: 0 samples written, exit 0, and only '21 / 0 / 0' in the summary."""
    from ingest.train.run.pipeline import ingest
    from ingest.train.run.settings import IngestConfig

    rig = _rig(tmp_path)
    chain = tmp_path / "camchain.yaml"
    topic = "  rostopic: /zed_lower/zed_node/rgb/color/rect/image\n"
    chain.write_text(chain.read_text().replace(topic, f"{topic}  timeshift_cam_imu: 0.999\n"))
    summary = ingest([INDOOR], IngestConfig(rig=rig, out=tmp_path / "ds", workers=1, height_full=64))
    assert (summary.frames, summary.pairs, summary.written) == (21, 0, 0)
    assert (
        "no upper frame has a lower frame within 16.7 ms of its exposure (of 21 upper and 21 lower frames; the "
        "nearest lie +665.7 ms apart, median): nothing can be written; check the camchain's timeshift_cam_imu of "
        "each camera and that both topics are the same recording's"
    ) in summary.warnings
