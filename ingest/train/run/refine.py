"""`sensorbox calib refine`: the clocks and rotations a recording reveals, and the rig they imply.

One pass over the bags reads both cameras and every IMU of the rig: each camera's
rotation between frames (`timeshift.pair_rotation`, streamed: a few frames in
memory per camera) and the gyros. Then, where the motion made them observable:
each camera's offset to the first IMU's (= LiDAR's) clock, written as Kalibr's
`timeshift_cam_imu`; each IMU's rotation in cam0 (`timeshift.estimate_imu_rotation`),
applied to it and to the LiDAR of its housing; and a check of the stereo rotation
(`timeshift.check_stereo_rotation`), reported only. What the motion did not reveal
keeps the rig's value, and the report says why.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from calibration.camera import CameraModel
from calibration.errors import CalibrationError
from calibration.housing import housing_lidar
from calibration.rig import Imu, Lidar, Rig, with_timeshifts
from calibration.types import F64, U8
from ingest.bags.decode import Frame, ImuSample
from ingest.bags.reader import open_bags
from ingest.errors import BagError
from ingest.topic_map import missing_topic
from ingest.train.gt.align import Alignment
from ingest.train.gt.align_check import (
    SIGNIFICANT,
    WARN_CLOCK_MS,
    SampleAlignments,
    check_calibration,
    combine,
    corrected,
)
from ingest.train.run.lidar_poses import (
    LidarRefinement,
    StereoAlignment,
    applies,
    common_cause,
    held_translations,
    stereo_alignment,
)
from ingest.train.run.timeshift import (
    TIMING_ROTATION_SIGMA_DEG,
    FrameRotations,
    ImuRotation,
    StereoCheck,
    TimeshiftEstimate,
    check_stereo_rotation,
    corners,
    estimate_imu_rotation,
    estimate_timeshift,
    pair_rotation,
)
from ingest.train.trajectory.clouds import GyroTrack, integrate_gyro

PAIR_GAPS = (3, 6, 12)
"""Frames are paired with the ones this many frames before: the offset's signal, the change of the angular
rate between the two, grows with the gap while the rotation's error does not, so a pair's information
grows with the gap squared and a gap of one frame would add 0.5 % of it for a quarter of the tracking
(8 s walk at 960x600: the same 1-sigma, 0.10 ms, with 17 % less CPU)."""
IN_FLIGHT = 32
"""Frame pairs queued for tracking at most (each holds two grey images)."""
TRACK_WIDTH_PX = 1000
"""Images wider than this are halved (repeatedly) before tracking: corners track as well, 4x faster."""


@dataclass(frozen=True)
class CameraRefinement:
    """One camera's clock offset: the rig's value, the estimate and whether the refined rig takes it."""

    camera: str
    rig_timeshift_ms: float
    estimate: TimeshiftEstimate
    applied: bool
    rejected: str = ""  # why an observable estimate is not written (the LiDAR points disagree)


@dataclass(frozen=True)
class ImuRefinement:
    """One IMU (and the LiDAR in its housing): its clock against cam0's and its orientation in cam0."""

    imu: str
    lidar: str | None  # the LiDAR of the same housing, whose rotation moves with it
    timeshift: TimeshiftEstimate  # cam0's exposure on this IMU's clock = stamp + this
    rotation: ImuRotation


