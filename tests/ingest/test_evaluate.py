"""`ingest.eval.evaluate` on a synthetic benchmark tree (exact expected numbers) and on a real ingested dataset."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from calibration.stereo import rotate_for_stereo, unrotate_from_stereo
from ingest.dataset.layout import encode_exr
from ingest.errors import EvalError
from ingest.eval.evaluate import EvalOptions, discover_gt, evaluate, write_report_json
from ingest.eval.report import compare, heatmap, markdown_compare, markdown_table
from ingest.eval.request import eval_request
from ingest.train.run.pipeline import ingest
from ingest.train.run.sample_job import SampleParams
from ingest.train.run.settings import IngestConfig
from sensorbox.sim.truth import truth_dir
from tests.paths import FIXTURES_DIR

SCENES = ("001_057_000", "002_010_000")
FOVS = (120, 195)
BASELINES = (65, 200)
SHAPE = (6, 10)
# disparity error (px) of the synthetic predictions per (FOV, baseline): multiples of 0.01 (exact in PNG)
STEREO_ERR = {(120, 65): 0.5, (120, 200): 0.25, (195, 65): 1.5, (195, 200): 4.0}
DEPTH_FACTOR = {(120, 65): 1.1, (120, 200): 1.0, (195, 65): 1.3, (195, 200): 2.0}  # pred = factor * gt


def imread(path: Path, flags: int = cv2.IMREAD_COLOR) -> np.ndarray:
    """cv2.imread that fails loudly."""
    image = cv2.imread(str(path), flags)
    assert image is not None, path
    return np.asarray(image)


def _gt_maps(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Disparity (px x 100) and depth (mm) uint16 maps, the same 12 pixels invalid in both."""
    rng = np.random.default_rng(seed)
    disp = rng.integers(200, 3000, SHAPE).astype(np.uint16)
    depth = rng.integers(500, 12_000, SHAPE).astype(np.uint16)
    disp[0, :] = 0
    depth[0, :] = 0
    disp[1, :2] = 0
    depth[1, :2] = 0
    return disp, depth


def make_benchmark(root: Path) -> Path:
    """A tiny tree in the benchmark layout: <scene>/<FOV>FOV/<B>mm/{CENTER,DOWN,RIGHT}/..."""
    for k, scene in enumerate(SCENES):
        (root / scene).mkdir(parents=True)
        (root / scene / "scene.yaml").write_text("scene: synthetic\n")
        for fov in FOVS:
            for b in BASELINES:
                cfg = root / scene / f"{fov}FOV" / f"{b}mm"
                disp, depth = _gt_maps(1000 * k + fov + b)
                for view in ("CENTER", "DOWN", "RIGHT"):
                    (cfg / view).mkdir(parents=True)
                    image = np.zeros((*SHAPE, 3), np.uint8)
                    image[:, ::2] = (40, 90, 200)  # vertical stripes: a known texture
                    cv2.imwrite(str(cfg / view / "pano_crop.png"), image)
                for kind, values in (("disparity", disp), ("depth", depth)):
                    (cfg / "CENTER" / kind).mkdir()
                    cv2.imwrite(str(cfg / "CENTER" / kind / "pano_crop.png"), values)
                    # a second view, and an EXR copy that is not GT
                    cv2.imwrite(str(cfg / "CENTER" / kind / "fisheye.png"), values)
                    scale = 100.0 if kind == "disparity" else 1000.0
                    exr = encode_exr((values / scale).astype(np.float32))
                    (cfg / "CENTER" / kind / "pano_crop.exr").write_bytes(exr)
    (root / "README.txt").write_text("not a scene\n")
    (root / "notes" / "120FOV").mkdir(parents=True)  # does not match <scene>/<FOV>FOV/<B>mm/CENTER
    return root


