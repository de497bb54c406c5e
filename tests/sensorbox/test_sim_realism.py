"""The simulator's real-world error sources, each against its exact truth: camera clock offsets, IMU
noise and bias, range noise that depends on range and reflectivity, mixed returns at depth edges."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from calibration.errors import SensorboxError
from calibration.rig import read_rig
from ingest.bags.decode import decode_imu
from sensorbox.sim.config import SimConfig, with_mid360_imu_noise
from sensorbox.sim.lidar import PULSE_SEPARATION_M, mixed_ranges, range_sigma_m
from sensorbox.sim.run import imu_biases, simulate
from sensorbox.sim.trajectory import imu_readings
from sensorbox.sim.truth import Truth


def _messages(bag: Path) -> dict[str, list[tuple[int, bytes]]]:
    """Per topic: (header stamp ns, raw bytes) of every image and IMU message, in log order."""
    out: dict[str, list[tuple[int, bytes]]] = {}
    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if "lidar" not in c.topic]
        for conn, _, raw in reader.messages(connections=conns):
            msg: Any = reader.deserialize(raw, conn.msgtype)
            stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            out.setdefault(conn.topic, []).append((stamp, bytes(msg.data) if "zed" in conn.topic else raw))
    return out


def test_camera_offset_moves_each_cameras_stamps_and_the_truth_rig_carries_it(tmp_path: Path) -> None:
    """Same seed, same frames: only the header stamps move, by each camera's own offset; the truth rig's
    timeshift_cam_imu maps them back to the true exposure (Kalibr: t_imu = t_cam + shift)."""
    base = SimConfig(scene="indoor", trajectory="walk", duration_s=0.2, scale=0.1, seed=4)
    simulate(base, tmp_path / "exact")
    simulate(SimConfig(**{**base.__dict__, "camera_offset_ns": (7_000_000, -3_500_000)}), tmp_path / "late")
    exact, late = _messages(tmp_path / "exact"), _messages(tmp_path / "late")
    cams = sorted(t for t in exact if "zed" in t)  # lower, upper
    for topic, offset_ns in zip(cams, (-3_500_000, 7_000_000), strict=True):
        assert len(exact[topic]) == len(late[topic]) >= 5
        for (s0, img0), (s1, img1) in zip(exact[topic], late[topic], strict=True):
            assert s1 - s0 == offset_ns
            assert img0 == img1  # rendered at the same true exposure
    for topic in (t for t in exact if "imu" in t):
        assert exact[topic] == late[topic]
    truth = Truth.load(tmp_path / "late")
    assert truth.camera_offset_ns == (7_000_000, -3_500_000)
    assert truth.exposure_ns(late[cams[1]][0][0], 0) == exact[cams[1]][0][0]
    rig = read_rig(truth.path / "rig.yaml")
    assert rig.upper.timeshift_cam_imu == pytest.approx(-0.007, abs=1e-15)
    assert rig.lower.timeshift_cam_imu == pytest.approx(0.0035, abs=1e-15)
    assert rig.upper.timeshift_ns == -7_000_000
    assert read_rig(Truth.load(tmp_path / "exact").path / "rig.yaml").upper.timeshift_cam_imu is None
    assert "realism" not in Truth.load(tmp_path / "exact").params


def test_imu_noise_has_the_datasheets_density_and_the_recorded_bias(tmp_path: Path) -> None:
    """Readings minus the closed-form motion: per-axis mean = the bias sim.yaml records (within 4 standard
    errors) and spread = density * sqrt(rate) (within 15 %, 400 readings a axis)."""
    cfg = with_mid360_imu_noise(
        SimConfig(scene="indoor", trajectory="walk", duration_s=2.0, scale=0.05, seed=2)
    )
    assert cfg.gyro_noise_rad_s == pytest.approx(np.radians(4.5e-3) * np.sqrt(200))
    assert cfg.acc_noise_g == pytest.approx(100e-6 * np.sqrt(200))
    simulate(cfg, tmp_path / "bag")
    truth = Truth.load(tmp_path / "bag")
    msgs = _messages(tmp_path / "bag")
    for k, imu in enumerate(truth.params["imus"]):
        readings = [decode_imu(raw) for _, raw in msgs[imu["topic"]]]
        offset_ns = truth.params["lidars"][k]["clock_offset_ns"]
        t_s = (np.array([r.stamp_ns for r in readings]) - truth.start_ns - offset_ns) / 1e9
        gyro, acc = imu_readings(truth.trajectory, t_s, np.array(imu["T_cam0_imu"]))
        e_gyro = np.array([r.gyro_rad_s for r in readings]) - gyro
        e_acc = np.array([r.acc for r in readings]) - acc
        gyro_bias, acc_bias = imu_biases(cfg, k)
        np.testing.assert_allclose(imu["gyro_bias_rad_s"], gyro_bias)
        np.testing.assert_allclose(imu["acc_bias_g"], acc_bias)
        n = len(readings)
        assert n == pytest.approx(400, abs=2)
        np.testing.assert_allclose(e_gyro.mean(0), gyro_bias, atol=4 * cfg.gyro_noise_rad_s / np.sqrt(n))
        np.testing.assert_allclose(e_acc.mean(0), acc_bias, atol=4 * cfg.acc_noise_g / np.sqrt(n))
        np.testing.assert_allclose(e_gyro.std(0), cfg.gyro_noise_rad_s, rtol=0.15)
        np.testing.assert_allclose(e_acc.std(0), cfg.acc_noise_g, rtol=0.15)


def test_mid360_range_sigma_grows_with_range_and_falls_with_reflectivity() -> None:
    sigma = range_sigma_m(
        np.array([10.0, 0.0, 30.0, 10.0, 10.0]), np.array([50.0, 50.0, 50.0, 200.0, 0.0]), 0.02
    )
    np.testing.assert_allclose(sigma, [0.02, 0.01, 0.04, 0.01, 0.02 * np.sqrt(10)])


class _Step:
    """A fake scene for `mixed_ranges`: rays with y > 0 meet a surface at `upper_m`, the rest at `lower_m`
    (inf: nothing)."""

    def __init__(self, upper_m: float, lower_m: float) -> None:
        self.upper_m, self.lower_m = upper_m, lower_m

    def cast(self, origins: Any, dirs: Any, t_s: Any) -> Any:
        class Hits:
            range_m = np.where(dirs[:, 1] > 0, self.upper_m, self.lower_m)

        return Hits()


def _beam(dirs: np.ndarray, scene: _Step) -> np.ndarray:
    centre = scene.cast(None, dirs, 0.0).range_m
    return mixed_ranges(scene, np.zeros_like(dirs), dirs, np.zeros(len(dirs)), centre, np.radians(0.2))  # type: ignore[arg-type]


def test_mixed_returns_at_a_depth_edge() -> None:
    """A beam straddling y = 0 with its centre just above: centre and the +y rim ray on the upper surface,
    the -y rim ray below, the two x rim rays (y = 1e-6 > 0) above. Energy weights 1/r^2."""
    d = np.array([[0.0, 1e-6, 1.0]])
    d /= np.linalg.norm(d)
    flat = _beam(d, _Step(4.0, 4.0))
    np.testing.assert_allclose(flat, [4.0])
    # within one pulse length: one return at the weighted mean range
    near = _beam(d, _Step(2.0, 2.0 + PULSE_SEPARATION_M / 2))
    w_up, w_lo = 4 / 2.0**2, 1 / 2.75**2
    np.testing.assert_allclose(near, [(w_up * 2.0 + w_lo * 2.75) / (w_up + w_lo)])
    # far apart: two groups, the one returning more energy wins (four rays near beat one far)
    np.testing.assert_allclose(_beam(d, _Step(2.0, 10.0)), [2.0])
    # centre just below: one rim ray on the near surface (energy 1/4), four on a farther one
    d_low = np.array([[0.0, -1e-6, 1.0]]) / np.linalg.norm([0.0, -1e-6, 1.0])
    far_m = 2.0 + PULSE_SEPARATION_M + 0.1
    np.testing.assert_allclose(_beam(d_low, _Step(2.0, far_m)), [far_m])  # 4 / 3.6^2 > 1 / 2^2: far wins
    np.testing.assert_allclose(_beam(d_low, _Step(2.0, 5.0)), [2.0])  # 4 / 5^2 < 1 / 2^2: near wins
    np.testing.assert_allclose(_beam(d_low, _Step(2.0, np.inf)), [2.0])  # the rest sees sky
    assert np.isinf(_beam(d, _Step(np.inf, np.inf))).all()


def test_realism_switches_are_recorded_and_exact_runs_unchanged(tmp_path: Path) -> None:
    """sim.yaml records what was on; a run with every switch off writes the same bag as before they
    existed (the bundled fixtures regenerate to their stored bytes: tests/sensorbox/test_fixtures.py)."""
    cfg = SimConfig(
        scene="outdoor", trajectory="walk", duration_s=0.2, scale=0.1, seed=1,
        range_noise_model="mid360", mixed_returns=True, camera_offset_ns=(1_000_000, 1_000_000),
    )  # fmt: skip
    simulate(with_mid360_imu_noise(cfg), tmp_path / "bag")
    params = Truth.load(tmp_path / "bag").params
    assert params["realism"] == {
        "camera_offset_ns": [1_000_000, 1_000_000], "range_noise_model": "mid360", "mixed_returns": True,
        "beam_divergence_deg": 0.2,
    }  # fmt: skip
    assert params["gyro_noise_rad_s"] > 0


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"range_noise_model": "gauss"}, r"--range-noise-model 'gauss': expected one of constant, mid360"),
        ({"camera_offset_ns": (2_000_000_000, 0)}, r"--camera-offset-ms 2000: expected within \+-1000 ms"),
        (
            {"camera_offset_ns": (0, 1_000_001_000)},
            r"--camera-offset-ms 1000.001: expected within \+-1000 ms",
        ),
    ],
)
def test_a_bad_realism_setting_is_one_line(tmp_path: Path, change: dict[str, object], message: str) -> None:
    cfg = SimConfig(**{"duration_s": 0.1, "scale": 0.1, **change})  # type: ignore[arg-type]
    with pytest.raises(SensorboxError, match=message):
        simulate(cfg, tmp_path / "bag")
    assert list(tmp_path.iterdir()) == []
