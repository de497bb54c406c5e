"""Benchmark layout from simulated scans: files, scene.yaml, disparity GT geometry, SGBM agreement, resume, CLI.

One small run (FOV 120 and 195, baselines 120 and 300 mm, 320x200 images,
full-sphere equirect of 640 rows) of a three-scan indoor site. Disparity GT is
checked by geometry independent of its formula: the CENTER pixel's 3D point,
seen by the partner camera, must land `disparity` pixels away along the
epipolar line; and against OpenCV's SGBM on the rendered images.
"""

import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import OpenEXR
import pytest
import yaml

from calibration import read_rig
from calibration.errors import CalibrationError, SensorboxError
from calibration.pinhole import Pinhole
from calibration.spherical import Cassini, Equirectangular
from calibration.stereo import depth_to_disparity, rotate_for_stereo, unrotate_from_stereo
from calibration.virtual import CroppedModel, virtual_ds
from calibration.warp import warp
from ingest.dataset.layout import DISP_SCALE, read_png_u16
from ingest.errors import BenchmarkError
from ingest.eval.evaluate import discover_gt
from ingest.raster.edges import edge_band
from ingest.raster.scan import Scan
from ingest.render.benchmark import run_benchmark
from ingest.render.plan import BenchmarkConfig, pinhole_camera
from ingest.render.scans import read_scans
from sensorbox.sim.appearance import Texture
from sensorbox.sim.scenes import build_scene
from sensorbox.sim.tls import TlsParams, bundle_poses, simulate_scan, true_range, write_site
from tests.calibration.test_virtual import RIG

ROOT = Path(__file__).resolve().parents[2]
CFG = BenchmarkConfig(
    fovs_deg=(120.0, 195.0),
    baselines_mm=(120.0, 300.0),
    width=320,
    height=200,
    height_full=640,
    centers=("s0",),
)


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench")
    scene = build_scene("indoor", 0)
    tex = Texture(0)
    params = TlsParams(step_deg=0.25)
    sims = [
        simulate_scan(scene, tex, T, params, f"s{k}") for k, T in enumerate(bundle_poses([-2.0, 0.0, 1.4]))
    ]
    manifest = write_site(root / "site", scene, sims, "ply", params)
    scans = read_scans([manifest])
    ref = read_rig(RIG).camera("cam0").model
    passes: list[tuple[str, int, int]] = []
    summary = run_benchmark(scans, ref, root / "out", CFG, passes=lambda *call: passes.append(call))
    doc = yaml.safe_load((root / "out" / "000_000_000" / "scene.yaml").read_text())
    return {"root": root, "out": root / "out", "scene": scene, "scans": scans, "ref": ref, "summary": summary,
            "doc": doc, "dir": root / "out" / "000_000_000", "passes": passes}  # fmt: skip


def _img(path, flags=cv2.IMREAD_UNCHANGED) -> np.ndarray:
    im = cv2.imread(str(path), flags)
    assert im is not None, path
    return np.asarray(im)


def _exr(path):
    with OpenEXR.File(str(path)) as f:
        return np.asarray(f.channels()["Y"].pixels, np.float32)


def _folder(b, fov, base, cam):
    return b["dir"] / f"{fov}FOV" / f"{base}mm" / cam


@pytest.mark.xdist_group("bench")  # one worker renders the module's benchmark once
def test_indexing_reports_each_scan_before_the_first_view(bench):
    from ingest.render.benchmark import PASS_INDEX

    n = len(bench["scans"])  # the bundle of three: every view uses them all
    assert bench["passes"] == [(PASS_INDEX, k, n) for k in range(n + 1)]