def write_predictions(bench: Path, pred: Path, task: str, view: str = "pano_crop") -> list[Path]:
    """Predictions with the errors of STEREO_ERR / DEPTH_FACTOR, in all three formats across the tree."""
    kind = "disparity" if task == "stereo" else "depth"
    written = []
    for n, gt_path in enumerate(sorted(bench.glob(f"*/*FOV/*mm/CENTER/{kind}/{view}.png"))):
        rel = gt_path.relative_to(bench).with_suffix("")
        fov, b = int(rel.parts[1][:-3]), int(rel.parts[2][:-2])
        raw = imread(gt_path, cv2.IMREAD_UNCHANGED)
        valid = raw > 0
        if task == "stereo":
            value = raw / 100.0 + STEREO_ERR[(fov, b)]
            scale = 100.0
        else:
            value = raw / 1000.0 * DEPTH_FACTOR[(fov, b)]
            scale = 1000.0
        value = np.where(valid, value, 0.0)
        out = pred / rel
        out.parent.mkdir(parents=True, exist_ok=True)
        if n % 3 == 0:
            path = out.with_suffix(".png")
            cv2.imwrite(str(path), np.round(value * scale).astype(np.uint16))
        elif n % 3 == 1:
            path = out.with_suffix(".exr")
            path.write_bytes(encode_exr(value.astype(np.float32)))
        else:
            path = out.with_suffix(".npy")
            np.save(path, value)
        written.append(path)
    return written


@pytest.fixture
def bench(tmp_path: Path) -> Path:
    return make_benchmark(tmp_path / "bench")


def test_discovery_parses_fov_and_baseline_from_the_path(bench: Path) -> None:
    layout, gts = discover_gt(bench, "stereo", "pano_crop")
    assert layout == "benchmark" and len(gts) == 8
    g = gts[0]
    assert g.rel == "001_057_000/120FOV/65mm/CENTER/disparity/pano_crop"
    assert (g.scene, g.view, g.fov_deg, g.baseline_mm, g.scale) == ("001_057_000", "pano_crop", 120, 65, 100)
    assert {(x.fov_deg, x.baseline_mm) for x in gts} == {(120, 65), (120, 200), (195, 65), (195, 200)}
    _, depth = discover_gt(bench, "mono")  # every view: pano_crop and fisheye
    assert len(depth) == 16 and all(x.rel.split("/")[4] == "depth" and x.scale == 1000.0 for x in depth)
    with pytest.raises(  # a view the benchmark does not have: the option is named, with the views it has
        EvalError, match=r"^--image-type 'pinhole': .* has disparity GT of the views fisheye, pano_crop$"
    ):
        discover_gt(bench, "stereo", "pinhole")
    with pytest.raises(EvalError, match="neither the WideDepth train layout"):
        discover_gt(bench / "notes", "stereo")


