"""Kalibr camchain YAML: read and write every model/distortion pair Kalibr accepts.

Kalibr's intrinsics order per ``camera_model``:

=========  ==========================  ==================================
model      intrinsics                  distortion_model
=========  ==========================  ==================================
pinhole    [fu, fv, pu, pv]            radtan, equidistant, fov, none
omni       [xi, fu, fv, pu, pv]        radtan, none
eucm       [alpha, beta, fu, fv, pu, pv]  none
ds         [xi, alpha, fu, fv, pu, pv]    none
=========  ==========================  ==================================

``pinhole`` + ``equidistant`` is read as `KannalaBrandt`. ``T_cn_cnm1`` of cam n
maps cam n-1 into cam n; it is chained into ``T_cam_cam0``. Focal lengths and
principal points must be floats (Kalibr rejects ints), resolutions ints.

What real files need beyond Kalibr's own reader:

- OpenCV's dialect (``%YAML:1.0`` header, ``!!opencv-matrix`` nodes), as written
  by OpenVINS and others (`calibration.opencv_yaml`).
- camchain-imucam files whose cam n has ``T_cam_imu`` but no ``T_cn_cnm1``:
  ``T_cn_cnm1 = T_cn_imu @ inv(T_cnm1_imu)``. When a camera has both, they must
  agree within `EXTRINSIC_TOL_DEG` and `EXTRINSIC_TOL_M`. OpenVINS's
  ``T_imu_cam`` (the inverse) is read as well.
- 4x4 matrices written as 16 numbers, row-major.
- Top-level keys other than cam0, cam1, ... are ignored with a logged warning
  that names them.
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from calibration.camera import CameraModel
from calibration.distortion import Fov, RadTan
from calibration.errors import CalibrationError, SensorboxError, WriteError
from calibration.files import read_text, write_atomic
from calibration.fisheye import DoubleSphere, ExtendedUnified, KannalaBrandt, Unified
from calibration.opencv_yaml import load_opencv_yaml, yaml_error_line
from calibration.pinhole import Omni, Pinhole
from calibration.transforms import as_transform, invert
from calibration.types import F64

_INTRINSIC_NAMES: dict[str, list[str]] = {
    "pinhole": ["fu", "fv", "pu", "pv"],
    "omni": ["xi", "fu", "fv", "pu", "pv"],
    "eucm": ["alpha", "beta", "fu", "fv", "pu", "pv"],
    "ds": ["xi", "alpha", "fu", "fv", "pu", "pv"],
}
_DISTORTIONS: dict[str, dict[str, int]] = {
    "pinhole": {"radtan": 4, "equidistant": 4, "fov": 1, "none": 0},
    "omni": {"radtan": 4, "none": 0},
    "eucm": {"none": 0},
    "ds": {"none": 0},
}
_FLOAT_ONLY = {"fu", "fv", "pu", "pv"}
_CAMERA_KEY = re.compile(r"cam(?:0|[1-9][0-9]*)")

MAX_TIMESHIFT_S = 1.0
"""Largest ``timeshift_cam_imu`` (s) taken as a camera's clock offset. Kalibr's estimates are
milliseconds (the reference rig's: a few ms); the simulator's camera offsets are held to the same
+-1 s (`sensorbox.sim.config.MAX_CAMERA_OFFSET_NS`). A shift beyond it is a value in the wrong unit (ms
or ns written as seconds) or a clock that was never synchronised: every stamp moved by it puts the
frames outside the LiDAR data, and ingest planned no sample without saying why."""

MAX_CAMERA_SEPARATION_M = 10.0
"""Farthest two consecutive cameras of a camchain may be apart (m, ``T_cn_cnm1``'s translation). The
rig is handheld: its baseline is 0.12 m, and over 2 m is warned about
(`calibration.rectify.MAX_PLAUSIBLE_BASELINE_M`) as most likely millimetres. 10 m is past any stereo
pair on a person or a vehicle (a car roof is 1.5 m wide) and a baseline of 10 mm or more written in
millimetres lands beyond it: such a pose, refused, would otherwise scale every disparity of the GT."""

EXTRINSIC_TOL_DEG = 0.05
"""Largest rotation (degrees) between a given ``T_cn_cnm1`` and the one ``T_cam_imu`` implies."""
EXTRINSIC_TOL_M = 0.001
"""Largest translation difference (metres) between a given ``T_cn_cnm1`` and the one ``T_cam_imu`` implies."""

MAX_IMAGE_SIDE_PX = 16384
"""Widest or tallest camera image read (pixels): 4 times a 4K camera's width. The warp maps and
rectified images of a camera are sized from its resolution, so 1e9 pixels would ask for exabytes."""

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class KalibrCamera:
    """One ``camN`` block of a camchain.

    ``T_cn_cnm1`` is kept exactly as read, or derived from ``T_cam_imu`` when the
    file has none (None for cam0), so a write-read round trip is exact;
    ``T_cam_cam0`` is the chained transform p_camN = T p_cam0.
    """

    name: str
    model: CameraModel
    T_cam_cam0: F64
    T_cn_cnm1: F64 | None = None
    T_cam_imu: F64 | None = None
    timeshift_cam_imu: float | None = None
    rostopic: str | None = None
    cam_overlaps: tuple[int, ...] | None = None


@dataclass(frozen=True, eq=False)
class CameraChain:
    """A Kalibr camchain: cameras in order cam0, cam1, ..."""

    cameras: tuple[KalibrCamera, ...]
    source: Path | None = field(default=None)

    def __getitem__(self, name: str) -> KalibrCamera:
        for cam in self.cameras:
            if cam.name == name:
                return cam
        known = ", ".join(c.name for c in self.cameras)
        raise CalibrationError(f"camchain has no camera {name!r} (has: {known})")


def model_to_kalibr(model: CameraModel) -> tuple[str, list[float], str, list[float]]:
    """Kalibr (camera_model, intrinsics, distortion_model, distortion_coeffs) of a model."""
    if isinstance(model, DoubleSphere):
        return "ds", [model.xi, model.alpha, model.fx, model.fy, model.cx, model.cy], "none", []
    if isinstance(model, ExtendedUnified):
        intr = [model.alpha, model.beta, model.fx, model.fy, model.cx, model.cy]
        return "eucm", intr, "none", []
    if isinstance(model, Unified):
        # UCM is EUCM with beta = 1; Kalibr has no separate ``ucm`` model.
        return "eucm", [model.alpha, 1.0, model.fx, model.fy, model.cx, model.cy], "none", []
    if isinstance(model, KannalaBrandt):
        coeffs = [model.k1, model.k2, model.k3, model.k4]
        return "pinhole", [model.fx, model.fy, model.cx, model.cy], "equidistant", coeffs
    if isinstance(model, Omni):
        odist = model.distortion
        return (
            "omni",
            [model.xi, model.fx, model.fy, model.cx, model.cy],
            "none" if odist is None else odist.kalibr_name,
            [] if odist is None else odist.coeffs(),
        )
    if isinstance(model, Pinhole):
        dist = model.distortion
        return (
            "pinhole",
            [model.fx, model.fy, model.cx, model.cy],
            "none" if dist is None else dist.kalibr_name,
            [] if dist is None else dist.coeffs(),
        )
    raise CalibrationError(f"{type(model).__name__} has no Kalibr representation")


def model_from_kalibr(
    camera_model: str,
    intrinsics: Sequence[float],
    distortion_model: str,
    coeffs: Sequence[float],
    resolution: Sequence[int],
) -> CameraModel:
    """Build a camera model from already type-checked Kalibr fields."""
    w, h = int(resolution[0]), int(resolution[1])
    if camera_model == "ds":
        xi, alpha, fu, fv, pu, pv = intrinsics
        return DoubleSphere(fu, fv, pu, pv, xi, alpha, w, h)
    if camera_model == "eucm":
        alpha, beta, fu, fv, pu, pv = intrinsics
        return ExtendedUnified(fu, fv, pu, pv, alpha, beta, w, h)
    radtan = RadTan(*coeffs) if distortion_model == "radtan" else None
    if camera_model == "omni":
        xi, fu, fv, pu, pv = intrinsics
        return Omni(xi, fu, fv, pu, pv, w, h, radtan)
    fu, fv, pu, pv = intrinsics
    if distortion_model == "equidistant":
        k1, k2, k3, k4 = coeffs
        return KannalaBrandt(fu, fv, pu, pv, k1, k2, k3, k4, w, h)
    if distortion_model == "fov":
        return Pinhole(fu, fv, pu, pv, w, h, Fov(coeffs[0]))
    return Pinhole(fu, fv, pu, pv, w, h, radtan)


def _number_list(value: object, where: str, count: int | None) -> list[float]:
    if not isinstance(value, list) or not all(
        isinstance(v, int | float) and not isinstance(v, bool) for v in value
    ):
        raise CalibrationError(f"{where}: expected a list of numbers, got {value!r}")
    if count is not None and len(value) != count:
        raise CalibrationError(f"{where}: expected {count} values, got {len(value)}")
    if not all(math.isfinite(v) for v in value):
        raise CalibrationError(f"{where}: values must be finite, got {value!r}")
    return list(value)


def load_yaml(path: Path, what: str) -> Any:
    """Read a YAML file (`calibration.files.read_text`: a regular file of at most 4 MiB), turning
    I/O and syntax errors into `CalibrationError`."""
    text = read_text(path, what)
    try:
        return load_opencv_yaml(text)
    except yaml.YAMLError as err:
        raise CalibrationError(yaml_error_line(path, err)) from err


def _parse_camera(name: str, block: object, where: str) -> dict[str, Any]:
    if not isinstance(block, Mapping):
        raise CalibrationError(f"{where}: expected a mapping of camera keys, got {block!r}")
    for key in (
        "camera_model",
        "intrinsics",
        "distortion_model",
        "distortion_coeffs",
        "resolution",
    ):
        if key not in block:
            raise CalibrationError(f"{where}: missing key '{key}'")
    return {"model": _camera_model(block, where), **_camera_extras(block, where)}


def _camera_model(block: Mapping[str, Any], where: str) -> CameraModel:
    """The camera model a camchain block states (model, intrinsics, distortion, resolution), checked as
    Kalibr checks it and so that it maps pixels to rays."""
    model = block["camera_model"]
    if model not in _INTRINSIC_NAMES:
        raise CalibrationError(
            f"{where}.camera_model: unknown model {model!r} (expected one of {', '.join(_INTRINSIC_NAMES)})"
        )
    names = _INTRINSIC_NAMES[model]
    intr = _number_list(
        block["intrinsics"], f"{where}.intrinsics ({model}: [{', '.join(names)}])", len(names)
    )
    for key, value in zip(names, intr, strict=True):
        if key in _FLOAT_ONLY and not isinstance(value, float):
            raise CalibrationError(
                f"{where}.intrinsics: {key} must be a float (Kalibr rejects integers), got {value!r}"
            )
        if key in ("fu", "fv") and value <= 0.0:
            raise CalibrationError(f"{where}.intrinsics: {key} must be > 0, got {value!r}")
    dist = block["distortion_model"]
    if dist not in _DISTORTIONS[model]:
        raise CalibrationError(
            f"{where}.distortion_model: {dist!r} is not valid with camera_model {model!r} "
            f"(expected one of {', '.join(_DISTORTIONS[model])})"
        )
    coeffs = _number_list(
        block["distortion_coeffs"], f"{where}.distortion_coeffs ({dist})", _DISTORTIONS[model][dist]
    )
    res = block["resolution"]
    if (
        not isinstance(res, list)
        or len(res) != 2
        or not all(isinstance(v, int) and not isinstance(v, bool) and 0 < v <= MAX_IMAGE_SIDE_PX for v in res)
    ):
        raise CalibrationError(
            f"{where}.resolution: expected [width, height] positive ints of at most {MAX_IMAGE_SIDE_PX}, "
            f"got {res!r}"
        )
    given = dict(zip(names, intr, strict=True))
    pu, pv = given["pu"], given["pv"]
    if not (0.0 <= pu <= res[0] and 0.0 <= pv <= res[1]):
        raise CalibrationError(
            f"{where}.intrinsics: the principal point (pu, pv) = ({pu:g}, {pv:g}) lies outside the "
            f"{res[0]}x{res[1]} image"
        )
    try:
        camera = model_from_kalibr(model, intr, dist, coeffs, res)
    except CalibrationError as err:
        raise CalibrationError(f"{where}: {err}") from err
    _require_rays(camera, where)
    return camera


def _camera_extras(block: Mapping[str, Any], where: str) -> dict[str, Any]:
    """A camchain block's optional keys, checked: its poses (T_cn_cnm1, T_cam_imu or T_imu_cam), clock
    offset (timeshift_cam_imu, s), rostopic and cam_overlaps."""
    out: dict[str, Any] = {}
    if "T_cn_cnm1" in block:
        out["T_cn_cnm1"] = as_transform(block["T_cn_cnm1"], f"{where}.T_cn_cnm1")
    elif OLD_T_CN_CNM1 in block:  # early Kalibr camchains (EuRoC's era) name the same pose so
        out["T_cn_cnm1"] = as_transform(block[OLD_T_CN_CNM1], f"{where}.{OLD_T_CN_CNM1}")
        log.warning("%s: %s read as T_cn_cnm1 (its name in early Kalibr camchains)", where, OLD_T_CN_CNM1)
    if "T_cam_imu" in block:
        out["T_cam_imu"] = as_transform(block["T_cam_imu"], f"{where}.T_cam_imu")
    if "T_imu_cam" in block:  # OpenVINS writes the inverse
        T_cam_imu = invert(as_transform(block["T_imu_cam"], f"{where}.T_imu_cam"))
        if "T_cam_imu" in out:
            _require_agreement(out["T_cam_imu"], T_cam_imu, f"{where}: T_cam_imu and inv(T_imu_cam)")
        out["T_cam_imu"] = T_cam_imu
    if "timeshift_cam_imu" in block:
        ts = block["timeshift_cam_imu"]
        if not isinstance(ts, int | float) or isinstance(ts, bool) or not math.isfinite(ts):
            raise CalibrationError(f"{where}.timeshift_cam_imu: expected seconds as a number, got {ts!r}")
        if abs(ts) > MAX_TIMESHIFT_S:
            raise CalibrationError(
                f"{where}.timeshift_cam_imu: {ts:g} s; expected within +-{MAX_TIMESHIFT_S:g} s (Kalibr's are "
                "milliseconds, 0.0042 for 4.2 ms: a value in ms or ns, or an unsynchronised clock?)"
            )
        out["timeshift_cam_imu"] = float(ts)
    if "rostopic" in block:
        if not isinstance(block["rostopic"], str):
            raise CalibrationError(f"{where}.rostopic: expected a string, got {block['rostopic']!r}")
        out["rostopic"] = block["rostopic"]
    if "cam_overlaps" in block:
        ov = block["cam_overlaps"]
        if not isinstance(ov, list) or not all(isinstance(i, int) for i in ov):
            raise CalibrationError(f"{where}.cam_overlaps: expected a list of camera indices, got {ov!r}")
        out["cam_overlaps"] = tuple(ov)
    return out


MIN_RAY_FRACTION = 0.05
"""Least share of a camera's image (sampled on a 32 x 20 grid of pixels) that must unproject to rays."""


def _require_rays(camera: CameraModel, where: str) -> None:
    """Refuse a model that maps (almost) no pixel to a ray: it would see nothing.

    Such parameters are valid numbers but not a lens: an omni xi of 1e3, an
    eucm beta of 1e3 shrink the valid image circle to a few pixels, and
    ingest divided by its zero valid pixels. A real fisheye's circle covers
    most of its image.
    """
    cols = (np.arange(32) + 0.5) * camera.width / 32 - 0.5
    rows = (np.arange(20) + 0.5) * camera.height / 20 - 0.5
    grid = np.stack(np.meshgrid(cols, rows), axis=-1).reshape(-1, 2)
    _, valid = camera.unproject(grid)
    if valid.mean() < MIN_RAY_FRACTION:
        raise CalibrationError(
            f"{where}: the {type(camera).__name__} model maps only {int(valid.sum())} of {len(grid)} sampled "
            f"pixels (a 32 x 20 grid) to rays; a lens sees through most of its image: check the intrinsics"
        )


def _require_agreement(given: F64, implied: F64, what: str) -> None:
    """Raise unless two transforms agree within `EXTRINSIC_TOL_DEG` and `EXTRINSIC_TOL_M`."""
    R_diff = given[:3, :3] @ implied[:3, :3].T
    angle_deg = math.degrees(math.acos(float(np.clip((np.trace(R_diff) - 1.0) / 2.0, -1.0, 1.0))))
    shift_m = float(np.linalg.norm(given[:3, 3] - implied[:3, 3]))
    if angle_deg > EXTRINSIC_TOL_DEG or shift_m > EXTRINSIC_TOL_M:
        raise CalibrationError(
            f"{what} disagree: rotation differs by {angle_deg:.4f} deg, translation by "
            f"{shift_m * 1000:.3f} mm (tolerance {EXTRINSIC_TOL_DEG} deg, {EXTRINSIC_TOL_M * 1000:g} mm)"
        )


def _camera_names(data: Mapping[Any, Any], source: str) -> list[str]:
    """cam0, cam1, ... in order; other top-level keys are logged and ignored."""
    cams = [k for k in data if isinstance(k, str) and _CAMERA_KEY.fullmatch(k)]
    others = [str(k) for k in data if k not in cams]
    if not cams:
        raise CalibrationError(
            f"{source}: expected a Kalibr camchain (keys cam0, cam1, ...), got keys {', '.join(others)}"
        )
    names = [f"cam{i}" for i in range(len(cams))]
    if sorted(cams) != sorted(names):
        raise CalibrationError(f"{source}: expected camera keys {', '.join(names)}, got {', '.join(cams)}")
    if others:
        log.warning("%s: ignoring top-level keys %s (not cameras cam0, cam1, ...)", source, ", ".join(others))
    return names


OLD_T_CN_CNM1 = "baseline_last_to_this_cam"
"""What early Kalibr camchains (those shipped with EuRoC-era datasets) call T_cn_cnm1: cam n-1 -> cam n."""


def _T_cn_cnm1(parsed: dict[str, Any], prev: dict[str, Any], name: str, prev_name: str, where: str) -> F64:
    """cam n's ``T_cn_cnm1`` as given, or from both cameras' ``T_cam_imu``; checked when both exist."""
    given: F64 | None = parsed.get("T_cn_cnm1")
    if "T_cam_imu" not in parsed or "T_cam_imu" not in prev:
        if given is None:
            raise CalibrationError(
                f"{where}: missing key 'T_cn_cnm1' (or T_cam_imu in both {prev_name} and {name} to derive it)"
            )
        return _require_near(given, f"{where}.T_cn_cnm1", prev_name)
    implied: F64 = parsed["T_cam_imu"] @ invert(prev["T_cam_imu"])
    if given is None:
        return _require_near(implied, f"{where}.T_cn_cnm1 (from T_cam_imu)", prev_name)
    _require_agreement(
        given, implied, f"{where}: T_cn_cnm1 and T_{name}_imu @ inv(T_{prev_name}_imu) (from T_cam_imu)"
    )
    return _require_near(given, f"{where}.T_cn_cnm1", prev_name)


def _require_near(T_cn_cnm1: F64, where: str, prev_name: str) -> F64:
    """`T_cn_cnm1`, or CalibrationError when its translation exceeds `MAX_CAMERA_SEPARATION_M`."""
    apart_m = float(np.linalg.norm(T_cn_cnm1[:3, 3]))
    if apart_m > MAX_CAMERA_SEPARATION_M:
        raise CalibrationError(
            f"{where}: translation {apart_m:.4g} m from {prev_name}: expected <= "
            f"{MAX_CAMERA_SEPARATION_M:g} m between two cameras of a rig (millimetres written as metres?)"
        )
    return T_cn_cnm1


def parse_kalibr_camchain(data: object, source: str) -> CameraChain:
    """Build a `CameraChain` from an already loaded YAML document."""
    if not isinstance(data, Mapping) or not data:
        raise CalibrationError(f"{source}: expected a Kalibr camchain (keys cam0, cam1, ...)")
    names = _camera_names(data, source)
    cameras: list[KalibrCamera] = []
    prev: dict[str, Any] = {}
    T_prev_cam0 = np.eye(4)
    for i, name in enumerate(names):
        parsed = _parse_camera(name, data[name], f"{source}: {name}")
        if i == 0:  # the chain's origin: a pose relative to a camera before it means nothing
            T_first = parsed.pop("T_cn_cnm1", None)
            if T_first is not None and not np.allclose(T_first, np.eye(4)):
                log.warning(
                    "%s: %s.T_cn_cnm1 ignored: the first camera of a chain is its origin, with no camera "
                    "before it (Kalibr writes none for it; cameras in another order?)", source, name,
                )  # fmt: skip
            T_cam_cam0 = np.eye(4)
        else:
            parsed["T_cn_cnm1"] = _T_cn_cnm1(parsed, prev, name, names[i - 1], f"{source}: {name}")
            T_cam_cam0 = parsed["T_cn_cnm1"] @ T_prev_cam0
        cameras.append(KalibrCamera(name=name, T_cam_cam0=T_cam_cam0, **parsed))
        T_prev_cam0, prev = T_cam_cam0, parsed
    return CameraChain(tuple(cameras))


def read_kalibr_camchain(path: str | Path) -> CameraChain:
    """Read a Kalibr camchain (or camchain-imucam) YAML file.

    Raises `CalibrationError` naming the file, camera and key at fault.
    """
    p = Path(path)
    chain = parse_kalibr_camchain(load_yaml(p, "Kalibr camchain"), str(p))
    return CameraChain(chain.cameras, source=p)


def matrix_to_list(T: F64) -> list[list[float]]:
    """A 4x4 matrix as nested lists of Python floats (exact in YAML via repr)."""
    return [[float(v) for v in row] for row in T]


def camchain_to_dict(chain: CameraChain) -> dict[str, Any]:
    """The camchain as the plain dict Kalibr writes."""
    out: dict[str, Any] = {}
    for i, cam in enumerate(chain.cameras):
        model, intr, dist, coeffs = model_to_kalibr(cam.model)
        block: dict[str, Any] = {}
        if cam.cam_overlaps is not None:
            block["cam_overlaps"] = list(cam.cam_overlaps)
        block["camera_model"] = model
        block["distortion_coeffs"] = [float(c) for c in coeffs]
        block["distortion_model"] = dist
        block["intrinsics"] = [float(v) for v in intr]
        block["resolution"] = [int(cam.model.width), int(cam.model.height)]
        if cam.rostopic is not None:
            block["rostopic"] = cam.rostopic
        if i > 0:
            T = cam.T_cn_cnm1
            if T is None:
                T = cam.T_cam_cam0 @ np.linalg.inv(chain.cameras[i - 1].T_cam_cam0)
            block["T_cn_cnm1"] = matrix_to_list(T)
        if cam.T_cam_imu is not None:
            block["T_cam_imu"] = matrix_to_list(cam.T_cam_imu)
        if cam.timeshift_cam_imu is not None:
            block["timeshift_cam_imu"] = float(cam.timeshift_cam_imu)
        out[f"cam{i}"] = block
    return out


def camchain_text(chain: CameraChain) -> str:
    """A camchain in Kalibr's YAML layout (floats written exactly, via repr)."""
    return yaml.safe_dump(camchain_to_dict(chain), default_flow_style=None, sort_keys=False)


def write_kalibr_camchain(
    chain: CameraChain, path: str | Path, error: type[SensorboxError] = WriteError
) -> None:
    """Write a camchain in Kalibr's YAML layout, whole or not at all (`calibration.files.write_atomic`: a
    refused write, or a path that is a device or FIFO, is `error` naming it)."""
    write_atomic(Path(path), camchain_text(chain).encode(), error)
