"""`calib refine` against the simulator's exact truth: camera clock offsets and IMU (LiDAR) rotations
recovered from the recording alone, unobservable ones reported and left as the rig has them.

The estimators are checked first on exact rotations (the simulator's closed-form motion, with the
Mid-360 gyro's noise and bias and 0.1 deg of image-rotation noise), then end to end on a rendered
walk at 480x300 (tracking on images, much coarser than the full-resolution bench)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from calibration.rig import REFERENCE_RIG, read_rig, with_timeshifts
from calibration.types import F64, I64
from ingest.train.run.refine import PAIR_GAPS, refine
from ingest.train.run.timeshift import (
    MAX_ROTATION_SIGMA_DEG,
    FrameRotations,
    check_stereo_rotation,
    estimate_imu_rotation,
    estimate_timeshift,
)
from ingest.train.trajectory.clouds import integrate_gyro
from sensorbox.sim.config import SimConfig, with_mid360_imu_noise
from sensorbox.sim.run import simulate
from sensorbox.sim.trajectory import imu_readings, static, walk
from sensorbox.sim.truth import Truth
from tests.faults.cli import sensorbox
from tests.paths import FIXTURES_DIR

START = np.array([0.0, 0.0, 1.4])
TURN = Rotation.from_rotvec(np.radians(1.0) * np.array([0.6, -0.48, 0.64])).as_matrix()


def _exact(kind: str, seconds: float, offset_ns: int, seed: int = 0) -> tuple[FrameRotations, F64, I64]:
    """cam0's rotations between frames `PAIR_GAPS` apart at 30 Hz (header stamp = exposure + offset), with
    0.1 deg of noise; the gyro's readings at 200 Hz in the reference rig's first IMU (noise, bias), and
    their stamps."""
    traj = walk(START, seed) if kind == "walk" else static(START)
    T_cam0_imu = read_rig(REFERENCE_RIG).imus[0].T_cam0_imu
    rng = np.random.default_rng(seed)
    exposure_ns = np.arange(0.2e9, (seconds - 0.2) * 1e9, 1e9 / 30).astype(np.int64)
    R = traj.T_world_cam0(exposure_ns / 1e9)[:, :3, :3]
    t0, t1, rv = [], [], []
    for gap in PAIR_GAPS:
        rel = np.einsum("nji,njk->nik", R[:-gap], R[gap:])
        noise = rng.normal(0, np.radians(0.1) / np.sqrt(3), (len(rel), 3))
        rv.append(Rotation.from_matrix(rel).as_rotvec() + noise)
        t0.append(exposure_ns[:-gap] + offset_ns)
        t1.append(exposure_ns[gap:] + offset_ns)
    t0_ns = np.concatenate(t0)
    rot = FrameRotations(t0_ns, np.concatenate(t1), np.concatenate(rv), np.full(len(t0_ns), 100, np.int64))
    imu_ns = np.arange(0, int(seconds * 1e9), 5_000_000, dtype=np.int64)
    cfg = with_mid360_imu_noise(SimConfig())
    gyro, _ = imu_readings(traj, imu_ns / 1e9, T_cam0_imu)
    gyro = gyro + rng.normal(0, cfg.gyro_bias_rad_s, 3) + rng.normal(0, cfg.gyro_noise_rad_s, gyro.shape)
    return rot, gyro, imu_ns


def test_the_offset_comes_back_from_exact_rotations_and_a_noisy_gyro() -> None:
    rot, gyro, imu_ns = _exact("walk", 6.0, 17_000_000)
    R_cam0_imu = read_rig(REFERENCE_RIG).imus[0].T_cam0_imu[:3, :3]
    est = estimate_timeshift(rot, integrate_gyro(imu_ns, gyro, R_cam0_imu), np.eye(3))
    assert est.observable
    assert est.timeshift_ms == pytest.approx(-17.0, abs=0.2)
    assert abs(est.timeshift_ms + 17.0) <= 3 * est.sigma_ms
    assert est.residual_after_deg < est.residual_before_deg / 3
    assert est.excitation_deg_s > 10


def test_an_imu_rotation_off_by_a_degree_comes_back() -> None:
    rot, gyro, imu_ns = _exact("walk", 6.0, 0)
    R_true = read_rig(REFERENCE_RIG).imus[0].T_cam0_imu[:3, :3]
    found = estimate_imu_rotation(rot, integrate_gyro(imu_ns, gyro, np.eye(3)), 0, TURN @ R_true)
    assert found.observable
    assert found.correction_deg == pytest.approx(1.0, abs=0.05)
    error_deg = np.degrees(np.linalg.norm(Rotation.from_matrix(found.R_cam0_imu @ R_true.T).as_rotvec()))
    assert error_deg < 0.05
    assert error_deg <= 3 * found.sigma_deg


def test_a_stereo_rotation_off_by_half_a_degree_is_found_and_an_exact_one_is_not() -> None:
    """cam1's rotations are cam0's seen through the true R_cam1_cam0 (0.1 deg of noise, stamps 0.1 ms
    later): a camchain whose stereo rotation is 0.5 deg off is flagged, the exact one is not."""
    upper, _, _ = _exact("walk", 6.0, 0)
    R_true = read_rig(REFERENCE_RIG).lower.T_cam_cam0[:3, :3]
    noise = np.random.default_rng(9).normal(0, np.radians(0.1) / np.sqrt(3), upper.rotvec.shape)
    lower = FrameRotations(upper.t0_ns + 100_000, upper.t1_ns + 100_000, upper.rotvec @ R_true.T + noise,
                           upper.tracks)  # fmt: skip
    exact = check_stereo_rotation(upper, lower, R_true)
    assert exact.observable and exact.pairs >= 0.95 * len(upper.t0_ns)
    assert exact.angle_deg <= 3 * exact.sigma_deg and not exact.disagrees
    off = check_stereo_rotation(
        upper, lower, Rotation.from_rotvec([0.0, np.radians(0.5), 0.0]).as_matrix() @ R_true
    )
    assert off.disagrees
    assert off.angle_deg == pytest.approx(0.5, abs=3 * off.sigma_deg)


def test_a_rig_that_stood_still_reveals_neither() -> None:
    rot, gyro, imu_ns = _exact("static", 3.0, 17_000_000)
    R_cam0_imu = read_rig(REFERENCE_RIG).imus[0].T_cam0_imu[:3, :3]
    est = estimate_timeshift(rot, integrate_gyro(imu_ns, gyro, R_cam0_imu), np.eye(3), prior_ms=2.0)
    assert not est.observable
    assert est.timeshift_ms == 2.0  # the prior, not a guess
    assert est.excitation_deg_s < 1.0
    found = estimate_imu_rotation(rot, integrate_gyro(imu_ns, gyro, np.eye(3)), 0, R_cam0_imu)
    assert not found.observable
    assert found.sigma_deg > MAX_ROTATION_SIGMA_DEG


@pytest.fixture(scope="module")
def late_walk(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """2.5 s of outdoor walking at 480x300, cameras stamped 10 ms late (upper) and 6 ms early (lower)."""
    out = tmp_path_factory.mktemp("refine") / "walk"
    cfg = SimConfig(
        scene="outdoor", trajectory="walk", duration_s=2.5, scale=0.25, seed=3,
        camera_offset_ns=(10_000_000, -6_000_000),
    )  # fmt: skip
    simulate(with_mid360_imu_noise(cfg), out)
    return out


@pytest.mark.xdist_group("late_walk")  # one worker renders the module's walk once
def test_refine_recovers_the_camera_offsets_of_a_rendered_walk(late_walk: Path) -> None:
    """The rig without its offsets and with the top LiDAR (and its IMU) turned by 1 deg: the offsets come
    back within 3 sigma and 1.5 ms at this resolution; the rotation is found to within its sigma but
    (over 2.5 s at 480x300) not certain enough to be written, so the rig keeps it."""
    truth = Truth.load(late_walk)
    exact = truth.rig
    plain = with_timeshifts(exact, {c.name: 0.0 for c in exact.cameras})
    turned_imu = replace(plain.imus[0], T_cam0_imu=_turned(plain.imus[0].T_cam0_imu))
    turned_lidar = replace(plain.lidars[0], T_cam0_lidar=_turned(plain.lidars[0].T_cam0_lidar))
    given = replace(plain, imus=(turned_imu, *plain.imus[1:]), lidars=(turned_lidar, *plain.lidars[1:]))
    found = refine([late_walk], given)
    assert found.frames == {"cam0": 75, "cam1": 75}
    for cam, true_ms in zip(found.cameras, (-10.0, 6.0), strict=True):
        assert cam.applied and cam.estimate.observable
        error = abs(cam.estimate.timeshift_ms - true_ms)
        assert error <= min(1.5, 3 * cam.estimate.sigma_ms), (cam.camera, cam.estimate)
        assert found.rig.camera(cam.camera).timeshift_cam_imu == pytest.approx(
            cam.estimate.timeshift_ms / 1e3
        )
    top = found.imus[0]
    assert (top.imu, top.lidar) == ("imu_top", "lidar_top")
    assert abs(top.rotation.correction_deg - 1.0) <= 3 * top.rotation.sigma_deg
    if not top.rotation.observable:
        np.testing.assert_array_equal(found.rig.lidars[0].T_cam0_lidar, turned_lidar.T_cam0_lidar)
        np.testing.assert_array_equal(found.rig.imus[0].T_cam0_imu, turned_imu.T_cam0_imu)


def _angle_deg(Ra: F64, Rb: F64) -> float:
    return float(np.degrees(Rotation.from_matrix(Ra @ Rb.T).magnitude()))


def _turned(T: F64) -> F64:
    out = T.copy()
    out[:3, :3] = TURN @ T[:3, :3]
    return out


def test_refine_cli_writes_the_refined_rig_and_says_what_it_could_not_see(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The fixture's static room with a rig that says its cameras are 2 ms late: the clocks are not
    observable and keep the rig's values, one warning line per camera says why and what to record; the
    LiDAR poses, exact here, come back within the issue's targets (0.05 deg, 5 mm): a negative control of
    the alignment."""
    bag = FIXTURES_DIR / "indoor_static_mcap"
    rig = tmp_path / "rig" / "plain.yaml"
    rig.parent.mkdir()
    exact = Truth.load(bag).rig
    from calibration.rig import write_rig

    write_rig(with_timeshifts(exact, {"cam0": 0.002, "cam1": 0.002}), rig)
    code, out, err = sensorbox(
        capsys, "calib", "refine", str(bag), "--rig", str(rig), "--out", str(tmp_path / "refined.yaml"),
        "--plot", str(tmp_path / "timeshift.png"),
    )  # fmt: skip
    assert code == 0, err
    refined = read_rig(tmp_path / "refined.yaml")
    assert [c.timeshift_cam_imu for c in refined.cameras] == [0.002, 0.002]
    for a, b in zip(refined.lidars, read_rig(rig).lidars, strict=True):
        assert _angle_deg(a.T_cam0_lidar[:3, :3], b.T_cam0_lidar[:3, :3]) < 0.05
        assert np.linalg.norm(a.T_cam0_lidar[:3, 3] - b.T_cam0_lidar[:3, 3]) < 0.005
    assert "LiDAR poses in cam0" in out
    warnings = [line for line in out.splitlines() if line.startswith("warning: cam")]
    assert len(warnings) == 2
    assert "clock offset not observable from this recording" in warnings[0]
    assert "the rig's +2.000 ms is kept" in warnings[0]
    assert (tmp_path / "timeshift.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    # a rig of another resolution than the images: one line, exit 2
    write_rig(read_rig(REFERENCE_RIG), tmp_path / "full.yaml")
    code, _, err = sensorbox(capsys, "calib", "refine", str(bag), "--rig", str(tmp_path / "full.yaml"),
                             "--out", str(tmp_path / "x.yaml"))  # fmt: skip
    assert code == 2
    assert len(err) == 1 and "a 480x300 image; camera cam" in err[0] and "is 1920x1200" in err[0], err
    assert not (tmp_path / "x.yaml").exists()


@pytest.mark.xdist_group("late_walk")  # one worker renders the module's walk once
def test_ingest_refine_times_the_samples_with_the_offsets_it_found(late_walk: Path, tmp_path: Path) -> None:
    """`ingest --refine` with a rig that has no offsets: every sample's exposure is its stamp plus the
    estimate (within 1.5 ms of the truth), the summary carries the refinement, dataset.yaml says where
    the offsets came from, and the dataset's rig is the refined one."""
    from calibration.rig import write_rig
    from ingest.train.run.pipeline import ingest
    from ingest.train.run.settings import IngestConfig

    exact = Truth.load(late_walk).rig
    rig = tmp_path / "rig" / "plain.yaml"
    rig.parent.mkdir()
    write_rig(with_timeshifts(exact, {c.name: 0.0 for c in exact.cameras}), rig)
    out = tmp_path / "ds"
    summary = ingest(
        [late_walk], IngestConfig(rig=rig, out=out, workers=1, every=5, refine=True, height_full=96)
    )
    assert summary.refinement is not None
    found_ms = summary.refinement.cameras[0].estimate.timeshift_ms
    assert abs(found_ms + 10.0) <= 1.5
    metas = [json.loads(p.read_text()) for p in sorted((out / "meta").glob("*.json"))]
    assert len(metas) == summary.written >= 10
    for m in metas:
        assert m["clock_offset_ms"] == pytest.approx(found_ms, abs=1e-6)
        assert m["exposure_ns"] - m["stamp_ns"] == round(found_ms * 1e6)
    doc = yaml.safe_load((out / "dataset.yaml").read_text())
    assert doc["rig"]["camera_clock_offsets"]["cam0"]["from"].startswith(
        "--refine: estimated from the recording"
    )
    assert read_rig(out / "rig" / "rig.yaml").upper.timeshift_cam_imu == pytest.approx(found_ms / 1e3)
    poses = doc["rig"]["lidar_poses"]
    assert set(poses) == {lidar.name for lidar in summary.refinement.rig.lidars}
    for lidar in summary.refinement.rig.lidars:
        np.testing.assert_allclose(poses[lidar.name]["T_cam0_lidar"], lidar.T_cam0_lidar, atol=1e-12)
        assert poses[lidar.name]["from"].startswith("--refine: its points laid onto cam0's images")


def test_lidar_poses_come_back_through_two_alignment_rounds() -> None:
    """`_refine_lidars` with an aligner that reports each LiDAR's true error (what a perfect alignment
    would, with 0.01 deg / 0.5 mm of noise per sample): both LiDARs, off by 1 deg / 30 mm and 0.5 deg /
    20 mm, come back within 0.02 deg and 1 mm, each IMU moves with the LiDAR of its housing, and the
    table's numbers are the corrections applied."""
    from ingest.train.gt.align import Alignment
    from ingest.train.run.lidar_poses import LidarRefinement
    from ingest.train.run.refine import Refinement, _refine_lidars
    from ingest.train.run.timeshift import StereoCheck

    truth = read_rig(REFERENCE_RIG)

    def moved(T: F64, rotvec_deg: list[float], shift_m: list[float]) -> F64:
        out = T.copy()
        out[:3, :3] = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix() @ T[:3, :3]
        out[:3, 3] = T[:3, 3] + shift_m
        return out

    errors = (([0.6, -0.48, 0.64], [0.02, -0.015, 0.0158]), ([-0.2, 0.3, 0.3464], [-0.01, 0.012, -0.0126]))
    given = replace(
        truth,
        lidars=tuple(replace(x, T_cam0_lidar=moved(x.T_cam0_lidar, *e)) for x, e in zip(truth.lidars, errors, strict=True)),
        imus=tuple(replace(x, T_cam0_imu=moved(x.T_cam0_imu, *e)) for x, e in zip(truth.imus, errors, strict=True)),
    )  # fmt: skip
    rng = np.random.default_rng(3)

    def align(candidate, frames):
        samples = []
        for _ in range(frames // 10):
            found = {}
            for lidar in candidate.lidars:
                fix = truth.lidar(lidar.name).T_cam0_lidar @ np.linalg.inv(lidar.T_cam0_lidar)
                rotvec = Rotation.from_matrix(fix[:3, :3]).as_rotvec() + rng.normal(0, np.radians(0.01), 3)
                info = np.diag([1 / np.radians(0.01) ** 2] * 3 + [1 / 0.0005**2] * 3)
                found[lidar.name] = Alignment(rotvec, fix[:3, 3] + rng.normal(0, 0.0005, 3), info, 9000, 0.8,
                                              0.1, 4.0, 5e-4)  # fmt: skip
            samples.append((found, rng.normal(0, 0.5, 6)))
        return samples, [(found, None) for found, _ in samples]

    stereo = StereoCheck(0.0, 1.0, False, 0, 0.0, 0.0)
    found = _refine_lidars(Refinement((), (), given, {"cam0": 400, "cam1": 400}, {}, stereo), align)
    for lidar, imu, (rotvec, _) in zip(found.rig.lidars, found.rig.imus, errors, strict=True):
        exact = truth.lidar(lidar.name)
        assert _angle_deg(lidar.T_cam0_lidar[:3, :3], exact.T_cam0_lidar[:3, :3]) < 0.02
        assert np.linalg.norm(lidar.T_cam0_lidar[:3, 3] - exact.T_cam0_lidar[:3, 3]) < 0.001
        exact_imu = next(i for i in truth.imus if i.name == imu.name)
        assert _angle_deg(imu.T_cam0_imu[:3, :3], exact_imu.T_cam0_imu[:3, :3]) < 0.02
        row: LidarRefinement = next(r for r in found.lidars if r.lidar == lidar.name)
        assert row.applied and row.samples == 40
        assert row.rotation_deg == pytest.approx(np.linalg.norm(rotvec), abs=0.02)
    assert found.stereo_alignment is not None and not found.stereo_alignment.disagrees
