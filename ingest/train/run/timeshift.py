"""A camera's clock offset to the LiDAR/IMU clock, from the recording alone: the camera's own rotation
between frames against the gyro's.

The idea is time_autosync's (ethz-asl): the rotation the images show between
two frames must equal the gyro's integral over the same two instants. With the
camera's exposure at stamp + d on the IMU's clock, the gyro's rotation over
[t0 + d, t1 + d] changes with d by (w(t1) - w(t0)) d, so the offset is found
where the two agree best, and it is observable only as far as the angular rate
changes between frames: a rig that stood still (or turned at a constant rate)
cannot reveal it, and `estimate_timeshift` says so instead of guessing.

Rotations come from the images by tracking corners (Lucas-Kanade, checked
forwards and backwards) and a five-point essential matrix on the tracks'
unit rays (RANSAC), so the rig's translation between frames does not leak
into the rotation. A constant gyro bias is estimated with the offset (it adds
bias x frame interval to every pair and would otherwise pull the offset).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from calibration.camera import CameraModel
from calibration.types import F64, I64, U8
from ingest.train.trajectory.clouds import GyroTrack

MAX_CORNERS = 400
MIN_TRACKS = 40
FB_MAX_PX = 0.5
"""A track is kept when tracking it back lands within this of where it started (px)."""
MIN_RAY_Z = 0.2
"""Rays closer than acos(0.2) = 78 deg to the image plane are left out of the essential matrix (their
normalised coordinates blow up)."""
SEARCH_MS = 100.0
"""Offsets searched: +-this around the rig's value (ms)."""
OBSERVABLE_SIGMA_MS = 1.0
"""An offset whose 1-sigma uncertainty exceeds this is reported as unobservable (ms)."""
MIN_EXCITATION_DEG_S = 3.0
"""Nor is an offset observable when the angular rate changed by less than this between paired frames (RMS,
deg/s): a rig that stood still or turned steadily. The Mid-360's gyro noise over `RATE_SPAN_NS` is about
0.03 deg/s; a handheld walk changes its rate by tens of deg/s."""
RATE_SPAN_NS = 20_000_000


@dataclass(frozen=True)
class FrameRotations:
    """Rotations between consecutive frames of one camera, measured from its images."""

    t0_ns: I64  # header stamp of each pair's first frame
    t1_ns: I64  # and of its second
    rotvec: F64  # (N, 3) rotation vector of R_cam(t0)^T R_cam(t1), in the camera frame (rad)
    tracks: I64  # inlier tracks behind each rotation


def _rays(model: CameraModel, px: F64) -> tuple[F64, np.ndarray]:
    rays, ok = model.unproject(px.astype(np.float64))
    return rays, ok & (rays[:, 2] > MIN_RAY_Z)


def corners(model: CameraModel, gray: U8) -> F64 | None:
    """Corners (N, 1, 2, float32 px) to track from a grey image of `model`; None when too few."""
    found = cv2.goodFeaturesToTrack(gray, MAX_CORNERS, 0.01, max(4.0, model.width / 80))
    if found is None or len(found) < MIN_TRACKS:
        return None
    out: F64 = np.asarray(found, np.float32)  # (cv2's trackers take float32 points)
    return out


