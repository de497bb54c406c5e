"""Which LiDAR pose corrections `calib refine` writes, from the samples' alignments of each LiDAR's points
on cam0's images (`ingest.train.gt.align_check.combine`): the rules (certain or significant, the
translation only where the recording places it, a fault common to every LiDAR named instead), each
LiDAR's row of the result, and the stereo pose checked through the same points."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from calibration.rig import Rig
from calibration.types import F64
from ingest.train.gt.align import Alignment
from ingest.train.gt.align_check import MATCH_RATIO, Combined, SampleAlignments, combine, corrected

STEREO_WARN_DEG = 0.1
STEREO_WARN_MM = 5.0
MAX_LIDAR_SIGMA_DEG = 0.05
MAX_LIDAR_SIGMA_MM = 5.0
"""A LiDAR correction is applied when it is at least this certain (1-sigma), or when it is significant
(over 3 sigma: the rig is surely off, and the estimate is nearer than the rig's value); else it is
reported and the rig's pose kept. Outdoors, points far away leave the translation at 6 mm (1-sigma) while
a 30 mm error is found to 3 mm (bench/bench_refine.py)."""
MAX_TRANSLATION_SIGMA_MM = 10.0
"""A LiDAR's translation is corrected only when the recording places it to this (1-sigma) or better, no
worse than a tape measure on the rig; else its rotation is found with the translation held and only
that is applied. A turn about an axis across the view is otherwise taken partly for a shift: on the
0.7 s simulated walk, lidar_top turned 2 deg came back 2.3 deg and 149 mm (1-sigma 24 mm) off."""


def applies(correction: Alignment) -> bool:
    """Whether a LiDAR's combined correction is certain or significant enough to apply (see above)."""
    angle = float(np.degrees(np.linalg.norm(correction.rotation_rad)))
    shift_mm = float(np.linalg.norm(correction.translation_m) * 1e3)
    sigma_deg, sigma_mm = correction.sigma_rotation_deg, correction.sigma_translation_mm
    certain = sigma_deg <= MAX_LIDAR_SIGMA_DEG and sigma_mm <= MAX_LIDAR_SIGMA_MM
    return certain or angle > 3 * sigma_deg or shift_mm > 3 * sigma_mm


def stereo_record(stereo: StereoAlignment | None) -> dict[str, object]:
    """The stereo pose check as dataset.yaml's `calibration_check` keeps it (deg, mm; none unchecked)."""
    if stereo is None:
        return {}
    return {"stereo_pose": {
        "lidar": stereo.lidar, "rotation_deg": round(stereo.rotation_deg, 4),
        "translation_mm": round(stereo.translation_mm, 2), "sigma_deg": round(stereo.sigma_rotation_deg, 4),
        "sigma_mm": round(stereo.sigma_translation_mm, 2), "off": stereo.disagrees,
    }}  # fmt: skip


def stereo_lines(stereo: StereoAlignment | None, rig: object) -> list[str]:
    """One warning line when the LiDAR points on both images put the camchain's stereo pose off: the
    lower image, warped by it, lies off the disparity GT."""
    if stereo is None or not stereo.disagrees:
        return []
    return [
        f"{stereo.lidar}'s points on both images put the camchain's stereo pose (cam1's T_cn_cnm1) "
        f"{stereo.rotation_deg:.2f} deg and {stereo.translation_mm:.1f} mm off (1-sigma "
        f"{stereo.sigma_rotation_deg:.2f} deg, {stereo.sigma_translation_mm:.1f} mm): the lower images, "
        "warped by it, lie off the disparity GT; recalibrate the stereo pair (kalibr_calibrate_cameras) and "
        f"give {rig} the new camchain, or check the lower camera's images"
    ]


def _median_correlations(worse: SampleAlignments, other: SampleAlignments) -> dict[str, tuple[float, float]]:
    """Per LiDAR aligned onto both cameras: the median correlation of its points with `worse`'s images and
    with `other`'s."""
    pairs = {}
    for name in sorted({n for found, _ in worse for n in found}):
        mine = [a.correlation for found, _ in worse if (a := found.get(name)) is not None]
        theirs = [a.correlation for found, _ in other if (a := found.get(name)) is not None]
        if mine and theirs:
            pairs[name] = (float(np.median(mine)), float(np.median(theirs)))
    return pairs


def camera_mismatch_lines(upper: SampleAlignments, lower: SampleAlignments) -> tuple[list[str], list[str]]:
    """(upper, lower): one warning line each when every LiDAR's points match that camera's images far worse
    than the other's (`_mismatch_line`)."""
    return _mismatch_line(upper, lower, ("upper", "lower")), _mismatch_line(lower, upper, ("lower", "upper"))


def _mismatch_line(worse: SampleAlignments, other: SampleAlignments, which: tuple[str, str]) -> list[str]:
    """One warning line when every LiDAR's points match one camera's images (`worse`) far worse than the
    other's (median correlation below `MATCH_RATIO` of it): that camera's images are not what the
    camchain says. `which`: the two cameras' words. On the fixtures both images match alike (0.52-0.79
    each); the lower images upside down, -0.35 and -0.05 against 0.70 and 0.79; the upper images
    mirrored, -0.01 and 0.23 against about 0.7."""
    pairs = _median_correlations(worse, other)
    if not pairs or not all(theirs > 0 and mine < MATCH_RATIO * theirs for mine, theirs in pairs.values()):
        return []
    found = ", ".join(f"{n} {mine:.2f} against {theirs:.2f}" for n, (mine, theirs) in pairs.items())
    camera = "cam1" if which[0] == "lower" else "cam0"
    what = (
        "the equirect pair is not a stereo pair of the GT"
        if camera == "cam1"
        else "the GT is drawn for the view these images do not show, and the LiDARs' poses cannot be judged "
        "from them"
    )
    return [
        f"the LiDAR points match the {which[0]} camera's images far worse than the {which[1]}'s (median "
        f"correlation {found}): {camera}'s images are not what the camchain says (turned, mirrored, another "
        f"camera's) or its intrinsics are off; {what}: check {camera}'s topic, images and camchain entry"
    ]


@dataclass(frozen=True)
class LidarRefinement:
    """One LiDAR's pose in cam0 from its points laid onto cam0's image (`ingest.train.gt.align`).

    `correction` is the total correction applied to the given rig's pose
    (rotation and translation in cam0), `sigma_*` its 1-sigma (largest axis).
    `shift_before_deg` and `shift_after_deg` are the median per-sample
    misalignment with the given rig and with the refined one; `samples` how
    many samples of each round aligned.
    """

    lidar: str
    rotation_deg: float
    translation_mm: float
    sigma_rotation_deg: float
    sigma_translation_mm: float
    shift_before_deg: float
    shift_after_deg: float
    samples: int
    applied: bool
    mismatch: str = ""  # why the rig's pose was kept though off (its points match far worse than another's,
    # or every LiDAR asks for the same turn: cam0's fault)
    translation_held: bool = False  # only the rotation corrected: the recording could not place the shift


@dataclass(frozen=True)
class StereoAlignment:
    """The camchain's stereo pose checked through the LiDAR points: laid onto both images, a LiDAR's
    correction in cam1 should be its correction in cam0 seen from cam1. What it is not is the error of
    T_cam1_cam0: its rotation (deg) and the change of cam1's position (mm), with 1-sigmas, from the
    LiDAR whose estimate is the surest. Reported, not applied."""

    lidar: str
    rotation_deg: float
    translation_mm: float
    sigma_rotation_deg: float
    sigma_translation_mm: float

    @property
    def disagrees(self) -> bool:
        """Beyond `STEREO_WARN_DEG` or `STEREO_WARN_MM`, and three sigma."""
        turned = self.rotation_deg > max(STEREO_WARN_DEG, 3 * self.sigma_rotation_deg)
        return turned or self.translation_mm > max(STEREO_WARN_MM, 3 * self.sigma_translation_mm)


def stereo_alignment(rig: Rig, upper: Combined, lower: Combined | None) -> StereoAlignment | None:
    """The stereo pose's error implied by each LiDAR's corrections onto cam0 (`upper`) and cam1
    (`lower`): true T_cam1_cam0 = C1 T_cam1_cam0 C0^-1; the LiDAR with the smallest rotation sigma
    speaks (None without a LiDAR aligned onto both)."""
    if lower is None:
        return None
    T10 = rig.lower.T_cam_cam0
    best: StereoAlignment | None = None
    for name, c0 in upper.corrections.items():
        c1 = lower.corrections.get(name)
        if c1 is None:
            continue
        true = corrected(np.eye(4), c1) @ T10 @ np.linalg.inv(corrected(np.eye(4), c0))
        error = true @ np.linalg.inv(T10)
        angle = float(np.degrees(np.linalg.norm(cv2.Rodrigues(error[:3, :3])[0])))
        moved = float(np.linalg.norm(true[:3, 3] - T10[:3, 3]) * 1e3)
        sigma_deg = float(np.hypot(c0.sigma_rotation_deg, c1.sigma_rotation_deg))
        sigma_mm = float(np.hypot(c0.sigma_translation_mm, c1.sigma_translation_mm))
        if best is None or sigma_deg < best.sigma_rotation_deg:
            best = StereoAlignment(name, angle, moved, sigma_deg, sigma_mm)
    return best


MIN_COMMON_RATE_DEG_S = 5.0
COMMON_ACROSS = 0.5
COMMON_DT_RATIO = 2.0
"""`common_cause`: a rig turning at this mean rate or more; each LiDAR's rotation correction within this
fraction of its size from the rate's direction; the clock offsets they imply within this ratio of each
other (on the 0.7 s walk with both cameras 40 ms late: 36 and 52 ms)."""


def held_translations(
    samples: SampleAlignments, combined: Combined, held: set[str], skip: set[str]
) -> Combined:
    """`combined` solved again with the translation held (added to `held`) of each LiDAR whose correction
    applies but whose translation is not placed to `MAX_TRANSLATION_SIGMA_MM`."""
    loose = {
        name
        for name, corr in combined.corrections.items()
        if name not in skip and applies(corr) and corr.sigma_translation_mm > MAX_TRANSLATION_SIGMA_MM
    }
    if not loose - held:
        return combined if not held else combine(samples, rotation_only=frozenset(held)) or combined
    held |= loose
    return combine(samples, rotation_only=frozenset(held)) or combined


def common_cause(combined: Combined, samples: SampleAlignments, skip: set[str]) -> str:
    """Why every LiDAR's pose is kept, or "": when the recording could not time cam0 against the LiDARs
    and each LiDAR asks for a significant turn along the rig's mean rotation rate, as much as cam0's
    exposure times late by one same dt would explain, a fault they share (cam0's clock, or cam0's own
    pose) is likelier than every LiDAR off alike, and steady motion cannot tell the clock from the pose."""
    rates = [twist[:3] for _, twist in samples if twist is not None]
    corrections = {n: c for n, c in combined.corrections.items() if n not in skip}
    if combined.clock_offset_ms is not None or not rates or len(corrections) < 2:
        return ""
    rate: F64 = np.mean(rates, axis=0)
    if np.degrees(np.linalg.norm(rate)) < MIN_COMMON_RATE_DEG_S:
        return ""
    dts_ms = {}
    for name, corr in corrections.items():
        if not applies(corr):
            return ""
        dt_s = float(corr.rotation_rad @ rate / (rate @ rate))
        across = float(np.linalg.norm(corr.rotation_rad - dt_s * rate))
        if across > COMMON_ACROSS * float(np.linalg.norm(corr.rotation_rad)):
            return ""
        dts_ms[name] = dt_s * 1e3
    low, high = min(dts_ms.values()), max(dts_ms.values())
    if low * high <= 0 or high / low > COMMON_DT_RATIO:
        return ""
    turns = ", ".join(
        f"{n} {np.degrees(np.linalg.norm(c.rotation_rad)):.2f} deg ({dts_ms[n]:+.0f} ms)"
        for n, c in corrections.items()
    )
    return (
        f"every LiDAR's points ask for a turn along the rig's rotation, as cam0's exposure times that much "
        f"late would ({turns}): cam0's clock or cam0's own pose is the likelier fault, and this recording's "
        "steady motion cannot tell the two apart; record the rig turned by hand for a few seconds, and "
        "check the cameras' timeshift_cam_imu"
    )