@dataclass(frozen=True)
class Refinement:
    """What `refine` found; `rig` is the refined rig (the input's where nothing was observable)."""

    cameras: tuple[CameraRefinement, ...]
    imus: tuple[ImuRefinement, ...]
    rig: Rig
    frames: dict[str, int]  # per camera: frames read
    imu_readings: dict[str, int]  # per IMU
    stereo: StereoCheck  # the camchain's stereo rotation against the cameras' own motion (not changed)
    lidars: tuple[LidarRefinement, ...] = ()  # with an `align` run: each LiDAR's pose from the images
    image_clock_ms: tuple[float, float] | None = None  # the alignment's own check of cam0's offset: the
    # exposure times were this much late after refining (ms, 1-sigma); None: not observable or not run
    stereo_alignment: StereoAlignment | None = None  # the stereo pose checked by the LiDAR points

    def unobserved_lines(self) -> list[str]:
        """One line per camera offset the recording could not reveal: what was kept and what to record."""
        lines = [f"{cam.camera}: {cam.rejected}" for cam in self.cameras if cam.rejected]
        for cam in self.cameras:
            e = cam.estimate
            if not e.observable:
                lines.append(
                    f"{cam.camera}: clock offset not observable from this recording (rate change "
                    f"{e.excitation_deg_s:.1f} deg/s, 1-sigma {e.sigma_ms:.2f} ms); the rig's "
                    f"{cam.rig_timeshift_ms:+.3f} ms is kept: record the rig turned by hand for a few seconds"
                )
        reasons: dict[str, list[str]] = {}
        for lidar in self.lidars:
            if lidar.mismatch:
                reasons.setdefault(lidar.mismatch, []).append(lidar.lidar)
        lines += [f"{', '.join(names)}: the rig's pose is kept: {why}" for why, names in reasons.items()]
        if self.stereo_alignment is not None and self.stereo_alignment.disagrees:
            a = self.stereo_alignment
            lines.append(
                f"{a.lidar}'s points on both images put the camchain's stereo pose {a.rotation_deg:.2f} deg "
                f"and {a.translation_mm:.1f} mm off (1-sigma {a.sigma_rotation_deg:.2f} deg, "
                f"{a.sigma_translation_mm:.1f} mm); recalibrate the stereo pair (kalibr_calibrate_cameras)"
            )
        if self.stereo.disagrees:
            s = self.stereo
            lines.append(
                f"the cameras' motion puts cam1 {s.angle_deg:.2f} deg (1-sigma {s.sigma_deg:.2f}) away from "
                "the camchain's stereo rotation; recalibrate the stereo pair (kalibr_calibrate_cameras)"
            )
        return lines


@dataclass
class _Recording:
    """What one pass over the bags keeps: both cameras' frame-pair rotations and every IMU's gyro."""

    pairs: tuple[list[tuple[int, int, F64, int]], list[tuple[int, int, F64, int]]]
    frames: list[int]
    gyro: dict[str, tuple[list[int], list[F64]]]  # per IMU name: stamps, readings (rad/s, IMU frame)


def _topic(topics: Sequence[str], wanted: str | None, what: str, where: str) -> str:
    """The bag's topic for a rig sensor: its own, or `<topic>/compressed` for a camera."""
    for cand in (wanted, f"{wanted}/compressed"):
        if cand is not None and cand in topics:
            return cand
    raise BagError(missing_topic(where, wanted, what, topics))