@pytest.mark.xdist_group("bench")  # one worker renders the module's benchmark once
def test_layout_files_and_types(bench):
    s = bench["summary"]
    # CENTER: pinhole + 3 per FOV; per baseline: DOWN pinhole + 2 per FOV, RIGHT pinhole + 3 per FOV
    assert s.scenes == ["000_000_000"] and s.renders == 1 + 2 * 3 + 2 * (1 + 2 * 2 + 1 + 2 * 3)
    for fov in (120, 195):
        for base in (120, 300):
            c = _folder(bench, fov, base, "CENTER")
            images = {"fisheye", "pano", "pano_crop", "cassini_crop"} | (
                {"pinhole", "pinhole_crop"} if fov == 120 else set()
            )
            assert {p.stem for p in c.glob("*.png")} == images
            assert {p.stem for p in (c / "depth").glob("*.png")} == images
            assert {p.stem for p in (c / "disparity").glob("*.png")} == images - {"fisheye"}
            assert {p.name for p in (c / "depth").glob("*.exr")} == {f"{n}.exr" for n in images}
            pinholes = {"pinhole", "pinhole_crop"} if fov == 120 else set()
            down = {"fisheye", "pano", "pano_crop"} | pinholes
            assert {p.stem for p in _folder(bench, fov, base, "DOWN").glob("*.png")} == down
            right = {"fisheye", "cassini_crop", "pano", "pano_crop"} | pinholes
            assert {p.stem for p in _folder(bench, fov, base, "RIGHT").glob("*.png")} == right
    c = _folder(bench, 120, 120, "CENTER")
    img = _img(c / "fisheye.png")
    depth = _img(c / "depth" / "fisheye.png")
    assert img.shape == (200, 320, 3) and img.dtype == np.uint8
    assert depth.shape == (200, 320) and depth.dtype == np.uint16
    pano = _img(c / "pano.png", cv2.IMREAD_COLOR)
    assert pano.shape == (640, 1280, 3)
    crop = bench["doc"]["cameras"]["120FOV"]["pano_crop"]
    r0, c0 = crop["row_offset"], crop["col_offset"]
    window = pano[r0 : r0 + crop["height"], c0 : c0 + crop["width"]]
    np.testing.assert_array_equal(
        window, _img(c / "pano_crop.png", cv2.IMREAD_COLOR)
    )  # pano = crop in the full sphere
    assert pano.sum() == window.sum()  # nothing outside what the fisheye sees
    # the same CENTER files in every baseline folder; EXR = PNG within the uint16 step
    for name in ("fisheye", "pano_crop"):
        a = _img(c / "depth" / f"{name}.png")
        b = _img(_folder(bench, 120, 300, "CENTER") / "depth" / f"{name}.png")
        np.testing.assert_array_equal(a, b)
        exr = _exr(c / "depth" / f"{name}.exr")
        assert np.abs(exr * 1000 - a).max() <= 0.5 and ((exr > 0) == (a > 0)).all()


@pytest.mark.xdist_group("bench")  # one worker renders the module's benchmark once
def test_scene_yaml_describes_every_camera(bench):
    doc, ref = bench["doc"], bench["ref"]
    assert doc["view"]["bundle"] == ["s0", "s1", "s2"] and doc["view"]["center_scan"] == "s0"
    for fov in (120, 195):
        fish = doc["cameras"][f"{fov}FOV"]["fisheye"]
        m = virtual_ds(ref, fov, 320, 200)
        assert (fish["fx"], fish["xi"], fish["alpha"]) == (m.fx, m.xi, m.alpha)
        assert fish["nominal_fov_deg"] == fov and fish["true_fov_deg"]["horizontal"] > 90
    assert "pinhole" in doc["cameras"]["120FOV"] and "pinhole" not in doc["cameras"]["195FOV"]
    assert doc["T_center_partner"]["DOWN"]["300mm"][1][3] == 0.3
    assert doc["T_center_partner"]["RIGHT"]["120mm"][0][3] == 0.12
    st = doc["stats"]["120FOV/300mm/DOWN/fisheye"]
    assert st["pixels_with_ray"] == 64000 and 0 <= st["hole_px"] < 0.01 * 64000
    assert doc["stats"]["120FOV/CENTER/fisheye"]["masked_px"] > 0  # the glass pane
    # the evaluation code finds this layout's ground truth
    layout, gt = discover_gt(bench["out"], "stereo")
    assert layout == "benchmark" and {g.view for g in gt} == {
        "pano",
        "pano_crop",
        "cassini_crop",
        "pinhole",
        "pinhole_crop",
    }


def _rays(model, cols, rows):
    rays, ok = model.unproject(np.stack([cols, rows], axis=1).astype(np.float64))
    assert ok.all()
    return rays