def pair_rotation(
    model: CameraModel, gray0: U8, gray1: U8, corners0: F64 | None = None
) -> tuple[F64, int] | None:
    """Rotation vector (rad, camera frame) of R_cam0^T R_cam1 between two grey images, and its inlier
    count; None when too few corners track. `corners0`: `corners(model, gray0)`, when known."""
    rad_per_px = np.pi / max(model.width, model.height)
    start = corners(model, gray0) if corners0 is None else corners0
    if start is None:
        return None
    lk: dict[str, Any] = {"winSize": (21, 21), "maxLevel": 3}
    flow: Any = cv2.calcOpticalFlowPyrLK  # (OpenCV's stubs reject a None nextPts, which it takes)
    p1, st1, _ = flow(gray0, gray1, start, None, **lk)
    back, st2, _ = flow(gray1, gray0, p1, None, **lk)
    good = (st1[:, 0] == 1) & (st2[:, 0] == 1) & (np.linalg.norm(back - start, axis=2)[:, 0] < FB_MAX_PX)
    r0, ok0 = _rays(model, start[good, 0])
    r1, ok1 = _rays(model, p1[good, 0])
    ok = ok0 & ok1
    if ok.sum() < MIN_TRACKS:
        return None
    n0 = r0[ok, :2] / r0[ok, 2:]
    n1 = r1[ok, :2] / r1[ok, 2:]
    E, inl = cv2.findEssentialMat(n0, n1, np.eye(3), cv2.RANSAC, 0.999, 0.7 * rad_per_px)
    if E is None or E.shape != (3, 3) or inl is None or inl.sum() < MIN_TRACKS:
        return None
    # E = [t]x R_10 (x1 = R_10 x0 + t) holds two rotations 180 deg apart about t; between frames of a
    # handheld camera the rotation is a few degrees, so the smaller one is it (a cheirality vote, as
    # recoverPose's, fails when the rig barely moved: most points then lie "at infinity")
    Ra, Rb, _ = cv2.decomposeEssentialMat(E)
    vectors = [Rotation.from_matrix(np.asarray(R).T).as_rotvec() for R in (Ra, Rb)]
    rv: F64 = min(vectors, key=lambda v: float(np.linalg.norm(v)))
    return rv, int(inl.sum())


def gyro_rotations(track: GyroTrack, t0_ns: I64, t1_ns: I64, R_cam_cam0: F64) -> F64:
    """Rotation vectors (N, 3, camera frame) of R_cam(t0)^T R_cam(t1) that the gyro track integrates."""
    R0, R1 = track.at(t0_ns), track.at(t1_ns)
    rel = np.einsum("nji,njk->nik", R0, R1)  # R_cam0(t0)^T R_cam0(t1)
    rel = R_cam_cam0 @ rel @ R_cam_cam0.T
    out: F64 = Rotation.from_matrix(rel).as_rotvec()
    return out


@dataclass(frozen=True)
class TimeshiftEstimate:
    """A camera's clock offset found from its images and the gyro, with its evidence."""

    timeshift_ms: float  # exposure = header stamp + this (Kalibr's timeshift_cam_imu, in ms)
    sigma_ms: float  # 1-sigma, from the residuals and the cost's curvature
    observable: bool  # False: the motion did not reveal the offset (sigma above OBSERVABLE_SIGMA_MS)
    pairs: int  # frame pairs used
    residual_before_deg: float  # RMS rotation residual per pair at the rig's offset
    residual_after_deg: float  # and at the estimate
    gyro_bias_rad_s: F64  # constant gyro bias estimated with it (camera frame)
    offsets_ms: F64  # the searched offsets
    cost: F64  # mean squared residual (deg^2) at each
    excitation_deg_s: float = 0.0  # RMS change of the angular rate between paired frames


def _residuals(rot: FrameRotations, track: GyroTrack, R_cam_cam0: F64, shift_ns: int) -> tuple[F64, F64]:
    """Per pair: image minus gyro rotation vector (rad) with the bias that fits best removed; the bias."""
    g = gyro_rotations(track, rot.t0_ns + shift_ns, rot.t1_ns + shift_ns, R_cam_cam0)
    e = rot.rotvec - g
    dt = ((rot.t1_ns - rot.t0_ns) / 1e9)[:, None]
    bias = -(e * dt).sum(0) / (dt**2).sum()  # gyro = truth + bias: the images lag it by bias * dt
    return e + bias * dt, bias


