"""Rig files: the reference rig, Livox extrinsics, round trips and bad input."""

import json
import math
import re
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

from calibration import CalibrationError, DoubleSphere, read_livox_config, read_rig, write_rig
from calibration.rig import REFERENCE_RIG
from calibration.transforms import livox_extrinsic_to_transform

REF = Path(__file__).resolve().parents[2] / "calibration" / "sensorbox.yaml"


def test_reference_rig_matches_design():
    rig = read_rig(REF)
    up, low = rig.upper, rig.lower
    assert (up.name, low.name) == ("cam0", "cam1")
    assert isinstance(up.model, DoubleSphere) and (up.model.width, up.model.height) == (1920, 1200)
    assert up.model.xi == pytest.approx(-0.18, abs=0.01) and up.model.alpha == pytest.approx(0.59, abs=0.01)
    assert up.model.fx == pytest.approx(500.0, abs=2.0)
    # lower camera 0.12 m below (cam y points down)
    c1 = low.T_cam0_cam[:3, 3]
    assert c1[1] == pytest.approx(0.12, abs=0.002) and abs(c1[0]) < 0.005 and abs(c1[2]) < 0.005
    assert rig.baseline_m() == pytest.approx(0.12, abs=0.002)
    top, bottom = rig.lidar("lidar_top"), rig.lidar("lidar_bottom")
    # LiDAR z (up) in cam0: top upright -> points up (-y), bottom upside down -> points down (+y)
    assert top.T_cam0_lidar[1, 2] < -0.999 and bottom.T_cam0_lidar[1, 2] > 0.999
    # LiDAR x (forward) looks along the camera axis for both
    assert top.T_cam0_lidar[2, 0] > 0.999 and bottom.T_cam0_lidar[2, 0] > 0.999
    assert top.T_cam0_lidar[1, 3] < 0 < c1[1] < bottom.T_cam0_lidar[1, 3]  # above cams, below cams
    assert {i.topic for i in rig.imus} == {"/livox/imu_192_168_1_12", "/livox/imu_192_168_1_13"}


def test_reference_lidars_cover_the_camera_view_vertically():
    # Elevation in cam0 seen by each Mid-360 (-7..+52 deg in its own frame), along the optical axis.
    rig = read_rig(REF)
    covered = []
    for lidar in rig.lidars:
        R = lidar.T_cam0_lidar[:3, :3]
        els = []
        for el in np.radians(np.linspace(-7, 52, 60)):
            d = R @ np.array([math.cos(el), 0.0, math.sin(el)])
            els.append(math.degrees(math.atan2(-d[1], d[2])))
        covered.append((min(els), max(els)))
    lo = min(c[0] for c in covered)
    hi = max(c[1] for c in covered)
    assert lo < -50 and hi > 50  # together the pair spans about -52..+52 deg
    overlap = min(c[1] for c in covered) - max(c[0] for c in covered)
    assert overlap > 10  # the -7..+7 bands overlap around the horizon