def test_a_dataset_that_is_a_file_or_lacks_depth_is_named_as_such(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(EvalError, match=r"file: is a file; expected a dataset folder$"):
        discover_gt(tmp_path / "file", "mono")
    (tmp_path / "ds" / "disp_equirect").mkdir(parents=True)
    with pytest.raises(EvalError, match=r"ds: no depth ground truth \(depth_fisheye/\*\.png\)$"):
        discover_gt(tmp_path / "ds", "mono")


def test_an_image_type_the_benchmark_does_not_have_is_named_with_those_it_has(bench: Path) -> None:
    """Sweep 5: `stats --image-type bogus` said "no depth ground truth (.../depth/bogus.png)", naming
    neither the option nor the views there are."""
    views = sorted({p.stem for p in bench.glob("*/*FOV/*mm/CENTER/depth/*.png")})
    with pytest.raises(EvalError) as err:
        discover_gt(bench, "mono", "bogus")
    assert str(err.value) == f"--image-type 'bogus': {bench} has depth GT of the views {', '.join(views)}"
    assert len(views) >= 1


def test_stereo_grouped_by_fov_and_baseline(bench: Path, tmp_path: Path) -> None:
    pred = tmp_path / "pred"
    files = write_predictions(bench, pred, "stereo")
    assert {p.suffix for p in files} == {".png", ".exr", ".npy"}
    report = evaluate(bench, pred, EvalOptions("stereo", by=("fov", "baseline"), image_type="pano_crop"))
    assert not report.missing and len(report.samples) == 8
    assert [g.label for g in report.groups] == ["120FOV/65mm", "120FOV/200mm", "195FOV/65mm", "195FOV/200mm"]
    per_px = SHAPE[0] * SHAPE[1] - 12
    for g in report.groups:
        m = g.metrics["all"]
        err = STEREO_ERR[(int(g.fov_deg or 0), int(g.baseline_mm or 0))]
        assert (g.samples, m["n_gt"], m["n"]) == (2, 2 * per_px, 2 * per_px)
        assert m["epe_px"] == pytest.approx(err, abs=1e-5)
        assert (m["median_px"], m["p95_px"]) == pytest.approx((err, err), abs=1e-5)
        assert (m["bad1"], m["bad2"], m["bad3"]) == tuple(float(err > k) for k in (1, 2, 3))
    overall = report.overall.metrics["all"]
    assert overall["epe_px"] == pytest.approx(sum(STEREO_ERR.values()) / 4, abs=1e-5)
    hm = heatmap(report, "epe_px")
    assert hm.fovs_deg == (120.0, 195.0) and hm.baselines_mm == (65.0, 200.0)
    np.testing.assert_allclose(hm.values, [[0.5, 0.25], [1.5, 4.0]], atol=1e-5)
    np.testing.assert_array_equal(heatmap(report, "bad1").values, [[0, 0], [1, 1]])

    rows = compare(report, "195FOV", "120FOV")  # paired within each baseline
    epe = {r.other: r for r in rows if r.metric == "epe_px"}
    assert epe["65mm"].change_pct == pytest.approx(200.0, abs=1e-3)  # 1.5 vs 0.5
    assert epe["200mm"].change_pct == pytest.approx(1500.0, abs=1e-2)  # 4.0 vs 0.25
    assert epe["65mm"].better == "B"
    table = markdown_compare(rows, "195FOV", "120FOV")
    assert "| 65mm | EPE [px] | 1.500 | 0.500 | +200.0 | B |" in table


def test_compare_pooled_over_the_other_key(bench: Path, tmp_path: Path) -> None:
    pred = tmp_path / "pred"
    write_predictions(bench, pred, "stereo")
    report = evaluate(bench, pred, EvalOptions("stereo", by=("fov",), image_type="pano_crop"))
    assert [g.label for g in report.groups] == ["120FOV", "195FOV"]
    rows = {r.metric: r for r in compare(report, "195FOV", "120FOV")}
    assert (rows["epe_px"].a, rows["epe_px"].b) == pytest.approx((2.75, 0.375), abs=1e-5)
    assert rows["epe_px"].change_pct == pytest.approx(100 * (2.75 - 0.375) / 0.375, rel=1e-5)
    assert rows["coverage"].change_pct == 0.0 and rows["coverage"].better == "="
    assert rows["bad1"].a == 1.0 and rows["bad1"].b == 0.0
    assert math.isnan(rows["bad1"].change_pct) and rows["bad1"].better == "B"  # +inf % is not printed
    with pytest.raises(EvalError, match="not grouped by baseline"):
        compare(report, "200mm", "65mm")
    with pytest.raises(EvalError, match="both must be FOVs or both baselines"):
        compare(report, "195FOV", "65mm")
    with pytest.raises(EvalError, match=r"no group holds both \(groups: 120FOV, 195FOV\)"):
        compare(report, "165FOV", "120FOV")
    with pytest.raises(EvalError, match="grouped by fov and baseline"):
        heatmap(report, "epe_px")


def test_depth_metrics_per_configuration_and_median_alignment(bench: Path, tmp_path: Path) -> None:
    pred = tmp_path / "pred"
    write_predictions(bench, pred, "mono")
    report = evaluate(bench, pred, EvalOptions("mono", by=("fov", "baseline"), image_type="pano_crop"))
    for g in report.groups:
        f = DEPTH_FACTOR[(int(g.fov_deg or 0), int(g.baseline_mm or 0))]
        m = g.metrics["all"]
        assert m["abs_rel"] == pytest.approx(f - 1.0, abs=2e-4)  # PNG predictions are rounded to mm
        assert m["delta1"] == float(f < 1.25) and m["delta3"] == float(f < 1.25**3)
    aligned = evaluate(bench, pred, EvalOptions("mono", image_type="pano_crop", align="median"))
    assert aligned.overall.metrics["all"]["abs_rel"] == pytest.approx(0.0, abs=2e-4)
    scales = {s.rel.split("/")[1] + "/" + s.rel.split("/")[2]: s.scale for s in aligned.samples}
    assert scales["195FOV/200mm"] == pytest.approx(0.5, rel=1e-4)
    with pytest.raises(EvalError, match="'median' for depth tasks only"):
        evaluate(bench, pred, EvalOptions("stereo", align="median"))


def test_missing_predictions_are_counted_and_listed(bench: Path, tmp_path: Path) -> None:
    pred = tmp_path / "pred"
    files = write_predictions(bench, pred, "stereo")
    for f in files:
        if "/120FOV/200mm/" in f.as_posix():
            f.unlink()
    report = evaluate(bench, pred, EvalOptions("stereo", image_type="pano_crop"))
    assert len(report.samples) == 6
    assert report.missing == (
        "001_057_000/120FOV/200mm/CENTER/disparity/pano_crop",
        "002_010_000/120FOV/200mm/CENTER/disparity/pano_crop",
    )
    everything = evaluate(bench, pred, EvalOptions("stereo"))  # the fisheye view has no predictions at all
    assert len(everything.samples) == 6 and len(everything.missing) == 10


def test_shape_mismatch_and_ambiguous_or_bad_predictions(bench: Path, tmp_path: Path) -> None:
    pred = tmp_path / "pred"
    files = write_predictions(bench, pred, "stereo")
    npy = next(p for p in files if p.suffix == ".npy")
    np.save(npy, np.zeros((SHAPE[1], SHAPE[0])))
    shapes = rf"{npy.name}: prediction shape \(10, 6\) but the GT .*pano_crop.png is \(6, 10\)"
    with pytest.raises(EvalError, match=shapes):
        evaluate(bench, pred, EvalOptions("stereo", image_type="pano_crop"))
    np.save(npy, np.zeros(SHAPE))
    shutil.copy(npy, npy.with_suffix(".png"))
    with pytest.raises(EvalError, match="several predictions"):
        evaluate(bench, pred, EvalOptions("stereo", image_type="pano_crop"))
    cv2.imwrite(str(npy.with_suffix(".png")), np.zeros((*SHAPE, 3), np.uint8))
    npy.unlink()
    with pytest.raises(EvalError, match=r"expected a 16-bit single-channel PNG .*got uint8"):
        evaluate(bench, pred, EvalOptions("stereo", image_type="pano_crop"))


def test_mask_regions_and_json(bench: Path, tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    pred = tmp_path / "pred"
    write_predictions(bench, pred, "stereo")
    masks = tmp_path / "masks"
    for gt in discover_gt(bench, "stereo", "pano_crop")[1]:
        m = np.zeros(SHAPE, np.uint8)
        m[3:, :] = 255 if gt.scene == SCENES[0] else 0  # the second scene's mask is empty
        (masks / gt.rel).parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(masks / f"{gt.rel}.png"), m)
    opts = EvalOptions("stereo", by=("fov",), image_type="pano_crop", masks=(("lower", masks),))
    report = evaluate(bench, pred, opts)
    assert report.regions == ("all", "edges", "lower")
    lower = report.overall.metrics["lower"]
    assert lower["n_gt"] == 4 * 3 * SHAPE[1]  # rows 3-5 of the first scene's 4 maps
    first = next(s for s in report.samples if s.scene == SCENES[1])
    assert first.metrics["lower"]["n_gt"] == 0 and math.isnan(float(first.metrics["lower"]["epe_px"]))
    out = write_report_json(report, tmp_path / "r" / "eval.json")

    def no_nan(token: str) -> float:
        raise AssertionError(f"non-standard JSON constant {token}")

    doc = json.loads(out.read_text(), parse_constant=no_nan)
    assert doc["options"]["masks"] == {"lower": str(masks)}
    assert doc["groups"][0]["label"] == "120FOV" and len(doc["samples"]) == 8
    assert doc["samples"][4]["metrics"]["lower"]["epe_px"] is None
    assert "| 120FOV | 4 | 192 | 100.00 | 0.375 |" in markdown_table(report)
    (masks / f"{report.samples[0].rel}.png").unlink()
    capfd.readouterr()
    with pytest.raises(EvalError, match="missing or unreadable mask"):
        evaluate(bench, pred, opts)
    assert capfd.readouterr().err == ""  # the one-line error only: no OpenCV warning on stderr before it


def test_a_colour_mask_counts_a_pixel_with_any_channel_set(bench: Path, tmp_path: Path) -> None:
    """A region mask is "non-zero = inside" per pixel: in a colour PNG one non-zero channel is enough.

    Each first-scene mask marks row 3 in pure blue, row 4 in pure green and row 5 in pure red
    (every pixel of those rows has valid GT): 3 rows x 10 columns in each of the 4 maps.
    """
    pred = tmp_path / "pred"
    write_predictions(bench, pred, "stereo")
    masks = tmp_path / "masks"
    for gt in discover_gt(bench, "stereo", "pano_crop")[1]:
        m = np.zeros((*SHAPE, 3), np.uint8)
        if gt.scene == SCENES[0]:
            m[3], m[4], m[5] = (255, 0, 0), (0, 255, 0), (0, 0, 1)  # BGR: one channel each
        (masks / gt.rel).parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(masks / f"{gt.rel}.png"), m)
    report = evaluate(bench, pred, EvalOptions("stereo", image_type="pano_crop", masks=(("marked", masks),)))
    assert report.overall.metrics["marked"]["n_gt"] == 4 * 3 * SHAPE[1]
    first = next(s for s in report.samples if s.scene == SCENES[0])
    assert first.metrics["marked"]["n_gt"] == 3 * SHAPE[1]


