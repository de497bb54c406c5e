"""Camera sources behind one interface, stereo pairing by stamp, and the camera nodes.

Sources (`CameraSource`: `open()`, `read(stop) -> Frame | None`, `close()`,
counters `frames` and `dropped`):

- `sources.ZedSource`: a ZED X One through the ZED SDK's Python API (`pyzed.sl.CameraOne`,
  imported only when opened; a clear `DriverError` when it is not installed).
  Stamps are the SDK's image time (`TIME_REFERENCE.IMAGE`), as the ROS wrapper
  publishes them; frames missing between two stamps are counted as dropped.
- `sources.OpenCVSource`: a V4L2 device (`/dev/video0`, or an index) or a video file
  through `cv2.VideoCapture`. Device frames are stamped with the host clock
  right after `grab()`; file frames with `start_ns + k / fps` (`stamps="file"`).
- The simulator's cameras (`sensorbox.sim.camera_source.SimCameraSource`) implement
  the same interface; launch files reach them through the node registry.

`StereoPairer` pairs the two cameras' frames by stamp (nearest within a
tolerance, each frame used once, unpaired frames counted). The nodes
(`CameraNode`, `StereoCameraNode`) read each source in its own thread and
encode there (`cv2.imencode` and the colour conversion release the GIL, so two
cameras encode on two cores), then publish `sensor_msgs/Image` (bgra8, the ZED
wrapper's encoding) or `CompressedImage` jpeg on `<topic>/compressed`.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Literal, Protocol

from calibration.types import U8
from ingest.bags.rostypes import COMPRESSED_IMAGE_TYPE, IMAGE_TYPE
from sensorbox import messages
from sensorbox.errors import DriverError
from sensorbox.live.bus import PRIORITY_SOURCE, NodeStatus, Publish, Shutdown

log = logging.getLogger(__name__)

ImageFormat = Literal["raw", "jpeg"]
PERIOD_30HZ_NS = 1_000_000_000 / 30.0


@dataclass(frozen=True)
class Frame:
    """One image: BGR uint8 (H, W, 3), its header stamp (ns) and the source's frame index."""

    stamp_ns: int
    bgr: U8
    seq: int


class CameraSource(Protocol):
    name: str
    frames: int  # delivered by read()
    dropped: int  # frames the source knows it missed

    def open(self) -> None: ...

    def read(self, stop: threading.Event) -> Frame | None: ...

    def close(self) -> None: ...


# ---------------------------------------------------------------- stereo pairing


class StereoPairer:
    """Pair upper/lower frames by stamp as they arrive: the pairs `ingest.train.sync.pair_stereo` makes of
    steady cameras (each frame with one candidate within the tolerance; a duplicated frame may differ).

    Frames of each camera must arrive in stamp order. When both cameras have a
    frame waiting, the two oldest are paired if within tolerance; otherwise the
    older one can never pair (the other camera's later frames are later still)
    and is dropped as unpaired. At most `max_pending` frames wait per camera
    (a silent partner ages the oldest out, also counted as unpaired). Frames
    still waiting when the stream stops are counted apart (`at_stop`): the two
    cameras' readers stop a frame apart, so one of them usually has a frame
    whose partner was simply never read; that is the end of the recording,
    not a drop.
    """

    def __init__(self, tolerance_ns: int, max_pending: int = 4) -> None:
        self.tolerance_ns = int(tolerance_ns)
        self.max_pending = max_pending
        self._pending: tuple[deque[tuple[int, Any]], deque[tuple[int, Any]]] = (deque(), deque())
        self.pairs = 0
        self.unpaired = [0, 0]
        self.at_stop = [0, 0]  # frames still waiting for their partner at flush()
        self.max_abs_dt_ns = 0
        self._lock = threading.Lock()

    def push(self, cam: int, stamp_ns: int, item: Any) -> list[tuple[Any, Any]]:
        """Add camera `cam`'s frame; the pairs (upper item, lower item) it completes, in order."""
        out: list[tuple[Any, Any]] = []
        with self._lock:
            q = self._pending[cam]
            q.append((int(stamp_ns), item))
            if len(q) > self.max_pending:
                q.popleft()
                self.unpaired[cam] += 1
            a, b = self._pending
            while a and b:
                dt = b[0][0] - a[0][0]
                if abs(dt) <= self.tolerance_ns:
                    out.append((a.popleft()[1], b.popleft()[1]))
                    self.pairs += 1
                    self.max_abs_dt_ns = max(self.max_abs_dt_ns, abs(dt))
                elif dt > 0:
                    a.popleft()
                    self.unpaired[0] += 1
                else:
                    b.popleft()
                    self.unpaired[1] += 1
        return out

    def flush(self) -> None:
        """End of the stream: count the frames still waiting in `at_stop` and forget them."""
        with self._lock:
            for cam, q in enumerate(self._pending):
                self.at_stop[cam] += len(q)
                q.clear()