def test_livox_extrinsic_convention():
    # R = Rz(yaw) Ry(pitch) Rx(roll), degrees; t in mm
    T = livox_extrinsic_to_transform(0.0, 0.0, 90.0, 100, -20, 5)
    assert np.allclose(T[:3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    assert np.allclose(T[:3, 3], [0.1, -0.02, 0.005])
    T = livox_extrinsic_to_transform(90.0, 0.0, 0.0, 0, 0, 0)
    assert np.allclose(T[:3, :3] @ [0, 1, 0], [0, 0, 1], atol=1e-15)
    # order: roll first, then pitch, then yaw (applied to the point)
    T = livox_extrinsic_to_transform(90.0, 90.0, 0.0, 0, 0, 0)
    # y --roll 90--> z --pitch 90 about y--> x
    assert np.allclose(T[:3, :3] @ [0, 1, 0], [1, 0, 0], atol=1e-12)


def test_livox_config_json(tmp_path):
    cfg = {
        "lidar_summary_info": {"lidar_type": 8},
        "lidar_configs": [
            {"ip": "192.168.1.12", "extrinsic_parameter": {"roll": 0.0, "pitch": 0.0, "yaw": 0.0, "x": 0, "y": 0, "z": 100}},
            {"ip": "192.168.1.13", "extrinsic_parameter": {"roll": 180.0, "pitch": 0.0, "yaw": 0.0, "x": 0, "y": 0, "z": -120}},
        ],
    }  # fmt: skip
    path = tmp_path / "MID360_config.json"
    path.write_text(json.dumps(cfg))
    table = read_livox_config(path)
    assert np.allclose(table["192.168.1.12"][:3, 3], [0, 0, 0.1])
    assert np.allclose(table["192.168.1.13"][:3, :3], np.diag([1, -1, -1]), atol=1e-15)
    # used from a rig file, placed in cam0 by T_cam0_base
    shutil.copy(REF.parent / "sensorbox-camchain.yaml", tmp_path)
    T_cam0_base = [[0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0], [0, 0, 0, 1]]
    rig_doc = {
        "sensorbox_rig": 1,
        "camchain": "sensorbox-camchain.yaml",
        "lidars": {"bottom": {"topic": "/l", "ip": "192.168.1.13", "livox_config": "MID360_config.json",
                              "T_cam0_base": T_cam0_base}},
    }  # fmt: skip
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(rig_doc))
    rig = read_rig(tmp_path / "rig.yaml")
    T = rig.lidar("bottom").T_cam0_lidar
    # base z up = cam -y; the bottom lidar sits 0.12 m below the base -> +0.12 in cam y; its z points down
    assert np.allclose(T[:3, 3], [0, 0.12, 0]) and np.allclose(T[:3, 2], [0, 1, 0])
    # saved by a Windows editor: a BOM reads the same
    path.write_bytes(b"\xef\xbb\xbf" + json.dumps(cfg).encode())
    assert np.array_equal(read_rig(tmp_path / "rig.yaml").lidar("bottom").T_cam0_lidar, T)
    where = f"{tmp_path / 'rig.yaml'}: lidars.bottom"
    for bad, message in (
        ({"livox_config": "."}, f"{where}.livox_config: {tmp_path}: is a folder, not a Livox config file"),
        ({"ip": None}, f"{where}: missing key 'ip' (which LiDAR of the livox_config it is)"),
    ):  # fmt: skip
        doc = yaml.safe_load(yaml.safe_dump(rig_doc))
        doc["lidars"]["bottom"].update(bad)
        doc["lidars"]["bottom"] = {k: v for k, v in doc["lidars"]["bottom"].items() if v is not None}
        (tmp_path / "bad.yaml").write_text(yaml.safe_dump(doc))
        with pytest.raises(CalibrationError) as err:
            read_rig(tmp_path / "bad.yaml")
        assert str(err.value) == message.replace("rig.yaml", "bad.yaml")
    blocks = json.loads(json.dumps(cfg))["lidar_configs"]
    twice = {"lidar_configs": [blocks[0], {**blocks[1], "ip": "192.168.1.12"}]}
    path.write_text(json.dumps(twice))  # two extrinsics for one LiDAR: which is meant cannot be told
    with pytest.raises(CalibrationError) as err:
        read_livox_config(path)
    assert str(err.value) == f"{path}: lidar_configs[1].ip: 192.168.1.12 is also lidar_configs[0]'s"
    path.write_bytes(b'{"lidar_configs": [{"ip": "caf\xe9"}]}')
    with pytest.raises(
        CalibrationError,
        match=r"MID360_config\.json: not a JSON Livox config file \(byte 30 is 0xe9, not UTF-8 text\)$",
    ):
        read_livox_config(path)


def test_rig_write_read_round_trip(tmp_path):
    rig = read_rig(REF)
    write_rig(rig, tmp_path / "copy.yaml")
    back = read_rig(tmp_path / "copy.yaml")
    assert [c.model for c in back.cameras] == [c.model for c in rig.cameras]
    assert [c.role for c in back.cameras] == ["upper", "lower"]
    for a, b in zip(rig.lidars, back.lidars, strict=True):
        assert (a.name, a.topic, a.ip) == (b.name, b.topic, b.ip)
        assert np.array_equal(a.T_cam0_lidar, b.T_cam0_lidar)
    for ia, ib in zip(rig.imus, back.imus, strict=True):
        assert np.array_equal(ia.T_cam0_imu, ib.T_cam0_imu) and ia.rate_hz == ib.rate_hz
    assert np.array_equal(back.lower.T_cam_cam0, rig.lower.T_cam_cam0)


def test_bare_camchain_is_a_rig():
    rig = read_rig(REF.parent / "sensorbox-camchain.yaml")
    assert rig.upper.name == "cam0" and rig.lower.name == "cam1" and rig.lidars == ()
    assert rig.upper.topic == "/zed_upper/zed_node/rgb/color/rect/image"


def _rig_with(tmp_path, **changes):
    shutil.copy(REF.parent / "sensorbox-camchain.yaml", tmp_path)
    doc = yaml.safe_load(REF.read_text())
    for dotted, value in changes.items():
        node = doc
        keys = dotted.split("__")
        for k in keys[:-1]:
            node = node[k]
        if value is None:
            del node[keys[-1]]
        else:
            node[keys[-1]] = value
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"sensorbox_rig": 7}, r"sensorbox_rig: expected version 1"),
        ({"camchain": "missing.yaml"}, r"missing\.yaml: Kalibr camchain \(referenced by rig\.yaml\) file not found"),
        ({"lidars__lidar_top__topic": None}, r"lidars\.lidar_top: missing key 'topic'"),
        ({"lidars__lidar_top__T_cam0_lidar": None}, r"lidars\.lidar_top: expected exactly one of 'T_cam0_lidar', 'livox_extrinsic', 'livox_config', got none"),
        ({"lidars__lidar_top__T_cam0_lidar": [[2.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}, r"lidars\.lidar_top\.T_cam0_lidar: rotation is not orthonormal"),
        ({"lidars__lidar_top__T_cam0_lidar": [[-1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}, r"T_cam0_lidar: rotation has determinant -1"),
        ({"cameras__cam0__role": "middle"}, r"cameras\.cam0\.role: expected one of \('upper', 'lower'\), got 'middle'"),
        ({"cameras__cam1__role": "upper"}, r"each role may be given to one camera only"),
        ({"cameras__cam5": {"role": "lower"}}, r"cameras \['cam5'\] are not in the camchain \(has: cam0, cam1\)"),
        ({"imus__imu_top__T_cam0_imu": None}, r"imus\.imu_top: missing key 'T_cam0_imu'"),
        ({"imus__imu_top__rate_hz": 0}, r"imus\.imu_top\.rate_hz: expected a positive number, got 0"),
        ({"imus__imu_top__rate_hz": float("nan")}, r"imus\.imu_top\.rate_hz: expected a positive number, got nan"),
        ({"imus__imu_top__rate_hz": float("inf")}, r"imus\.imu_top\.rate_hz: expected a positive number, got inf"),
        ({"imus__imu_top__rate_hz": 10**400}, r"imus\.imu_top\.rate_hz: expected a positive number, got 1000"),
        ({"lidars__lidar_top__livox_extrinsic": {"roll": 0.0}}, r"expected exactly one of .*got \['T_cam0_lidar', 'livox_extrinsic'\]"),
        ({"lidars__lidar_top__ip": "192.168.1.300"}, r"lidars\.lidar_top\.ip: expected a dotted IPv4 address such as 192\.168\.1\.12, got '192\.168\.1\.300'"),
        ({"lidars__lidar_top__ip": 3232235788}, r"lidars\.lidar_top\.ip: expected a dotted IPv4 address .*got 3232235788"),
        ({"lidars__lidar_bottom__topic": "/livox/lidar_192_168_1_12"}, r"rig\.yaml: lidars\.lidar_bottom\.topic and lidars\.lidar_top\.topic are both /livox/lidar_192_168_1_12: each sensor needs its own topic \(for Livox LiDARs, livox_ros_driver2's multi_topic: 1\)$"),
        ({"imus__imu_top__topic": "/livox/lidar_192_168_1_12"}, r"lidars\.lidar_top\.topic and imus\.imu_top\.topic are both /livox/lidar_192_168_1_12: each sensor needs its own topic$"),
        ({"lidars__lidar_bottom__ip": "192.168.1.12"}, r"rig\.yaml: lidars\.lidar_bottom\.ip and lidars\.lidar_top\.ip are both 192\.168\.1\.12: each LiDAR has its own address$"),
        ({"lidars__lidar_top__T_cam0_lidar": [[1.0, 0, 0, 4.3], [0, 1, 0, -86.8], [0, 0, 1, -21.4], [0, 0, 0, 1]]}, r"rig\.yaml: lidars\.lidar_top\.T_cam0_lidar: translation 89\.5 m from cam0: expected <= 2 m on a handheld rig \(millimetres written as metres\?\)$"),
        ({"lidars__lidar_top__T_cam0_lidar": [[1.0, 0, 0, 1e12], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}, r"lidars\.lidar_top\.T_cam0_lidar: translation 1e\+12 m from cam0: expected <= 2 m on a handheld rig"),
        ({"lidars__lidar_top__T_cam0_lidar": None, "lidars__lidar_top__livox_extrinsic": {"roll": 0.0, "pitch": 0.0, "yaw": 0.0, "x": 0, "y": 0, "z": 2500}}, r"rig\.yaml: lidars\.lidar_top\.livox_extrinsic: translation 2\.5 m from cam0: expected <= 2 m on a handheld rig \(the Livox x, y, z are millimetres, T_cam0_base metres\)$"),
        ({"lidars__lidar_top__T_cam0_lidar": None, "lidars__lidar_top__livox_extrinsic": {"roll": 0.0, "pitch": 0.0, "yaw": 0.0, "x": 0, "y": 0, "z": 100}, "lidars__lidar_top__T_cam0_base": [[1.0, 0, 0, 0], [0, 1, 0, 3.0], [0, 0, 1, 0], [0, 0, 0, 1]]}, r"lidars\.lidar_top\.livox_extrinsic @ T_cam0_base: translation 3\.002 m from cam0"),
        ({"imus__imu_top__T_cam0_imu": [[1.0, 0, 0, -18.7], [0, 1, 0, -42.6], [0, 0, 1, -10.1], [0, 0, 0, 1]]}, r"rig\.yaml: imus\.imu_top\.T_cam0_imu: translation 47\.61 m from cam0: expected <= 2 m on a handheld rig \(millimetres written as metres\?\)$"),
        ({"imus": None, "imu": {"imu_top": {"topic": "/livox/imu_192_168_1_12", "T_cam0_imu": np.eye(4).tolist()}}}, r"rig\.yaml: unknown key 'imu' \(did you mean 'imus'\?\); known keys: sensorbox_rig, name, camchain, cameras, lidars, imus$"),
        ({"lidar": {}}, r"rig\.yaml: unknown key 'lidar' \(did you mean 'lidars'\?\); known keys: "),
        ({"calibration": "x"}, r"rig\.yaml: unknown key 'calibration'; known keys: sensorbox_rig, name, camchain, cameras, lidars, imus$"),
        ({"lidars__lidar_top__T_cam0_base": np.eye(4).tolist()}, r"rig\.yaml: lidars\.lidar_top\.T_cam0_base: places a livox_extrinsic or livox_config in cam0; with T_cam0_lidar it would be ignored \(give T_cam0_lidar = T_cam0_base @ T_base_lidar alone\)$"),
        ({"lidars__lidar_top__T_cam_lidar": np.eye(4).tolist()}, r"rig\.yaml: lidars\.lidar_top: unknown key 'T_cam_lidar' \(did you mean 'T_cam0_lidar'\?\); known keys: topic, ip, T_cam0_lidar, livox_extrinsic, livox_config, T_cam0_base$"),
        ({"lidars__lidar_top__T_cam0_lidar": None, "lidars__lidar_top__livox_extrinsic": {"roll": 0.0, "pitch": 0.0, "yaw": 0.0, "x": 0, "y": 0, "z": 100, "z_mm": 100}}, r"rig\.yaml: lidars\.lidar_top\.livox_extrinsic: unknown key 'z_mm'; known keys: roll, pitch, yaw, x, y, z$"),
        ({"imus__imu_top__rate": 200}, r"rig\.yaml: imus\.imu_top: unknown key 'rate' \(did you mean 'rate_hz'\?\); known keys: topic, T_cam0_imu, rate_hz$"),
        ({"cameras__cam0__topic": "/zed_lower/zed_node/rgb/color/rect/image", "cameras__cam1__topic": "/zed_upper/zed_node/rgb/color/rect/image"}, r"rig\.yaml: cameras\.cam0\.topic: /zed_lower/zed_node/rgb/color/rect/image is cam1's rostopic in the camchain \(.*sensorbox-camchain\.yaml\): cam1's calibration was made on that topic's images; expected cam0's own topic \(camchain: /zed_upper/zed_node/rgb/color/rect/image\), or the cameras named to match the camchain$"),
        ({"cameras__cam1__topic": "zed_upper/zed_node/rgb/color/rect/image/", "cameras__cam0__topic": "/zed/left"}, r"rig\.yaml: cameras\.cam1\.topic: /zed_upper/zed_node/rgb/color/rect/image is cam0's rostopic in the camchain"),
        ({"cameras__cam0__roll": "upper"}, r"rig\.yaml: cameras\.cam0: unknown key 'roll' \(did you mean 'role'\?\); known keys: role, topic$"),
    ],
)  # fmt: skip
def test_bad_rig_messages(tmp_path, changes, message):
    path = _rig_with(tmp_path, **changes)
    with pytest.raises(CalibrationError, match=message):
        read_rig(path)


def test_a_rig_topic_the_camchain_gives_no_camera_is_taken(tmp_path):
    """The calibration bag may have used other topic names: a topic of the rig's own overrides the
    camchain's rostopic, as documented; only another camera's rostopic is refused."""
    rig = read_rig(
        _rig_with(tmp_path, cameras__cam0__topic="/left/image", cameras__cam1__topic="/right/image")
    )
    assert (rig.upper.topic, rig.lower.topic) == ("/left/image", "/right/image")


def test_the_largest_plausible_lever_arm_is_read(tmp_path):
    """2 m from cam0 is still a handheld rig: the bound refuses only what is over it."""
    T = np.eye(4)
    T[:3, 3] = [0.0, -2.0, 0.0]
    rig = read_rig(_rig_with(tmp_path, lidars__lidar_top__T_cam0_lidar=T.tolist()))
    assert np.array_equal(rig.lidar("lidar_top").T_cam0_lidar, T)


def test_relative_topics_are_the_absolute_ones_a_bag_stores(tmp_path):
    path = _rig_with(tmp_path, lidars__lidar_top__topic="livox/lidar_192_168_1_12/", imus__imu_top__topic="livox/imu_192_168_1_12",
                     cameras__cam0__topic="zed_upper/zed_node/rgb/color/rect/image")  # fmt: skip

    def topics(rig):
        imu = next(i for i in rig.imus if i.name == "imu_top")
        return rig.lidar("lidar_top").topic, imu.topic, rig.upper.topic

    assert topics(read_rig(path)) == topics(read_rig(REF)) == (
        "/livox/lidar_192_168_1_12", "/livox/imu_192_168_1_12", "/zed_upper/zed_node/rgb/color/rect/image"
    )  # fmt: skip


def test_unknown_role_lookup_lists_cameras():
    rig = read_rig(REF)
    with pytest.raises(
        CalibrationError, match=r"no camera named or role 'left' \(has: cam0 \(upper\), cam1 \(lower\)\)"
    ):
        rig.camera("left")


def test_rotations_printed_to_six_decimals_are_accepted_and_coarser_ones_refused():
    """Many tools print 6 decimals: those rotations are off orthonormal by up to ~3e-6 and are read as
    written; 4 decimals (~1e-4) are used as their nearest rotation; beyond 1e-3 a matrix is refused."""
    from scipy.spatial.transform import Rotation

    from calibration.transforms import as_transform

    T = np.eye(4)
    for R in Rotation.random(2000, random_state=3).as_matrix():
        T[:3, :3] = np.round(R, 6)
        as_transform(T.tolist(), "six decimals")
    R = Rotation.from_euler("xyz", [0.3, -1.1, 2.0]).as_matrix()
    T[:3, :3] = np.round(R, 4)
    nearest = as_transform(T.tolist(), "four")[:3, :3]
    assert np.abs(nearest.T @ nearest - np.eye(3)).max() < 1e-12 and np.abs(nearest - R).max() < 1e-4
    T[:3, :3] = np.round(R, 2)
    with pytest.raises(
        CalibrationError,
        match=r"^two: rotation is not orthonormal \(max \|R\^T R - I\| = .*, expected <= 1e-03\)$",
    ):
        as_transform(T.tolist(), "two")


def _rig_with_chain(tmp_path, scale: float):
    """The reference rig with cam1's T_cn_cnm1 translation multiplied by `scale`."""
    path = _rig_with(tmp_path)
    chain = yaml.safe_load((tmp_path / "sensorbox-camchain.yaml").read_text())
    T = np.array(chain["cam1"]["T_cn_cnm1"], float)
    T[:3, 3] *= scale
    chain["cam1"]["T_cn_cnm1"] = T.tolist()
    (tmp_path / "sensorbox-camchain.yaml").write_text(yaml.safe_dump(chain))
    return path


def test_a_lower_camera_beside_the_upper_one_is_named(tmp_path):
    """Sweep 6: a camchain whose baseline runs along x passed `calib check` and ingest without a word; the
    disparity GT was 2.8 px off the truth (median)."""
    from calibration.rectify import stereo_warnings

    path = _rig_with(tmp_path)
    chain = yaml.safe_load((tmp_path / "sensorbox-camchain.yaml").read_text())
    T = np.array(chain["cam1"]["T_cn_cnm1"], float)
    T[:3, 3] = [-np.linalg.norm(T[:3, 3]), 0.0, 0.0]  # the same length, along x
    chain["cam1"]["T_cn_cnm1"] = T.tolist()
    (tmp_path / "sensorbox-camchain.yaml").write_text(yaml.safe_dump(chain))
    (line,) = stereo_warnings(read_rig(path))
    found = re.fullmatch(
        r".*rig\.yaml: the lower camera cam1 is beside the upper camera cam0, not below it \(its centre at "
        r"\[0\.1\d{3}, -?0\.0\d{3}, -?0\.0\d{3}\] m in cam0, (\d+) deg from cam0's y axis, which points down\): "
        r"the SensorBox's cameras are stacked; check cam1's T_cn_cnm1 in the camchain",
        line,
    )
    assert found and 80 <= int(found.group(1)) <= 100, line


def test_stereo_layout_warnings_and_a_zero_baseline(tmp_path):
    from calibration.rectify import rectify_rig, stereo_warnings

    assert stereo_warnings(read_rig(REF)) == []
    for sub in "abc":
        (tmp_path / sub).mkdir()
    swapped = read_rig(_rig_with(tmp_path / "a", cameras__cam0__role="lower", cameras__cam1__role="upper"))
    (line,) = stereo_warnings(swapped)
    assert "rig.yaml: the lower camera cam0 is not below the upper camera cam1 (its centre at [" in line
    assert line.endswith("are the roles swapped?")
    # 4.8 m: over 2 m, a warning; a camchain in millimetres (120 m) is refused (MAX_CAMERA_SEPARATION_M)
    (line,) = stereo_warnings(read_rig(_rig_with_chain(tmp_path / "b", 40.0)))
    assert line.endswith(
        "rig.yaml: stereo baseline 4.812 m; is the camchain in millimetres? (Kalibr writes metres)"
    )
    zero = read_rig(_rig_with_chain(tmp_path / "c", 0.0))
    assert stereo_warnings(zero) == []  # no pair at all: refused, not warned about
    with pytest.raises(
        CalibrationError,
        match=r"rig\.yaml: cameras cam0 and cam1 are 0\.000 mm apart; a stereo pair needs a baseline of at least 1 mm: "
        r"check cam1's T_cn_cnm1 in the camchain$",
    ):
        rectify_rig(zero)


def test_calib_check_refuses_cameras_that_are_no_stereo_pair(tmp_path, capsys):
    """Sweep 11: a camchain whose cam1 T_cn_cnm1 is the identity (baseline 0) passed `calib check` with exit 0
    and a warning that ingest refuses it. The check now refuses it as ingest does, after its report."""
    from tests.faults.cli import sensorbox

    rig = _rig_with_chain(tmp_path, 0.0)
    code, out, err = sensorbox(capsys, "calib", "check", str(rig))
    assert code == 2
    assert err == [
        f"error: {rig}: cameras cam0 and cam1 are 0.000 mm apart; a stereo pair needs a baseline of at least "
        "1 mm: check cam1's T_cn_cnm1 in the camchain"
    ]
    assert "Stereo baseline upper->lower: 0.00 mm" in out  # the report first: what the file says


def test_an_imu_off_its_lidars_housing_is_named(tmp_path):
    """Sweep 6/7: a rig with lidar_top turned 2 deg and imu_top exact (a Mid-360's IMU sits in its LiDAR's
    housing) passed every check; refine then turned the housing as a whole and moved the exact IMU."""
    from scipy.spatial.transform import Rotation

    from calibration.housing import housing_warnings

    assert housing_warnings(read_rig(REFERENCE_RIG)) == []
    rig = read_rig(REFERENCE_RIG)
    top = rig.lidar("lidar_top")
    T = top.T_cam0_lidar.copy()
    T[:3, :3] = T[:3, :3] @ Rotation.from_euler("z", 2.0, degrees=True).as_matrix()
    turned = replace(rig, lidars=tuple(replace(li, T_cam0_lidar=T) if li is top else li for li in rig.lidars))
    (line,) = housing_warnings(turned)
    assert re.fullmatch(
        r".*: imu_top is 2\.00 deg and \d\.\d mm from where lidar_top's housing puts it \(a Mid-360's IMU sits "
        r"unturned at \(11\.0, 23\.29, -44\.12\) mm in its LiDAR's frame\): one of the two poses is off; calib "
        r"refine turns a housing as a whole, so check lidar_top's T_cam0_lidar and imu_top's T_cam0_imu first",
        line,
    ), line
