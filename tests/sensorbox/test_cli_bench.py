"""`sensorbox bench --quick` on a fixture bag: tables, CSVs, charts, errors."""

from __future__ import annotations

import csv
from pathlib import Path

import cv2
import typer
from typer.testing import CliRunner

from calibration.errors import SensorboxError
from sensorbox.analysis.tradeoff import QUICK
from sensorbox.cli.bench import bench_cmd
from sensorbox.cli.main import app as main_app
from tests.paths import FIXTURES_DIR

app = typer.Typer(pretty_exceptions_enable=False, add_completion=False)
app.command("bench")(bench_cmd)


@app.callback()
def _root() -> None:
    """Test app."""


runner = CliRunner()
BAG = FIXTURES_DIR / "indoor_static_mcap"


def test_quick_bench_on_a_fixture_bag(tmp_path: Path) -> None:
    out = tmp_path / "bench"
    res = runner.invoke(app, ["bench", "--bag", str(BAG), "--quick", "--every", "7", "--out", str(out)])
    assert res.exit_code == 0, res.output
    text = res.output
    assert "| alternative | samples | samples/s | x default |" in text
    assert "| default | 3 |" in text and "| occlusion filter off | 3 |" in text
    assert "| equirect |" in text and "| cubemap |" in text and "| cubemap, padded faces |" in text
    rows = list(csv.DictReader((out / "bench_tradeoff.csv").open()))
    assert [r["alternative"] for r in rows] == [*QUICK, *QUICK]  # per bag, then pooled
    assert [r["bag"] for r in rows] == ["indoor_static_mcap"] * len(QUICK) + ["all"] * len(QUICK)
    by_name = {r["alternative"]: r for r in rows if r["bag"] == "all"}
    # on a static bag only the occlusion filter changes the depth GT
    for name in ("motion compensation off", "equirect 0.5x", "PNG level 0"):
        assert by_name[name]["depth_median_mm"] == by_name["default"]["depth_median_mm"]
    assert float(by_name["occlusion filter off"]["depth_outlier_pct"]) > float(
        by_name["default"]["depth_outlier_pct"]
    )
    assert float(by_name["PNG level 0"]["kb_per_sample"]) > float(by_name["default"]["kb_per_sample"])
    projections = list(csv.DictReader((out / "bench_projection.csv").open()))
    assert [p["projection"] for p in projections] == ["equirect", "cubemap", "cubemap, padded faces"]
    for name in ("bench_tradeoff.png", "bench_projection.png"):
        image = cv2.imread(str(out / name))
        assert image is not None and image.shape[0] > 300


def test_bench_errors_are_sensorbox_errors(tmp_path: Path) -> None:
    res = runner.invoke(app, ["bench", "--bag", str(BAG), "--only", "fastest", "--out", str(tmp_path)])
    assert isinstance(res.exception, SensorboxError) and "no alternative 'fastest'" in str(res.exception)
    lonely = tmp_path / "no_truth.mcap"
    lonely.write_bytes(b"")
    res = runner.invoke(app, ["bench", "--bag", str(lonely), "--out", str(tmp_path)])
    assert isinstance(res.exception, SensorboxError) and "no simulator truth" in str(res.exception)
    res = runner.invoke(app, ["bench", "--repeats", "0", "--out", str(tmp_path)])
    assert isinstance(res.exception, SensorboxError) and "--repeats" in str(res.exception)


def test_bench_is_registered_in_the_main_cli() -> None:
    res = runner.invoke(main_app, ["bench", "--help"])
    assert res.exit_code == 0 and "Speed vs accuracy" in res.output and "--quick" in res.output