# ---------------------------------------------------------------- encoding and nodes


def encode(frame: Frame, fmt: ImageFormat, frame_id: str, jpeg_quality: int = 90) -> tuple[str, bytes]:
    """(msgtype, serialised ROS 2 message) of one frame: Image bgra8 or CompressedImage jpeg."""
    if fmt == "jpeg":
        return COMPRESSED_IMAGE_TYPE, messages.compressed_image_msg(
            frame.stamp_ns, frame_id, frame.bgr, jpeg_quality
        )
    return IMAGE_TYPE, messages.image_msg(frame.stamp_ns, frame_id, frame.bgr)


def image_topic(topic: str, fmt: ImageFormat) -> str:
    """The image_transport topic: `<topic>/compressed` for jpeg."""
    return topic.rstrip("/") + "/compressed" if fmt == "jpeg" else topic


@dataclass(frozen=True)
class CameraOutput:
    topic: str  # the raw image topic; jpeg goes to <topic>/compressed
    frame_id: str


class _Reader:
    """One source read and encoded in its own thread; `deliver(cam, frame, msgtype, raw)` gets each."""

    def __init__(
        self,
        node: str,
        cam: int,
        source: CameraSource,
        fmt: ImageFormat,
        quality: int,
        frame_id: str,
        deliver: Callable[[int, Frame, str, bytes], None],
        stop: threading.Event,
        on_error: Callable[[str], None],
    ) -> None:
        self.cam, self.source, self.fmt, self.quality, self.frame_id = cam, source, fmt, quality, frame_id
        self.deliver, self.stop, self.on_error = deliver, stop, on_error
        self.encode_errors = 0
        self.encode_s = 0.0
        self.done = False
        self.thread = threading.Thread(target=self._run, name=f"{node}-{source.name}", daemon=True)

    def _run(self) -> None:
        try:
            while not self.stop.is_set():
                frame = self.source.read(self.stop)
                if frame is None:
                    break
                t0 = time.perf_counter()
                try:
                    msgtype, raw = encode(frame, self.fmt, self.frame_id, self.quality)
                except Exception as err:
                    self.encode_errors += 1
                    log.warning("camera %s: frame %d not encoded: %s", self.source.name, frame.seq, err)
                    continue
                self.encode_s += time.perf_counter() - t0
                self.deliver(self.cam, frame, msgtype, raw)
        except Exception as err:
            log.exception("camera %s failed", self.source.name)
            self.on_error(f"camera {self.source.name}: {err}")
        finally:
            self.done = True


