"""sensorbox.analysis.tradeoff: Pareto front, alternatives as data, the runner on a fixture bag, equirect vs cubemap SGBM."""

from __future__ import annotations

import csv
import io
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import cv2
import numpy as np
import pytest
import yaml

from calibration.pinhole import Pinhole
from calibration.rectify import rectify_rig
from calibration.stereo import depth_to_disparity
from calibration.warp import covering_crop, default_height_full
from ingest.dataset.meta import read_meta
from ingest.train.run.settings import IngestConfig
from sensorbox.analysis.projection import Sgbm, compare_projections, num_disparities_for
from sensorbox.analysis.tradeoff import (
    ALTERNATIVES,
    QUICK,
    Alternative,
    Measurement,
    csv_bytes,
    pareto_front,
    pool,
    run_alternatives,
    select,
)
from sensorbox.sim.score import _edge_band, score_dataset
from sensorbox.sim.truth import Truth, truth_dir
from tests.paths import FIXTURES_DIR

BAG = FIXTURES_DIR / "indoor_static_mcap"
RIG = truth_dir(BAG) / "rig.yaml"


def test_pareto_front_by_hand() -> None:
    speed = [1.0, 2.0, 3.0, 2.0, float("nan"), 2.0]
    error = [1.0, 2.0, 3.0, 1.0, 0.0, 1.0]
    # A(1,1) and B(2,2) lose to D(2,1); C is the fastest; D and its twin F tie; E has no speed
    assert pareto_front(speed, error).tolist() == [False, False, True, True, False, True]
    with pytest.raises(ValueError, match="equal 1-D"):
        pareto_front([1.0, 2.0], [1.0])


def test_pareto_front_against_brute_force() -> None:
    rng = np.random.default_rng(5)
    s, e = rng.uniform(0, 10, 200).round(1), rng.uniform(0, 10, 200).round(1)
    front = pareto_front(s, e)
    for i in range(len(s)):
        beaten = [(s[j] >= s[i] and e[j] <= e[i] and (s[j] > s[i] or e[j] < e[i])) for j in range(len(s))]
        assert front[i] == (not any(beaten))
    # the front is a staircase: sorted by speed, the error rises strictly
    order = np.argsort(s[front])
    assert np.all(np.diff(e[front][order]) >= 0)


def test_alternatives_apply_their_changes() -> None:
    base = IngestConfig(rig=RIG, out=Path("x"), workers=1)
    by_name = {a.name: a for a in ALTERNATIVES}
    assert len(by_name) == len(ALTERNATIVES) and {a.name for a in select(QUICK)} <= set(by_name)
    off = by_name["occlusion filter off"].apply(base)
    assert off.sample.gt.occlusion is False and off.sample.gt.window_rad == base.sample.gt.window_rad
    flip = by_name["z-buffer order flipped"].apply(base)
    assert flip.sample.gt.zbuffer == "farthest"
    assert by_name["motion: rotation only"].apply(base).sample.motion == "rotation"
    assert by_name["PNG level 3"].apply(base).sample.png_level == 3
    assert by_name["interpolation cubic"].apply(base).sample.interpolation == "cubic"
    from calibration.rig import read_rig

    h = default_height_full(read_rig(RIG).upper.model)
    assert h == 512
    assert by_name["equirect 0.5x"].apply(base).height_full == 256
    assert by_name["equirect 2x"].apply(base).height_full == 1024
    assert by_name["default"].apply(base) == base
    assert by_name["occlusion window 2x"].describe() == "gt.window_rad=0.036, gt.window_spacings=4.0"
    with pytest.raises(KeyError, match="no alternative 'fast'"):
        select(["default", "fast"])


def test_scaled_equirect_height_rounds_to_the_nearest_multiple_of_64() -> None:
    """height_full x scale goes to the nearest multiple of 64, at least 64: 1000 x 0.5 = 500 -> 512 (not
    448), 1000 x 2 = 2000 -> 1984, 100 x 0.5 = 50 -> 64."""
    half, double = Alternative("h", "r", height_scale=0.5), Alternative("d", "r", height_scale=2.0)
    base = IngestConfig(rig=RIG, out=Path("x"), workers=1, height_full=1000)
    assert (half.apply(base).height_full, double.apply(base).height_full) == (512, 1984)
    assert half.apply(replace(base, height_full=100)).height_full == 64


def test_csv_has_every_column_of_any_row() -> None:
    text = csv_bytes([{"a": 1, "b": 0.5}, {"a": 2, "c": "x"}]).decode()
    rows = list(csv.DictReader(io.StringIO(text)))
    assert rows == [{"a": "1", "b": "0.5", "c": ""}, {"a": "2", "b": "", "c": "x"}]


