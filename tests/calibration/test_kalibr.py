"""Kalibr camchain YAML: exact round trips, chaining and every bad-input message."""

import textwrap

import numpy as np
import pytest
import yaml

from calibration import (
    CalibrationError,
    DoubleSphere,
    ExtendedUnified,
    Fov,
    KannalaBrandt,
    Omni,
    Pinhole,
    RadTan,
    Unified,
    read_kalibr_camchain,
    write_kalibr_camchain,
)
from calibration.kalibr import CameraChain, KalibrCamera
from calibration.transforms import make_transform, rodrigues

RNG = np.random.default_rng(42)


def rand(lo, hi):
    return float(RNG.uniform(lo, hi))


def random_pose():
    return make_transform(rodrigues(RNG.normal(0, 0.3, 3)), RNG.normal(0, 0.2, 3))


MODELS = {
    "ds": DoubleSphere(rand(300, 600), rand(300, 600), rand(600, 700), rand(400, 500), rand(-0.3, 0), rand(0.5, 0.7), 1280, 960),
    "eucm": ExtendedUnified(rand(300, 600), rand(300, 600), 640.1, 480.3, rand(0.5, 0.7), rand(0.9, 1.2), 1280, 960),
    "omni": Omni(rand(0.5, 1.5), rand(600, 900), rand(600, 900), 640.7, 480.2, 1280, 960),
    "omni_radtan": Omni(0.93, 800.2, 801.3, 640.7, 480.2, 1280, 960, RadTan(rand(-0.1, 0), rand(0, 0.05), 1e-4, -3e-4)),
    "pinhole": Pinhole(rand(400, 600), rand(400, 600), 320.4, 240.9, 640, 480),
    "pinhole_radtan": Pinhole(500.3, 501.7, 320.4, 240.9, 640, 480, RadTan(rand(-0.3, 0), rand(0, 0.1), 2e-4, 1e-4)),
    "pinhole_fov": Pinhole(500.3, 501.7, 320.4, 240.9, 640, 480, Fov(rand(0.5, 1.0))),
    "pinhole_equidistant": KannalaBrandt(380.1, 380.9, 640.3, 512.8, rand(-0.1, 0.1), rand(-0.01, 0.01), 1e-3, -2e-4, 1280, 1024),
}  # fmt: skip


def make_chain(models):
    """A chain as Kalibr writes it: every T_cam_imu = T_cam_cam0 @ T_cam0_imu, consistent with T_cn_cnm1."""
    cams, T_prev, T_cam0_imu = [], np.eye(4), random_pose()
    for i, m in enumerate(models):
        T_cn_cnm1 = None if i == 0 else random_pose()
        T = np.eye(4) if T_cn_cnm1 is None else T_cn_cnm1 @ T_prev
        cams.append(
            KalibrCamera(
                f"cam{i}", m, T, T_cn_cnm1=T_cn_cnm1, T_cam_imu=T @ T_cam0_imu,
                timeshift_cam_imu=rand(-0.01, 0.01), rostopic=f"/cam{i}/image_raw",
                cam_overlaps=tuple(j for j in range(len(models)) if j != i),
            )
        )  # fmt: skip
        T_prev = T
    return CameraChain(tuple(cams))


@pytest.mark.parametrize("name", sorted(MODELS))
def test_write_read_round_trip_is_exact(tmp_path, name):
    chain = make_chain([MODELS[name], MODELS["ds"]])
    path = tmp_path / "camchain.yaml"
    write_kalibr_camchain(chain, path)
    back = read_kalibr_camchain(path)
    assert [c.model for c in back.cameras] == [c.model for c in chain.cameras]  # dataclass equality: exact
    for a, b in zip(chain.cameras, back.cameras, strict=True):
        assert a.rostopic == b.rostopic and a.cam_overlaps == b.cam_overlaps
        assert a.timeshift_cam_imu == b.timeshift_cam_imu
        assert a.T_cam_imu is not None and b.T_cam_imu is not None
        assert np.array_equal(a.T_cam_imu, b.T_cam_imu)
        assert (a.T_cn_cnm1 is None) == (b.T_cn_cnm1 is None)
        if a.T_cn_cnm1 is not None and b.T_cn_cnm1 is not None:
            assert np.array_equal(a.T_cn_cnm1, b.T_cn_cnm1)
    # writing what we read gives the same bytes
    path2 = tmp_path / "again.yaml"
    write_kalibr_camchain(back, path2)
    assert path2.read_bytes() == path.read_bytes()