class CameraNode:
    """One or two camera sources published independently, or (`pair=True`) as stereo pairs only."""

    priority = PRIORITY_SOURCE

    def __init__(
        self,
        name: str,
        sources: Sequence[CameraSource],
        outputs: Sequence[CameraOutput],
        publish: Publish,
        shutdown: Shutdown | None = None,
        *,
        image: ImageFormat = "jpeg",
        jpeg_quality: int = 90,
        pair_tolerance_ns: int | None = None,
        on_open: Callable[[], None] | None = None,
    ) -> None:
        if len(sources) != len(outputs) or not 1 <= len(sources) <= 2:
            raise DriverError(f"camera node {name}: expected 1 or 2 sources with one output each")
        if pair_tolerance_ns is not None and len(sources) != 2:
            raise DriverError(f"camera node {name}: stereo pairing needs two sources")
        if image not in ("raw", "jpeg"):
            raise DriverError(f"camera node {name}: image {image!r}: expected 'raw' or 'jpeg'")
        if not 1 <= jpeg_quality <= 100:
            raise DriverError(f"camera node {name}: jpeg_quality {jpeg_quality}: expected 1..100")
        self.name = name
        self.sources = list(sources)
        self.outputs = list(outputs)
        self.topics = [image_topic(o.topic, image) for o in outputs]
        self.publishes = tuple(self.topics)  # what the launch checks no other node publishes
        self.expects: dict[str, str] = {}  # topics the rig this node writes names, and why (GraphSnapshot)
        self.claims: tuple[str, ...] = ()  # the devices it opens, set by the graph's factory (the same)
        self._publish = publish
        self._shutdown = shutdown
        self.image: ImageFormat = image
        self.quality = jpeg_quality
        self.pairer = StereoPairer(pair_tolerance_ns) if pair_tolerance_ns is not None else None
        self._on_open = on_open
        self._stop = threading.Event()
        self._readers: list[_Reader] = []
        self._publish_lock = threading.Lock()
        self.published = [0] * len(sources)
        self.error: str | None = None

    def start(self) -> None:
        opened: list[CameraSource] = []
        try:
            with ThreadPoolExecutor(len(self.sources)) as pool:  # open (or pre-render) both at once
                jobs = [pool.submit(s.open) for s in self.sources]
                for s, job in zip(self.sources, jobs, strict=True):
                    job.result()
                    opened.append(s)
        except BaseException:
            for s in opened:
                with contextlib.suppress(Exception):
                    s.close()
            raise
        if self._on_open is not None:
            self._on_open()
        epoch = time.monotonic()
        for s in self.sources:
            start_clock = getattr(s, "start_clock", None)
            if start_clock is not None:
                start_clock(epoch)
        self._stop.clear()
        self._readers = [
            _Reader(
                self.name, k, s, self.image, self.quality, o.frame_id, self._deliver, self._stop, self._fail
            )
            for k, (s, o) in enumerate(zip(self.sources, self.outputs, strict=True))
        ]
        for r in self._readers:
            r.thread.start()

    def _fail(self, message: str) -> None:
        self.error = f"{self.name}: {message}"
        if self._shutdown is not None:
            self._shutdown.request(self.error, error=True)

    def _send(self, cam: int, frame: Frame, msgtype: str, raw: bytes) -> None:
        self._publish(self.topics[cam], msgtype, frame.stamp_ns, raw)
        self.published[cam] += 1

    def _deliver(self, cam: int, frame: Frame, msgtype: str, raw: bytes) -> None:
        if self.pairer is None:
            self._send(cam, frame, msgtype, raw)
            return
        with self._publish_lock:  # pairs leave in the order they formed: upper, lower, next pair
            for upper, lower in self.pairer.push(cam, frame.stamp_ns, (frame, msgtype, raw)):
                self._send(0, *upper)
                self._send(1, *lower)

    def stop(self) -> None:
        self._stop.set()
        for r in self._readers:
            r.thread.join(timeout=10.0)
        if self.pairer is not None:
            self.pairer.flush()
        for s in self.sources:
            with contextlib.suppress(Exception):
                s.close()

    def status(self) -> NodeStatus:
        counters: dict[str, float] = {}
        drops: dict[str, int] = {"source": 0, "encode": 0}
        readers: list[_Reader | None] = list(self._readers) or [None] * len(self.sources)
        for k, (s, r) in enumerate(zip(self.sources, readers, strict=True)):
            counters[f"{s.name}.frames"] = float(s.frames)
            counters[f"{s.name}.published"] = float(self.published[k])
            drops["source"] += s.dropped
            if r is not None:
                drops["encode"] += r.encode_errors
                if s.frames:
                    counters[f"{s.name}.encode_ms"] = 1e3 * r.encode_s / s.frames
        if self.pairer is not None:
            drops["pair"] = sum(self.pairer.unpaired)
            counters["pairs"] = float(self.pairer.pairs)
            counters["pair_max_dt_ms"] = self.pairer.max_abs_dt_ns / 1e6
            counters["unpaired_at_stop"] = float(sum(self.pairer.at_stop))
        return NodeStatus(counters, drops, error=self.error)

    @property
    def done(self) -> bool:
        """True when every source ended (video files)."""
        return bool(self._readers) and all(r.done for r in self._readers)