def _m(name: str, ms: tuple[float, ...], wall: float = 1.0) -> Measurement:
    n = len(ms)
    return Measurement(name, "f", "bag", ms, {"a": ms, "b": tuple(0.0 for _ in ms)}, (0.001,) * n, (100,) * n,
                       (1.0,) * n, (0.01,) * n, (50,) * n, (0.5,) * n, 1000, wall)  # fmt: skip


def test_repeats_take_each_samples_median_and_pooling_concatenates() -> None:
    m = _m("x", (10.0, 20.0, 30.0)).with_repeats(
        [_m("x", (12.0, 10.0, 90.0), 3.0), _m("x", (11.0, 40.0, 30.0), 2.0)]
    )
    assert m.sample_ms == (11.0, 20.0, 30.0) and m.stage_ms["a"] == (11.0, 20.0, 30.0) and m.wall_s == 2.0
    row = m.row()
    assert row["ms_per_sample"] == 20.0 and row["samples_per_s"] == 50.0
    assert row["depth_median_mm"] == pytest.approx(1.0) and row["depth_outlier_pct"] == pytest.approx(1.0)
    assert row["disp_over_1px_pct"] == pytest.approx(1.0) and row["kb_per_sample"] == pytest.approx(
        1000 / 3 / 1024
    )
    both = pool([_m("x", (1.0,)), _m("y", (5.0,)), _m("x", (3.0, 4.0))])
    assert [(p.alternative, p.sample_ms, p.bag) for p in both] == [
        ("x", (1.0, 3.0, 4.0), "all"),
        ("y", (5.0,), "all"),
    ]
    assert both[0].stage_ms["a"] == (1.0, 3.0, 4.0)
    # pooled over bags, the median error is the mean of the bags' medians: a static bag's many
    # samples must not hide a walk's larger error
    a = replace(_m("x", (1.0,)), depth_median_m=(0.001,))
    b = replace(_m("x", (2.0, 3.0)), depth_median_m=(0.010, 0.020))
    row = pool([a, b])[0].row()
    assert row["depth_median_mm"] == pytest.approx((1.0 + 15.0) / 2) and row["ms_per_sample"] == 1.75