@pytest.mark.xdist_group("bench")  # one worker renders the module's benchmark once
def test_vertical_disparity_is_where_the_down_camera_sees_the_point(bench):
    cam = bench["doc"]["cameras"]["120FOV"]["pano_crop"]
    eq = Equirectangular(640).crop(cam["row_offset"], cam["col_offset"], cam["height"], cam["width"])
    c = _folder(bench, 120, 300, "CENTER")
    rng, disp = _exr(c / "depth" / "pano_crop.exr"), _exr(c / "disparity" / "pano_crop.exr")
    rows, cols = np.nonzero(disp)
    assert len(rows) > 0.8 * np.count_nonzero(rng)  # stability mask drops only the poles' neighbourhood
    p = _rays(eq, cols, rows) * rng[rows, cols, None].astype(np.float64) - [0.0, 0.3, 0.0]  # in DOWN
    uv, ok = eq.project(p)
    assert ok.all()
    np.testing.assert_allclose(uv[:, 0], cols, atol=1e-3)  # same column: columns are epipolar lines
    np.testing.assert_allclose(uv[:, 1], rows - disp[rows, cols], atol=2e-3)
    # and the GT equals the exact disparity of the mesh, away from depth edges
    T = np.array(bench["doc"]["view"]["T_world_center"])
    exact, _ = true_range(bench["scene"], eq, T)
    d_exact = depth_to_disparity(
        np.nan_to_num(exact), eq.theta_of_row(np.arange(eq.height, dtype=np.float64))[:, None], 0.3, 640
    )
    inner = (disp > 0) & ~edge_band(np.nan_to_num(exact).astype(np.float32), 3)
    assert np.median(np.abs(disp - d_exact)[inner]) < 0.01


def _bad3(gt, est):
    ok = (gt > 0) & (est > 0)
    return float((np.abs(gt - est)[ok] > 3.0).mean()), int(ok.sum())


@pytest.mark.xdist_group("bench")  # one worker renders the module's benchmark once
def test_sgbm_agrees_with_the_vertical_pair_gt(bench):
    c, d = _folder(bench, 120, 120, "CENTER"), _folder(bench, 120, 120, "DOWN")
    up, down = (_img(f / "pano_crop.png", cv2.IMREAD_GRAYSCALE) for f in (c, d))
    gt = read_png_u16(c / "disparity" / "pano_crop.png", DISP_SCALE)
    sgbm = cv2.StereoSGBM.create(
        0, 64, 5, P1=8 * 25, P2=32 * 25, uniquenessRatio=10, mode=cv2.STEREO_SGBM_MODE_HH
    )
    est = unrotate_from_stereo(
        sgbm.compute(rotate_for_stereo(up), rotate_for_stereo(down)).astype(np.float32) / 16
    )
    bad, n = _bad3(gt, est)
    assert n > 0.5 * np.count_nonzero(gt) and bad < 0.08  # measured about 3 %
    shifted, _ = _bad3(np.where(gt > 0, gt + 5.0, 0.0), est)
    assert shifted > 0.8  # a GT 5 px off would be caught


