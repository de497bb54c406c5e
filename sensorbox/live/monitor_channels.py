"""The live monitor's streams (rig topics), their decoding off the recording path, and its Foxglove channels.

A `Stream` is one rig sensor the monitor shows: a camera (its raw topic and
its image_transport `/compressed` topic), a LiDAR or an IMU, with the channel
it goes out on. `decode_for_monitor` reads a message as little as the view
needs: a JPEG decoded directly at 1/2, 1/4 or 1/8 of its size (libjpeg's
scaled decoding), a raw image subsampled; a sweep moved into cam0. `Channels`
owns the foxglove-sdk channels and writes the messages (foxglove.CompressedImage,
foxglove.PointCloud, JSON for IMU and status).
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from calibration.rig import Rig
from ingest.bags.decode import Sweep, decode, decode_imu
from ingest.bags.rostypes import typestore
from sensorbox.live.bus import GraphSnapshot
from sensorbox.live.coverage import preview_factor, rigid

F32 = np.ndarray[Any, np.dtype[np.float32]]
U8 = np.ndarray[Any, np.dtype[np.uint8]]
STATUS_TOPIC = "/monitor/status"
COVERAGE_TOPIC = "/monitor/coverage"
PREVIEW_MAX_WIDTH_PX = 640
JPEG_QUALITY = 80
_REDUCED = {1: cv2.IMREAD_COLOR, 2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4,
            8: cv2.IMREAD_REDUCED_COLOR_8}  # fmt: skip

STATUS_SCHEMA = {
    "title": "sensorbox.MonitorStatus",
    "type": "object",
    "properties": {
        "elapsed_s": {"type": "number"},
        "topics": {
            "type": "array",
            "description": "per topic: published, written, rate_hz (written, last interval), "
            "monitor_sent, monitor_skipped",
        },
        "drops": {"type": "object", "description": "node.stage -> messages lost there"},
        "bag_bytes": {"type": "number", "description": "the bags' size on disk"},
        "written_bytes": {"type": "number", "description": "serialised message bytes written"},
        "disk_free_bytes": {"type": "number"},
        "coverage_fraction": {"type": "number"},
        "monitor_skipped": {"type": "object", "description": "reason -> messages not sent to the monitor"},
    },
}
IMU_SCHEMA = {
    "title": "sensorbox.MonitorImu",
    "type": "object",
    "properties": {
        "stamp_ns": {"type": "integer"},
        "gyro_rad_s": {"type": "object", "description": "angular rate in cam0 (x right, y down, z forward)"},
        "acc": {"type": "object", "description": "acceleration in the IMU frame, as published (Livox: g)"},
    },
}


@dataclass
class Stream:
    """One rig sensor on the monitor: kind image | lidar | imu, its name (camera role, LiDAR or IMU
    name), channel topic, and the pose that takes its vectors into cam0."""

    kind: str
    name: str
    channel: str
    T_cam0_sensor: np.ndarray[Any, np.dtype[np.float64]]
    feeds_coverage: bool
    frame_id: str = "cam0"  # the frame of what goes out: the camera's own, cam0 for points and gyro
    factor: int = 0  # images: the reduction, learnt from the first frame (0 = not yet)


@dataclass(frozen=True)
class Preview:
    """A camera frame reduced for the monitor: header stamp (ns), BGR uint8 image, reduction factor."""

    stamp_ns: int
    image: U8
    factor: int


@dataclass(frozen=True)
class CloudCam0:
    """A sweep in cam0: header stamp and mid time (ns), points (N, 3) and intensity (N,) float32."""

    stamp_ns: int
    mid_ns: int
    xyz_m: F32
    intensity: F32


@dataclass(frozen=True)
class Gyro:
    """An IMU sample: header stamp (ns), angular rate in cam0 (rad/s), acceleration as published."""

    stamp_ns: int
    gyro_cam0_rad_s: np.ndarray[Any, np.dtype[np.float64]]
    acc: np.ndarray[Any, np.dtype[np.float64]]


def streams_of(rig: Rig) -> dict[str, Stream]:
    """Bus topic -> stream for the rig's cameras (raw and `/compressed`), LiDARs and IMUs; the first
    IMU's gyro places the coverage."""
    out: dict[str, Stream] = {}
    for cam in rig.cameras:
        if cam.role is None or not cam.topic:
            continue
        s = Stream(
            "image", cam.role, f"/monitor/{cam.role}/image", cam.T_cam0_cam, cam.role == "upper", cam.name
        )
        out[cam.topic] = out[cam.topic.rstrip("/") + "/compressed"] = s
    for lidar in rig.lidars:
        out[lidar.topic] = Stream(
            "lidar", lidar.name, f"/monitor/{lidar.name}/points", lidar.T_cam0_lidar, True
        )
    for k, imu in enumerate(rig.imus):
        out[imu.topic] = Stream("imu", imu.name, f"/monitor/{imu.name}", imu.T_cam0_imu, k == 0)
    return out