def _gray(frame: Frame, halvings: int) -> U8:
    """A frame as 8-bit grey, halved `halvings` times."""
    img: Any = np.asarray(frame.image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    if img.dtype != np.uint8:  # mono16
        img = (img // 257).astype(np.uint8)
    for _ in range(halvings):
        img = cv2.pyrDown(img)
    out: U8 = np.asarray(img, np.uint8)
    return out


def _halvings(width: int) -> int:
    n = 0
    while width > TRACK_WIDTH_PX:
        width //= 2
        n += 1
    return n


def _housing_lidar(rig: Rig, imu: Imu, k: int) -> Lidar | None:
    """The LiDAR built into the same Mid-360 as `imu` (`calibration.housing.housing_lidar`), else the k-th."""
    return housing_lidar(rig, imu) or (rig.lidars[k] if k < len(rig.lidars) else None)


def _read(bags: Sequence[Path], rig: Rig, progress: Callable[[int, int], None] | None) -> _Recording:
    """One pass: frame-pair rotations of both cameras (`PAIR_GAPS`) and the readings of every IMU."""
    cams = (rig.upper, rig.lower)
    rec = _Recording(([], []), [0, 0], {imu.name: ([], []) for imu in rig.imus})
    with open_bags(list(bags)) as bagset:
        names = list(bagset.topics())
        topics = [_topic(names, c.topic, f"camera {c.name}", bagset.label) for c in cams]
        imu_of = {_topic(names, i.topic, f"imu {i.name}", bagset.label): i.name for i in rig.imus}
        halvings = [_halvings(c.model.width) for c in cams]
        models = [c.model.scaled(0.5**h) if h else c.model for c, h in zip(cams, halvings, strict=True)]
        recent: list[list[tuple[int, U8, Future[F64 | None]]]] = [[], []]  # per camera: last frames
        pending: deque[tuple[int, int, int, Future[tuple[F64, int] | None]]] = deque()
        # OpenCV's trackers release the GIL: corners and pairs are tracked on two threads while the
        # next frames are read and decoded; at most IN_FLIGHT pairs wait, so memory stays bounded
        with ThreadPoolExecutor(2) as pool:
            for msg in bagset.messages(topics=[*topics, *imu_of], progress=progress):
                decoded = msg.decoded(bagset.label)  # a failure names the bags, the topic and the log time
                if isinstance(decoded, ImuSample):
                    stamps, readings = rec.gyro[imu_of[msg.topic]]
                    stamps.append(decoded.stamp_ns)
                    readings.append(decoded.gyro_rad_s)
                    continue
                assert isinstance(decoded, Frame)
                c = topics.index(msg.topic)
                h, w = decoded.image.shape[:2]
                if (w, h) != (cams[c].model.width, cams[c].model.height):
                    raise BagError(
                        f"{bagset.label}: topic {msg.topic!r} at stamp {decoded.stamp_ns}: a {w}x{h} image; "
                        f"camera {cams[c].name} of the rig is {cams[c].model.width}x{cams[c].model.height} "
                        "(a rig of another resolution?)"
                    )
                gray = _gray(decoded, halvings[c])
                rec.frames[c] += 1
                for gap in PAIR_GAPS:
                    if len(recent[c]) >= gap and decoded.stamp_ns > recent[c][-gap][0]:
                        t0, gray0, corners0 = recent[c][-gap]
                        job = pool.submit(_pair, models[c], gray0, gray, corners0)
                        pending.append((c, t0, decoded.stamp_ns, job))
                recent[c] = [
                    *recent[c][-max(PAIR_GAPS) + 1 :],
                    (decoded.stamp_ns, gray, pool.submit(corners, models[c], gray)),
                ]
                while len(pending) > IN_FLIGHT:
                    _collect(rec, pending.popleft())
            while pending:
                _collect(rec, pending.popleft())
    for imu in rig.imus:
        if len(rec.gyro[imu.name][0]) < 2:
            where = ", ".join(map(str, bags))
            n = len(rec.gyro[imu.name][0])
            raise BagError(f"{where}: topic {imu.topic!r} has {n} readings; refine needs its gyro")
    return rec


def _pair(model: CameraModel, gray0: U8, gray1: U8, corners0: Future[F64 | None]) -> tuple[F64, int] | None:
    start = corners0.result()
    return None if start is None else pair_rotation(model, gray0, gray1, start)


def _collect(rec: _Recording, item: tuple[int, int, int, Future[tuple[F64, int] | None]]) -> None:
    """Keep a tracked pair's rotation (camera, first and second stamp, the job) when it tracked."""
    c, t0, t1, job = item
    got = job.result()
    if got is not None:
        rec.pairs[c].append((t0, t1, got[0], got[1]))


def _rotations(found: list[tuple[int, int, F64, int]]) -> FrameRotations:
    return FrameRotations(
        np.array([p[0] for p in found], np.int64), np.array([p[1] for p in found], np.int64),
        np.array([p[2] for p in found]).reshape(-1, 3), np.array([p[3] for p in found], np.int64),
    )  # fmt: skip


def _track(rec: _Recording, imu: Imu, R_cam0_imu: F64) -> GyroTrack:
    stamps, readings = rec.gyro[imu.name]
    return integrate_gyro(np.array(stamps, np.int64), np.array(readings), R_cam0_imu)


def _rotated(T: F64, R_new: F64, R_old: F64) -> F64:
    """`T` (4x4, cam0 <- sensor) turned in place (position kept) by the correction R_new R_old^T."""
    out = T.copy()
    out[:3, :3] = R_new @ R_old.T @ T[:3, :3]
    return out


Aligner = Callable[[Rig, int], tuple[SampleAlignments, SampleAlignments]]
"""Per-sample LiDAR-to-image alignments of the recording under a rig, given how many frames cam0
recorded: onto the upper images (with cam0's twist) and onto the lower ones (in cam1); a sparse ingest
of some of the frames (`ingest.train.run.pipeline.refine_rig`)."""
ALIGN_ROUNDS = 2
"""Alignment rounds: the second starts from the first's rig, where each sample's linearisation and its
visibility test are closer to the truth (a 1 deg, 3 cm error: 6.4 mm left after one round outdoors)."""


def refuse_unsynced(clock_spread: str | None) -> None:
    """CalibrationError when the recording's LiDARs seem to be on clocks apart (`clock_spread`, the
    survey's `lidar_clock_spread` line): a LiDAR's points placed at wrong times land off cam0's images,
    and a pose refined from them would take the clock error in (35 ms on the walk: 0.98 deg)."""
    if clock_spread:
        raise CalibrationError(
            f"{clock_spread}; refine lays each LiDAR's points onto cam0's images by their times, so a pose "
            "refined from them would take the clock error in: sync the LiDARs and record again, then refine"
        )


def refine(
    bags: Sequence[Path],
    rig: Rig,
    progress: Callable[[int, int], None] | None = None,
    align: Aligner | None = None,
) -> Refinement:
    """Each camera's clock offset to the rig's first IMU, and each IMU's (with its LiDAR's) rotation in
    cam0, from the recording in `bags`; with `align`, then each LiDAR's pose in cam0 (rotation and
    translation) from its points laid onto cam0's images, applied to it and to the IMU of its housing."""
    found = _refine_clocks(bags, rig, progress)
    if align is None:
        return found
    return _clock_checked(_refine_lidars(found, align), rig)


def _clock_checked(found: Refinement, given: Rig) -> Refinement:
    """`found` with the cameras' clock offsets of `given` back when the LiDAR points on cam0's images put
    the refined clock off beyond `WARN_CLOCK_MS` and three sigma: the gyro's estimate and the points
    disagree, and neither is written (the exact rig on the simulated indoor walk: the gyro said +4.2 ms,
    the points +4.1 ms off that, 1-sigma 0.1)."""
    if found.image_clock_ms is None:
        return found
    ms, sigma = found.image_clock_ms
    applied = [c for c in found.cameras if c.applied]
    if abs(ms) <= max(WARN_CLOCK_MS, SIGNIFICANT * sigma) or not applied:
        return found
    names = {c.camera for c in applied}
    shift = {c.name: c.timeshift_cam_imu for c in given.cameras}
    rig = found.rig
    cameras = tuple(
        replace(c, timeshift_cam_imu=shift[c.name]) if c.name in names else c for c in rig.cameras
    )
    chain = rig.camchain and replace(rig.camchain, cameras=tuple(
        replace(k, timeshift_cam_imu=shift[k.name]) if k.name in names else k for k in rig.camchain.cameras
    ))  # fmt: skip
    why = (
        f"the gyro's estimate is not written: the LiDAR points on cam0's images put the clock it gives "
        f"{ms:+.3f} ms off (1-sigma {sigma:.3f}), so the two disagree; the rig's value is kept: check the "
        "IMUs' stamps against the LiDARs' clock"
    )
    kept = tuple(replace(c, applied=False, rejected=why) if c.camera in names else c for c in found.cameras)
    return replace(found, rig=replace(rig, cameras=cameras, camchain=chain), cameras=kept)


def _refine_lidars(found: Refinement, align: Aligner) -> Refinement:
    """`found` with each LiDAR's pose corrected by `ALIGN_ROUNDS` rounds of `align` and `combine`."""
    rig = found.rig
    total = {lidar.name: np.eye(4) for lidar in rig.lidars}
    shifts: list[dict[str, float]] = []
    counts: dict[str, int] = {}
    sigmas: dict[str, tuple[float, float]] = {}
    clock: tuple[float, float] | None = None
    stereo: StereoAlignment | None = None
    mismatch: dict[str, str] = {}
    held: set[str] = set()  # LiDARs whose translation the recording cannot place: their rotation only
    kept: dict[str, str] = {}  # LiDARs kept for a cause common to every LiDAR (`_common_cause`)
    for _ in range(ALIGN_ROUNDS):
        samples, lower = align(rig, found.frames.get(rig.upper.name, 0))
        check = check_calibration(samples)
        if check is None:
            break
        mismatch = {name: check.mismatch_phrase(name, best) for name, best in check.mismatched().items()}
        for name in mismatch:  # beyond the alignment's reach: its correction would be a wrong one
            rig = _with_lidar_pose(rig, found.rig, name)
            total[name] = np.eye(4)
        stereo = stereo_alignment(rig, check.combined, combine([(found_, None) for found_, _ in lower]))
        shifts.append(check.median_shift_deg)
        combined = held_translations(samples, check.combined, held, set(mismatch))
        clock = (
            None if combined.clock_offset_ms is None else (combined.clock_offset_ms, combined.sigma_clock_ms)
        )
        common = common_cause(combined, samples, set(mismatch))
        for name, corr in combined.corrections.items():
            counts[name] = sum(name in s for s, _ in samples)
            sigmas[name] = (corr.sigma_rotation_deg, corr.sigma_translation_mm)
            if common:
                kept[name] = common
            if name in mismatch or name in kept or not applies(corr):
                continue
            rig = _with_lidar_corrected(rig, name, corr)
            total[name] = corrected(total[name], corr)
    lidars = []
    for name, T in total.items():
        if name not in sigmas:
            continue
        angle = float(np.degrees(np.linalg.norm(cv2.Rodrigues(T[:3, :3])[0])))
        applied = not np.array_equal(T, np.eye(4))
        before, after = shifts[0].get(name, float("nan")), shifts[-1].get(name, float("nan"))
        lidars.append(LidarRefinement(
            name, angle, float(np.linalg.norm(T[:3, 3]) * 1e3), *sigmas[name], before, after, counts[name],
            applied, mismatch.get(name, "") or kept.get(name, ""), name in held,
        ))  # fmt: skip
    return replace(found, rig=rig, lidars=tuple(lidars), image_clock_ms=clock, stereo_alignment=stereo)


def _with_lidar_pose(rig: Rig, given: Rig, name: str) -> Rig:
    """`rig` with LiDAR `name` and the IMU of its housing back at their poses in `given`."""
    lidars = tuple(given.lidar(name) if lidar.name == name else lidar for lidar in rig.lidars)
    imus = tuple(
        given.imus[k]
        if (housing := _housing_lidar(rig, imu, k)) is not None and housing.name == name
        else imu
        for k, imu in enumerate(rig.imus)
    )
    return replace(rig, lidars=lidars, imus=imus)


def _with_lidar_corrected(rig: Rig, name: str, correction: Alignment) -> Rig:
    """`rig` with LiDAR `name` and the IMU of its housing moved by `correction` (in cam0)."""
    lidars = tuple(
        replace(lidar, T_cam0_lidar=corrected(lidar.T_cam0_lidar, correction))
        if lidar.name == name
        else lidar
        for lidar in rig.lidars
    )
    imus = tuple(
        replace(imu, T_cam0_imu=corrected(imu.T_cam0_imu, correction))
        if (housing := _housing_lidar(rig, imu, k)) is not None and housing.name == name
        else imu
        for k, imu in enumerate(rig.imus)
    )
    return replace(rig, lidars=lidars, imus=imus)


def _refine_clocks(bags: Sequence[Path], rig: Rig, progress: Callable[[int, int], None] | None) -> Refinement:
    """`refine`'s first part: the cameras' clocks and the IMUs' rotations from the gyros."""
    if not rig.imus:
        where = rig.source or rig.name
        raise BagError(f"{where}: the rig names no IMU; refine needs a gyro to time the cameras")
    rec = _read(bags, rig, progress)
    cam0_rot = _rotations(rec.pairs[0])
    first = rig.imus[0]
    # the first IMU's rotation errs the cameras' offsets a little, and the offset its rotation: the
    # offset with the rig's rotation, then every IMU's rotation, then the offsets again with the new one
    rough = estimate_timeshift(cam0_rot, _track(rec, first, first.T_cam0_imu[:3, :3]), np.eye(3))
    prior_ms = rough.timeshift_ms if rough.observable else (rig.upper.timeshift_cam_imu or 0.0) * 1e3
    imus, lidars = list(rig.imus), list(rig.lidars)
    found_imus = []
    timing_R: list[F64] = []  # per IMU: the rotation the cameras are timed with
    for k, imu in enumerate(rig.imus):
        R_rig = imu.T_cam0_imu[:3, :3]
        shift = estimate_timeshift(cam0_rot, _track(rec, imu, R_rig), np.eye(3), prior_ms)
        shift_ns = round(shift.timeshift_ms * 1e6)
        rotation = estimate_imu_rotation(cam0_rot, _track(rec, imu, np.eye(3)), shift_ns, R_rig)
        R_timing = rotation.R_cam0_imu if rotation.sigma_deg <= TIMING_ROTATION_SIGMA_DEG else R_rig
        timing_R.append(R_timing)
        # the IMU's clock against cam0 once more, with its rotation found
        shift = estimate_timeshift(cam0_rot, _track(rec, imu, R_timing), np.eye(3), prior_ms)
        housing = _housing_lidar(rig, imu, k)
        found_imus.append(ImuRefinement(imu.name, housing.name if housing else None, shift, rotation))
        if rotation.observable:
            imus[k] = replace(imu, T_cam0_imu=_rotated(imu.T_cam0_imu, rotation.R_cam0_imu, R_rig))
            if housing is not None:
                j = lidars.index(housing)
                T = _rotated(housing.T_cam0_lidar, rotation.R_cam0_imu, R_rig)
                lidars[j] = replace(housing, T_cam0_lidar=T)
    cams = []
    for cam, found in zip((rig.upper, rig.lower), rec.pairs, strict=True):
        rig_ms = (cam.timeshift_cam_imu or 0.0) * 1e3
        track = _track(rec, first, timing_R[0])
        est = estimate_timeshift(_rotations(found), track, cam.T_cam_cam0[:3, :3], rig_ms)
        cams.append(CameraRefinement(cam.name, rig_ms, est, est.observable))
    refined = with_timeshifts(rig, {r.camera: r.estimate.timeshift_ms / 1e3 for r in cams if r.applied})
    refined = replace(refined, imus=tuple(imus), lidars=tuple(lidars))
    frames = {c.name: n for c, n in zip((rig.upper, rig.lower), rec.frames, strict=True)}
    readings = {name: len(v[0]) for name, v in rec.gyro.items()}
    stereo = check_stereo_rotation(cam0_rot, _rotations(rec.pairs[1]), rig.lower.T_cam_cam0[:3, :3])
    return Refinement(tuple(cams), tuple(found_imus), refined, frames, readings, stereo)