def estimate_timeshift(
    rot: FrameRotations, track: GyroTrack, R_cam_cam0: F64, prior_ms: float = 0.0
) -> TimeshiftEstimate:
    """The offset that best aligns the image rotations with the gyro's, searched over +-`SEARCH_MS` around
    `prior_ms` (1 ms grid, then a parabola through the best three), with a robust (Huber) weight per
    pair; its uncertainty from the Gauss-Newton curvature and the residuals' spread."""
    inside = track.covers(rot.t0_ns - round(SEARCH_MS * 1e6)) & track.covers(
        rot.t1_ns + round(SEARCH_MS * 1e6)
    )
    rot = FrameRotations(rot.t0_ns[inside], rot.t1_ns[inside], rot.rotvec[inside], rot.tracks[inside])
    offsets = prior_ms + np.arange(-SEARCH_MS, SEARCH_MS + 0.5, 1.0)
    if len(rot.t0_ns) < 3:
        nan = float("nan")
        return TimeshiftEstimate(
            prior_ms, nan, False, len(rot.t0_ns), nan, nan, np.zeros(3), offsets, offsets * nan
        )

    def cost(ms: float) -> float:
        e, _ = _residuals(rot, track, R_cam_cam0, round(ms * 1e6))
        r = np.linalg.norm(e, axis=1)
        scale = 1.4826 * np.median(r) + 1e-12
        huber = np.where(r <= 2 * scale, r**2, 2 * 2 * scale * r - (2 * scale) ** 2)
        return float(np.degrees(np.sqrt(huber.mean())) ** 2)

    costs = np.array([cost(float(m)) for m in offsets])
    k = int(np.clip(np.argmin(costs), 1, len(offsets) - 2))
    c0, c1, c2 = costs[k - 1 : k + 2]
    curve = c0 - 2 * c1 + c2
    best = float(offsets[k] + (0.5 * (c0 - c2) / curve if curve > 0 else 0.0))
    e_best, bias = _residuals(rot, track, R_cam_cam0, round(best * 1e6))
    e_prior, _ = _residuals(rot, track, R_cam_cam0, round(prior_ms * 1e6))
    # Gauss-Newton: the residual of a pair moves with the offset by the change of the angular rate
    # between its frames (rad per ms), taken from the gyro averaged over RATE_SPAN_NS so that the
    # readings' noise does not pose as motion
    shift = round(best * 1e6)
    change = _rate(track, rot.t1_ns + shift, R_cam_cam0) - _rate(track, rot.t0_ns + shift, R_cam_cam0)
    jac = (change * 1e-3).ravel()
    sigma_r = 1.4826 * np.median(np.abs(e_best.ravel() - np.median(e_best.ravel())))
    info = float(jac @ jac)
    sigma_ms = float(sigma_r / np.sqrt(info)) * _overlap(rot.t0_ns, rot.t1_ns) if info > 0 else float("inf")
    excitation = float(np.degrees(np.sqrt((change**2).sum(1).mean())))
    observable = sigma_ms <= OBSERVABLE_SIGMA_MS and excitation >= MIN_EXCITATION_DEG_S
    return TimeshiftEstimate(
        best if observable else prior_ms, sigma_ms, observable, len(rot.t0_ns), _rms_deg(e_prior),
        _rms_deg(e_best), bias, offsets, costs, excitation,
    )  # fmt: skip


def _overlap(t0_ns: I64, t1_ns: I64) -> float:
    """How much frame pairs (t0, t1) that share frames inflate a standard error: sqrt(pairs / frames).
    A frame's tracking error enters every pair it is in, so the pairs are not independent samples."""
    frames = len(np.union1d(t0_ns, t1_ns))
    return float(np.sqrt(max(1.0, len(t0_ns) / max(frames, 1))))


def _rotation_sigma_deg(rotated: F64, residuals: F64) -> float:
    """1-sigma (deg, the worst-constrained axis) of a rotation fitted to map vectors onto `rotated` (N, 3)
    with `residuals` (N, 3, rad) left: Gauss-Newton with J = -[v]x per pair, the residuals' robust
    spread; infinite when the vectors leave an axis unconstrained (a rig that did not turn)."""
    info = np.zeros((3, 3))
    for x in rotated:
        K = np.array([[0.0, -x[2], x[1]], [x[2], 0.0, -x[0]], [-x[1], x[0], 0.0]])
        info += K.T @ K
    sigma_r = 1.4826 * float(np.median(np.abs(residuals.ravel())))
    eig = np.linalg.eigvalsh(info)
    return float(np.degrees(sigma_r / np.sqrt(eig[0]))) if eig[0] > 0 else float("inf")