CHANNELS_OF = {"bgra8": 4, "rgba8": 4, "bgr8": 3, "rgb8": 3, "mono8": 1}  # raw encodings the monitor shows


def _image_pixels(msgtype: str, raw: bytes) -> tuple[int, U8, str]:
    """(header stamp ns, bytes or H x W x C pixels, format or encoding) of a CompressedImage or Image,
    without decoding a JPEG."""
    msg: Any = typestore(2).deserialize_cdr(memoryview(raw), msgtype)
    stamp = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
    data: U8 = np.asarray(msg.data, np.uint8)
    if msgtype.endswith("CompressedImage"):
        return stamp, data, str(msg.format)
    channels = CHANNELS_OF.get(str(msg.encoding))
    if channels is None:
        raise ValueError(f"Image encoding {msg.encoding!r}: the monitor shows {', '.join(CHANNELS_OF)}")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    pixels: U8 = data.reshape(h, step)[:, : w * channels].reshape(h, w, channels)
    return stamp, pixels, str(msg.encoding)


def decode_preview(stream: Stream, msgtype: str, raw: bytes) -> Preview:
    """The frame reduced to at most 640 pixels wide, BGR: a JPEG decoded at that size directly (the
    first frame of a stream whole, to learn its size), a raw image subsampled."""
    stamp, data, kind = _image_pixels(msgtype, raw)
    image: U8
    if msgtype.endswith("CompressedImage"):
        decoded = cv2.imdecode(data, _REDUCED[stream.factor or 1])
        if decoded is None:
            raise ValueError(f"CompressedImage ({kind}, {data.size} bytes) could not be decoded")
        image = np.asarray(decoded, np.uint8)
        if not stream.factor:
            stream.factor = preview_factor(image.shape[1], PREVIEW_MAX_WIDTH_PX)
            f = 1 / stream.factor
            image = np.asarray(cv2.resize(image, None, fx=f, fy=f, interpolation=cv2.INTER_AREA), np.uint8)
        return Preview(stamp, image, stream.factor)
    stream.factor = stream.factor or preview_factor(data.shape[1], PREVIEW_MAX_WIDTH_PX)
    small = data[:: stream.factor, :: stream.factor]
    if small.shape[2] == 1:
        image = np.asarray(cv2.cvtColor(np.ascontiguousarray(small), cv2.COLOR_GRAY2BGR), np.uint8)
    else:
        image = np.ascontiguousarray(small[..., 2::-1] if kind.startswith("rgb") else small[..., :3])
    return Preview(stamp, image, stream.factor)


