"""The command line as a user runs it: exit codes, output, files."""

import subprocess
import sys
from pathlib import Path

import cv2
import pytest

from tests.faults.cli import run_here

ROOT = Path(__file__).resolve().parents[2]
REF = ROOT / "calibration" / "sensorbox.yaml"


def test_calib_check_reference_rig(tmp_path, capsys):
    png = tmp_path / "rig.png"
    res = run_here(capsys, "calib", "check", str(REF), "--plot", str(png))
    assert res.returncode == 0, res.stderr
    assert "181.7°" in res.stdout and "182.1°" in res.stdout  # true HFOV of cam0 / cam1
    assert "120.31 mm" in res.stdout
    for name in ("lidar_top", "lidar_bottom", "imu_top", "/livox/lidar_192_168_1_13"):
        assert name in res.stdout
    img = cv2.imread(str(png))
    assert img is not None and img.shape[0] > 400 and img.shape[1] > 800


def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("cam0:\n  camera_model: fancy\n")
    res = run_here(capsys, "calib", "check", str(bad))
    assert res.returncode == 2
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith("error: ") and "bad.yaml: cam0: missing key" in lines[0]
    assert "Traceback" not in res.stderr


def test_help_texts(capsys):
    for args in ([], ["calib"], ["calib", "check"]):
        res = run_here(capsys, *args, "--help")
        assert res.returncode == 0 and "Usage" in res.stdout


def test_errors_print_brackets_as_they_are(tmp_path, capsys):
    """A path with [v2] in it is named as it is, not eaten as markup (issue 20, class 5)."""
    rig = tmp_path / "rig[v2].yaml"
    rig.write_text("cameras: [/b]\n")
    res = run_here(capsys, "calib", "check", str(rig))
    assert res.returncode == 2, res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "rig[v2].yaml" in lines[0], res.stderr


def test_os_errors_on_the_output_side_are_one_line_and_exit_3(tmp_path, capsys):
    res = run_here(capsys, "calib", "check", str(REF), "--plot", "/proc/sensorbox-nothere/rig.png")
    assert res.returncode == 3, res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert lines == ["error: /proc/sensorbox-nothere: No such file or directory"], res.stderr


def test_the_cli_gives_numpys_blas_one_thread_unless_the_user_chose():
    import os

    code = "import sensorbox.cli.main, os; print(os.environ['OPENBLAS_NUM_THREADS'])"
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    for given, expected in ((None, "1"), ("3", "3")):
        run_env = env if given is None else {**env, "OPENBLAS_NUM_THREADS": given}
        out = subprocess.run(
            [sys.executable, "-c", code], env=run_env, capture_output=True, text=True, check=True
        )
        assert out.stdout.strip() == expected


def test_segment_s_sets_the_trajectory_passs_segments(tmp_path, capsys, monkeypatch):
    """`--segment-s` reaches the run's `trajectory_segments` (inf: one pass, whatever the recording's
    length); a length under three overlaps less half a second, or NaN, is one line and exit 2."""
    import ingest.train.run.pipeline as pipeline
    from ingest.errors import DatasetError
    from ingest.train.trajectory.segments import ONE_PASS_NS, SegmentParams, plan_segments

    asked = []

    def captured(bags, cfg, **kwargs):
        asked.append(cfg.trajectory_segments)
        raise DatasetError("stopped before reading")

    monkeypatch.setattr(pipeline, "ingest", captured)
    args = ("ingest", str(tmp_path / "no.bag"), "--rig", str(REF), "--out", str(tmp_path / "out"))
    for value in ("10", "12.5", "inf"):
        res = run_here(capsys, *args, "--segment-s", value)
        assert res.returncode == 2 and res.stderr.strip() == "error: stopped before reading"
    assert asked == [
        SegmentParams(),
        SegmentParams(length_ns=12_500_000_000, overlap_ns=3_000_000_000),
        SegmentParams(length_ns=ONE_PASS_NS, overlap_ns=3_000_000_000),
    ]
    day_ns = 86_400_000_000_000
    assert plan_segments((0, day_ns), asked[2], 50_000_000) == [(0, day_ns)]
    assert len(plan_segments((0, day_ns), asked[1], 50_000_000)) > 1
    for value in ("8", "nan", "-inf"):
        res = run_here(capsys, *args, "--segment-s", value)
        assert res.returncode == 2 and res.stderr.strip() == (
            f"error: --segment-s {float(value):g}: expected at least 8.5 s (three times the segments' 3 s "
            "overlap less half a second: consecutive joins apart), or inf for one pass"
        )
    assert len(asked) == 3