def test_kalibr_layout_and_intrinsics_order(tmp_path):
    ds = DoubleSphere(501.5, 502.5, 960.25, 600.75, -0.18, 0.59, 1920, 1200)
    path = tmp_path / "c.yaml"
    write_kalibr_camchain(CameraChain((KalibrCamera("cam0", ds, np.eye(4)),)), path)
    data = yaml.safe_load(path.read_text())
    assert data == {
        "cam0": {
            "camera_model": "ds",
            "distortion_coeffs": [],
            "distortion_model": "none",
            "intrinsics": [-0.18, 0.59, 501.5, 502.5, 960.25, 600.75],
            "resolution": [1920, 1200],
        }
    }


def test_unified_is_written_as_eucm_with_beta_one(tmp_path):
    """UCM is EUCM with beta = 1, and Kalibr's eucm intrinsics are [alpha, beta, fu, fv, pu, pv]:
    a `Unified` camera is written with alpha first and beta = 1.0 second, and reads back as that EUCM."""
    ucm = Unified(501.5, 502.5, 960.25, 600.75, 0.625, 1920, 1200)
    path = tmp_path / "c.yaml"
    write_kalibr_camchain(CameraChain((KalibrCamera("cam0", ucm, np.eye(4)),)), path)
    cam0 = yaml.safe_load(path.read_text())["cam0"]
    assert (cam0["camera_model"], cam0["distortion_model"]) == ("eucm", "none")
    assert cam0["intrinsics"] == [0.625, 1.0, 501.5, 502.5, 960.25, 600.75]
    back = read_kalibr_camchain(path).cameras[0].model
    assert back == ExtendedUnified(501.5, 502.5, 960.25, 600.75, 0.625, 1.0, 1920, 1200)


def test_principal_point_is_checked_against_width_and_height_in_that_order(tmp_path):
    """resolution is [width, height]: pu may go up to the width (1920) even past the height (1200)."""
    path = write_bad(tmp_path, cam0={"intrinsics": [-0.18, 0.59, 500.0, 500.0, 1500.0, 600.0]})
    assert read_kalibr_camchain(path).cameras[0].model == DoubleSphere(
        500.0, 500.0, 1500.0, 600.0, -0.18, 0.59, 1920, 1200
    )


def test_chaining_T_cn_cnm1(tmp_path):
    chain = make_chain([MODELS["ds"], MODELS["ds"], MODELS["eucm"]])
    path = tmp_path / "c.yaml"
    write_kalibr_camchain(chain, path)
    back = read_kalibr_camchain(path)
    T10 = back.cameras[1].T_cn_cnm1
    T21 = back.cameras[2].T_cn_cnm1
    assert T10 is not None and T21 is not None
    assert np.allclose(back.cameras[2].T_cam_cam0, T21 @ T10, atol=1e-15)
    # a point in cam0 maps into cam2 through cam1
    p0 = np.array([0.3, -0.1, 2.0, 1.0])
    assert np.allclose(back.cameras[2].T_cam_cam0 @ p0, T21 @ (T10 @ p0))


