"""Camera sources: ZED X One through the ZED SDK, V4L2 devices and video files through OpenCV.

Each implements `sensorbox.live.cameras.CameraSource` (`open()`, `read(stop) -> Frame | None`,
`close()`, counters `frames` and `dropped`); see that module for what each does."""

from __future__ import annotations

import importlib
import logging
import threading
import time
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np

from sensorbox.errors import DriverError
from sensorbox.live.cameras import Frame

log = logging.getLogger(__name__)


def _count_gap(prev_ns: int | None, stamp_ns: int, period_ns: float) -> int:
    """Frames missing between two consecutive stamps of a camera running at `period_ns`."""
    if prev_ns is None or period_ns <= 0:
        return 0
    return max(0, round((stamp_ns - prev_ns) / period_ns) - 1)


def import_pyzed() -> Any:
    """The ZED SDK's `pyzed.sl` module, or a DriverError saying how to get it."""
    try:
        return importlib.import_module("pyzed.sl")
    except ImportError as err:
        raise DriverError(
            "ZED camera: the ZED SDK Python API (pyzed) is not installed; install the ZED SDK and run its"
            " get_python_api.py, or use camera source 'opencv' (V4L2) or 'sim'"
        ) from err


class ZedSource:
    """A ZED X One (`sl.CameraOne`), BGR frames stamped with the SDK's image time."""

    def __init__(
        self, serial: int | None = None, resolution: str = "HD1200", fps: int = 30, name: str = "zed"
    ) -> None:
        self.serial = serial
        self.resolution = resolution
        self.fps = fps
        self.name = name
        self.frames = 0
        self.dropped = 0
        self.grab_errors = 0
        self._sl: Any = None
        self._cam: Any = None
        self._mat: Any = None
        self._prev_ns: int | None = None

    def _label(self) -> str:
        return f"ZED camera {self.name}" + (f" (serial {self.serial})" if self.serial else "")

    def open(self) -> None:
        sl = import_pyzed()
        init = sl.InitParametersOne()
        try:
            init.camera_resolution = getattr(sl.RESOLUTION, self.resolution)
        except AttributeError as err:
            raise DriverError(
                f"{self._label()}: resolution {self.resolution!r} unknown to the SDK (e.g. HD1200, HD1080)"
            ) from err
        init.camera_fps = self.fps
        if self.serial:
            init.set_from_serial_number(int(self.serial))
        cam = sl.CameraOne()
        status = cam.open(init)
        if not status <= sl.ERROR_CODE.SUCCESS:  # the SDK's samples: values above SUCCESS are errors
            raise DriverError(f"{self._label()}: open failed: {status}")
        self._sl, self._cam, self._mat = sl, cam, sl.Mat()

    def read(self, stop: threading.Event) -> Frame | None:
        sl, cam = self._sl, self._cam
        if cam is None:
            raise DriverError(f"{self._label()}: read() before open()")
        failures = 0
        while not stop.is_set():
            status = cam.grab()
            if status <= sl.ERROR_CODE.SUCCESS:
                break
            self.grab_errors += 1
            failures += 1
            if failures >= 30:
                raise DriverError(f"{self._label()}: grab failed {failures} times in a row: {status}")
            time.sleep(0.01)
        else:
            return None
        cam.retrieve_image(self._mat)
        stamp = int(cam.get_timestamp(sl.TIME_REFERENCE.IMAGE).get_nanoseconds())
        data = np.asarray(self._mat.get_data())
        bgr = cv2.cvtColor(data, cv2.COLOR_BGRA2BGR) if data.ndim == 3 and data.shape[2] == 4 else data
        self.dropped += _count_gap(self._prev_ns, stamp, 1e9 / self.fps)
        self._prev_ns = stamp
        frame = Frame(stamp, np.ascontiguousarray(bgr, np.uint8), self.frames)
        self.frames += 1
        return frame

    def close(self) -> None:
        if self._cam is not None:
            self._cam.close()
            self._cam = None


def _device_index(device: str) -> int | None:
    """0 for "0" or "/dev/video0"; None for anything else (a file or URL)."""
    d = device.removeprefix("/dev/video")
    return int(d) if d.isdigit() else None


class OpenCVSource:
    """A V4L2 camera (`/dev/videoN` or N) or a video file through cv2.VideoCapture."""

    def __init__(
        self,
        device: str,
        *,
        width: int = 0,
        height: int = 0,
        fps: float = 0.0,
        fourcc: str = "MJPG",
        stamps: Literal["host", "file"] | None = None,
        start_ns: int | None = None,
        realtime: bool = False,
        name: str = "opencv",
    ) -> None:
        self.device = str(device)
        self.index = _device_index(self.device)
        self.width, self.height, self.fps, self.fourcc = width, height, fps, fourcc
        self.stamps = stamps or ("host" if self.index is not None else "file")
        self.start_ns = start_ns
        self.realtime = realtime
        self.name = name
        self.frames = 0
        self.dropped = 0
        self.grab_errors = 0
        self._cap: Any = None
        self._period_ns = 0.0
        self._prev_ns: int | None = None
        self._t0 = 0.0

    def open(self) -> None:
        if self.index is not None:
            cap = cv2.VideoCapture(self.index, cv2.CAP_V4L2)
        else:
            if not Path(self.device).exists():
                raise DriverError(f"camera {self.name}: no such device or video file {self.device!r}")
            cap = cv2.VideoCapture(self.device)
        if not cap.isOpened():
            raise DriverError(f"camera {self.name}: OpenCV cannot open {self.device!r}")
        if self.index is not None:
            if self.fourcc:
                cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter.fourcc(*self.fourcc[:4]))
            wanted = (
                (cv2.CAP_PROP_FRAME_WIDTH, self.width),
                (cv2.CAP_PROP_FRAME_HEIGHT, self.height),
                (cv2.CAP_PROP_FPS, self.fps),
            )
            for prop, value in wanted:
                if value:
                    cap.set(prop, value)
            cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # newest frame, not a stale queue
        fps = self.fps or float(cap.get(cv2.CAP_PROP_FPS)) or 30.0
        self._period_ns = 1e9 / fps
        if self.start_ns is None:
            self.start_ns = time.time_ns()
        self._cap = cap
        self._t0 = time.monotonic()

    def read(self, stop: threading.Event) -> Frame | None:
        cap = self._cap
        if cap is None:
            raise DriverError(f"camera {self.name}: read() before open()")
        if self.realtime and self.stamps == "file":
            due = self._t0 + self.frames * self._period_ns / 1e9
            if stop.wait(max(0.0, due - time.monotonic())):
                return None
        failures = 0
        while not stop.is_set():
            ok = cap.grab()
            host_ns = time.time_ns()
            if ok:
                ok, img = cap.retrieve()
            if ok and img is not None:
                break
            if self.index is None:
                return None  # end of the file
            self.grab_errors += 1
            failures += 1
            if failures >= 30:
                raise DriverError(f"camera {self.name}: {self.device} delivered no frame {failures} times")
            time.sleep(0.01)
        else:
            return None
        if self.stamps == "file":
            assert self.start_ns is not None
            stamp = self.start_ns + round(self.frames * self._period_ns)
        else:
            stamp = host_ns
            self.dropped += _count_gap(self._prev_ns, stamp, self._period_ns)
        self._prev_ns = stamp
        if img.ndim == 2:
            img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
        frame = Frame(stamp, np.ascontiguousarray(img[..., :3], np.uint8), self.frames)
        self.frames += 1
        return frame

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None