def test_ingest_backend_is_checked_before_any_bag_is_read(tmp_path, capsys):
    """`--backend` (the dense-GT renderer): an unknown one, or cuda without a GPU, is one line, exit 2 (run in
    this process: each option's check is the CLI's own, and a subprocess per case imported torch anew)."""

    out = tmp_path / "out"
    args = ("ingest", str(tmp_path / "no.bag"), "--rig", str(REF), "--out", str(out), "--gt", "dense")
    res = run_here(capsys, *args, "--backend", "gpu")
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode == 2 and len(lines) == 1, res.stderr
    assert lines[0] == "error: --backend 'gpu': expected numba, numpy, torch or cuda"
    for option, value, line in (
        ("--window-ms", "nan", "error: --window-ms must be a finite number, got nan"),
        ("--gt-window-ms", "inf", "error: --gt-window-ms must be a finite number, got inf"),
        ("--window-ms", "-5", "error: --window-ms -5: expected > 0"),
        ("--motion", "off", "error: --motion 'off': expected full with --gt 'dense', which places every point "
         "with the trajectory (--motion chooses the motion model of sparse GT: --gt sparse or auto)"),
    ):  # fmt: skip
        res = run_here(capsys, *args, option, value)
        assert res.returncode == 2 and [ln for ln in res.stderr.splitlines() if ln.strip()] == [line], (
            res.stderr
        )
    sparse = [a if a != "dense" else "sparse" for a in args]
    res = run_here(
        capsys, *sparse, "--gt-window-ms", "300"
    )  # dense GT's window, given for sparse GT: not silently ignored
    assert res.returncode == 2 and res.stderr.strip() == (
        "error: --gt-window-ms sets the window of dense GT (--gt dense or auto); sparse GT's is --window-ms"
    )
    auto = [a if a != "dense" else "auto" for a in args]
    res = run_here(
        capsys, *auto, "--gt-window-ms", "40", "--window-ms", "80"
    )  # the gaps' sparse GT reads within it
    assert res.returncode == 2 and " ".join(res.stderr.split()) == (
        "error: --gt-window-ms 40: expected at least --window-ms with --gt 'auto': the sparse GT it gives "
        "frames in trajectory gaps reads --window-ms of points from the dense window"
    )
    try:
        import torch
    except ImportError:
        return
    if not torch.cuda.is_available():
        res = run_here(capsys, *args, "--backend", "cuda")
        assert (
            res.returncode == 2
            and "--backend 'cuda': expected a renderer this machine runs (torch" in res.stderr
        )
        assert "sees no CUDA GPU" in res.stderr and "Traceback" not in res.stderr
    assert not out.exists()


def test_library_log_records_become_warning_and_error_lines(capsys):
    import logging

    from sensorbox.cli.main import _WarningLines

    log = logging.getLogger("sensorbox.test.lines")
    log.propagate = False
    log.addHandler(_WarningLines(logging.WARNING))
    try:
        log.info("not shown")
        log.warning("disk at %d %%", 91)
        log.error("recorder stopped")
        try:
            raise OSError(28, "No space left on device")
        except OSError:
            log.exception("recorder writer failed")
    finally:
        log.handlers.clear()
    lines = capsys.readouterr().err.splitlines()
    assert lines == [
        "warning: disk at 91 %",
        "error: recorder stopped",
        "error: recorder writer failed: OSError: [Errno 28] No space left on device",
    ]


def test_ingest_chooses_its_ground_truth_itself_by_default(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """With no --gt, `sensorbox ingest` runs the trajectory pass and decides (`--gt auto`): the static
    indoor recording gets dense GT over +-1 s, and the decision is written to dataset.yaml and the meta."""
    import yaml

    from ingest.dataset.meta import read_meta
    from tests.faults.cli import sensorbox
    from tests.ingest.test_pipeline import INDOOR, _rig

    out = tmp_path / "ds"
    args = ["ingest", str(INDOOR), "--rig", str(_rig(INDOOR)), "--out", str(out), "--workers", "1"]
    code, _, err = sensorbox(capsys, *args, "--every", "10", "--height-full", "64", "--no-preview")
    assert code == 0, err
    gt = yaml.safe_load((out / "dataset.yaml").read_text())["sources"][0]["ground_truth"]
    assert gt["method"] == "dense" and gt["decision"].startswith("auto: ")
    assert "window +-1000 ms" in gt["decision"] and gt["trajectory"] is not None
    metas = [read_meta(out, p.stem) for p in sorted((out / "meta").glob("*.json"))]
    assert metas and all(m.gt.method == "dense" and m.gt.decision == gt["decision"] for m in metas)


CTRL_C_IN_IMPORT = """
import sys
class CtrlC:  # Ctrl-C while the command modules load
    def find_spec(self, name, path=None, target=None):
        if name == "sensorbox.cli.main":
            raise KeyboardInterrupt
sys.meta_path.insert(0, CtrlC())
from sensorbox.cli import run
run()
"""
CTRL_C_IN_COMMAND = """
import sys
import sensorbox.sim.run
def pressed(*args, **kwargs):
    raise KeyboardInterrupt
sensorbox.sim.run.simulate = pressed
from sensorbox.cli import run
run()
"""


@pytest.mark.parametrize("code", [CTRL_C_IN_IMPORT, CTRL_C_IN_COMMAND], ids=["start-up", "command"])
def test_ctrl_c_is_one_line_and_exit_130(tmp_path, code):
    """Ctrl-C while the CLI's modules load or while a command works: 'interrupted', exit code 130,
    no traceback (ingest says more: tests/sensorbox/test_cli_interrupt.py)."""
    args = ["simulate", "--out", str(tmp_path / "bag"), "--duration", "0.2"]
    res = subprocess.run(
        [sys.executable, "-c", code, *args], capture_output=True, text=True, cwd=ROOT, check=False
    )
    assert res.returncode == 130, res.stderr
    assert [ln for ln in res.stderr.splitlines() if ln.strip()] == ["interrupted"], res.stderr
    assert not (tmp_path / "bag").exists()
