"""Many samples' LiDAR-to-image alignments (`ingest.train.gt.align`) summed up: each LiDAR's pose
correction and the upper camera's clock offset (`combine`), the check ingest records and warns from
(`check_calibration`), and the samples' alignments read back from their metadata."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from calibration.types import F64
from ingest.dataset.meta import AlignmentMeta, SampleMeta
from ingest.train.gt.align import Alignment, rotation_matrix

SYSTEMATIC_PX = 0.15
"""What the combined correction cannot resolve however many samples agree (1-sigma, in pixels: in angle
for the rotation, at the points' median range for the translation): each scene's texture and shading
bias its samples alike. On the simulated 0.7 s fixtures an exact rig came back 0.25 deg and 55 mm off at
240x150 (0.8 deg pixels, points at 8 m) and within 0.03 deg and 3 mm at 480x300."""
MAX_OFFSET_SIGMA_MS = 1.0
"""A clock offset whose 1-sigma exceeds this is reported as unobservable (the rig hardly moved)."""
CAUCHY_D2 = 4.0 * 6
"""The Cauchy scale of a sample's squared Mahalanobis distance (6 degrees of freedom) to the model."""


SampleAlignments = Sequence[tuple[Mapping[str, "Alignment"], F64 | None]]
"""Per sample: its alignment per LiDAR and cam0's twist (angular rad/s, linear m/s, in cam0) or None."""


@dataclass(frozen=True)
class Combined:
    """What many samples' alignments say together (`combine`).

    `corrections` per LiDAR: the correction of its rig-file pose (as an
    `Alignment`: rotation and translation in cam0, with the information of
    the combined estimate). `clock_offset_ms`: how much later than the truth
    the exposure times were taken (the upper camera's `timeshift_cam_imu`
    should be that much smaller); None when the motion did not reveal it.
    `spread` is the residuals' scale over the per-sample information (1 when
    each sample's stated uncertainty is right); the stated sigmas include it.
    """

    corrections: dict[str, Alignment]
    clock_offset_ms: float | None
    sigma_clock_ms: float
    samples: int
    spread: float


def combine(
    samples: SampleAlignments, iterations: int = 5, rotation_only: frozenset[str] = frozenset()
) -> Combined | None:
    """The rig-file correction of each LiDAR and the upper camera's clock offset from the per-sample
    alignments and cam0's twist at each sample (`(alignments by LiDAR, twist)` pairs).

    Each sample's correction is modelled as its LiDAR's constant correction
    plus the clock offset times the rig's motion (a sample taken at a time
    off by dt sees the points moved by dt times cam0's angular and linear
    velocity), weighted by its information; samples far from the model
    (a mover, a bad frame) are down-weighted (Cauchy on the Mahalanobis
    distance). The offset is solved only when the motion varied enough to
    tell it from a constant correction (`MAX_OFFSET_SIGMA_MS`). The LiDARs
    named in `rotation_only` keep their translation (its correction is held
    at zero). None without any alignment.
    """
    names = sorted({name for found, _ in samples for name in found})
    if not names:
        return None
    with_twist = all(twist is not None for _, twist in samples)
    result = _solve(samples, names, with_twist, iterations, rotation_only)
    if with_twist and result.sigma_clock_ms > MAX_OFFSET_SIGMA_MS:
        result = _solve(samples, names, False, iterations, rotation_only)
    return result


PINNED_INFORMATION = 1e12
"""The information (1/m^2) that holds a translation correction at zero (`combine`'s `rotation_only`)."""


def _solve(
    samples: SampleAlignments, names: list[str], offset: bool, iterations: int, rotation_only: frozenset[str]
) -> Combined:
    """`combine` with (`offset`) or without the clock offset among the unknowns."""
    n = 6 * len(names) + (1 if offset else 0)
    pinned: F64 = np.zeros((n, n))
    for k, name in enumerate(names):
        if name in rotation_only:
            pinned[6 * k + 3 : 6 * k + 6, 6 * k + 3 : 6 * k + 6] = PINNED_INFORMATION * np.eye(3)
    terms = []  # (design (6, n), observed (6,), information (6, 6))
    for found, twist in samples:
        for name, al in found.items():
            design = np.zeros((6, n))
            k = names.index(name)
            design[:, 6 * k : 6 * k + 6] = np.eye(6)
            if offset:
                assert twist is not None
                design[:, -1] = twist
            terms.append((design, al.vector, al.information))
    weights = np.ones(len(terms))
    x: F64 = np.zeros(n)
    H: F64 = np.eye(n)
    d2: F64 = np.zeros(len(terms))
    for _ in range(iterations):
        H = sum((w * D.T @ info @ D for w, (D, _, info) in zip(weights, terms, strict=True)), pinned)
        g = sum((w * D.T @ info @ obs for w, (D, obs, info) in zip(weights, terms, strict=True)), np.zeros(n))
        x = np.asarray(np.linalg.lstsq(H, g, rcond=None)[0], np.float64)
        d2 = np.array([float((obs - D @ x) @ info @ (obs - D @ x)) for D, obs, info in terms])
        scale = max(float(np.median(d2)) / 5.35, 1.0)  # 5.35: the median of chi-square with 6 dof
        weights = 1.0 / (1.0 + d2 / (CAUCHY_D2 * scale))
    spread = max(float(np.median(d2)) / 5.35, 1.0)
    cov = np.linalg.pinv(H) * spread
    corrections = {}
    for k, name in enumerate(names):
        block = slice(6 * k, 6 * k + 6)
        mine = [found[name] for found, _ in samples if name in found]
        range_m = float(np.median([a.range_m for a in mine]))
        pixel_rad = float(np.median([a.pixel_rad for a in mine]))
        floor_rad = SYSTEMATIC_PX * pixel_rad
        floor = np.diag([floor_rad**2] * 3 + [(floor_rad * range_m) ** 2] * 3)
        info = np.linalg.pinv(cov[block, block] + floor)
        corrections[name] = Alignment(
            x[block][:3], x[block][3:], info, len(mine), float("nan"), float("nan"), range_m, pixel_rad
        )
    sigma_ms = _offset_sigma_s(H, spread) * 1e3 if offset else float("inf")
    return Combined(
        corrections, float(x[-1] * 1e3) if offset else None, sigma_ms, len(samples), float(np.sqrt(spread))
    )


def corrected(T_cam0_sensor: F64, correction: Alignment) -> F64:
    """A sensor's pose in cam0 (4x4) with a LiDAR's `correction` applied: points it measured, placed in
    cam0 through the result, land where the correction moved them."""
    delta = np.eye(4)
    delta[:3, :3] = rotation_matrix(correction.rotation_rad)
    delta[:3, 3] = correction.translation_m
    out: F64 = delta @ T_cam0_sensor
    return out


WARN_ROTATION_DEG = 0.1
WARN_TRANSLATION_MM = 10.0
WARN_CLOCK_MS = 2.0
"""A recording's combined alignment says "the rig file or the clocks are off" beyond these (and beyond
`SIGNIFICANT` sigmas): on the simulated walks, an exact rig gives 0.01 deg, 1 mm and 0.05 ms, a
0.25 deg or 5 ms error about 0.25 deg or 5 ms (bench/bench_refine.py)."""
SIGNIFICANT = 3.0
MIN_POSE_SAMPLES = 3
"""A LiDAR pose or camera clock is called off from this many aligned samples or more: with fewer the
samples' spread, which scales the sigmas, is a guess (two samples of a right rig on the walk, its lower
frames thinned, said 0.36 deg and 87 mm)."""
MATCH_RATIO = 0.6
"""A LiDAR whose points match cam0's images (median correlation of image intensity and reflectivity at
the alignment) below this fraction of the best-matching LiDAR's is off by more than the alignment can
measure: it is a local search whose reach is about a degree, and it reports a LiDAR turned 5, 20 or
45 deg as about 1 deg off. On the simulated fixtures the LiDARs of an exact rig match at 0.70 and
0.79, one turned by 5 to 120 deg at 0.25 to 0.35."""


@dataclass(frozen=True)
class CalibrationCheck:
    """A recording's samples' alignments summed up: per LiDAR the median misalignment of its points on
    cam0's images (deg), and what `combine` makes of them."""

    median_shift_deg: dict[str, float]
    combined: Combined
    median_correlation: dict[str, float] = field(default_factory=dict)

    def mismatched(self) -> dict[str, str]:
        """The LiDARs whose points match cam0's images far worse than the best one's (`MATCH_RATIO`), each
        with the best one's name; none with a single LiDAR (nothing to compare with)."""
        known = {n: c for n, c in self.median_correlation.items() if np.isfinite(c)}
        if len(known) < 2:
            return {}
        best = max(known, key=lambda n: known[n])
        if known[best] <= 0.0:  # no LiDAR's points match the images: nothing to compare against
            return {}
        return {n: best for n, c in known.items() if n != best and c < MATCH_RATIO * known[best]}

    def mismatch_phrase(self, name: str, best: str) -> str:
        """What `mismatched` found about `name`, in words."""
        mine, theirs = self.median_correlation[name], self.median_correlation[best]
        return (
            f"{name}'s points match cam0's images far worse than {best}'s (median correlation {mine:.2f} "
            f"against {theirs:.2f}): its pose is off by more than this check measures (about 1 deg), or its "
            "clock or IMU is"
        )

    def suspects(self) -> list[str]:
        """One phrase per finding beyond the warning limits: a LiDAR's pose, the upper camera's clock."""
        mismatched = self.mismatched()
        found = [self.mismatch_phrase(name, best) for name, best in mismatched.items()]
        for name, corr in self.combined.corrections.items():
            if name in mismatched or self.combined.samples < MIN_POSE_SAMPLES:
                continue
            angle = float(np.degrees(np.linalg.norm(corr.rotation_rad)))
            shift_mm = float(np.linalg.norm(corr.translation_m) * 1e3)
            turned = angle > max(WARN_ROTATION_DEG, SIGNIFICANT * corr.sigma_rotation_deg)
            moved = shift_mm > max(WARN_TRANSLATION_MM, SIGNIFICANT * corr.sigma_translation_mm)
            if turned or moved:
                found.append(f"{name}'s pose in cam0 looks off by {angle:.2f} deg and {shift_mm:.0f} mm")
        ms, sigma = self.combined.clock_offset_ms, self.combined.sigma_clock_ms
        few = self.combined.samples < MIN_POSE_SAMPLES
        if ms is not None and not few and abs(ms) > max(WARN_CLOCK_MS, SIGNIFICANT * sigma):
            found.append(f"the upper camera's exposure times look {ms:+.1f} ms off the LiDAR clock")
        return found

    def warnings(self, rig: object, refined: bool = False) -> list[str]:
        """One line naming what looks off and the command that fixes it (none when nothing does); with
        `refined` (the run refined the rig first), what is left is beyond refine's reach."""
        suspects = self.suspects()
        if not suspects:
            return []
        if refined or self.mismatched():  # beyond what refine corrects
            fix = (
                f"check {rig}'s LiDAR and IMU poses and clocks by hand (refine corrects about a degree and "
                "a few centimetres" + (", and this run refined the rig first)" if refined else ")")
            )
        else:
            fix = (
                f"refine the rig (sensorbox calib refine BAGS --rig {rig} --out REFINED.yaml) and ingest "
                "with it, or ingest with --refine"
            )
        where = f"from {self.combined.samples} samples' LiDAR points on cam0's images"
        names = self.combined.corrections.keys()
        if len(names) > 1 and all(any(s.startswith(f"{n}'s ") for s in suspects) for n in names):
            where += "; every LiDAR looks off, so cam0 itself may be: its intrinsics, its images or its clock"
        return [f"{'; '.join(suspects)} ({where}): {fix}"]

    def as_yaml(self) -> dict[str, object]:
        """The check as dataset.yaml keeps it (deg, mm, ms)."""
        lidars = {}
        for name, corr in self.combined.corrections.items():
            lidars[name] = {
                "median_misalignment_deg": round(self.median_shift_deg.get(name, float("nan")), 4),
                "pose_correction_deg": round(float(np.degrees(np.linalg.norm(corr.rotation_rad))), 4),
                "pose_correction_mm": round(float(np.linalg.norm(corr.translation_m) * 1e3), 2),
                "sigma_deg": round(corr.sigma_rotation_deg, 4),
                "sigma_mm": round(corr.sigma_translation_mm, 2),
                "median_correlation": round(self.median_correlation.get(name, float("nan")), 3),
            }
        ms = self.combined.clock_offset_ms
        return {
            "samples": self.combined.samples,
            "lidars": lidars,
            "upper_clock_offset_ms": None if ms is None else round(ms, 3),
            "upper_clock_sigma_ms": None if ms is None else round(self.combined.sigma_clock_ms, 3),
            "suspects": self.suspects(),
        }


def check_calibration(samples: SampleAlignments) -> CalibrationCheck | None:
    """`CalibrationCheck` of a recording's samples; None when none aligned."""
    combined = combine(samples)
    if combined is None:
        return None
    shifts, correlations = {}, {}
    for name in combined.corrections:
        mine = [found[name] for found, _ in samples if name in found]
        shifts[name] = float(np.median([a.shift_deg for a in mine]))
        correlations[name] = float(np.median([a.correlation for a in mine]))
    return CalibrationCheck(shifts, combined, correlations)


def _offset_sigma_s(H: F64, spread: float) -> float:
    """1-sigma (s) of the clock offset, the last unknown of normal equations `H`, the poses marginalised
    out; infinite when the motion gave it no information of its own (a rig standing still)."""
    poses, across = H[:-1, :-1], H[:-1, -1]
    own = float(H[-1, -1] - across @ np.linalg.lstsq(poses, across, rcond=None)[0])
    return float(np.sqrt(spread / own)) if own > 1e-12 * max(float(H[-1, -1]), 1e-300) else float("inf")


def from_metas(metas: Sequence[SampleMeta]) -> tuple[SampleAlignments, SampleAlignments]:
    """The samples' alignments as their metadata recorded them: onto the upper images (with cam0's
    twist) and onto the lower ones."""
    return from_records([(m.alignment, m.alignment_lower, m.twist_cam0) for m in metas])


AlignmentRecord = tuple[Mapping[str, AlignmentMeta], Mapping[str, AlignmentMeta], Sequence[float] | None]
"""A sample's recorded alignments: per LiDAR onto the upper image, onto the lower one, and cam0's twist."""


def from_records(records: Sequence[AlignmentRecord]) -> tuple[SampleAlignments, SampleAlignments]:
    """`from_metas` of the samples' recorded alignments (`AlignmentRecord`)."""
    upper = [
        ({name: Alignment.from_meta(a) for name, a in up.items()},
         None if twist is None else np.asarray(twist, np.float64))
        for up, _, twist in records
    ]  # fmt: skip
    lower = [({name: Alignment.from_meta(a) for name, a in low.items()}, None) for _, low, _ in records]
    return upper, lower
