"""The live monitor's coverage state: recent sweeps, the gyro and the latest upper frame, drawn on demand.

`CoverageView.feed` keeps what the preview needs (the worker thread calls it
with each decoded message); `render` places the last `window_s` of both
LiDARs' sweeps (those whose mid time is within `window_s` of the newest's) into
the latest upper frame with `sensorbox.live.coverage`.
Sweeps and gyro samples are kept by their header stamps (the LiDAR clock); the
frame's stamp is moved onto that clock by the camera's `timeshift_cam_imu`.
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from calibration.camera import CameraModel
from calibration.rig import Rig
from sensorbox.live.coverage import Coverage, coverage, draw_coverage, place_sweeps
from sensorbox.live.monitor_channels import CloudCam0, Gyro, Preview, Stream

log = logging.getLogger(__name__)

U8 = np.ndarray[Any, np.dtype[np.uint8]]
GYRO_KEEP_S = 3.0  # gyro samples older than this before the newest are let go
GYRO_MARGIN_NS = 100_000_000  # gyro samples kept before the oldest sweep: the one whose rate it starts in
CLOCKS_APART_NS = 500_000_000
"""A frame stamped this far from the newest sweep is on another clock (a camera without its
timeshift, a simulator's camera started late): the points are placed at the newest sweep's time, and
the caption says so, instead of turning them by a gyro integrated over the gap."""


@dataclass(frozen=True)
class Rendered:
    """A coverage preview: the drawn image, the frame's stamp (ns, LiDAR clock), the coverage."""

    image: U8
    stamp_ns: int
    coverage: Coverage


class CoverageView:
    """Recent sweeps (cam0), gyro samples (cam0) and the latest upper frame; see the module docstring."""

    def __init__(self, rig: Rig, window_s: float) -> None:
        self.upper = rig.upper
        self.window_ns = round(window_s * 1e9)
        self.window_s = window_s
        self._sweeps: deque[tuple[int, np.ndarray[Any, Any]]] = deque()
        self._gyro: deque[tuple[int, np.ndarray[Any, Any]]] = deque()
        self._frame: Preview | None = None
        self._models: dict[tuple[int, int], CameraModel | None] = {}
        self.last: Rendered | None = None
        self._warned = False

    def feed(self, stream: Stream, item: Preview | CloudCam0 | Gyro) -> None:
        """Keep what the preview needs of one decoded message of a stream that feeds it."""
        if not stream.feeds_coverage:
            return
        if isinstance(item, Preview):
            self._frame = item
        elif isinstance(item, CloudCam0):
            self._sweeps.append((item.mid_ns, item.xyz_m))
            newest = max(t for t, _ in self._sweeps)
            while self._sweeps and self._sweeps[0][0] < newest - 2 * self.window_ns:
                self._sweeps.popleft()
        else:
            self._gyro.append((item.stamp_ns, item.gyro_cam0_rad_s))
            while self._gyro and self._gyro[0][0] < item.stamp_ns - GYRO_KEEP_S * 1e9:
                self._gyro.popleft()

    def _model(self, height: int, width: int) -> CameraModel | None:
        """The upper camera's model at the preview's size, or None (warned once) when the frame's
        aspect does not match the rig's camera."""
        key = (height, width)
        if key not in self._models:
            model = self.upper.model
            factor = width / model.width
            if abs(model.height * factor - height) > 1.0:
                log.warning(
                    "monitor: upper camera frames are %dx%d, the rig's model %dx%d: no coverage preview",
                    width, height, model.width, model.height,
                )  # fmt: skip
                self._models[key] = None
            else:
                self._models[key] = model.scaled(factor)
        return self._models[key]

    def render(self) -> Rendered | None:
        """The coverage preview of the latest upper frame, or None before a frame (or without a model)."""
        frame = self._frame
        if frame is None:
            return None
        model = self._model(*frame.image.shape[:2])
        if model is None:
            return None
        image_ns = frame.stamp_ns + self.upper.timeshift_ns
        newest = max((t for t, _ in self._sweeps), default=image_ns)
        sweeps = [(t, p) for t, p in self._sweeps if t > newest - self.window_ns]
        gyro = sorted(self._gyro, key=lambda s: s[0])
        stamps = np.array([t for t, _ in gyro], np.int64)
        rates = np.array([w for _, w in gyro], np.float64).reshape(-1, 3)
        at_ns, note = image_ns, ""
        if abs(image_ns - newest) > CLOCKS_APART_NS:  # no gyro between the frame and the sweeps
            at_ns, note = newest, f"frame {(image_ns - newest) / 1e9:+.1f} s off the LiDAR clock"
            if not self._warned:
                self._warned = True
                log.warning(
                    "monitor: upper frames are stamped %+.1f s off the LiDARs' clock%s",
                    (image_ns - newest) / 1e9,
                    ": the coverage preview places the points at the newest sweep's time",
                )
        first = min((t for t, _ in sweeps), default=at_ns)
        keep = (stamps >= min(first, at_ns) - GYRO_MARGIN_NS) & (stamps <= max(newest, at_ns))
        stamps, rates = stamps[keep], rates[keep]  # the gyro between the oldest sweep and the frame
        cov = coverage(place_sweeps(sweeps, stamps, rates, at_ns, self.upper.T_cam_cam0), model)
        self.last = Rendered(draw_coverage(frame.image, cov, self.window_s, note=note), frame.stamp_ns, cov)
        return self.last
