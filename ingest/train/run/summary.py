"""What an ingest run did (`IngestSummary`): the counts, timings and decisions the CLI's summary table and
dataset.yaml report, gathered sample by sample."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from calibration.types import F64
from ingest.dataset.meta import SampleMeta
from ingest.train.gt.align import Alignment
from ingest.train.gt.align_check import CalibrationCheck, SampleAlignments, from_metas
from ingest.train.run.frame_check import FrameFlags, FrameRecord, frame_flags, kind
from ingest.train.run.frame_lines import flag_lines, lower_off_line
from ingest.train.run.lidar_rate import THIN_FRACTION
from ingest.train.run.refine import Refinement
from ingest.train.run.sample_dense import GAP_FALLBACK
from ingest.train.run.sample_job import ALIGNED, SampleAlignment, SampleResult
from ingest.train.run.stream import ALREADY_HELD
from ingest.train.trajectory.estimate import TrajectorySummary
from ingest.train.trajectory.imu_check import GyroAgreement

if TYPE_CHECKING:
    from ingest.train.run.plan import Survey

_OTHER = {"upper": "lower image", "lower": "upper image"}
"""A camera's samples to leave out of its calibration check are those of every finding but the other
camera's own (`IngestSummary.unflagged_alignments`)."""
OVER_UINT16 = "over the depth PNG's 65.535 m, left empty"


RANGE_DISAGREE = 0.01
RANGE_MIN_PIXELS = 200
"""A LiDAR's ranges disagree with the first LiDAR's beyond this fraction (median of the samples' median
ratios, over at least this many pixels seen by both): on the simulated room and walk an exact rig agrees
to 0.03 %, a LiDAR reading 5 % long gives 0.952, one reading 0.3 m long 0.93."""
RANGE_SCATTER = 0.02
"""The LiDARs' ranges scatter beyond this (median over the samples of the ratios' robust 1-sigma,
`ingest.train.gt.lidar_agreement.range_ratios`, over at least `RANGE_MIN_PIXELS` pixels): the simulated
fixtures with a Mid-360's 2 cm noise give 0.1-0.9 %, ranges with 0.1 m noise 3.2-3.5 %, 0.3 m 9-10 %."""

PLANE_SCATTER_M = 0.03
"""A LiDAR's points scatter about the other LiDARs' local planes beyond this (m, median over the samples of
`ingest.train.gt.lidar_agreement.plane_scatter`): a Mid-360 measures within 2 cm (1-sigma at 10 m, 3 cm at
0.2 m); the simulated fixtures give 0-8 mm without range noise and 18-22 mm with 2 cm on both LiDARs, 5 cm
on one 40-43 mm for it (12-20 mm for the other)."""