@pytest.mark.xdist_group("bench")  # one worker renders the module's benchmark once
def test_horizontal_pinhole_pair(bench):
    ph = bench["doc"]["cameras"]["120FOV"]["pinhole"]
    model = Pinhole(ph["fx"], ph["fy"], ph["cx"], ph["cy"], ph["width"], ph["height"])
    c, r = _folder(bench, 120, 300, "CENTER"), _folder(bench, 120, 300, "RIGHT")
    z, disp = _exr(c / "depth" / "pinhole.exr"), _exr(c / "disparity" / "pinhole.exr")
    rows, cols = np.nonzero(disp)
    np.testing.assert_allclose(disp[rows, cols], model.fx * 0.3 / z[rows, cols], rtol=1e-6)  # f B / z
    p = _rays(model, cols, rows)
    p = p / p[:, 2:] * z[rows, cols, None] - [0.3, 0.0, 0.0]  # the point, in RIGHT
    uv, _ = model.project(p)
    np.testing.assert_allclose(uv[:, 0], cols - disp[rows, cols], atol=2e-3)
    np.testing.assert_allclose(uv[:, 1], rows, atol=1e-6)
    T = np.array(bench["doc"]["view"]["T_world_center"])
    exact, _ = true_range(bench["scene"], model, T)
    rays, _ = model.unproject(model.pixel_grid())
    z_exact = np.nan_to_num(exact) * rays[..., 2]
    inner = (disp > 0) & ~edge_band(z_exact.astype(np.float32), 3)
    assert np.median(np.abs(disp - model.fx * 0.3 / np.where(z_exact > 0, z_exact, np.inf))[inner]) < 0.01
    left, right = (_img(f / "pinhole.png", cv2.IMREAD_GRAYSCALE) for f in (c, r))
    sgbm = cv2.StereoSGBM.create(
        0, 96, 5, P1=8 * 25, P2=32 * 25, uniquenessRatio=10, mode=cv2.STEREO_SGBM_MODE_HH
    )
    bad, n = _bad3(disp, sgbm.compute(left, right).astype(np.float32) / 16)
    assert n > 0.4 * len(rows) and bad < 0.08
    crop = bench["doc"]["cameras"]["120FOV"]["pinhole_crop"]
    dc = _exr(c / "disparity" / "pinhole_crop.exr")
    r0, c0 = crop["row_offset"], crop["col_offset"]
    assert (c0, r0, dc.shape) == ((320 - 160) // 2, (200 - 100) // 2, (100, 160))  # the centre half per axis
    np.testing.assert_array_equal(dc, disp[r0 : r0 + crop["height"], c0 : c0 + crop["width"]])


def test_pinhole_crop_is_the_central_window_of_the_pinhole_image():
    """(col, row, width, height) of the crop: half of each axis, centred; rows from the height, columns
    from the width (a crop placed by the width would run past the bottom of a wide image)."""
    ph, crop = pinhole_camera(BenchmarkConfig())
    assert (ph.width, ph.height) == (2048, 1152) and crop == (512, 288, 1024, 576)
    assert pinhole_camera(CFG)[1] == (80, 50, 160, 100)


# The WideDepth release loader's stereo configurations: per FOV folder and baseline, every image
# type with each partner (DOWN: vertical pair, RIGHT: horizontal pair), pinholes in 120FOV only;
# its tasks (mono/stereo x depth/disparity) read at most these four files of a configuration
RELEASE_FILES = ("CENTER/{i}.png", "{p}/{i}.png", "CENTER/depth/{i}.png", "CENTER/disparity/{i}.png")


def _release_configs(fovs, baselines):
    for fov in fovs:
        images = ("pano", "pano_crop", *(("pinhole", "pinhole_crop") if fov == 120 else ()))
        for base in baselines:
            yield from ((fov, base, i, p) for i in images for p in ("DOWN", "RIGHT"))


@pytest.mark.xdist_group("bench")  # one worker renders the module's benchmark once
def test_every_release_configuration_has_aligned_files(bench):
    configs = list(_release_configs((120, 195), (120, 300)))
    assert len(configs) == 2 * (8 + 4)  # 120FOV: 8 per baseline, 195FOV: 4
    for fov, base, image, partner in configs:
        folder = bench["dir"] / f"{fov}FOV" / f"{base}mm"
        shapes = {_img(folder / f.format(i=image, p=partner)).shape[:2] for f in RELEASE_FILES}
        assert len(shapes) == 1, (fov, base, image, partner, shapes)


@pytest.mark.xdist_group("bench")  # one worker renders the module's benchmark once
def test_vertical_pinhole_pair_shares_f_b_over_z(bench):
    c, d = _folder(bench, 120, 300, "CENTER"), _folder(bench, 120, 300, "DOWN")
    gt = _exr(c / "disparity" / "pinhole.exr")
    up, down = (_img(f / "pinhole.png", cv2.IMREAD_GRAYSCALE) for f in (c, d))
    sgbm = cv2.StereoSGBM.create(
        0, 96, 5, P1=8 * 25, P2=32 * 25, uniquenessRatio=10, mode=cv2.STEREO_SGBM_MODE_HH
    )
    est = unrotate_from_stereo(
        sgbm.compute(rotate_for_stereo(up), rotate_for_stereo(down)).astype(np.float32) / 16
    )
    bad, n = _bad3(gt, est)
    assert n > 0.4 * np.count_nonzero(gt) and bad < 0.08
    shifted, _ = _bad3(np.where(gt > 0, gt + 5.0, 0.0), est)
    assert shifted > 0.8


@pytest.mark.xdist_group("bench")  # one worker renders the module's benchmark once
def test_right_pano_is_the_right_camera_in_center_orientation(bench):
    """RIGHT/pano warped to the Cassini window equals RIGHT/cassini_crop (another render of that camera)."""
    cam = bench["doc"]["cameras"]["120FOV"]["cassini_crop"]
    cas = CroppedModel(
        Cassini(cam["height_full"]), cam["col_offset"], cam["row_offset"], cam["width"], cam["height"]
    )
    eq = Equirectangular(cam["height_full"])

    def diff(pano_cam, cassini_cam):
        pano = _img(_folder(bench, 120, 300, pano_cam) / "pano.png", cv2.IMREAD_GRAYSCALE)
        cassini = _img(_folder(bench, 120, 300, cassini_cam) / "cassini_crop.png", cv2.IMREAD_GRAYSCALE)
        warped, ok = warp(pano, eq, cas, np.eye(3))
        ok &= (warped > 0) & (cassini > 0)
        return float(np.median(np.abs(warped.astype(float) - cassini)[ok]))

    # resampling a textured render costs a few grey levels (CENTER's own pair gives the floor); the
    # CENTER pano 300 mm away is far off
    floor, same, other = diff("CENTER", "CENTER"), diff("RIGHT", "RIGHT"), diff("CENTER", "RIGHT")
    assert same <= 1.5 * floor and other > 5.0 * same, (floor, same, other)
    assert (_folder(bench, 120, 300, "RIGHT") / "pano_crop.png").exists()
    assert (
        "cassini_crop" in bench["doc"]["conventions"]["pairs"]["horizontal CENTER-RIGHT"]["pano, pano_crop"]
    )


@pytest.mark.xdist_group("bench")  # one worker renders the module's benchmark once
def test_cassini_pair_disparity_runs_along_rows(bench):
    cam = bench["doc"]["cameras"]["195FOV"]["cassini_crop"]
    m = CroppedModel(
        Cassini(cam["height_full"]), cam["col_offset"], cam["row_offset"], cam["width"], cam["height"]
    )
    c = _folder(bench, 195, 120, "CENTER")
    rng, disp = _exr(c / "depth" / "cassini_crop.exr"), _exr(c / "disparity" / "cassini_crop.exr")
    rows, cols = np.nonzero(disp)
    assert len(rows) > 1000
    p = _rays(m, cols, rows) * rng[rows, cols, None].astype(np.float64) - [0.12, 0.0, 0.0]  # in RIGHT
    uv, _ = m.project(p)
    np.testing.assert_allclose(uv[:, 0], cols - disp[rows, cols], atol=2e-3)
    np.testing.assert_allclose(uv[:, 1], rows, atol=2e-3)


@pytest.mark.xdist_group("bench")  # one worker renders the module's benchmark once
def test_rerun_skips_finished_scenes_and_bad_setups_are_refused(bench):
    stamp = (bench["dir"] / "scene.yaml").stat().st_mtime_ns
    again = run_benchmark(bench["scans"], bench["ref"], bench["out"], CFG)
    assert again.skipped == ["000_000_000"] and again.renders == 0
    assert (bench["dir"] / "scene.yaml").stat().st_mtime_ns == stamp
    # another size, FOV set or baseline into the same folder: refused, not skipped as done (exit 0 before)
    other = r"scene.yaml: this scene was rendered with other settings \("
    for change in ({"width": CFG.width + 8}, {"fovs_deg": (*CFG.fovs_deg, 90.0)}, {"baselines_mm": (100.0,)}):
        with pytest.raises(BenchmarkError, match=other):
            run_benchmark(bench["scans"], bench["ref"], bench["out"], replace(CFG, **change))
    assert (bench["dir"] / "scene.yaml").stat().st_mtime_ns == stamp
    with pytest.raises(BenchmarkError, match="Double Sphere"):
        run_benchmark(bench["scans"], Pinhole(100, 100, 50, 50, 100, 100), bench["root"] / "x", CFG)
    with pytest.raises(BenchmarkError, match=r"--center 'nope'.*s0, s1, s2"):
        run_benchmark(bench["scans"], bench["ref"], bench["root"] / "x", replace(CFG, centers=("nope",)))
    with pytest.raises(BenchmarkError, match="--fov"):
        run_benchmark(bench["scans"], bench["ref"], bench["root"] / "x", replace(CFG, fovs_deg=(400.0,)))
    nan, inf = float("nan"), float("inf")
    bad: tuple[
        tuple[dict[str, Any], str], ...
    ] = (  # each rendered empty or clipped scenes (exit 0) or crashed
        ({"baselines_mm": (inf,)}, r"--baseline \[inf\]: each baseline must be a finite number > 0 mm"),
        ({"yaws_deg": (inf,)}, r"--yaw \[inf\]: each value must be a finite number"),
        ({"heights_m": (nan,)}, r"--height \[nan\]: each value must be a finite number"),
        ({"render": replace(CFG.render, clip_m=0.0)}, r"--clip 0.0: must be a finite number > 0 m"),
        ({"height_full": 0}, r"--height-full must be >= 64 rows \(.*\), got 0"),
        ({"site_id": -1}, r"--site-id must be >= 0, got -1"),
    )
    for change, message in bad:
        with pytest.raises(BenchmarkError, match=message):
            run_benchmark(bench["scans"], bench["ref"], bench["root"] / "x", replace(CFG, **change))
    assert not (bench["root"] / "x").exists()


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "sensorbox.cli", *args], capture_output=True, text=True, cwd=ROOT,
                          check=False)  # fmt: skip