def _rms_deg(e: F64) -> float:
    """RMS length (deg) of rotation vectors (N, 3, rad)."""
    return float(np.degrees(np.sqrt((e**2).sum(1).mean())))


def _rate(track: GyroTrack, t_ns: I64, R_cam_cam0: F64) -> F64:
    """Angular rate (rad/s, camera frame) averaged over +-RATE_SPAN_NS / 2 around each time."""
    half = RATE_SPAN_NS // 2
    out: F64 = gyro_rotations(track, t_ns - half, t_ns + half, R_cam_cam0) / (2 * half / 1e9)
    return out


TIMING_ROTATION_SIGMA_DEG = 1.0
"""An IMU rotation found this well (1-sigma, deg) is used to time the cameras even when it is not written
to the refined rig: a rig rotation off by a degree biases the offset (1.7 ms in a 2.5 s walk at 480x300)."""
MAX_ROTATION_SIGMA_DEG = 0.1
"""A rotation whose 1-sigma uncertainty (largest axis) exceeds this is reported as unobservable (deg):
below it the estimate is better than a target-based LiDAR-camera calibration's 0.1-0.3 deg."""


@dataclass(frozen=True)
class ImuRotation:
    """An IMU's orientation in cam0 found by aligning its gyro's rotations with cam0's image rotations."""

    R_cam0_imu: F64  # (3, 3) the estimate (whether observable or not: see `sigma_deg`)
    correction_deg: float  # angle between the estimate and the rig's
    sigma_deg: float  # 1-sigma, largest axis
    observable: bool
    pairs: int
    residual_before_deg: float  # RMS per pair with the rig's rotation
    residual_after_deg: float


def _kabsch(src: F64, dst: F64, w: F64) -> F64:
    """The rotation R minimising sum w |dst - R src|^2 (rows are vectors)."""
    H = (src * w[:, None]).T @ dst
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(Vt.T @ U.T)))])
    out: F64 = Vt.T @ D @ U.T
    return out


def estimate_imu_rotation(
    rot: FrameRotations, track_imu: GyroTrack, shift_ns: int, R_cam0_imu_rig: F64
) -> ImuRotation:
    """Hand-eye on rotations: the R_cam0_imu that maps the gyro's rotation between two frame times (IMU
    frame, `track_imu` integrated with an identity mounting, exposure = stamp + `shift_ns`) onto cam0's
    own rotation between them (`rot`, from cam0's images), with the gyro's constant bias; pairs whose
    residual exceeds three times the median are left out of the second fit. Its uncertainty comes from
    the residuals and how much, and about which axes, the rig turned: a rig that barely turned cannot
    reveal it, and the rig's value is kept."""
    inside = track_imu.covers(rot.t0_ns + shift_ns) & track_imu.covers(rot.t1_ns + shift_ns)
    phi_cam = rot.rotvec[inside]
    phi_imu = gyro_rotations(track_imu, rot.t0_ns[inside] + shift_ns, rot.t1_ns[inside] + shift_ns, np.eye(3))
    dt = ((rot.t1_ns[inside] - rot.t0_ns[inside]) / 1e9)[:, None]
    n = len(phi_cam)

    def residual(R: F64, bias: F64) -> F64:
        out: F64 = phi_cam - (phi_imu - bias * dt) @ R.T
        return out

    before = residual(R_cam0_imu_rig, np.zeros(3))
    if n < 3:
        nan = float("nan")
        return ImuRotation(R_cam0_imu_rig, 0.0, nan, False, n, nan, nan)
    w = np.ones(n)
    R, bias = R_cam0_imu_rig, np.zeros(3)
    for it in range(6):
        R = _kabsch(phi_imu - bias * dt, phi_cam, w)
        e = phi_cam - phi_imu @ R.T  # = -R bias dt + noise
        bias = -R.T @ ((e * dt * w[:, None]).sum(0) / (w[:, None] * dt**2).sum())
        if it == 2:  # then refit without the outliers
            r = np.linalg.norm(residual(R, bias), axis=1)
            w = (r <= 3 * np.median(r)).astype(np.float64)
    e_after = residual(R, bias)[w > 0]
    v = (phi_imu - bias * dt)[w > 0] @ R.T
    sigma_deg = _rotation_sigma_deg(v, e_after) * _overlap(rot.t0_ns, rot.t1_ns)
    observable = sigma_deg <= MAX_ROTATION_SIGMA_DEG
    correction = float(np.degrees(np.linalg.norm(Rotation.from_matrix(R @ R_cam0_imu_rig.T).as_rotvec())))
    return ImuRotation(
        R, correction, sigma_deg, observable, int((w > 0).sum()),
        _rms_deg(before), _rms_deg(e_after),
    )  # fmt: skip