@dataclass
class IngestSummary:
    """What an ingest run did, for the CLI's summary table."""

    written: int = 0
    resumed: int = 0
    skipped: dict[str, int] = field(default_factory=dict)
    flagged: dict[str, int] = field(default_factory=dict)  # written, with a warning in their meta
    undecodable: dict[str, int] = field(default_factory=dict)  # per topic: messages skipped (--max-bad)
    dropped: dict[str, dict[str, int]] = field(default_factory=dict)  # per topic, reason: `plausible`
    frames: int = 0
    pairs: int = 0
    planned: int = 0
    density_by_method: dict[str, list[float]] = field(default_factory=dict)  # under --gt auto both occur
    skew_ms: list[float] = field(default_factory=list)
    stereo_dt_ms: list[float] = field(default_factory=list)  # lower minus upper header stamp, per sample
    motion_applied: int = 0
    dense_points: dict[str, int] = field(default_factory=dict)  # dense GT: totals over the samples
    seen_through: int = 0  # sparse GT: points removed that the window's other slices saw through, in all
    stage_ms: dict[str, list[float]] = field(default_factory=dict)  # sequential: they add up per sample
    overlapped_ms: dict[str, list[float]] = field(default_factory=dict)  # helper threads beside them
    seconds: float = 0.0
    dense_warm_up_s: float | None = None  # dense GT's kernels and pixel rays, before the samples
    compile_s: float = 0.0  # numba compiling in this process (`ingest.runtime.jit`): a checkout's first run
    dense_planes: tuple[int, float] | None = None  # dense GT: (blocks fitted, workers' seconds on them)
    out: Path | None = None
    method: str = "sparse"
    decision: str = ""
    trajectory: TrajectorySummary | None = None
    imu_check: GyroAgreement | None = None  # the IMU's gyro against the LiDARs' odometry (`check_gyro`)
    lost: dict[str, int] = field(default_factory=dict)  # topic -> messages in corrupt chunks (--salvage)
    lost_chunks: list[str] = field(default_factory=list)  # one line per corrupt chunk skipped
    duplicates: dict[str, int] = field(default_factory=dict)  # per topic: repeated stamps, first read
    uncovered: int = 0  # stereo pairs without LiDAR points within the window: not planned
    imu_gaps_ms: list[float] = field(default_factory=list)  # IMU intervals over 5 periods (plan.imu_gaps)
    clock_spread: str | None = (
        None  # the survey's line on the LiDARs' clocks disagreeing (`lidar_clock_spread`)
    )
    warnings: list[str] = field(default_factory=list)  # about the inputs, one line each (the rig's layout)
    stale_temporaries: int = 0  # left in the output by a killed run, removed (`ingest.dataset.lock`)
    without_gt: int = 0  # samples written with no GT pixel in their depth PNG
    without_gt_points: dict[str, int] = field(default_factory=dict)  # their windows' points, by filter
    without_disparity: int = 0  # samples written with depth GT but no disparity GT pixel
    frame_records: list[FrameRecord] = field(
        default_factory=list
    )  # what `frame_check` needs of each written one
    frame_flags: dict[str, list[str]] = field(default_factory=dict)  # its findings: kind -> sample ids
    _frame_lines: list[str] = field(default_factory=list)  # their warning lines (`flag_frames`)
    _frames: FrameFlags | None = None  # what `flag_frames` found
    range_ratios: dict[str, list[tuple[float, int, float | None]]] = field(
        default_factory=dict
    )  # per LiDAR, per sample: `SampleMeta.points.range_ratio` (scatter None in an older meta)
    plane_scatters: dict[str, list[float]] = field(default_factory=dict)  # per LiDAR, per sample (m)

    def range_line(self, first: str) -> str:
        """One warning line on the LiDARs whose ranges disagree with the rig's first LiDAR's (`first`) by
        over `RANGE_DISAGREE`, median over the samples, where cam0 sees both in a pixel ('' if none)."""
        lines = []
        for name, found in self.range_ratios.items():
            ratio, pixels = float(np.median([r for r, _, _ in found])), sum(n for _, n, _ in found)
            if abs(ratio - 1.0) <= RANGE_DISAGREE or pixels < RANGE_MIN_PIXELS:
                continue
            how = f"{100 * abs(ratio - 1):.2f} % {'longer' if ratio > 1 else 'shorter'}"
            lines.append(
                f"{name}'s ranges read {how} than {first}'s on the surfaces cam0 sees both on (median over "
                f"{pixels:,} pixels of {len(found)} samples; a right rig agrees to 0.05 %): one of them "
                "measures ranges wrong (a range scale or offset) or its pose is off along the view, and the "
                "depth GT mixes both: ingest with each alone (the other left out of the rig) to see which "
                "matches the images"
            )
        return "; ".join(lines)

    def scatter_line(self, first: str) -> str:
        """One warning line on the LiDARs whose ranges scatter against the first LiDAR's (`first`) beyond
        `RANGE_SCATTER` where cam0 sees both in a pixel ('' if none)."""
        return "; ".join(
            line
            for name, found in self.range_ratios.items()
            if (line := _scatter_line(name, first, found, sum(n for _, n, _ in found)))
        )

    def plane_line(self) -> str:
        """One warning line on the LiDARs whose points scatter about the other LiDARs' surfaces beyond
        `PLANE_SCATTER_M`, median over the samples ('' if none)."""
        medians = {name: float(np.median(found)) for name, found in self.plane_scatters.items() if found}
        lines = []
        for name, sigma_m in medians.items():
            if sigma_m <= PLANE_SCATTER_M:
                continue
            others = ", ".join(f"{o}'s {1e3 * m:.0f} mm" for o, m in medians.items() if o != name)
            lines.append(
                f"{name}'s points scatter {1e3 * sigma_m:.0f} mm (robust 1-sigma, median over "
                f"{len(self.plane_scatters[name])} samples) about the surfaces the other LiDARs' points give "
                f"({others} about its); a Mid-360 measures within 20 mm: {name} measures with range noise "
                "beyond its specification (a degraded or wrong sensor) and the depth GT carries it: ingest "
                "without it (leave it out of the rig) to compare"
            )
        return "; ".join(lines)

    def closing_lines(self, first_lidar: str) -> list[str]:
        """The warning lines the written samples give together, in order (`first_lidar`: the rig's first
        LiDAR, the others' ranges are compared with), with those of `flag_frames`."""
        found = [self.without_gt_line(), self.without_disparity_line(), *self._frame_lines]
        ranges = (self.range_line(first_lidar), self.scatter_line(first_lidar), self.plane_line())
        return [line for line in (*found, *ranges) if line]

    def without_gt_line(self) -> str:
        """One warning line when written samples hold no GT pixel, with their points by filter ('' if none).

        A recording whose points are all NaN, zero, noise-tagged or out of every view writes samples with
        an empty depth PNG, which a training set must not take for ground truth without a word.
        """
        if not self.without_gt:
            return ""
        counts = self.without_gt_points
        points = {why: n for why, n in counts.items() if why not in ("total", OVER_UINT16) and n}
        reasons = ", ".join(f"{n:,} {why}" for why, n in points.items())
        over = counts.get(OVER_UINT16, 0)
        return (
            f"{self.without_gt} of {self.written} samples written hold no ground truth pixel; their windows' "
            f"LiDAR points: {counts.get('total', 0):,}{f' ({reasons})' if reasons else ''}"
            + (f"; {over:,} GT pixels {OVER_UINT16}" if over else "")
        )

    def without_disparity_line(self) -> str:
        """One warning line when written samples hold depth GT but not one disparity GT pixel ('' if none):
        the equirect pair's disparity is read from the same planes, so only too few rows lose it all (at
        `--height-full 64` the 0.12 m baseline's disparity stays under what the GT keeps)."""
        if not self.without_disparity:
            return ""
        return (
            f"{self.without_disparity} of {self.written} samples written hold depth GT but no disparity GT "
            "pixel: the equirect pair is too coarse for the baseline's disparity (more --height-full rows "
            "keep it: 128 and up)"
        )

    held_elsewhere: int = 0  # of `resumed`: frames that samples of other ids hold (`ingest.dataset.identity`)
    refinement: Refinement | None = None  # --refine: what `ingest.train.run.refine` found and the rig it made
    alignments: list[tuple[Mapping[str, Alignment], F64 | None]] = field(default_factory=list)  # per sample
    alignments_lower: list[tuple[Mapping[str, Alignment], F64 | None]] = field(default_factory=list)  # cam1's
    alignment_ids: tuple[list[str], list[str]] = field(default_factory=lambda: ([], []))  # their samples' ids
    calibration: CalibrationCheck | None = None  # the samples' alignments summed up (`ingest.train.gt.align`)
    damaged: list[str] = field(default_factory=list)  # finished samples found damaged, written again: why
    aligned: dict[str, SampleAlignment] = field(default_factory=dict)  # per sample id: alignment_only's

    @property
    def density(self) -> list[float]:
        """GT density (fisheye) of every written sample, grouped by GT method."""
        return [d for by_method in self.density_by_method.values() for d in by_method]

    def add_resumed(self, meta: SampleMeta) -> None:
        """A sample an earlier run finished (`AlreadyDone`): counted, and its alignments join the
        recording's calibration check, which covers every sample of it, not only this run's."""
        self.resumed += 1
        self._add_alignments(meta)
        self.frame_records.append(FrameRecord.from_meta(meta))

    def _add_alignments(self, meta: SampleMeta) -> None:
        """A sample's alignments onto both images, for the calibration check, with its id."""
        if meta.alignment:
            upper, lower = from_metas([meta])
            self.alignments.extend(upper)
            self.alignment_ids[0].append(meta.id)
            if lower[0][0]:
                self.alignments_lower.append((lower[0][0], None))
                self.alignment_ids[1].append(meta.id)

    def add_survey(self, surveyed: Survey) -> None:
        """What the first pass found of the inputs: the IMU's gaps, the warning lines, the LiDARs' clocks."""
        self.imu_gaps_ms = [float(g) / 1e6 for g in surveyed.imu_gaps_ns]
        self.warnings += surveyed.warnings
        self.clock_spread = surveyed.clock_spread

    def flag_frames(self) -> None:
        """Name the samples whose frames stand out (`frame_check.frame_flags`), in `frame_flags` and
        `flagged`; once, before the calibration check leaves them out (`unflagged_alignments`)."""
        self._frames = flags = frame_flags(self.frame_records)
        self.frame_flags, self._frame_lines = dict(flags.found), flag_lines(flags)
        for what, ids in flags.found.items():
            self.flagged[what] = len(ids)

    def lower_off_unexplained(self) -> None:
        """Name the lower images off in most samples (`FrameFlags.lower_off_most`), when the stereo pose's
        check found no pose error to explain them."""
        if self._frames is not None and (ids := self._frames.lower_off_most):
            what = kind("lower", "off")
            self.frame_flags[what] = ids
            self.flagged[what] = len(ids)
            self._frame_lines.append(lower_off_line(ids, self._frames.samples))

    def unflagged_alignments(self) -> tuple[SampleAlignments, SampleAlignments]:
        """`alignments` and `alignments_lower` without the samples whose upper (lower) frame is flagged: a
        frame out of place would pull the rig's pose and the stereo pose towards itself."""
        out = []
        for camera, found, ids in (
            ("upper", self.alignments, self.alignment_ids[0]),
            ("lower", self.alignments_lower, self.alignment_ids[1]),
        ):
            bad = {sid for what, flagged in self.frame_flags.items() if not what.startswith(_OTHER[camera])
                   for sid in flagged}  # fmt: skip
            out.append([a for a, sid in zip(found, ids, strict=True) if sid not in bad])
        return out[0], out[1]

    def add(self, result: SampleResult) -> None:
        if result.reason == ALIGNED and result.aligned is not None:
            self.aligned[result.sid] = result.aligned
            return
        if result.reason == ALREADY_HELD:
            self.resumed += 1
            self.held_elsewhere += 1
            return
        if not result.written:
            self.skipped[result.reason] = self.skipped.get(result.reason, 0) + 1
            return
        self.written += 1
        meta = result.meta
        assert meta is not None  # written samples carry their metadata
        self.density_by_method.setdefault(meta.gt.method, []).append(meta.gt.density)
        if meta.gt.depth_pixels > 0 and meta.gt.disp_pixels == 0:
            self.without_disparity += 1
        if meta.gt.depth_pixels == 0:
            self.without_gt += 1
            p = meta.points
            for why, n in (
                ("total", p.total), ("zero", p.zero), ("non-finite", p.non_finite),
                ("nearer than --min-range", p.too_close), ("noise-tagged", p.noise_tag),
                ("outside the IMU's span", p.off_imu), ("out of view", p.out_of_view),
                ("occluded", p.occluded), ("visible", p.kept - p.out_of_view - p.occluded),
                (OVER_UINT16, meta.dropped.get("depth_over_uint16", 0)),
            ):  # fmt: skip
                self.without_gt_points[why] = self.without_gt_points.get(why, 0) + n
        self._add_alignments(meta)
        self.frame_records.append(FrameRecord.from_meta(meta))
        self.skew_ms.extend(meta.lidar_skew_ms.values())
        for name, (ratio, pixels, *scatter) in meta.points.range_ratio.items():
            spread = scatter[0] if scatter else None
            self.range_ratios.setdefault(name, []).append((ratio, int(pixels), spread))
        for name, (sigma_m, _) in meta.points.plane_scatter.items():
            self.plane_scatters.setdefault(name, []).append(float(sigma_m))
        self.stereo_dt_ms.append(meta.stereo_dt_ms)
        for name in meta.points.silent_lidars:
            key = f"{name} silent in the window"
            self.flagged[key] = self.flagged.get(key, 0) + 1
        for name in meta.points.thin_lidars:
            key = f"{name} thin in the window (< {THIN_FRACTION:.0%} of its rate)"
            self.flagged[key] = self.flagged.get(key, 0) + 1
        self.motion_applied += meta.motion.applied
        if meta.gt.decision == GAP_FALLBACK:
            key = "sparse GT (frame in a trajectory gap)"
            self.flagged[key] = self.flagged.get(key, 0) + 1
        if meta.gt.method == "dense":
            for key, n in (
                ("accumulated", meta.gt.accumulated_points),
                ("removed as movers", meta.gt.removed_moving),
                ("left out: no registered pose near the frame", meta.points.off_trajectory),
            ):
                self.dense_points[key] = self.dense_points.get(key, 0) + n
        else:
            self.seen_through += meta.gt.removed_moving
        for k, v in result.stage_ms.items():
            self.stage_ms.setdefault(k, []).append(v)
        for k, v in result.overlapped_ms.items():
            self.overlapped_ms.setdefault(k, []).append(v)


def _scatter_line(name: str, first: str, found: list[tuple[float, int, float | None]], pixels: int) -> str:
    """One warning line when LiDAR `name`'s ranges scatter against the first LiDAR's (`first`) beyond
    `RANGE_SCATTER` (median over the samples that measured it; '' otherwise)."""
    measured = [s for _, _, s in found if s is not None]
    if not measured or pixels < RANGE_MIN_PIXELS or (scatter := float(np.median(measured))) <= RANGE_SCATTER:
        return ""
    return (
        f"{name}'s and {first}'s ranges scatter by {100 * scatter:.1f} % against each other on the surfaces "
        f"cam0 sees both on (robust 1-sigma of their ratio, median over {len(measured)} samples and "
        f"{pixels:,} pixels; two Mid-360s agree within about 1 %): one of them or both measure with range "
        "noise far beyond a Mid-360's 2 cm (a degraded or wrong sensor), or their points land apart (a "
        "clock or pose error that varies over the window), and the depth GT carries that noise: ingest with "
        "each alone (the other left out of the rig) to see which matches the images"
    )
