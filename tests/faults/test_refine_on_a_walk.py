"""Sweep 6: `calib refine` on the 0.7 s walk wrote rigs worse than its input and called them refined.

- lidar_top turned 2 deg in the rig file came back 0.50 deg and 149 mm off: a turn about an axis across
  the view was taken partly for a shift the recording cannot place (1-sigma 24 mm), and the shift was
  written. The translation is now corrected only when placed to `MAX_TRANSLATION_SIGMA_MM`; else the
  rotation is found with the position held.
- both cameras' stamps 40 ms late (an exact rig): every LiDAR's pose was "refined" by 1.4-1.7 deg and
  45-157 mm. Each LiDAR asked for a turn along the rig's rotation, as late exposure times would; a cause
  shared by every LiDAR (cam0's clock or pose) is now named and the rig's poses are kept.
"""

from __future__ import annotations

import re
import shutil
import struct
from pathlib import Path

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from calibration.rig import read_rig
from ingest.train.run.lidar_poses import MAX_TRANSLATION_SIGMA_MM
from ingest.train.run.pipeline import ingest, refine_rig
from ingest.train.run.settings import IngestConfig
from sensorbox.sim.truth import truth_dir
from tests.faults.bags import Keep, frames_swapped, rewrite
from tests.paths import FIXTURES_DIR

WALK = FIXTURES_DIR / "outdoor_walk_mcap"
CAMERAS = ("/zed_upper/zed_node/rgb/color/rect/image", "/zed_lower/zed_node/rgb/color/rect/image")


def _angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    return float(np.degrees(Rotation.from_matrix(Ra @ Rb.T).magnitude()))


def test_a_lidar_turned_2_deg_comes_back_without_a_made_up_shift(tmp_path: Path) -> None:
    truth = read_rig(truth_dir(WALK) / "rig.yaml")
    shutil.copy(truth_dir(WALK) / "camchain.yaml", tmp_path / "camchain.yaml")
    doc = yaml.safe_load((truth_dir(WALK) / "rig.yaml").read_text())
    T = np.array(doc["lidars"]["lidar_top"]["T_cam0_lidar"], np.float64)
    T[:3, :3] = T[:3, :3] @ Rotation.from_euler("z", 2.0, degrees=True).as_matrix()  # about its own z
    doc["lidars"]["lidar_top"]["T_cam0_lidar"] = T.tolist()
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(doc))

    refinement = refine_rig([WALK], read_rig(tmp_path / "rig.yaml"), workers=1)

    top = next(r for r in refinement.lidars if r.lidar == "lidar_top")
    assert top.applied and top.translation_held and top.sigma_translation_mm > MAX_TRANSLATION_SIGMA_MM
    written = refinement.rig.lidar("lidar_top").T_cam0_lidar
    exact = truth.lidar("lidar_top").T_cam0_lidar
    assert _angle_deg(written[:3, :3], exact[:3, :3]) < 0.5  # from 2 deg
    assert np.linalg.norm(written[:3, 3] - exact[:3, 3]) < 0.005  # 149 mm before
    bottom = refinement.rig.lidar("lidar_bottom").T_cam0_lidar
    np.testing.assert_array_equal(bottom, truth.lidar("lidar_bottom").T_cam0_lidar)


def _cameras_late(ms: int) -> Keep:
    def keep(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        if topic not in CAMERAS:
            return [(topic, raw)]
        sec, nsec = struct.unpack_from("<iI", raw, 4)
        stamp_ns = sec * 1_000_000_000 + nsec + ms * 1_000_000
        return [(topic, raw[:4] + struct.pack("<iI", *divmod(stamp_ns, 1_000_000_000)) + raw[12:])]

    return keep


COMMON = re.compile(
    r"^lidar_\w+, lidar_\w+: the rig's pose is kept: every LiDAR's points ask for a turn along the rig's "
    r"rotation, as cam0's exposure times that much late would \(lidar_\w+ \d\.\d\d deg \(\+(\d+) ms\), "
    r"lidar_\w+ \d\.\d\d deg \(\+(\d+) ms\)\): cam0's clock or cam0's own pose is the likelier fault, and this "
    r"recording's steady motion cannot tell the two apart; record the rig turned by hand for a few "
    r"seconds, and check the cameras' timeshift_cam_imu$"
)


def test_cameras_40_ms_late_are_named_and_the_lidar_poses_kept(tmp_path: Path) -> None:
    bag, rig_path = rewrite(tmp_path / "late.mcap", _cameras_late(40), src=WALK)
    given = read_rig(rig_path)

    refinement = refine_rig([bag], given, workers=1)

    found = [m for line in refinement.unobserved_lines() if (m := COMMON.match(line))]
    assert len(found) == 1, refinement.unobserved_lines()
    assert all(15 <= int(ms) <= 80 for ms in found[0].groups())  # the 40 ms, as each LiDAR sees it
    for lidar in given.lidars:
        np.testing.assert_array_equal(refinement.rig.lidar(lidar.name).T_cam0_lidar, lidar.T_cam0_lidar)
    for imu, kept in zip(refinement.rig.imus, given.imus, strict=True):
        np.testing.assert_array_equal(imu.T_cam0_imu, kept.T_cam0_imu)
    assert not any(r.applied for r in refinement.lidars)


def test_a_frame_under_its_neighbours_stamp_is_named_and_flagged(tmp_path: Path) -> None:
    """Sweep 7 S5: cam0's 5th and 6th images exchanged (stamps kept): sample 000001 held the image taken
    33 ms away while its GT is for its stamp, and its own alignment said 2 deg, without a word."""
    bag, rig = rewrite(tmp_path / "swapped.mcap", frames_swapped(WALK, CAMERAS[0], 4, 5), src=WALK)
    summary = ingest([bag], IngestConfig(rig=rig, out=tmp_path / "ds", workers=1, every=5, height_full=96))
    assert summary.written == 4
    assert summary.frame_flags == {"upper image off every LiDAR's points (> 1 deg)": ["000001"]}
    assert summary.flagged["upper image off every LiDAR's points (> 1 deg)"] == 1
    assert (
        "1 of 4 samples have an upper image that lies off every LiDAR's points by over 1 deg (000001): "
        "each image is not the one taken at its stamp (a frame published under another's stamp, or a camera "
        "clock that jumped); the samples are written and flagged in the summary: leave them out of training"
    ) in summary.warnings


def test_a_clock_offset_its_own_lidar_check_rejects_is_not_written() -> None:
    """Sweep 7 S8: refine on the indoor walk with the exact rig (no camera clock offset) wrote cam0's
    timeshift +4.2 ms from the gyro, while its own check of the LiDAR points on cam0's images put that
    clock +4.1 ms off (1-sigma 0.1). The rig's value is kept and one line names both."""
    walk = FIXTURES_DIR / "indoor_walk_db3"
    given = read_rig(truth_dir(walk) / "rig.yaml")
    refinement = refine_rig([walk], given, workers=1)
    cam0 = refinement.cameras[0]
    assert cam0.estimate.observable and not cam0.applied
    assert refinement.rig.upper.timeshift_cam_imu == given.upper.timeshift_cam_imu
    assert refinement.image_clock_ms is not None
    ms, sigma = refinement.image_clock_ms
    assert abs(ms) > 3 * sigma and abs(ms) > 2.0
    assert (
        f"cam0: the gyro's estimate is not written: the LiDAR points on cam0's images put the clock it gives "
        f"{ms:+.3f} ms off (1-sigma {sigma:.3f}), so the two disagree; the rig's value is kept: check the IMUs' "
        "stamps against the LiDARs' clock"
    ) in refinement.unobserved_lines()