@pytest.mark.xdist_group("bench")  # one worker renders the module's benchmark once
def test_cli_renders_and_summarises(bench, tmp_path):
    res = _cli("render-benchmark", str(bench["root"] / "site" / "site.yaml"), "--rig", str(RIG), "--out",
               str(tmp_path / "b"), "--size", "96x64", "--fov", "140", "--baseline", "65", "--center", "s1",
               "--yaw", "90", "--height", "0.2", "--no-exr", "--workers", "1")  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert "000_001_000" in res.stdout and "140FOV" in res.stdout and "holes CENTER" in res.stdout
    doc = yaml.safe_load((tmp_path / "b" / "000_001_000" / "scene.yaml").read_text())
    assert doc["view"]["yaw_deg"] == 90.0 and doc["view"]["height_m"] == 0.2
    T = np.array(doc["view"]["T_world_center"])
    R_world_scan = bench["scans"][1].T_world_scan[:3, :3]
    np.testing.assert_allclose(T[:3, 2], R_world_scan[:, 1], atol=1e-12)  # yaw 90: along the scan's +y
    np.testing.assert_allclose(T[:3, 3], bench["scans"][1].origin_world + np.array([0, 0, 0.2]))
    assert not list((tmp_path / "b").rglob("*.exr"))
    bad = _cli("render-benchmark", str(bench["root"] / "site" / "site.yaml"), "--rig", str(RIG), "--out",
               str(tmp_path / "c"), "--size", "96by64")  # fmt: skip
    assert bad.returncode == 2 and bad.stderr.strip().startswith("error: --size '96by64'")


