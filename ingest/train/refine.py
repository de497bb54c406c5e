"""`sensorbox calib refine`: what a recording says about its rig's clocks, and the rig it implies.

One pass over the bags reads both cameras and the rig's first IMU: each camera's
rotation between consecutive frames (`timeshift.frame_rotations`, streamed: two
frames in memory per camera) and the gyro. Each camera's offset to the IMU's
(= LiDAR's) clock is then estimated (`timeshift.estimate_timeshift`) and, where
the motion made it observable, written to the refined rig as Kalibr's
`timeshift_cam_imu`; where it did not, the rig's value is kept and the report
says why.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from calibration.rig import Camera, Rig, with_timeshifts
from calibration.types import F64, U8
from ingest.bags.decode import Frame, ImuSample, decode
from ingest.bags.reader import open_bags
from ingest.errors import BagError
from ingest.train.clouds import integrate_gyro
from ingest.train.timeshift import (
    FrameRotations,
    TimeshiftEstimate,
    corners,
    estimate_timeshift,
    pair_rotation,
)

PAIR_GAPS = (1, 3, 6)
"""Frames are paired with the ones this many frames before: the offset's signal, the change of the angular
rate between the two, grows with the gap while the rotation's error does not."""
TRACK_WIDTH_PX = 1000
"""Images wider than this are halved (repeatedly) before tracking: corners track as well, 4x faster."""


@dataclass(frozen=True)
class CameraRefinement:
    """One camera's clock offset: the rig's value, the estimate and whether the refined rig takes it."""

    camera: str
    rig_timeshift_ms: float
    estimate: TimeshiftEstimate
    applied: bool


@dataclass(frozen=True)
class Refinement:
    """What `refine` found; `rig` is the refined rig (the input's where nothing was observable)."""

    cameras: tuple[CameraRefinement, ...]
    rig: Rig
    frames: dict[str, int]  # per camera: frames read
    imu_readings: int


def _topic(topics: Sequence[str], wanted: str | None, what: str, where: str) -> str:
    """The bag's topic for a rig sensor: its own, or `<topic>/compressed` for a camera."""
    for cand in (wanted, f"{wanted}/compressed"):
        if cand is not None and cand in topics:
            return cand
    listing = ", ".join(sorted(topics))
    raise BagError(f"{where}: no topic {wanted!r} for {what} (from the rig); the bag has: {listing}")


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


def refine(bags: Sequence[Path], rig: Rig, progress: Callable[[int, int], None] | None = None) -> Refinement:
    """Each camera's clock offset to the rig's first IMU, from the recording in `bags`."""
    if not rig.imus:
        raise BagError(
            f"{rig.source or rig.name}: the rig names no IMU; refine needs a gyro to time the cameras"
        )
    imu = rig.imus[0]
    cams: tuple[Camera, Camera] = (rig.upper, rig.lower)
    with open_bags(list(bags)) as bagset:
        names = list(bagset.topics())
        topics = [_topic(names, c.topic, f"camera {c.name}", bagset.label) for c in cams]
        imu_topic = _topic(names, imu.topic, f"imu {imu.name}", bagset.label)
        halvings = [_halvings(c.model.width) for c in cams]
        models = [c.model.scaled(0.5**h) if h else c.model for c, h in zip(cams, halvings, strict=True)]
        recent: list[list[tuple[int, U8, F64 | None]]] = [[], []]  # per camera: its last frames, corners
        pairs: list[list[tuple[int, int, F64, int]]] = [[], []]
        frames = [0, 0]
        imu_t: list[int] = []
        imu_w: list[F64] = []
        for msg in bagset.messages(topics=[*topics, imu_topic], progress=progress):
            decoded = decode(msg.msgtype, msg.data(), bagset.ros_version)
            if isinstance(decoded, ImuSample):
                imu_t.append(decoded.stamp_ns)
                imu_w.append(decoded.gyro_rad_s)
                continue
            assert isinstance(decoded, Frame)
            c = topics.index(msg.topic)
            h, w = decoded.image.shape[:2]
            if (w, h) != (cams[c].model.width, cams[c].model.height):
                raise BagError(
                    f"{bagset.label}: topic {msg.topic!r} at stamp {decoded.stamp_ns}: a {w}x{h} image; camera "
                    f"{cams[c].name} of the rig is {cams[c].model.width}x{cams[c].model.height} (a rig of "
                    "another resolution?)"
                )
            gray = _gray(decoded, halvings[c])
            frames[c] += 1
            for gap in PAIR_GAPS:
                if len(recent[c]) >= gap and decoded.stamp_ns > recent[c][-gap][0]:
                    t0, gray0, corners0 = recent[c][-gap]
                    got = None if corners0 is None else pair_rotation(models[c], gray0, gray, corners0)
                    if got is not None:
                        pairs[c].append((t0, decoded.stamp_ns, got[0], got[1]))
            recent[c] = [
                *recent[c][-max(PAIR_GAPS) + 1 :],
                (decoded.stamp_ns, gray, corners(models[c], gray)),
            ]
    if len(imu_t) < 2:
        raise BagError(
            f"{', '.join(map(str, bags))}: topic {imu_topic!r} has {len(imu_t)} readings; need a gyro"
        )
    track = integrate_gyro(np.array(imu_t, np.int64), np.array(imu_w), imu.T_cam0_imu[:3, :3])
    results = []
    for cam, found in zip(cams, pairs, strict=True):
        rot = FrameRotations(
            np.array([p[0] for p in found], np.int64), np.array([p[1] for p in found], np.int64),
            np.array([p[2] for p in found]).reshape(-1, 3), np.array([p[3] for p in found], np.int64),
        )  # fmt: skip
        prior_ms = (cam.timeshift_cam_imu or 0.0) * 1e3
        est = estimate_timeshift(rot, track, cam.T_cam_cam0[:3, :3], prior_ms)
        results.append(CameraRefinement(cam.name, prior_ms, est, est.observable))
    refined = with_timeshifts(rig, {r.camera: r.estimate.timeshift_ms / 1e3 for r in results if r.applied})
    return Refinement(
        tuple(results), refined, {c.name: n for c, n in zip(cams, frames, strict=True)}, len(imu_t)
    )