def test_chain_without_T_cn_cnm1_is_written_from_T_cam_cam0(tmp_path):
    """A chain given only each camera's T_cam_cam0 is written with T_cn_cnm1 = T_cn_cam0 @ inv(T_cnm1_cam0)
    (p_cn = T_cn_cam0 p_cam0 = T_cn_cam0 inv(T_cnm1_cam0) p_cnm1), so reading it back gives the same poses.
    Three cameras: for cam1 the order of the product does not matter (T_cam0_cam0 = I), for cam2 it does."""
    poses = [np.eye(4), random_pose(), random_pose()]
    chain = CameraChain(tuple(KalibrCamera(f"cam{i}", MODELS["ds"], T) for i, T in enumerate(poses)))
    path = tmp_path / "c.yaml"
    write_kalibr_camchain(chain, path)
    written = yaml.safe_load(path.read_text())
    assert np.allclose(written["cam2"]["T_cn_cnm1"], poses[2] @ np.linalg.inv(poses[1]), atol=1e-12)
    back = read_kalibr_camchain(path)
    for cam, T in zip(back.cameras, poses, strict=True):
        assert np.allclose(cam.T_cam_cam0, T, atol=1e-12)


def test_reads_a_real_kalibr_style_file(tmp_path):
    path = tmp_path / "camchain-imucam.yaml"
    path.write_text(textwrap.dedent("""\
        cam0:
          T_cam_imu:
          - [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975]
          - [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768]
          - [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949]
          - [0.0, 0.0, 0.0, 1.0]
          cam_overlaps: [1]
          camera_model: ds
          distortion_coeffs: []
          distortion_model: none
          intrinsics: [-0.17213086034353243, 0.5931177593944744, 158.28600034966977, 158.2743455478755, 254.96116578191653, 256.8894394501779]
          resolution: [512, 512]
          rostopic: /cam0/image_raw
          timeshift_cam_imu: 0.00012
        cam1:
          T_cn_cnm1:
          - [0.999997256477, 0.00231206719295, 0.000376008102415, -0.110073808127]
          - [-0.00231713572422, 0.999898048507, 0.0140898358497, 0.000399121547014]
          - [-0.000343393120525, -0.0140906685417, 0.999900662638, -0.000853702503357]
          - [0.0, 0.0, 0.0, 1.0]
          camera_model: pinhole
          distortion_coeffs: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
          distortion_model: radtan
          intrinsics: [458.654, 457.296, 367.215, 248.375]
          resolution: [752, 480]
          rostopic: /cam1/image_raw
        """))  # fmt: skip
    chain = read_kalibr_camchain(path)
    cam0, cam1 = chain.cameras
    assert isinstance(cam0.model, DoubleSphere) and cam0.model.fx == 158.28600034966977
    assert cam0.model.xi == -0.17213086034353243 and (cam0.model.width, cam0.model.height) == (512, 512)
    assert cam0.timeshift_cam_imu == 0.00012 and cam0.rostopic == "/cam0/image_raw"
    assert isinstance(cam1.model, Pinhole) and cam1.model.distortion == RadTan(
        -0.28340811, 0.07395907, 0.00019359, 1.76187114e-05
    )
    assert cam1.T_cam_cam0[0, 3] == pytest.approx(-0.110073808127)


GOOD_CAM = {
    "camera_model": "ds",
    "distortion_coeffs": [],
    "distortion_model": "none",
    "intrinsics": [-0.18, 0.59, 500.0, 500.0, 960.0, 600.0],
    "resolution": [1920, 1200],
}