def _ground_scan(up_axis: int) -> Scan:
    """An outdoor scan of flat ground 1.6 m below the scanner, 40 m across; ``up_axis`` 1: y-up, 2: z-up."""
    g = np.arange(-20.0, 20.0, 0.2)
    a, b = (c.ravel() for c in np.meshgrid(g, g))
    xyz = np.zeros((len(a), 3), np.float32)
    xyz[:, 0], xyz[:, 3 - up_axis], xyz[:, up_axis] = a, b, -1.6
    rgb = np.random.default_rng(0).integers(0, 256, (len(a), 3)).astype(np.uint8)
    return Scan("ground", np.eye(4), xyz, rgb, source="ground.ply")


def _png(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert image is not None, path
    return np.asarray(image)


NO_DISPARITY_64 = (
    "000_000_000: 2 renders draw a surface but their disparity maps hold no pixel (120FOV/CENTER/pano, "
    "120FOV/CENTER/cassini): at --height-full 64 the baseline's disparity is too small a part of a pixel to "
    "keep (more --height-full rows or a longer --baseline keep it)"
)


def test_disparity_maps_without_a_pixel_are_named(tmp_path):
    """Sweep 6 S5: at `--height-full 64` every angular disparity map was empty without a word. The line
    names the renders whose disparity holds no pixel, and only those (the pinhole's f B / z keeps it)."""
    cfg = BenchmarkConfig(fovs_deg=(120.0,), baselines_mm=(65.0,), width=48, height=32, height_full=64,
                          yaws_deg=(90.0,), workers=1, exr=False)  # fmt: skip
    ref = read_rig(RIG).camera("cam0").model
    coarse = run_benchmark([_ground_scan(2)], ref, tmp_path / "c", cfg)
    assert coarse.warnings == [NO_DISPARITY_64]
    center = tmp_path / "c" / "000_000_000" / "120FOV" / "65mm" / "CENTER"
    valid = {p.name: int(np.count_nonzero(_png(p))) for p in (center / "disparity").glob("*.png")}
    assert valid["pano.png"] == valid["pano_crop.png"] == valid["cassini_crop.png"] == 0
    assert valid["pinhole.png"] > 0
    doc = yaml.safe_load((tmp_path / "c" / "000_000_000" / "scene.yaml").read_text())
    assert doc["warnings"] == [NO_DISPARITY_64]
    assert doc["stats"]["120FOV/CENTER/pano"]["disparity_px"] == 0
    fine = run_benchmark([_ground_scan(2)], ref, tmp_path / "f", replace(cfg, height_full=512))
    assert not fine.warnings
    assert fine.stats["000_000_000"]["120FOV/CENTER/pano"]["disparity_px"] > 0


def test_a_y_up_scan_renders_nothing_and_says_why(tmp_path):
    cfg = BenchmarkConfig(fovs_deg=(120.0,), baselines_mm=(65.0,), width=48, height=32, height_full=64,
                          yaws_deg=(90.0,), workers=1, exr=False)  # fmt: skip
    ref = read_rig(RIG).camera("cam0").model
    dropped = replace(_ground_scan(2), dropped_points=3)  # as read from a file with 3 NaN points
    z_up = run_benchmark([dropped], ref, tmp_path / "z", cfg)  # looks along +y: ground below
    assert z_up.warnings == [NO_DISPARITY_64] and not z_up.empty  # 64 rows keep no angular disparity
    doc = yaml.safe_load((tmp_path / "z" / "000_000_000" / "scene.yaml").read_text())
    assert (doc["scans"][0]["points"], doc["scans"][0]["dropped_points"]) == (40_000, 3)
    y_up = run_benchmark([_ground_scan(1)], ref, tmp_path / "y", cfg)  # "along +y" is the sky
    stats = y_up.stats["000_000_000"]
    assert sorted(y_up.empty["000_000_000"]) == sorted(stats) and all(
        s["surface_px"] == 0 for s in stats.values()
    )
    (line,) = y_up.warnings
    assert line.startswith(f"000_000_000: {len(stats)} of {len(stats)} renders show (almost) nothing")
    assert "likely frame not z-up (the smallest extent is along y" in line and "scan ground" in line
    doc = yaml.safe_load((tmp_path / "y" / "000_000_000" / "scene.yaml").read_text())
    assert doc["warnings"] == [line]


def test_a_damaged_finished_scene_is_rendered_again_and_another_scan_pose_refused(tmp_path):
    """Issue 49: a deleted or cut view of a finished scene is rendered again and named (it was kept as
    'Already done'); a rerun with the scan at another pose is one line naming the folder and the change
    (it printed 'Already done' and kept the stale views)."""
    cfg = BenchmarkConfig(fovs_deg=(120.0,), baselines_mm=(65.0,), width=48, height=32, height_full=64,
                          yaws_deg=(90.0,), workers=1, exr=False)  # fmt: skip
    ref = read_rig(RIG).camera("cam0").model
    scan, out = _ground_scan(2), tmp_path / "b"
    first = run_benchmark([scan], ref, out, cfg)
    scene = out / "000_000_000"
    kept = {p: p.read_bytes() for p in scene.rglob("*.png")}
    doc = yaml.safe_load((scene / "scene.yaml").read_text())
    assert len(doc["files"]) == len(kept) == first.files - 1  # every file but scene.yaml itself
    gone = scene / "120FOV" / "65mm" / "DOWN" / "fisheye.png"
    cut = scene / "120FOV" / "65mm" / "CENTER" / "depth" / "pano.png"
    gone.unlink()
    cut.write_bytes(kept[cut][:50])
    again = run_benchmark([scan], ref, out, cfg)
    assert (again.skipped, again.damaged) == ([], [f"{scene}/120FOV/65mm/CENTER/depth/pano.png: 50 bytes, "
                                                   f"{len(kept[cut])} were written"])  # fmt: skip
    assert again.renders == first.renders
    assert {p: p.read_bytes() for p in scene.rglob("*.png")} == kept
    assert run_benchmark([scan], ref, out, cfg).skipped == ["000_000_000"]
    moved = np.eye(4)
    moved[0, 3] = 0.5
    with pytest.raises(BenchmarkError) as refused:
        run_benchmark([replace(scan, T_world_scan=moved)], ref, out, cfg)
    assert str(refused.value) == (
        f"{scene}: this scene was rendered from other scans or another view (scan ground: T_world_scan moved "
        f"by 0.5 m and turned by 0 deg); choose a new --out or delete {scene}"
    )
    with pytest.raises(BenchmarkError, match=r"\(scan ground: source: ground.ply -> other.ply\)"):
        run_benchmark([replace(scan, source="other.ply")], ref, out, cfg)
    (scene / "scene.yaml").unlink()  # a FIFO in its place would block the rerun's read of it
    os.mkfifo(scene / "scene.yaml")
    with pytest.raises(BenchmarkError) as fifo:
        run_benchmark([scan], ref, out, cfg)
    assert (
        str(fifo.value)
        == f"{scene}/scene.yaml: is a FIFO (named pipe), not a finished scene description file"
    )


def test_an_equirect_beyond_memory_is_refused_before_any_work(tmp_path):
    """--height-full 100000 (a 1.8 TB sphere): one line suggesting a smaller --height-full, in both commands;
    0 is refused as a value, not taken for the default."""
    from ingest.train.run.sample_job import Geometry

    pattern = r"^--height-full 100000: .* needs about 1800\.0 GB, .* pass --height-full \d+ or less$"
    with pytest.raises(CalibrationError, match=pattern):
        Geometry.from_rig(read_rig(RIG), 100_000)
    with pytest.raises(CalibrationError, match=pattern):
        run_benchmark([_ground_scan(2)], read_rig(RIG).camera("cam0").model, tmp_path / "b",
                      replace(CFG, height_full=100_000, centers=()))  # fmt: skip
    assert not (tmp_path / "b").exists()
    with pytest.raises(CalibrationError, match=r"^--height-full must be >= 64 rows \(.*\), got 0$"):
        Geometry.from_rig(read_rig(RIG), 0)  # 0 is a value, not "the default"


def test_an_image_size_whose_sphere_is_over_the_memory_budget_is_named_as_the_cause(tmp_path, monkeypatch):
    """--size chose the equirect's rows; the message blamed --height-full, which was not given."""
    from ingest.render.request import BenchmarkRequest, prepare

    monkeypatch.setattr("calibration.warp.memory_budget_bytes", lambda: 4 * 10**9)
    with pytest.raises(CalibrationError) as err:
        prepare(BenchmarkRequest([tmp_path / "missing.e57"], RIG, tmp_path / "out", size="16000x16000"))
    assert str(err.value) == (
        "--size 16000x16000 (the 120 deg fisheye's default --height-full 29184): a full-sphere equirect of "
        "29184 x 58368 needs about 153.3 GB, over the budget of 4.0 GB (half this machine's memory); pass "
        "--height-full 4608 or less"
    )


@pytest.mark.parametrize(
    ("changes", "pattern"),
    [
        ({"clip_m": -1.0}, r"^--clip -1\.0: must be a finite number > 0 m$"),
        (
            {"baselines_mm": (float("inf"),)},
            r"^--baseline \[inf\]: each baseline must be a finite number > 0 mm$",
        ),
        ({"height_full": 100_000}, r"^--height-full 100000: .* pass --height-full \d+ or less$"),
        ({"points_per_px": float("inf")}, r"^--points-per-px inf: must be a finite number > 0$"),
        ({"size": "100000x100000"}, r"^--size 100000x100000: expected at most 16384 px a side$"),
        ({"pitch_deg": 200.0}, r"^--pitch 200\.0: must be within -90\.\.90 degrees \(up > 0\)$"),
        (  # sweep 7 S3: two scenes of the same view, pixel for pixel
            {"yaws_deg": (0.0, 360.0)},
            r"^--yaw 360 \(the same as 0\) is given twice; its views would be rendered twice and weigh double "
            r"in every score$",
        ),
        ({"baselines_mm": (65.0, 65.0)}, r"^--baseline 65 is given twice; its views would be rendered twice"),
        ({"centers": ("s0", "s0")}, r"^--center s0 is given twice; its views would be rendered twice"),
        (
            {"fovs_deg": (140.0, 195.0), "pinhole_fovs": (120.0,)},
            r"^--pinhole-in 120: not one of the rendered FOVs \(140, 195\); the pinhole images go into those folders$",
        ),
    ],
)
def test_options_are_refused_before_the_scans_are_read(tmp_path, changes, pattern):
    """A bad option is named at once, not after minutes of reading scans: here the scan does not even exist."""
    from ingest.render.request import BenchmarkRequest, prepare

    request = BenchmarkRequest([tmp_path / "missing.e57"], RIG, tmp_path / "out", **changes)
    with pytest.raises(SensorboxError, match=pattern):
        prepare(request)
    with pytest.raises(SensorboxError, match=r"missing\.e57"):  # the same request with good options: the scan
        prepare(BenchmarkRequest([tmp_path / "missing.e57"], RIG, tmp_path / "out"))
