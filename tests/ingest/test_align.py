"""LiDAR points laid onto cam0's image (`ingest.train.gt.align`), against the simulator's exact truth: one
rendered frame's points come back where they belong from a 1 deg, 30 mm error; `combine` tells a rig-file
error from a clock offset; ingest flags a turned LiDAR and not an exact rig."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from calibration.rig import write_rig
from calibration.types import F64
from ingest.train.gt.align import Alignment, ImageLevels, align_points
from ingest.train.gt.align_check import check_calibration, combine
from ingest.train.run.pipeline import ingest
from ingest.train.run.settings import IngestConfig
from sensorbox.sim.camera import render
from sensorbox.sim.config import SimConfig
from sensorbox.sim.lidar import simulate_sweep, sweep_windows
from sensorbox.sim.run import setup_sim
from sensorbox.sim.truth import Truth
from tests.paths import FIXTURES_DIR

AXIS = np.array([0.6, -0.48, 0.64])
SHIFT_M = np.array([0.02, -0.015, 0.0158])  # 29.6 mm


@pytest.fixture(scope="module")
def frame() -> tuple[object, np.ndarray, F64, F64]:
    """An indoor walk's frame at 960x600 (cam0 model, BGR image) and the top LiDAR's points of the
    +-50 ms around it placed exactly in cam0 at the exposure, with their reflectivity."""
    s = setup_sim(SimConfig(scene="indoor", trajectory="walk", duration_s=2.0, scale=0.5, range_noise_m=0.02))
    t_s = 1.6
    T_wc = s.traj.T_world_cam0(np.array([t_s]))[0]
    image = render(s.cams[0], s.scene, s.texture, T_wc, 1, t_s)
    lidar, t_ns = s.lidars[0], int(t_s * 1e9)
    pts, refl = [], []
    for window in sweep_windows(lidar, 0, s.duration_ns):
        if not (window[1] > t_ns - 50_000_000 and window[0] < t_ns + 50_000_000):
            continue
        sweep = simulate_sweep(lidar, s.scene, s.texture, s.traj, 0, window)
        assert sweep is not None
        p = sweep.points
        stamps = sweep.timebase_ns + p["offset_time"].astype(np.int64) - lidar.clock_offset_ns
        ok = (np.abs(stamps - t_ns) <= 50_000_000) & (p["tag"] == 0) & ((p["x"] != 0) | (p["y"] != 0))
        xyz = np.stack([p["x"], p["y"], p["z"]], axis=1)[ok].astype(np.float64)
        R_wc, p_wc = s.traj.pose(stamps[ok] / 1e9)
        in_cam0 = xyz @ lidar.T_cam0_lidar[:3, :3].T + lidar.T_cam0_lidar[:3, 3]
        world = np.einsum("nij,nj->ni", R_wc, in_cam0) + p_wc
        pts.append((world - T_wc[:3, 3]) @ T_wc[:3, :3])
        refl.append(p["reflectivity"][ok].astype(np.float64))
    return s.cams[0].model, image, np.concatenate(pts), np.concatenate(refl)


def _left(found: Alignment, R_err: F64, t_err: F64) -> tuple[float, float]:
    """(deg, mm) of the error that remains after `found` is applied on top of (R_err, t_err)."""
    R_fix = Rotation.from_rotvec(found.rotation_rad)
    rotation = R_fix * Rotation.from_matrix(R_err)
    translation = R_fix.apply(t_err) + found.translation_m
    return float(np.degrees(rotation.magnitude())), float(np.linalg.norm(translation) * 1e3)


def test_exact_points_stay_and_a_turned_and_moved_set_comes_back(frame) -> None:
    model, image, pts, refl = frame
    levels = ImageLevels.from_bgr(image)
    exact = align_points(model, levels, pts, refl)
    assert exact is not None and exact.points > 5000
    deg, mm = _left(exact, np.eye(3), np.zeros(3))
    assert deg < 0.03 and mm < 2.0, (deg, mm)
    assert exact.shift_deg < 0.03
    assert exact.correlation > 0.5  # the image's intensity follows the points' reflectivity

    R_err = Rotation.from_rotvec(np.radians(1.0) * AXIS / np.linalg.norm(AXIS)).as_matrix()
    wrong = pts @ R_err.T + SHIFT_M
    found = align_points(model, levels, wrong, refl)
    assert found is not None
    assert found.shift_deg > 0.8  # what the wrong pose did to the points on the image
    deg, mm = _left(found, R_err, SHIFT_M)
    assert deg < 0.03 and mm < 2.0, (deg, mm)
    assert found.sigma_rotation_deg < 0.03 and found.sigma_translation_mm < 2.0


def test_without_texture_there_is_nothing_to_align(frame) -> None:
    model, image, pts, refl = frame
    assert align_points(model, ImageLevels.from_bgr(np.full_like(image, 128)), pts, refl) is None


def test_the_compiled_normal_equations_are_the_robust_cost_written_out(frame) -> None:
    """`normal_equations` against the cost of the module docstring in numpy, the image read by OpenCV's
    bilinear remap: the same H and g (to OpenCV's float32 sampling), spread, points and intensities."""
    import cv2

    from ingest.train.gt.align_kernels import normal_equations

    model, image, pts, refl = frame
    level = ImageLevels.from_bgr(image).levels[1]
    p = pts[::7]
    px, ok = model.project(p)
    ok &= model.in_image(px)
    px = np.where(ok[:, None], px, 0.0)
    rng = np.random.default_rng(5)
    J = rng.normal(0.0, 300.0, (len(p), 2, 3))
    affine = np.array([0.8, 12.0])
    H, g, n, spread, weighted_sq, intensity, used_refl, used_p = normal_equations(
        px, ok, p, J, refl[::7], level, affine, 2.0
    )
    x, y = (np.ascontiguousarray(px[ok, k], np.float32).reshape(-1, 1) for k in (0, 1))
    sampled = cv2.remap(level, x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(-1, 3)
    grad = np.einsum("ni,nik->nk", sampled[:, 1:].astype(np.float64), J[ok])
    rf = refl[::7][ok]
    rows = np.c_[np.cross(p[ok], grad), grad, -rf, -np.ones(len(rf))]
    residual = sampled[:, 0] - (affine[0] * rf + affine[1])
    mad = 1.4826 * np.median(np.abs(residual - np.median(residual)))
    weight = 1.0 / (1.0 + (residual / (2.0 * mad)) ** 2)
    assert n == ok.sum() > 1000
    np.testing.assert_allclose(intensity, sampled[:, 0], atol=2e-3)
    np.testing.assert_array_equal(used_refl, rf)
    np.testing.assert_array_equal(used_p, p[ok])
    assert spread == pytest.approx(mad, rel=1e-3)
    np.testing.assert_allclose(H, (rows * weight[:, None]).T @ rows, rtol=1e-3, atol=1e-6 * np.abs(H).max())
    np.testing.assert_allclose(
        g, (rows * weight[:, None]).T @ residual, rtol=1e-3, atol=1e-6 * np.abs(g).max()
    )
    assert weighted_sq == pytest.approx(float(np.sum(weight * residual**2)), rel=1e-3)


def _edge_points(pts: F64) -> F64:
    """`pts` with points the projection refuses (behind the fold, NaN, the origin) and points whose
    forward differences cross the image border or the validity limit, where the compiled paths must
    agree with numpy bit for bit."""
    behind = pts[:50] * np.array([1.0, 1.0, -40.0])
    special = np.array([[np.nan, 0.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [1e-300, 0.0, 1e-300]])
    return np.concatenate([pts, behind, special])


def test_the_compiled_projection_and_jacobians_are_numpys_to_the_bit(frame) -> None:
    """`visible_jacobians` and `pixels_in_image` against `CameraModel.project`, `in_image` and numpy's
    forward differences: the same pixels (NaN where numpy has NaN), the same points kept, the same
    Jacobians, bit for bit (the alignments they feed are then unchanged)."""
    from ingest.train.gt.align import JACOBIAN_STEP_M
    from ingest.train.gt.align_kernels import pixels_in_image, visible_jacobians

    model, _, pts, _ = frame
    p = _edge_points(pts)
    px, ok = model.project(p)
    ok &= model.in_image(px)
    steps = np.eye(3) * JACOBIAN_STEP_M
    moved, _ = model.project(p[ok][None, :, :] + steps[:, None, :])
    J = ((moved - px[ok]) / JACOBIAN_STEP_M).transpose(1, 2, 0)
    finite = np.isfinite(J.reshape(len(J), 6).sum(axis=1))
    kept = ok.copy()
    kept[ok] = finite
    got_px, got_ok = pixels_in_image(model, p)
    np.testing.assert_array_equal(got_px, px)  # NaN where numpy's are
    np.testing.assert_array_equal(got_ok, ok)
    got_px, got_J, got_kept = visible_jacobians(model, p, JACOBIAN_STEP_M)
    np.testing.assert_array_equal(got_px, px)
    np.testing.assert_array_equal(got_kept, kept)
    assert kept.sum() > 1000
    np.testing.assert_array_equal(got_J, J[finite])


def test_the_compiled_nearest_in_cell_is_the_sorted_z_buffer(frame) -> None:
    """`nearest_in_cell` against a z-buffer written with numpy's sort: each point kept when within
    `NEAREST_TOLERANCE` of its cell's nearest range, on the frame's points and on crafted cells."""
    from ingest.train.gt.align import CELL_PX, NEAREST_TOLERANCE, nearest_in_cell

    def sorted_z_buffer(px: F64, range_m: F64) -> np.ndarray:
        cell = np.floor(px / CELL_PX).astype(np.int64)
        key = cell[:, 1] * (1 << 20) + cell[:, 0]
        order = np.argsort(key, kind="stable")
        k, ranges = key[order], range_m[order]
        first = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])
        nearest = np.repeat(np.minimum.reduceat(ranges, first), np.diff(np.r_[first, len(k)]))
        keep = np.zeros(len(px), bool)
        keep[order] = ranges <= nearest * (1 + NEAREST_TOLERANCE)
        return keep

    model, _, pts, _ = frame
    px, ok = model.project(pts)
    ok &= model.in_image(px)
    range_m = np.linalg.norm(pts[ok], axis=1)
    keep = nearest_in_cell(px[ok], range_m)
    np.testing.assert_array_equal(keep, sorted_z_buffer(px[ok], range_m))
    assert 0 < (~keep).sum() < keep.sum()  # some hidden, most seen
    # 2-px cells: (-0.5, 0) alone in cell (-1, 0); two points in cell (0, 0), two in cell (1, 0)
    crafted = np.array([[-0.5, 0.0], [1.9, 1.9], [0.1, 0.1], [2.0, 0.0], [3.9, 1.0]])
    assert nearest_in_cell(crafted, np.array([50.0, 10.0, 10.2, 4.0, 4.1])).all()
    behind = nearest_in_cell(crafted, np.array([50.0, 10.4, 10.0, 4.0, 4.2]))
    assert behind.tolist() == [True, False, True, True, False]
    assert nearest_in_cell(np.zeros((0, 2)), np.zeros(0)).shape == (0,)


def _sample(delta: F64, twist: F64, rng: np.random.Generator, sigma_rad: float = 2e-4) -> Alignment:
    info = np.diag([1 / sigma_rad**2] * 3 + [1 / (sigma_rad * 3) ** 2] * 3)
    noisy = delta + rng.normal(0, 1, 6) * np.r_[[sigma_rad] * 3, [sigma_rad * 3] * 3]
    return Alignment(noisy[:3], noisy[3:], info, 8000, 0.8, 0.0, 3.0, 1e-3)


def test_combine_tells_a_pose_error_from_a_clock_offset() -> None:
    """Per-sample corrections = each LiDAR's constant one + the offset times cam0's twist, with noise
    and one wild sample: both come back within 3 sigma; without motion the offset is not claimed."""
    rng = np.random.default_rng(7)
    top = np.r_[np.radians([0.3, -0.2, 0.1]), 0.01, -0.005, 0.002]
    bottom = np.zeros(6)
    offset_s = 0.004
    samples = []
    for k in range(40):
        twist = np.r_[rng.normal(0, 0.6, 3), rng.normal(0, 0.5, 3)]
        found = {"top": _sample(top + offset_s * twist, twist, rng),
                 "bottom": _sample(bottom + offset_s * twist, twist, rng)}  # fmt: skip
        if k == 5:
            found["top"] = _sample(top + np.r_[0.05, 0, 0, 0.2, 0, 0], twist, rng)  # a mover's frame
        samples.append((found, twist))
    c = combine(samples)
    assert c is not None and c.clock_offset_ms is not None
    assert abs(c.clock_offset_ms - 4.0) < 3 * c.sigma_clock_ms and c.sigma_clock_ms < 0.1
    for name, truth in (("top", top), ("bottom", bottom)):
        err = c.corrections[name].vector - truth
        sigma = np.sqrt(np.diag(c.corrections[name].covariance))
        assert np.all(np.abs(err) < 3 * sigma), (name, err, sigma)

    still = [({"top": _sample(top, np.zeros(6), rng)}, np.zeros(6)) for _ in range(20)]
    c = combine(still)
    assert c is not None and c.clock_offset_ms is None
    assert np.allclose(c.corrections["top"].vector, top, atol=5e-4)


def test_two_samples_name_no_pose_or_clock_and_three_do() -> None:
    """Sweep 7 U8: a right rig whose lower frames were thinned kept two aligned samples, and the check
    called lidar_top 0.36 deg and 87 mm off from them: with fewer than three samples their spread, which
    scales the sigmas, is a guess. The same samples, three of them, are named."""
    from ingest.train.gt.align_check import MIN_POSE_SAMPLES, check_calibration

    rng = np.random.default_rng(3)
    top = np.r_[np.radians([0.4, 0.0, 0.0]), 0.02, 0.0, 0.0]

    def samples(n: int) -> list[tuple[dict[str, Alignment], F64 | None]]:
        return [({"top": _sample(top, np.zeros(6), rng)}, None) for _ in range(n)]

    assert MIN_POSE_SAMPLES == 3
    few = check_calibration(samples(2))
    assert few is not None and few.suspects() == [] and few.warnings("rig.yaml") == []
    enough = check_calibration(samples(3))
    assert enough is not None and [s.split(" looks off")[0] for s in enough.suspects()] == [
        "top's pose in cam0"
    ]


def _ingest(bag: Path, out: Path, R_top: F64 | None) -> tuple[dict[str, Any], list[str]]:
    rig = Truth.load(bag).rig
    if R_top is not None:
        T = rig.lidars[0].T_cam0_lidar.copy()
        T[:3, :3] = R_top @ T[:3, :3]
        rig = replace(rig, lidars=(replace(rig.lidars[0], T_cam0_lidar=T), *rig.lidars[1:]))
    rig_file = out.with_suffix(".rig") / "rig.yaml"
    rig_file.parent.mkdir(parents=True)
    write_rig(replace(rig, camchain=None), rig_file)
    summary = ingest([bag], IngestConfig(rig=rig_file, out=out, workers=1, gt="sparse"))
    doc = yaml.safe_load((out / "dataset.yaml").read_text())
    return doc["sources"][0]["calibration_check"], summary.warnings


def test_ingest_flags_a_lidar_turned_by_a_quarter_degree_and_not_the_exact_rig(tmp_path: Path) -> None:
    """The indoor walk fixture (0.7 s, 480x300): with the exact rig, dataset.yaml's calibration check
    names no suspect and ingest warns of none; with lidar_top turned by 0.25 deg it names lidar_top's
    pose and the warning says how to refine the rig."""
    bag = FIXTURES_DIR / "indoor_walk_db3"
    check, warnings = _ingest(bag, tmp_path / "exact", None)
    assert check["suspects"] == [] and not [w for w in warnings if "calib refine" in w]
    assert check["samples"] >= 15
    assert check["lidars"]["lidar_top"]["median_misalignment_deg"] < 0.1

    turned = Rotation.from_rotvec(np.radians(0.25) * AXIS / np.linalg.norm(AXIS)).as_matrix()
    check, warnings = _ingest(bag, tmp_path / "turned", turned)
    assert len(check["suspects"]) == 1 and check["suspects"][0].startswith(
        "lidar_top's pose in cam0 looks off"
    )
    assert abs(check["lidars"]["lidar_top"]["pose_correction_deg"] - 0.25) < 0.05
    assert check["lidars"]["lidar_top"]["median_misalignment_deg"] > 0.15
    line = next(w for w in warnings if "calib refine" in w)
    assert line.startswith("lidar_top's pose in cam0 looks off by 0.2") and "--refine" in line


def test_lidars_are_compared_only_against_a_match_and_all_of_them_off_points_at_cam0() -> None:
    """Sweep 6: cam0's images upside down gave "lidar_top's points match cam0's images far worse than
    lidar_top's (-0.04 against -0.04)", and swapped camera cables blamed both LiDARs' poses alone."""
    from ingest.train.gt.align_check import CalibrationCheck, Combined

    off = np.eye(4)
    off[:3, :3] = Rotation.from_euler("y", 0.7, degrees=True).as_matrix()
    both = Combined({"top": _correction(off), "bottom": _correction(off)}, None, float("inf"), 5, 1.0)
    none_match = CalibrationCheck({}, both, {"top": -0.04, "bottom": -0.30})
    assert none_match.mismatched() == {}
    (line,) = none_match.warnings("rig.yaml")
    hint = (
        "(from 5 samples' LiDAR points on cam0's images; every LiDAR looks off, so cam0 itself may be: its "
        "intrinsics, its images or its clock)"
    )
    assert hint in line
    one = Combined({"top": _correction(off), "bottom": _correction(np.eye(4))}, None, float("inf"), 5, 1.0)
    (line,) = CalibrationCheck({}, one, {"top": 0.25, "bottom": 0.70}).warnings("rig.yaml")
    assert (
        line.startswith("top's points match cam0's images far worse than bottom's")
        and "every LiDAR" not in line
    )


def test_check_calibration_of_no_alignment_is_none() -> None:
    assert check_calibration([({}, None), ({}, np.zeros(6))]) is None


def _correction(T: F64) -> Alignment:
    """An `Alignment` holding the rigid motion `T` (4x4), with a tight information matrix."""
    rotvec = Rotation.from_matrix(T[:3, :3]).as_rotvec()
    return Alignment(rotvec, T[:3, 3].copy(), np.eye(6) * 1e10, 40, float("nan"), float("nan"), 3.0, 1e-3)


def test_the_stereo_pose_error_comes_back_from_both_images_corrections() -> None:
    """A LiDAR off by X in cam0 and a stereo pose off by E: the corrections onto cam0 (X) and onto cam1
    (E T10 X T10^-1) give E back, 0.3 deg and 5 mm; an exact stereo pose gives nothing."""
    from calibration.rig import REFERENCE_RIG, read_rig
    from ingest.train.gt.align_check import Combined
    from ingest.train.run.lidar_poses import stereo_alignment

    rig = read_rig(REFERENCE_RIG)
    T10 = rig.lower.T_cam_cam0

    def motion(rotvec_deg: list[float], shift_m: list[float]) -> F64:
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
        T[:3, 3] = shift_m
        return T

    X = motion([0.6, -0.48, 0.64], [0.02, -0.015, 0.0158])
    for E, deg, mm in ((motion([0.0, 0.3, 0.0], [0.005, 0.0, 0.0]), 0.3, 5.0), (np.eye(4), 0.0, 0.0)):
        upper = Combined({"top": _correction(X)}, None, float("inf"), 40, 1.0)
        lower = Combined({"top": _correction(E @ T10 @ X @ np.linalg.inv(T10))}, None, float("inf"), 40, 1.0)
        found = stereo_alignment(rig, upper, lower)
        assert found is not None and found.lidar == "top"
        assert found.rotation_deg == pytest.approx(deg, abs=1e-6)
        moved = np.linalg.norm((E @ T10)[:3, 3] - T10[:3, 3]) * 1e3
        assert found.translation_mm == pytest.approx(moved, abs=1e-6) and moved == pytest.approx(mm, abs=0.5)
        assert found.disagrees == (deg > 0)


def test_an_alignment_only_run_writes_no_sample_and_finds_what_the_metas_record(tmp_path: Path) -> None:
    """`calib refine`'s rounds (`SampleParams.alignment_only`) on the indoor walk fixture: no image,
    GT or meta file is written, and each sample's alignments onto both images and cam0's twist are the
    ones a sparse ingest that writes the samples records in its metas (to JSON's rounding)."""
    from ingest.dataset.meta import read_meta
    from ingest.train.gt.align_check import from_metas, from_records
    from ingest.train.run.sample_job import SampleParams

    bag = FIXTURES_DIR / "indoor_walk_db3"
    rig_file = tmp_path / "rig" / "rig.yaml"
    rig_file.parent.mkdir()
    write_rig(replace(Truth.load(bag).rig, camchain=None), rig_file)
    runs = {}
    for name, only in (("written", False), ("aligned", True)):
        cfg = IngestConfig(rig=rig_file, out=tmp_path / name, workers=1, gt="sparse")
        sample = SampleParams(align_lower=True, lower_every=1, alignment_only=only)
        runs[name] = ingest([bag], replace(cfg, sample=sample))
    files = [p for p in (tmp_path / "aligned").rglob("*") if p.is_file() and p.name != "dataset.yaml"]
    assert runs["aligned"].written == 0 and not [p for p in files if p.suffix in (".png", ".json", ".exr")]
    metas = [
        read_meta(tmp_path / "written", p.stem) for p in sorted((tmp_path / "written/meta").glob("*.json"))
    ]
    assert len(metas) == runs["written"].written == len(runs["aligned"].aligned) >= 15
    aligned = [runs["aligned"].aligned[sid] for sid in sorted(runs["aligned"].aligned)]
    got = from_records([(a.upper, a.lower, a.twist_cam0) for a in aligned])
    for mine, theirs in zip(got, from_metas(metas), strict=True):
        assert len(mine) == len(theirs)
        for (found, twist), (recorded, twist_recorded) in zip(mine, theirs, strict=True):
            assert set(found) == set(recorded) and found
            for name, a in found.items():
                np.testing.assert_allclose(a.vector, recorded[name].vector, atol=1e-6)
            assert (twist is None) == (twist_recorded is None)
            if twist is not None and twist_recorded is not None:
                assert np.abs(twist - twist_recorded).max() <= 1e-6


def test_images_too_coarse_to_align_on_are_said_and_not_aligned() -> None:
    """Sweep 6 U1: the tool's own 48x30 px emulated capture of a right rig was said to have lidar_top 10.4
    deg and 641 mm off (4 deg pixels: the alignment cannot measure a pose there). Such images get one
    line and no alignment; the reference rig's own images are aligned."""
    from calibration.rig import REFERENCE_RIG, read_rig
    from ingest.train.run.sample_job import Geometry
    from sensorbox.sim.run import scaled_rig

    coarse = Geometry.from_rig(scaled_rig(read_rig(REFERENCE_RIG), 0.025))
    assert coarse.too_coarse_to_align
    assert coarse.coarse_line() == (
        "cam0's images (48x30 px, 3.7 deg a pixel) are too coarse to lay the LiDAR points on (over 2 "
        "deg a pixel): the pose, clock and stereo checks were not run"
    )
    fine = Geometry.from_rig(read_rig(REFERENCE_RIG))
    assert not fine.too_coarse_to_align and fine.coarse_line() == ""
