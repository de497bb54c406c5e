"""`sensorbox eval` and `sensorbox stats` as a user runs them: tables, JSON, PNGs, errors."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from calibration.errors import SensorboxError
from sensorbox.cli.eval import eval_cmd, stats_cmd
from tests.faults.cli import run_here
from tests.ingest.test_evaluate import make_benchmark, write_predictions

ROOT = Path(__file__).resolve().parents[2]
app = typer.Typer(pretty_exceptions_enable=False, add_completion=False)
app.command("eval")(eval_cmd)
app.command("stats")(stats_cmd)


@app.callback()
def _root() -> None:
    """Test app."""


runner = CliRunner()


def test_eval_tables_compare_heatmap_and_json(tmp_path: Path) -> None:
    bench = make_benchmark(tmp_path / "bench")
    pred = tmp_path / "pred"
    files = write_predictions(bench, pred, "stereo")
    next(f for f in files if "002_010_000/195FOV/200mm" in f.as_posix()).unlink()
    png, js = tmp_path / "out" / "heat.png", tmp_path / "out" / "eval.json"
    args = [
        "eval",
        "--dataset",
        str(bench),
        "--pred",
        str(pred),
        "--task",
        "stereo",
        "--image-type",
        "pano_crop",
    ]
    res = runner.invoke(
        app,
        [*args, "--compare", "195FOV,120FOV", "--heatmap", str(png), "--json", str(js)],
        catch_exceptions=False,
    )
    assert res.exit_code == 0, res.output
    out = res.output
    assert "# stereo on" in out and "7 of 8 samples scored" in out
    assert "## region: all" in out and "## region: edges" in out
    # --compare 195FOV,... groups by fov; --heatmap adds baseline: one row per (FOV, baseline) cell
    assert "| 120FOV/65mm | 2 | 96 | 100.00 | 0.500 | 0.500 | 0.500 | 0.00 | 0.00 | 0.00 |" in out
    assert "| 195FOV/200mm | 1 | 48 | 100.00 | 4.000 |" in out
    assert (
        "Missing predictions: 1 of 8 (not scored):\n  002_010_000/195FOV/200mm/CENTER/disparity/pano_crop\n"
        in out
    )
    assert "## 195FOV vs 120FOV (region all; change = (A - B) / |B|)" in out
    assert "| 65mm | EPE [px] | 1.500 | 0.500 | +200.0 | B |" in out
    assert "| 200mm | EPE [px] | 4.000 | 0.250 | +1500.0 | B |" in out
    img = cv2.imread(str(png))
    assert img is not None and img.shape[0] > 200 and img.shape[1] > 300
    doc = json.loads(js.read_text())
    assert doc["options"]["by"] == ["fov", "baseline"] and doc["missing"] == [
        "002_010_000/195FOV/200mm/CENTER/disparity/pano_crop"
    ]
    assert [g["label"] for g in doc["groups"]] == [
        "120FOV/65mm",
        "120FOV/200mm",
        "195FOV/65mm",
        "195FOV/200mm",
    ]

    res = runner.invoke(app, [*args, "--by", "baseline", "--no-edges"], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    assert "| 65mm | 4 | 192 | 100.00 | 1.000 |" in res.output and "region: edges" not in res.output
    assert (pred / "eval_stereo.json").is_file()  # the default JSON place
    res = runner.invoke(app, [*args, "--no-edges", "--region", "edges"])
    assert isinstance(res.exception, SensorboxError)
    assert str(res.exception) == "--region 'edges': expected one of all"


def test_stats_writes_json_and_histograms(tmp_path: Path) -> None:
    bench = make_benchmark(tmp_path / "bench")
    out = tmp_path / "stats"
    res = runner.invoke(app, ["stats", str(bench), "--out", str(out), "--image-type", "pano_crop"])
    assert res.exit_code == 0, res.output
    assert "8 depth maps" in res.output and "| depth | 0-1 m | 1-2 m | 2-5 m | 5-10 m | 10+ m |" in res.output
    assert "| 80.000 |" in res.output  # 48 of 60 pixels valid in every map
    doc = json.loads((out / "stats.json").read_text())
    assert sum(doc["depth_counts"]) == 8 * 48 and len(doc["samples"]) == 8
    assert doc["density_mean"] == 0.8
    img = cv2.imread(str(out / "stats.png"))
    assert img is not None and img.shape[1] > 1000


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "sensorbox.cli", *args], capture_output=True, text=True, cwd=ROOT, check=False
    )


def test_errors_are_one_line_and_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bench = make_benchmark(tmp_path / "bench")
    pred = tmp_path / "pred"
    files = write_predictions(bench, pred, "stereo")
    npy = next(p for p in files if p.suffix == ".npy")
    np.save(npy, np.zeros((3, 3)))
    res = run_here(capsys, "eval", "--dataset", str(bench), "--pred", str(pred), "--task", "stereo")
    assert res.returncode == 2, res.stdout + res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), res.stderr
    assert f"{npy}: prediction shape (3, 3) but the GT" in lines[0] and "is (6, 10)" in lines[0]
    res = run_here(capsys, "eval", "--dataset", str(bench), "--pred", str(pred), "--task", "depth")
    assert res.returncode == 2 and "--task 'depth': expected one of stereo, mono, completion" in res.stderr
    npy.write_bytes(b"")  # an empty prediction file printed only "Aborted!" (issue 20, class 10)
    res = run_here(capsys, "eval", "--dataset", str(bench), "--pred", str(pred), "--task", "stereo")
    assert res.returncode == 2 and f"error: {npy}: cannot read the .npy file" in res.stderr, res.stderr
    empty = tmp_path / "empty"  # a prediction folder that matches nothing (wrong level, say)
    empty.mkdir()
    res = run_here(capsys, "eval", "--dataset", str(bench), "--pred", str(empty), "--task", "stereo")
    assert res.returncode == 2 and f"error: {empty}: no prediction for any of the 16 GT samples" in res.stderr
    assert (
        "(the prediction folder mirrors the dataset's)" in res.stderr
        and not (empty / "eval_stereo.json").exists()
    )
    gt = sorted(bench.rglob("depth/*.png"))[0]
    gt.write_bytes(gt.read_bytes()[:60])  # a GT PNG cut short
    res = run_here(capsys, "stats", str(bench))
    assert res.returncode == 2, res.stdout + res.stderr
    assert f"error: {gt}: cannot be decoded (60 bytes: empty, cut short or not an image)" in res.stderr
    for cmd in ("eval", "stats"):
        res = run_here(capsys, cmd, "--help")
        assert res.returncode == 0 and "Usage" in res.stdout