def test_each_bag_and_alternative_takes_the_median_of_its_own_rounds(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two alternatives on two bags, three rounds: each (alternative, bag) pair's time is the median of
    its own three rounds (100 a + 10 b + round, so 100 a + 10 b + 1), never another pair's."""

    def fake_measure(bag: Path, cfg: Any, alt: Any, score: Any, keep: bool = False) -> Measurement:
        rep, a, b = (int(x) for x in cfg.name.split("_")[:3])
        return replace(_m(alt.name, (100.0 * a + 10.0 * b + rep,)), bag=bag.name)

    monkeypatch.setattr("sensorbox.analysis.tradeoff.measure", fake_measure)
    bags = [(Path("b0"), RIG), (Path("b1"), RIG)]
    alts = select(["default", "occlusion filter off"])
    got = run_alternatives(bags, alts, tmp_path, lambda bag, ds: [], base=lambda rig, out: out, repeats=3)  # type: ignore[arg-type,return-value]
    assert [(m.alternative, m.bag, m.sample_ms) for m in got] == [
        ("default", "b0", (1.0,)), ("default", "b1", (11.0,)),
        ("occlusion filter off", "b0", (101.0,)), ("occlusion filter off", "b1", (111.0,)),
    ]  # fmt: skip


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> list[Measurement]:
    """Default and occlusion-off on the indoor fixture, every 7th frame, two timing rounds."""
    work = tmp_path_factory.mktemp("tradeoff")
    truth = Truth.load(BAG)
    return run_alternatives(
        [(BAG, RIG)], select(["default", "occlusion filter off"]), work,
        lambda bag, ds: score_dataset(ds, truth),
        base=lambda rig, out: IngestConfig(rig=rig, out=out, workers=1, every=7), repeats=2,
    )  # fmt: skip


@pytest.mark.xdist_group("tradeoff_runs")  # one worker measures the runs once
def test_runner_measures_and_scores_each_alternative(runs: list[Measurement]) -> None:
    default, off = runs
    assert (default.alternative, off.alternative) == ("default", "occlusion filter off")
    assert default.samples == off.samples == 3 and len(default.depth_pixels) == 3
    assert all(ms > 0 for ms in default.sample_ms) and set(default.stage_ms) >= {"clouds", "ground_truth"}
    d, o = default.row(), off.row()
    assert d["depth_median_mm"] < 2.0 and d["depth_outlier_pct"] < 0.5  # the pipeline's targets
    assert o["depth_outlier_pct"] > 2 * d["depth_outlier_pct"]  # parallax bleed without the filter
    assert default.out is not None and (default.out / "dataset.yaml").exists()  # kept for the projections
    assert off.out is None and not any(
        p.name.endswith("occlusion_filter_off") for p in default.out.parent.iterdir()
    )
    assert d["kb_per_sample"] > 100


def test_sgbm_finds_a_vertical_shift() -> None:
    rng = np.random.default_rng(1)
    upper = cv2.resize(rng.uniform(0, 255, (60, 80)), (320, 240), interpolation=cv2.INTER_CUBIC)
    upper = np.clip(upper, 0, 255).astype(np.uint8)
    lower = np.roll(upper, -7, axis=0)  # a point at row v of the upper image is at row v - 7 below
    disp = Sgbm(32).compute(upper, lower)
    assert np.nanmedian(disp[40:-10, 10:-10]) == pytest.approx(7.0, abs=0.1)
    assert np.isnan(disp[:20]).all()  # the search range does not fit above the first rows
    assert num_disparities_for(512 / np.pi, 0.12, 0.5) == 48


@pytest.mark.xdist_group("tradeoff_runs")  # one worker measures the runs once
def test_equirect_vs_cubemap_on_a_fixture_sample(runs: list[Measurement]) -> None:
    out = runs[0].out
    assert out is not None
    sid = "000001"
    stamp = read_meta(out, sid).stamp_ns
    upper = cv2.imread(str(out / "left_fisheye" / f"{sid}.png"))
    lower = cv2.imread(str(out / "right_fisheye" / f"{sid}.png"))
    assert upper is not None and lower is not None
    height = int(yaml.safe_load((out / "dataset.yaml").read_text())["height_full"])
    truth = Truth.load(BAG)
    eq, cube, padded = compare_projections(
        upper, lower, truth.rig, height, lambda r: truth.range_along(r, stamp)
    )
    assert (eq.name, cube.name, padded.name) == ("equirect", "cubemap", "cubemap, padded faces")
    for res in (eq, cube, padded):
        assert res.stereo.n > 20_000 and res.stereo.epe_px < 1.0 and res.depth.abs_rel < 0.15
        assert res.depth_common.n == eq.depth_common.n > 50_000  # the same fisheye pixels for all three
    # up/down faces are no vertical stereo pairs: the cubemap leaves part of the fisheye uncovered
    assert eq.depth.coverage > padded.depth.coverage > cube.depth.coverage + 0.05
    # the seams: SGBM has no match where the mask says so, and padding the faces removes them
    s, gt, disp = cube.maps["stable"], cube.maps["gt"], cube.maps["disp"]
    gt_ok, matched = np.isfinite(gt), np.isfinite(disp)
    reach = num_disparities_for(height / np.pi, truth.rig.baseline_m())
    top = np.broadcast_to(np.arange(gt.shape[0])[:, None] < reach, gt.shape)
    assert not (s & top).any() and not matched[top].any()  # the search range leaves the face at its top
    assert matched[gt_ok & s].mean() > 0.9
    with np.errstate(invalid="ignore"):
        bad = np.abs(disp - gt) > 1.0
    assert bad[gt_ok & ~s & matched].mean() > 2 * bad[gt_ok & s & matched].mean()  # block margins
    assert (
        cube.stereo_stable.n_gt < 0.9 * cube.stereo.n_gt
        and padded.stereo_stable.n_gt > 0.95 * padded.stereo.n_gt
    )
    # both GT disparities come from the exact range: along rectified +z (centre of the front face,
    # the equator of the equirect) they agree, as the face's focal length is the equirect's px/rad
    rect = rectify_rig(truth.rig)
    crop = covering_crop(truth.rig.upper.model, rect.R_cam0_rect, height)
    (u, v), _ = crop.project(np.array([0.0, 0.0, 1.0]))
    F = cube.maps["gt"].shape[0]
    on_eq = eq.maps["gt"][round(v), round(u)]
    on_face = cube.maps["gt"][F // 2, F // 2]
    r = float(truth.range_along(np.array([[0.0, 0.0, 1.0]]) @ rect.R_cam0_rect.T, stamp)[0])
    assert on_eq == pytest.approx(float(depth_to_disparity(r, np.pi / 2, rect.baseline_m, height)), rel=0.02)
    assert on_face == pytest.approx(on_eq, rel=0.02)


def test_edge_band_reaches_band_px_either_side_of_a_depth_step() -> None:
    """The edge band is every pixel within `band_px` (a (2 band_px + 1)^2 square) of a range step: a
    1 m | 2 m wall at columns 9 | 10 of a 20 px image marks columns 9 and 10 (the 3x3 step), and
    band_px = 3 widens that to columns 6..13."""
    model = Pinhole(10.0, 10.0, 9.5, 9.5, 20, 20)

    def range_at(m: Pinhole, pixels: np.ndarray, stamp_ns: int) -> np.ndarray:
        return np.where(pixels[:, 0] < 10, 1.0, 2.0)

    truth: Any = SimpleNamespace(rig=SimpleNamespace(upper=SimpleNamespace(model=model)), range_at=range_at)
    band = _edge_band(truth, 0, band_px=3)
    assert band.shape == (20, 20) and (band == band[:1]).all()  # the same in every row
    assert np.flatnonzero(band[0]).tolist() == list(range(6, 14))