def decode_cloud(stream: Stream, msgtype: str, raw: bytes) -> CloudCam0:
    """A CustomMsg or PointCloud2 sweep with its points moved into cam0."""
    sweep = decode(msgtype, raw)
    assert isinstance(sweep, Sweep)
    T = stream.T_cam0_sensor
    xyz = rigid(T[:3, :3], T[:3, 3], sweep.xyz_m)
    intensity = (
        np.asarray(sweep.reflectivity, np.float32)
        if sweep.reflectivity is not None
        else np.zeros(len(xyz), np.float32)
    )
    lo, hi = sweep.span_ns
    return CloudCam0(sweep.stamp_ns, (lo + hi) // 2, xyz.astype(np.float32), intensity)


def decode_for_monitor(stream: Stream, msgtype: str, raw: bytes) -> Preview | CloudCam0 | Gyro:
    """One message as the monitor shows it (ValueError, MessageDecodeError... when it cannot be read)."""
    if stream.kind == "image":
        return decode_preview(stream, msgtype, raw)
    if stream.kind == "lidar":
        return decode_cloud(stream, msgtype, raw)
    sample = decode_imu(raw)
    return Gyro(sample.stamp_ns, stream.T_cam0_sensor[:3, :3] @ sample.gyro_rad_s, sample.acc)


def bag_bytes(snap: GraphSnapshot) -> int:
    """Bytes on disk of the bags the graph's recorders write (their folders' files), now."""
    total = 0
    for status in snap.nodes.values():
        for folder in status.files:
            with contextlib.suppress(OSError):  # a bag being split or removed meanwhile
                total += sum(f.stat().st_size for f in Path(folder).iterdir() if f.is_file())
    return total


def _ts(stamp_ns: int) -> Any:
    from foxglove.messages import Timestamp

    return Timestamp(sec=stamp_ns // 1_000_000_000, nsec=stamp_ns % 1_000_000_000)


def jpeg(image: U8) -> bytes:
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise ValueError(f"cannot encode a {image.shape} image as JPEG")
    return bytes(buf)


@dataclass
class Channels:
    """The monitor's foxglove-sdk channels on one context, and how each message goes out."""

    context: Any
    rig: Rig
    by_topic: dict[str, Any] = field(default_factory=dict)
    _prev: GraphSnapshot | None = None

    STATUS = STATUS_TOPIC
    COVERAGE = COVERAGE_TOPIC

    def __post_init__(self) -> None:
        import foxglove
        from foxglove.channels import CompressedImageChannel, PointCloudChannel

        ctx = self.context
        for stream in {id(s): s for s in streams_of(self.rig).values()}.values():
            if stream.kind == "image":
                self.by_topic[stream.channel] = CompressedImageChannel(stream.channel, context=ctx)
            elif stream.kind == "lidar":
                self.by_topic[stream.channel] = PointCloudChannel(stream.channel, context=ctx)
            else:
                self.by_topic[stream.channel] = foxglove.Channel(
                    stream.channel, schema=IMU_SCHEMA, context=ctx
                )
        self.by_topic[self.COVERAGE] = CompressedImageChannel(self.COVERAGE, context=ctx)
        self.by_topic[self.STATUS] = foxglove.Channel(self.STATUS, schema=STATUS_SCHEMA, context=ctx)

    def subscribed(self, channel: str) -> bool:
        """Whether a client subscribed to the channel (foxglove-sdk logs to subscribed clients only)."""
        return bool(self.by_topic[channel].has_sinks())

    def send(self, stream: Stream, item: Preview | CloudCam0 | Gyro) -> str | None:
        """Send one decoded message on its stream's channel; None when sent, else the reason it was not."""
        if not self.subscribed(stream.channel):
            return "no_client"
        ch = self.by_topic[stream.channel]
        if isinstance(item, Preview):
            self._image(ch, item, stream)
        elif isinstance(item, CloudCam0):
            self._cloud(ch, item)
        else:
            w, a = item.gyro_cam0_rad_s, item.acc
            ch.log({"stamp_ns": item.stamp_ns, "gyro_rad_s": dict(zip("xyz", map(float, w), strict=True)),
                    "acc": dict(zip("xyz", map(float, a), strict=True))}, log_time=item.stamp_ns)  # fmt: skip
        return None

    def _image(self, ch: Any, item: Preview, stream: Stream) -> None:
        from foxglove.messages import CompressedImage

        msg = CompressedImage(
            timestamp=_ts(item.stamp_ns), frame_id=stream.frame_id, data=jpeg(item.image), format="jpeg"
        )
        ch.log(msg, log_time=item.stamp_ns)

    def _cloud(self, ch: Any, item: CloudCam0) -> None:
        from foxglove.messages import PackedElementField, PackedElementFieldNumericType, PointCloud

        f32 = PackedElementFieldNumericType.Float32
        packed = np.empty((len(item.xyz_m), 4), np.float32)
        packed[:, :3], packed[:, 3] = item.xyz_m, item.intensity
        fields = [
            PackedElementField(name=n, offset=4 * k, type=f32)
            for k, n in enumerate(("x", "y", "z", "intensity"))
        ]
        msg = PointCloud(timestamp=_ts(item.stamp_ns), frame_id="cam0", point_stride=16, fields=fields,
                         data=packed.tobytes())  # fmt: skip
        ch.log(msg, log_time=item.stamp_ns)

    def send_status(
        self, snap: GraphSnapshot, tallies: dict[str, Any], coverage_fraction: float | None
    ) -> None:
        """The graph's state on /monitor/status (rates over the interval since the previous snapshot)."""
        prev, self._prev = self._prev, snap
        dt = snap.elapsed_s - prev.elapsed_s if prev is not None else snap.elapsed_s
        topics = []
        for t in sorted(set(snap.published) | set(snap.written)):
            before = prev.written.get(t, 0) if prev is not None else 0
            tally = tallies.get(t)
            sent, skipped_t = (tally.sent, dict(tally.skipped)) if tally else (0, {})
            topics.append({
                "topic": t, "published": snap.published.get(t, 0), "written": snap.written.get(t, 0),
                "rate_hz": (snap.written.get(t, 0) - before) / dt if dt > 0 else 0.0,
                "monitor_sent": sent, "monitor_skipped": skipped_t,
            })  # fmt: skip
        skipped: dict[str, int] = {}
        for tally in tallies.values():
            for reason, n in tally.skipped.items():
                skipped[reason] = skipped.get(reason, 0) + n
        status = {
            "elapsed_s": snap.elapsed_s, "topics": topics, "drops": dict(snap.drops),
            "total_drops": snap.total_drops(), "bag_bytes": bag_bytes(snap),
            "written_bytes": snap.counter("bytes_written") or 0.0,
            "disk_free_bytes": snap.counter("disk_free_bytes") or -1.0,
            "coverage_fraction": coverage_fraction, "monitor_skipped": skipped,
        }  # fmt: skip
        self.by_topic[self.STATUS].log(status)

    def send_coverage(self, image: U8, stamp_ns: int) -> None:
        from foxglove.messages import CompressedImage

        msg = CompressedImage(timestamp=_ts(stamp_ns), frame_id="cam0", data=jpeg(image), format="jpeg")
        self.by_topic[self.COVERAGE].log(msg, log_time=stamp_ns)