@pytest.mark.parametrize("task", ["stereo", "mono"])
def test_edges_use_the_step_thresholds_of_the_tasks_unit(bench: Path, tmp_path: Path, task: str) -> None:
    """The "edges" region finds steps of max(0.25 px, 3 %) in disparity and max(5 cm, 3 %) in depth.

    Every GT map steps from 1.0 to 1.1 between columns 4 and 5. In depth that is a 10 cm step
    (more than 5 cm): columns 4 and 5 are steps, and the 3 px band around them holds columns
    1-8 of all 6 rows, 48 pixels per map. In disparity 0.1 px is no step: no edges at all.
    """
    kind, scale = ("disparity", 100) if task == "stereo" else ("depth", 1000)
    step = np.full(SHAPE, 1.0 * scale, np.float64)
    step[:, 5:] = 1.1 * scale
    for path in bench.glob(f"*/*FOV/*mm/CENTER/{kind}/pano_crop.png"):
        cv2.imwrite(str(path), np.round(step).astype(np.uint16))
    pred = tmp_path / "pred"
    write_predictions(bench, pred, task)
    report = evaluate(bench, pred, EvalOptions(task, image_type="pano_crop"))  # type: ignore[arg-type]
    assert len(report.samples) == 8
    per_map = 0 if task == "stereo" else 48
    assert [s.metrics["edges"]["n_gt"] for s in report.samples] == [per_map] * 8
    assert report.overall.metrics["all"]["n_gt"] == 8 * SHAPE[0] * SHAPE[1]