def write_bad(tmp_path, cam0=None, cam1=None, text=None):
    path = tmp_path / "bad-camchain.yaml"
    if text is not None:
        path.write_text(text)
    else:
        doc = {"cam0": {**GOOD_CAM, **(cam0 or {})}}
        if cam1 is not None:
            doc["cam1"] = {**GOOD_CAM, **cam1}
        path.write_text(yaml.safe_dump(doc))
    return path


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"text": "cam0:\n  camera_model: ds\n  intrinsics: [1, 2\n"}, r"bad-camchain\.yaml: line \d+, column \d+: malformed YAML"),
        ({"cam0": {"camera_model": "fisheye624"}}, r"bad-camchain\.yaml: cam0\.camera_model: unknown model 'fisheye624' \(expected one of pinhole, omni, eucm, ds\)"),
        ({"cam0": {"intrinsics": [-0.18, 0.59, 500.0, 500.0, 960.0]}}, r"cam0\.intrinsics \(ds: \[xi, alpha, fu, fv, pu, pv\]\): expected 6 values, got 5"),
        ({"cam0": {"intrinsics": [-0.18, 0.59, 500, 500.0, 960.0, 600.0]}}, r"cam0\.intrinsics: fu must be a float \(Kalibr rejects integers\), got 500"),
        ({"cam0": {"intrinsics": [-0.18, 0.59, -500.0, 500.0, 960.0, 600.0]}}, r"cam0\.intrinsics: fu must be > 0, got -500\.0"),
        ({"cam0": {"intrinsics": [-0.18, 1.5, 500.0, 500.0, 960.0, 600.0]}}, r"cam0: DoubleSphere: alpha must be in \[0, 1\), got 1\.5"),
        ({"cam0": {"intrinsics": [-0.18, 0.59, 0.0, 500.0, 960.0, 600.0]}}, r"cam0\.intrinsics: fu must be > 0, got 0\.0"),
        ({"cam0": {"intrinsics": [-0.18, 0.59, 500.0, 500.0, -240.0, 600.0]}}, r"cam0\.intrinsics: the principal point \(pu, pv\) = \(-240, 600\) lies outside the 1920x1200 image"),
        ({"cam0": {"intrinsics": [-0.18, 0.59, 500.0, 500.0, 960.0, 1300.0]}}, r"cam0\.intrinsics: the principal point \(pu, pv\) = \(960, 1300\) lies outside the 1920x1200 image"),
        ({"cam0": {"distortion_model": "radtan", "distortion_coeffs": [0.0, 0.0, 0.0, 0.0]}}, r"cam0\.distortion_model: 'radtan' is not valid with camera_model 'ds' \(expected one of none\)"),
        ({"cam0": {"camera_model": "pinhole", "intrinsics": [5.0, 5.0, 1.0, 1.0], "distortion_model": "radtan", "distortion_coeffs": [0.1]}}, r"cam0\.distortion_coeffs \(radtan\): expected 4 values, got 1"),
        ({"cam0": {"resolution": [1920.0, 1200]}}, r"cam0\.resolution: expected \[width, height\] positive ints"),
        ({"cam0": {"intrinsics": "abc"}}, r"cam0\.intrinsics .*: expected a list of numbers, got 'abc'"),
        ({"cam1": {"T_cn_cnm1": [[1.0, 0.1, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}}, r"cam1\.T_cn_cnm1: rotation is not orthonormal"),
        ({"cam1": {"T_cn_cnm1": [[1.0, 0, 0], [0, 1, 0], [0, 0, 1]]}}, r"cam1\.T_cn_cnm1: expected a 4x4 matrix \(or 16 numbers, row-major\), got shape \(3, 3\)"),
        ({"cam1": {}}, r"cam1: missing key 'T_cn_cnm1' \(or T_cam_imu in both cam0 and cam1 to derive it\)"),
        ({"text": "cam0: {}\ncam2: {}\n"}, r"expected camera keys cam0, cam1, got cam0, cam2"),
        ({"text": "- just\n- a list\n"}, r"expected a Kalibr camchain \(keys cam0, cam1, \.\.\.\)"),
    ],
)  # fmt: skip
def test_bad_camchain_messages(tmp_path, kwargs, message):
    path = write_bad(tmp_path, **kwargs)
    with pytest.raises(CalibrationError, match=message) as info:
        read_kalibr_camchain(path)
    assert str(path) in str(info.value)


def test_missing_file_message(tmp_path):
    with pytest.raises(CalibrationError, match=r"nope\.yaml: Kalibr camchain file not found"):
        read_kalibr_camchain(tmp_path / "nope.yaml")


def test_missing_key_message(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump({"cam0": {k: v for k, v in GOOD_CAM.items() if k != "resolution"}}))
    with pytest.raises(CalibrationError, match=r"c\.yaml: cam0: missing key 'resolution'"):
        read_kalibr_camchain(path)
