"""The simulator's two cameras as a live camera source (`sensorbox.live.cameras.CameraSource`).

`SimCameraSource`: one simulated camera of the rig, frames at 30 Hz of real
time with the simulator's stamps (sim clock: `start_ns` + frame time, jitter
and stereo offset as `sensorbox simulate` writes them). When one frame renders
faster than half a period it is rendered live; otherwise a loop of frames (one
for a static trajectory, whose frames are all identical) is pre-rendered and
replayed, stamps still advancing. Like a camera driver with a ring of
`buffer_frames` buffers (V4L2's default is 4), a reader that falls further
behind loses the oldest frames, counted as dropped.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any, Literal

import numpy as np

from calibration.rig import write_rig
from calibration.types import U8
from ingest.errors import OutputError
from sensorbox.errors import DriverError
from sensorbox.live.cameras import Frame
from sensorbox.sim.camera import render
from sensorbox.sim.run import setup_sim

log = logging.getLogger(__name__)


class SimCameras:
    """The rig's two simulated cameras: frame times and poses as `sensorbox simulate` makes them."""

    def __init__(self, cfg: Any) -> None:
        self.cfg = cfg
        self.setup = setup_sim(cfg)
        self.period_ns = 1e9 / cfg.camera_rate_hz
        self.static = cfg.trajectory == "static"

    def sim_ns(self, k: int, cam: int) -> int:
        """Frame k's time of camera `cam` (0 upper, 1 lower) in sim ns since the start (mid-exposure)."""
        cfg = self.cfg
        nominal = self.setup.camera_phase_ns + k * self.period_ns
        jitter = np.random.default_rng([cfg.seed, k, 0x1A]).uniform(-1, 1, 2) * cfg.camera_jitter_ns
        return round(float(nominal + cam * cfg.stereo_offset_ns + jitter[cam]))

    def stamp_ns(self, k: int, cam: int) -> int:
        """Frame k's header stamp: its mid-exposure plus the camera's clock offset (`camera_offset_ns`)."""
        return int(self.cfg.start_ns) + self.sim_ns(k, cam) + int(self.cfg.camera_offset_ns[cam])

    def render(self, k: int, cam: int) -> U8:
        s = self.setup
        t_s = self.sim_ns(k, cam) / 1e9
        pose = s.traj.T_world_cam0(np.array([t_s]))[0]
        return render(s.cams[cam], s.scene, s.texture, pose, self.cfg.supersample, t_s)

    def topic(self, cam: int) -> str:
        return self.setup.cam_topics[cam]

    def write_rig(self, path: Path) -> Path:
        """Write the rig at render resolution (rig file + camchain beside it), both or neither; its path.

        `calibration.rig.write_rig` writes them as one set: a refused write, or a path that is a device
        or FIFO, is an `OutputError` naming the file (exit code 3), and no empty or cut file is left.
        """
        path = Path(path)
        write_rig(replace(self.setup.rig, camchain=None), path, error=OutputError)
        return path


class SimCameraSource:
    """One simulated camera paced to real time (see the module docstring)."""

    def __init__(
        self,
        sim: SimCameras,
        cam: int,
        *,
        prerender: Literal["auto", "always", "never"] = "auto",
        loop_frames: int = 30,
        buffer_frames: int = 4,
        name: str | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        """`clock` (monotonic seconds) paces the frames; tests pass a manual one."""
        if cam not in (0, 1):
            raise DriverError(f"simulated camera index {cam}: expected 0 (upper) or 1 (lower)")
        self.sim = sim
        self.cam = cam
        self.prerender = prerender
        self.loop_frames = max(1, int(loop_frames))
        self.buffer_frames = max(1, int(buffer_frames))
        self.name = name or ("upper", "lower")[cam]
        self.frames = 0
        self.dropped = 0
        self.render_s = 0.0  # time of one render, measured at open()
        self.loop: list[U8] = []  # pre-rendered frames (empty: rendered live)
        self._epoch: float | None = None
        self._k = 0
        self._clock = clock

    def open(self) -> None:
        t0 = time.perf_counter()
        first = self.sim.render(0, self.cam)
        self.render_s = time.perf_counter() - t0
        live = self.prerender == "never" or (
            self.prerender == "auto" and self.render_s <= 0.5 * self.sim.period_ns / 1e9
        )
        if live:
            return
        n = 1 if self.sim.static else self.loop_frames
        self.loop = [first, *(self.sim.render(k, self.cam) for k in range(1, n))]
        log.info(
            "sim camera %s: %.0f ms per frame, replaying %d pre-rendered", self.name, self.render_s * 1e3, n
        )

    def start_clock(self, epoch_monotonic: float) -> None:
        """Sim time 0 is this monotonic time (share it between the two cameras of a pair)."""
        self._epoch = epoch_monotonic

    def read(self, stop: threading.Event) -> Frame | None:
        if self._epoch is None:
            self._epoch = self._clock()
        period_s = self.sim.period_ns / 1e9
        k = self._k
        late = self._clock() - (self._epoch + self.sim.sim_ns(k, self.cam) / 1e9)
        newer = int(late / period_s)  # frames produced since frame k
        if newer >= self.buffer_frames:  # the ring overwrote the oldest: keep the newest buffer_frames
            skip = newer - self.buffer_frames + 1
            self.dropped += skip
            k += skip
        due = self._epoch + self.sim.sim_ns(k, self.cam) / 1e9
        if stop.wait(max(0.0, due - self._clock())):
            return None
        img = self.loop[k % len(self.loop)] if self.loop else self.sim.render(k, self.cam)
        self._k = k + 1
        self.frames += 1
        return Frame(self.sim.stamp_ns(k, self.cam), img, k)

    def close(self) -> None:
        self.loop = []
