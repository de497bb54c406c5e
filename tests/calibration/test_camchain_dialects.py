"""Camchain files as other tools write them (issue 19, item 1).

Each fixture reproduces one way real files were refused: OpenCV's
``%YAML:1.0`` header and ``!!opencv-matrix`` nodes, camchain-imucam files
whose cam n has ``T_cam_imu`` but no ``T_cn_cnm1``, 4x4 matrices written as 16
numbers, and top-level keys that are not cameras. The extrinsics are EuRoC's
(the camera-IMU poses as OpenVINS ships them, and Kalibr's cam1-cam0 pose).
"""

import logging
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from calibration import CalibrationError, DoubleSphere, Pinhole, RadTan, read_kalibr_camchain, read_rig
from calibration.kalibr import EXTRINSIC_TOL_DEG, EXTRINSIC_TOL_M
from calibration.transforms import invert, make_transform, rot_z

ROOT = Path(__file__).resolve().parents[2]

T_IMU_CAM0 = np.array([
    [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
    [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
    [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
    [0.0, 0.0, 0.0, 1.0],
])  # fmt: skip
T_IMU_CAM1 = np.array([
    [0.0125552670891, -0.999755099723, 0.0182237714554, -0.0198435579556],
    [0.999598781151, 0.0130119051815, 0.0251588363115, 0.0453689425024],
    [-0.0253898008918, 0.0179005838253, 0.999517347078, 0.00786212447038],
    [0.0, 0.0, 0.0, 1.0],
])  # fmt: skip
T_C1_C0_KALIBR = np.array([
    [0.999997256477, 0.00231206719295, 0.000376008102415, -0.110073808127],
    [-0.00231713572422, 0.999898048507, 0.0140898358497, 0.000399121547014],
    [-0.000343393120525, -0.0140906685417, 0.999900662638, -0.000853702503357],
    [0.0, 0.0, 0.0, 1.0],
])  # fmt: skip
RADTAN0 = RadTan(-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)


def rows(T, indent=4):
    """A 4x4 matrix as Kalibr writes it (a YAML block list of rows), indented."""
    pad = " " * indent
    return "\n".join(f"{pad}- [{', '.join(repr(float(v)) for v in row)}]" for row in T)


def flat(T):
    return "[" + ", ".join(repr(float(v)) for v in np.asarray(T).ravel()) + "]"


def camera(name, extra, intrinsics="[458.654, 457.296, 367.215, 248.375]"):
    return textwrap.dedent(f"""\
        {name}:
          camera_model: pinhole
          distortion_coeffs: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
          distortion_model: radtan
          intrinsics: {intrinsics}
          resolution: [752, 480]
          rostopic: /{name}/image_raw
        """) + textwrap.indent(extra, "  ")


def kalibr_with_T_cn_cnm1():
    """The plain Kalibr camchain that every dialect below must read the same as."""
    return camera("cam0", "") + camera("cam1", f"T_cn_cnm1:\n{rows(T_C1_C0_KALIBR, 2)}\n")


def read(tmp_path, text, name="camchain.yaml"):
    path = tmp_path / name
    path.write_text(text)
    return read_kalibr_camchain(path)


def assert_same_chain(a, b, atol=0.0):
    assert [c.name for c in a.cameras] == [c.name for c in b.cameras]
    for ca, cb in zip(a.cameras, b.cameras, strict=True):
        assert ca.model == cb.model
        assert np.allclose(ca.T_cam_cam0, cb.T_cam_cam0, atol=atol, rtol=0.0)


# -- %YAML:1.0 and !!opencv-matrix ---------------------------------------------------------------


@pytest.mark.parametrize(
    "header",
    [
        "%YAML:1.0\n",
        "%YAML:1.0\n---\n",
        "%YAML:1.0\r\n\r\n",
        "%YAML:1.0 # need to specify the file type at the top!\n",
    ],
)
def test_opencv_yaml_header_is_read(tmp_path, header):
    plain = read(tmp_path, kalibr_with_T_cn_cnm1(), "plain.yaml")
    chain = read(tmp_path, header + kalibr_with_T_cn_cnm1())
    assert_same_chain(chain, plain)
    assert chain.cameras[0].model == Pinhole(458.654, 457.296, 367.215, 248.375, 752, 480, RADTAN0)


def test_an_extrinsic_printed_with_five_decimals_is_used_as_its_nearest_rotation(tmp_path, caplog):
    """KAIST's OpenVINS camchain prints five decimals: |R^T R - I| = 2.1e-5 was refused (tolerance 1e-5).
    Such a rotation is replaced by its nearest one with a warning naming it; beyond 1e-3 it is refused."""
    from scipy.spatial.transform import Rotation

    def chain_with(T):
        return camera("cam0", "") + camera("cam1", f"T_cn_cnm1:\n{rows(T, 2)}\n")

    R = Rotation.random(
        random_state=2018
    ).as_matrix()  # of 3000 random rotations, the farthest off at 5 decimals
    T = np.eye(4)
    T[:3, :3] = np.round(R, 5)
    T[:3, 3] = T_C1_C0_KALIBR[:3, 3]
    assert 1e-5 < np.abs(T[:3, :3].T @ T[:3, :3] - np.eye(3)).max() < 1e-4
    with caplog.at_level(logging.WARNING):
        chain = read(tmp_path, chain_with(T), "five.yaml")
    R_read = chain.cameras[1].T_cam_cam0[:3, :3]
    assert np.abs(R_read.T @ R_read - np.eye(3)).max() < 1e-12
    assert np.abs(R_read - R).max() < 1e-5
    assert any(
        "cam1.T_cn_cnm1: rotation off orthonormal by 1.6e-05" in r.getMessage() for r in caplog.records
    )
    bad = T.copy()
    bad[0, 1] += 0.01
    with pytest.raises(
        CalibrationError, match=r"cam1\.T_cn_cnm1: rotation is not orthonormal .* expected <= 1e-03"
    ):
        read(tmp_path, chain_with(bad), "bad.yaml")


def test_exponents_without_a_dot_are_numbers_and_a_repeated_key_is_refused(tmp_path):
    """YAML 1.1 reads an exponent without a dot (458654e-3, 5e-4), as C++ and YAML 1.2 writers print
    numbers, as a string. A camera given twice was silently the last copy."""
    plain = read(tmp_path, kalibr_with_T_cn_cnm1(), "plain.yaml")
    text = kalibr_with_T_cn_cnm1().replace("458.654, 457.296", "458654e-3, 457296E-3", 1)
    text = text.replace("1.76187114e-05", "176187114e-13", 1)
    assert_same_chain(read(tmp_path, text, "exp.yaml"), plain)
    twice = kalibr_with_T_cn_cnm1() + camera("cam1", f"T_cn_cnm1:\n{rows(T_C1_C0_KALIBR, 2)}\n")
    with pytest.raises(
        CalibrationError, match=r"twice\.yaml: line \d+, column 1: malformed YAML: key 'cam1' given twice"
    ):
        read(tmp_path, twice, "twice.yaml")


def test_opencv_matrix_nodes_are_read(tmp_path):
    text = "%YAML:1.0\n---\n" + camera(
        "cam0", "", intrinsics="!!opencv-matrix {rows: 1, cols: 4, dt: d, data: [458.654, 457.296, 367.215, 248.375]}"
    ) + camera(
        "cam1",
        "T_cn_cnm1: !!opencv-matrix\n   rows: 4\n   cols: 4\n   dt: d\n"
        f"   data: {flat(T_C1_C0_KALIBR)}\n",
    )  # fmt: skip
    assert_same_chain(read(tmp_path, text), read(tmp_path, kalibr_with_T_cn_cnm1(), "plain.yaml"))


def test_bad_opencv_matrix_names_line_and_problem(tmp_path):
    text = "%YAML:1.0\n" + camera(
        "cam0", "T_cam_imu: !!opencv-matrix {rows: 4, cols: 4, dt: d, data: [1.0, 0.0, 0.0]}\n"
    )
    with pytest.raises(CalibrationError) as info:
        read(tmp_path, text)
    assert str(info.value) == (
        f"{tmp_path / 'camchain.yaml'}: line 9, column 14: malformed YAML: "
        "!!opencv-matrix: data has 3 numbers, expected rows x cols = 16"
    )


def test_openvins_imucam_chain_as_shipped(tmp_path):
    """OpenVINS's euroc_mav/kalibr_imucam_chain.yaml: %YAML:1.0, T_imu_cam, no T_cn_cnm1."""
    text = "%YAML:1.0\n\n" + "".join(
        camera(f"cam{i}", f"T_imu_cam: #rotation from camera to IMU R_CtoI, position of camera in IMU p_CinI\n{rows(T)}\n")
        for i, T in enumerate((T_IMU_CAM0, T_IMU_CAM1))
    )  # fmt: skip
    chain = read(tmp_path, text)
    cam0, cam1 = chain.cameras
    # read as T_cam_imu = inv(T_imu_cam) (the file's rotations are orthonormal to about 1e-12)
    assert cam0.T_cam_imu is not None and np.allclose(cam0.T_cam_imu @ T_IMU_CAM0, np.eye(4), atol=1e-11)
    # the same cam1-cam0 pose Kalibr printed (12 significant digits), to 1e-10
    assert np.abs(cam1.T_cam_cam0 - T_C1_C0_KALIBR).max() < 1e-10


# -- T_cn_cnm1 from T_cam_imu ----------------------------------------------------------------------


def imucam(T_cam0_imu, T_cam1_imu, T_cn_cnm1=None):
    cam1_extra = f"T_cam_imu:\n{rows(T_cam1_imu, 2)}\n"
    if T_cn_cnm1 is not None:
        cam1_extra += f"T_cn_cnm1:\n{rows(T_cn_cnm1, 2)}\n"
    return camera("cam0", f"T_cam_imu:\n{rows(T_cam0_imu, 2)}\ntimeshift_cam_imu: 0.0\n") + camera(
        "cam1", cam1_extra + "timeshift_cam_imu: 0.0\n"
    )


def test_T_cn_cnm1_derived_from_T_cam_imu(tmp_path):
    """Kalibr's camchain-imucam without T_cn_cnm1: T_c1_c0 = T_c1_imu @ inv(T_c0_imu)."""
    T_c0_imu, T_c1_imu = invert(T_IMU_CAM0), invert(T_IMU_CAM1)
    chain = read(tmp_path, imucam(T_c0_imu, T_c1_imu))
    cam1 = chain.cameras[1]
    assert np.allclose(cam1.T_cam_cam0, T_c1_imu @ np.linalg.inv(T_c0_imu), atol=1e-11, rtol=0.0)
    assert cam1.T_cn_cnm1 is not None and np.array_equal(cam1.T_cn_cnm1, cam1.T_cam_cam0)
    assert np.abs(cam1.T_cam_cam0 - T_C1_C0_KALIBR).max() < 1e-10
    # a point seen by the IMU lands at the same place in cam1 either way
    p_imu = np.array([0.4, -1.2, 3.0, 1.0])
    assert np.allclose(cam1.T_cam_cam0 @ (T_c0_imu @ p_imu), T_c1_imu @ p_imu, atol=1e-14)


def test_three_cameras_chain_through_T_cam_imu(tmp_path):
    T_c0_imu, T_c1_imu = invert(T_IMU_CAM0), invert(T_IMU_CAM1)
    T_c2_imu = make_transform(rot_z(0.3), [0.05, -0.2, 0.01]) @ T_c1_imu
    text = imucam(T_c0_imu, T_c1_imu) + camera("cam2", f"T_cam_imu:\n{rows(T_c2_imu, 2)}\n")
    cam2 = read(tmp_path, text).cameras[2]
    assert np.allclose(cam2.T_cam_cam0, T_c2_imu @ np.linalg.inv(T_c0_imu), atol=1e-11, rtol=0.0)


def test_T_cn_cnm1_and_T_cam_imu_that_agree_keep_the_given_T_cn_cnm1(tmp_path):
    chain = read(tmp_path, imucam(invert(T_IMU_CAM0), invert(T_IMU_CAM1), T_C1_C0_KALIBR))
    assert np.array_equal(chain.cameras[1].T_cn_cnm1, T_C1_C0_KALIBR)


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        (make_transform(np.eye(3), [0.0, 0.005, 0.0]), "rotation differs by 0.0000 deg, translation by 5.000 mm"),
        (make_transform(rot_z(np.radians(0.2)), [0.0, 0.0, 0.0]), "rotation differs by 0.2000 deg, translation by 0.384 mm"),
    ],
)  # fmt: skip
def test_T_cn_cnm1_and_T_cam_imu_that_disagree(tmp_path, change, expected):
    stale = change @ T_C1_C0_KALIBR
    with pytest.raises(CalibrationError) as info:
        read(tmp_path, imucam(invert(T_IMU_CAM0), invert(T_IMU_CAM1), stale))
    assert str(info.value) == (
        f"{tmp_path / 'camchain.yaml'}: cam1: T_cn_cnm1 and T_cam1_imu @ inv(T_cam0_imu) (from T_cam_imu) "
        f"disagree: {expected} (tolerance {EXTRINSIC_TOL_DEG} deg, {EXTRINSIC_TOL_M * 1000:g} mm)"
    )


def test_T_cn_cnm1_missing_and_not_derivable(tmp_path):
    text = camera("cam0", "") + camera("cam1", f"T_cam_imu:\n{rows(invert(T_IMU_CAM1), 2)}\n")
    with pytest.raises(
        CalibrationError, match=r"cam1: missing key 'T_cn_cnm1' \(or T_cam_imu in both cam0 and cam1"
    ):
        read(tmp_path, text)


# -- 4x4 as 16 numbers -----------------------------------------------------------------------------


def test_4x4_as_16_numbers(tmp_path):
    text = camera("cam0", f"T_cam_imu: {flat(invert(T_IMU_CAM0))}\n") + camera(
        "cam1", f"T_cam_imu: {flat(invert(T_IMU_CAM1))}\nT_cn_cnm1: {flat(T_C1_C0_KALIBR)}\n"
    )
    chain = read(tmp_path, text)
    assert np.array_equal(chain.cameras[1].T_cn_cnm1, T_C1_C0_KALIBR)
    assert np.array_equal(chain.cameras[0].T_cam_imu, invert(T_IMU_CAM0))


def test_16_numbers_column_major_is_named(tmp_path):
    text = camera("cam0", "") + camera("cam1", f"T_cn_cnm1: {flat(T_C1_C0_KALIBR.T)}\n")
    with pytest.raises(CalibrationError, match=r"cam1\.T_cn_cnm1: bottom row must be \[0, 0, 0, 1\], got .* "
                       r"\(these 16 numbers look column-major; expected row-major\)"):  # fmt: skip
        read(tmp_path, text)


# -- top-level keys that are not cameras -----------------------------------------------------------


def test_extra_top_level_keys_are_ignored_with_a_warning(tmp_path, caplog):
    text = (
        kalibr_with_T_cn_cnm1()
        + "imu0:\n  rostopic: /imu0\n  update_rate: 200.0\ncalibrated_on: 2024-05-02\n"
    )
    with caplog.at_level(logging.WARNING, logger="calibration.kalibr"):
        chain = read(tmp_path, text)
    assert [c.name for c in chain.cameras] == ["cam0", "cam1"]
    assert caplog.messages == [
        f"{tmp_path / 'camchain.yaml'}: ignoring top-level keys imu0, calibrated_on (not cameras cam0, cam1, ...)"
    ]


def test_a_gap_in_camera_numbers_is_still_an_error(tmp_path):
    text = camera("cam0", "") + camera("cam2", f"T_cn_cnm1:\n{rows(T_C1_C0_KALIBR, 2)}\n") + "notes: x\n"
    with pytest.raises(CalibrationError, match=r"expected camera keys cam0, cam1, got cam0, cam2$"):
        read(tmp_path, text)


# -- what a user sees -----------------------------------------------------------------------------


def test_calib_check_reads_such_a_file(tmp_path):
    """All four quirks and the issue's Double Sphere camera in one file, through `sensorbox calib check`."""
    ds = DoubleSphere(480.1, 479.9, 962.4, 597.9, -0.19, 0.594, 1920, 1200)
    intr = f"[{ds.xi}, {ds.alpha}, {ds.fx}, {ds.fy}, {ds.cx}, {ds.cy}]"
    T_c0_imu = invert(T_IMU_CAM0)
    T_c1_imu = make_transform(np.eye(3), [0.0, -0.12, 0.0]) @ T_c0_imu  # cam1 120 mm below cam0
    text = "%YAML:1.0\n---\n"
    for name, T in (("cam0", T_c0_imu), ("cam1", T_c1_imu)):
        text += textwrap.dedent(f"""\
            {name}:
              camera_model: ds
              distortion_coeffs: []
              distortion_model: none
              intrinsics: {intr}
              resolution: [1920, 1200]
              T_cam_imu: {flat(T)}
            """)
    text += "imu0: {rostopic: /imu0}\n"
    path = tmp_path / "zed-camchain-imucam.yaml"
    path.write_text(text)
    res = subprocess.run(
        [sys.executable, "-m", "sensorbox.cli", "calib", "check", str(path)],
        capture_output=True, text=True, cwd=ROOT, check=False,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert (
        res.stderr.strip() == f"warning: {path}: ignoring top-level keys imu0 (not cameras cam0, cam1, ...)"
    )
    assert "Stereo baseline upper->lower: 120.00 mm" in res.stdout
    # DFOV and the model's limit are both 248.1 deg (it was 250.3 deg before issue 19)
    cam0_row = next(line for line in res.stdout.splitlines() if "cam0" in line and "DoubleSphere" in line)
    assert cam0_row.count("248.1°") == 2, cam0_row
    assert read_rig(path).cameras[1].T_cam_cam0[1, 3] == pytest.approx(-0.12, abs=1e-12)


def test_merge_keys_are_read_and_a_list_as_key_is_one_line() -> None:
    """The duplicate-key check leaves YAML's merge key (`<<: *defaults`) to PyYAML, which flattens it,
    and lets PyYAML refuse an unhashable key in its own one-line error rather than a TypeError."""
    import yaml

    from calibration.opencv_yaml import OpenCvSafeLoader

    doc = "defaults: &d {model: ds, rate_hz: 30}\ncam0:\n  <<: *d\n  rate_hz: 60\n"
    assert yaml.load(doc, Loader=OpenCvSafeLoader)["cam0"] == {"model": "ds", "rate_hz": 60}
    with pytest.raises(yaml.constructor.ConstructorError, match="found unhashable key"):
        yaml.load("? [a, b]\n: 1\n", Loader=OpenCvSafeLoader)


def test_an_early_kalibr_camchains_baseline_last_to_this_cam_is_its_t_cn_cnm1(tmp_path, caplog):
    """Early Kalibr camchains (EuRoC's era) name cam n-1 -> cam n `baseline_last_to_this_cam`; it was
    refused as "missing key 'T_cn_cnm1'"."""
    plain = read(tmp_path, kalibr_with_T_cn_cnm1(), "plain.yaml")
    with caplog.at_level(logging.WARNING):
        old = read(
            tmp_path, kalibr_with_T_cn_cnm1().replace("T_cn_cnm1:", "baseline_last_to_this_cam:"), "old.yaml"
        )
    assert_same_chain(old, plain)
    assert any("cam1: baseline_last_to_this_cam read as T_cn_cnm1" in r.getMessage() for r in caplog.records)