# ---- a real dataset made by `ingest` from a fixture bag ----------------------------------------

INDOOR = FIXTURES_DIR / "indoor_static_mcap"


@pytest.fixture(scope="module")
def ingested(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three samples of the indoor fixture (480x300 fisheyes, 512 x 1024 equirect), with EXR copies."""
    out = tmp_path_factory.mktemp("eval") / "ds"
    cfg = IngestConfig(
        rig=truth_dir(INDOOR) / "rig.yaml", out=out, workers=1, every=10, sample=SampleParams(exr=True)
    )
    assert ingest([INDOOR], cfg).written == 3
    return out


def test_gt_as_prediction_scores_zero(ingested: Path, tmp_path: Path) -> None:
    pred = tmp_path / "pred"
    shutil.copytree(ingested / "disp_equirect", pred / "disp_equirect")
    shutil.copytree(ingested / "depth_fisheye", pred / "depth_fisheye")
    stereo = evaluate(ingested, pred, EvalOptions("stereo"))
    assert stereo.layout == "train" and len(stereo.samples) == 3 and not stereo.missing
    for row in (*[s.metrics for s in stereo.samples], stereo.overall.metrics):
        assert row["all"]["n"] == row["all"]["n_gt"] > 5_000
        m = row["all"]
        assert [m[k] for k in ("epe_px", "median_px", "p95_px", "bad1", "bad2", "bad3")] == [0] * 6
    m = stereo.overall.metrics["edges"]
    assert m["n"] == m["n_gt"] > 50
    assert [m[k] for k in ("epe_px", "median_px", "p95_px", "bad1", "bad2", "bad3")] == [0] * 6
    for task in ("mono", "completion"):
        depth = evaluate(ingested, pred, EvalOptions(task)).overall.metrics["all"]
        assert depth["n"] > 10_000 and (depth["abs_rel"], depth["mae_m"], depth["rmse_m"]) == (0, 0, 0)
        assert (depth["delta1"], depth["coverage"]) == (1.0, 1.0)
    # the unquantised EXR copies as predictions: only the PNG's rounding (<= 0.005 px, 0.5 mm) remains
    exr = tmp_path / "exr"
    shutil.copytree(ingested / "disp_equirect_exr", exr / "disp_equirect")
    shutil.copytree(ingested / "depth_fisheye_exr", exr / "depth_fisheye")
    s = evaluate(ingested, exr, EvalOptions("stereo")).overall.metrics["all"]
    # rounding to 0.01 px: errors uniform in [0, 0.005], mean 0.0025
    assert 0.002 < float(s["epe_px"]) < 0.003 and float(s["p95_px"]) <= 0.005 + 1e-6 and s["bad1"] == 0
    d = evaluate(ingested, exr, EvalOptions("mono")).overall.metrics["all"]
    assert 0 < float(d["mae_m"]) <= 0.0005 and d["delta1"] == 1.0


def _sgbm(up: np.ndarray, down: np.ndarray) -> np.ndarray:
    left = cv2.cvtColor(rotate_for_stereo(up), cv2.COLOR_BGR2GRAY)
    right = cv2.cvtColor(rotate_for_stereo(down), cv2.COLOR_BGR2GRAY)
    matcher = cv2.StereoSGBM_create(  # type: ignore[attr-defined]
        minDisparity=0, numDisparities=64, blockSize=5, P1=200, P2=800, uniquenessRatio=5,
        mode=cv2.STEREO_SGBM_MODE_HH,
    )  # fmt: skip
    disp = matcher.compute(left, right).astype(np.float32) / 16.0  # -1 = no match
    return unrotate_from_stereo(disp)


def test_sgbm_predictions_give_plausible_numbers(ingested: Path, tmp_path: Path) -> None:
    pred = tmp_path / "sgbm"
    (pred / "disp_equirect").mkdir(parents=True)
    for k, f in enumerate(sorted((ingested / "equirect_up").glob("*.png"))):
        disp = _sgbm(imread(f), imread(ingested / "equirect_down_virt" / f.name))
        target = pred / "disp_equirect" / f.stem
        if k == 0:  # as the release stores it: uint16 px x 100, 0 = none
            cv2.imwrite(str(target) + ".png", np.round(np.clip(disp, 0, None) * 100).astype(np.uint16))
        else:
            np.save(str(target) + ".npy", disp)
    report = evaluate(ingested, pred, EvalOptions("stereo"))
    assert len(report.samples) == 3
    for m in (*[s.metrics["all"] for s in report.samples], report.overall.metrics["all"]):
        assert 0.9 < float(m["coverage"]) < 1.0  # SGBM leaves some pixels unmatched
        assert 0.05 < float(m["median_px"]) < 0.5
        assert 0.1 < float(m["epe_px"]) < 1.0
        assert 0.005 < float(m["bad3"]) < 0.1 and m["bad1"] >= m["bad2"] >= m["bad3"]
    edges, everywhere = report.overall.metrics["edges"], report.overall.metrics["all"]
    assert float(edges["epe_px"]) > float(everywhere["epe_px"])  # matching is harder at depth edges
    # the same pair one row out of register must score clearly worse: the numbers do measure something
    shifted = tmp_path / "shifted"
    (shifted / "disp_equirect").mkdir(parents=True)
    for f in sorted((ingested / "equirect_up").glob("*.png")):
        down = np.roll(imread(ingested / "equirect_down_virt" / f.name), 1, axis=0)
        np.save(shifted / "disp_equirect" / f"{f.stem}.npy", _sgbm(imread(f), down))
    worse = evaluate(ingested, shifted, EvalOptions("stereo")).overall.metrics["all"]
    assert float(worse["median_px"]) > 0.8


def test_grouping_needs_the_benchmark_layout(ingested: Path, tmp_path: Path) -> None:
    with pytest.raises(EvalError, match=r"^--by fov: grouping by fov needs the benchmark layout"):
        evaluate(ingested, tmp_path, EvalOptions("stereo", by=("fov",)))
    heatmap = eval_request("stereo", [], None, True, [], "all", None, True, "none").options
    with pytest.raises(
        EvalError,
        match=r"^--heatmap: grouping by fov/baseline needs the benchmark layout .*this dataset is the train layout$",
    ):
        evaluate(ingested, tmp_path, heatmap)  # it asked for no --by
    both = eval_request("stereo", ["fov"], "195FOV,120FOV", False, [], "all", None, True, "none").options
    with pytest.raises(EvalError, match=r"^--by fov, --compare 195FOV,120FOV: grouping by fov needs"):
        evaluate(ingested, tmp_path, both)
    with pytest.raises(EvalError, match="no such prediction folder"):
        evaluate(ingested, tmp_path / "nope", EvalOptions("stereo"))