STEREO_MATCH_NS = 5_000_000
"""A lower-camera frame pair stands beside an upper one when both its frames lie this close (ns) to the
upper pair's: the two cameras expose together, 0.1 ms and their jitter apart."""


@dataclass(frozen=True)
class StereoCheck:
    """The stereo rotation the two cameras' own motion implies, against the rig's R_cam1_cam0."""

    angle_deg: float  # between the rig's R_cam1_cam0 and the one the images imply
    sigma_deg: float  # 1-sigma, largest axis
    observable: bool
    pairs: int
    residual_before_deg: float  # RMS per pair with the rig's stereo rotation
    residual_after_deg: float

    @property
    def disagrees(self) -> bool:
        """The rig's stereo rotation is off by more than 3 sigma and 0.1 deg (a camchain to redo)."""
        return self.observable and self.angle_deg > max(3 * self.sigma_deg, 0.1)


def check_stereo_rotation(upper: FrameRotations, lower: FrameRotations, R_cam1_cam0_rig: F64) -> StereoCheck:
    """Both cameras turn together, so each lower-camera rotation between two frames is the upper one's
    seen from cam1: phi_cam1 = R_cam1_cam0 phi_cam0. The best R_cam1_cam0 over the frame pairs of both
    cameras taken at the same times (`STEREO_MATCH_NS`) checks the camchain's stereo rotation; the
    baseline is not observable this way (rotations carry no translation)."""
    key = {(int(a) // STEREO_MATCH_NS, int(b) // STEREO_MATCH_NS): k for k, (a, b) in
           enumerate(zip(upper.t0_ns, upper.t1_ns, strict=True))}  # fmt: skip
    iu, il = [], []
    for j, (a, b) in enumerate(zip(lower.t0_ns, lower.t1_ns, strict=True)):
        for da in (-1, 0, 1):
            k = key.get((int(a) // STEREO_MATCH_NS + da, int(b) // STEREO_MATCH_NS + da))
            if k is not None and abs(int(upper.t0_ns[k]) - int(a)) <= STEREO_MATCH_NS:
                iu.append(k)
                il.append(j)
                break
    src, dst = upper.rotvec[iu].reshape(-1, 3), lower.rotvec[il].reshape(-1, 3)
    n = len(src)
    nan = float("nan")
    if n < 3:
        return StereoCheck(nan, nan, False, n, nan, nan)
    R = _kabsch(src, dst, np.ones(n))
    r = np.linalg.norm(dst - src @ R.T, axis=1)
    w = (r <= 3 * np.median(r)).astype(np.float64)
    R = _kabsch(src, dst, w)
    e_after = (dst - src @ R.T)[w > 0]
    sigma_deg = _rotation_sigma_deg((src @ R.T)[w > 0], e_after) * _overlap(upper.t0_ns[iu], upper.t1_ns[iu])
    angle = float(np.degrees(np.linalg.norm(Rotation.from_matrix(R @ R_cam1_cam0_rig.T).as_rotvec())))
    return StereoCheck(
        angle, sigma_deg, sigma_deg <= MAX_ROTATION_SIGMA_DEG, int((w > 0).sum()),
        _rms_deg(dst - src @ R_cam1_cam0_rig.T), _rms_deg(e_after),
    )  # fmt: skip
