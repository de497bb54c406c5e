"""Write ROS bags (ROS 2 mcap or sqlite3, ROS 1) that any ROS tool reads, atomically.

Every connection embeds its full message definition (rosbags `typestore=`), so
`ros2 bag`, Foxglove, the `mcap` library and rosbags' AnyReader read the bag
without registering types. rosbag2 bags use metadata version 8, which Humble's
`ros2 bag` still parses (version 9's QoS format breaks it, notes/rosbags.md).
With `compress` (the default) mcap chunks are zstd-compressed (transparent to
every mcap reader), sqlite3 messages are zstd-compressed one by one (rosbag2's
`--compression-mode message`), and ROS 1 chunks use lz4 in the frame form ROS 1's
own `rosbag` (roslz4) reads. mcap chunks carry their CRC-32 (sensorbox/live/interop.py).

The bag is written under a hidden temporary name beside the target and renamed
into place only when it was closed cleanly, so a crash or Ctrl-C never leaves a
half-written bag at the requested path.

`in_place=True` (the live recorder) instead writes at the target path from the
start: a recording killed with SIGKILL or a power cut then leaves a rosbag2
folder without metadata.yaml whose mcap holds every chunk written so far
(`ingest --salvage` reads them), where the hidden name would hide it and the
next run would delete it. `flush()` closes the open mcap chunk and hands the
file's buffered bytes to the OS, which bounds what such a kill loses.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from types import TracebackType
from typing import Any, Literal, Self

from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

from calibration.errors import SensorboxError
from ingest.bags.rostypes import typestore
from sensorbox.live.interop import Ros1Writer, Ros2Writer

BagFormat = Literal["mcap", "db3", "bag"]
FORMATS: tuple[BagFormat, ...] = ("mcap", "db3", "bag")


def bag_path(out: Path, fmt: BagFormat) -> Path:
    """Where a bag of `fmt` lands for `--out out`: a rosbag2 folder, or `out.bag` for ROS 1."""
    if fmt == "bag":
        return out if out.suffix == ".bag" else out.with_name(out.name + ".bag")
    return out


class BagWriter:
    """Context manager: `add(topic, msgtype)` then `write(topic, log_ns, raw)` in any topic order."""

    def __init__(self, path: Path, fmt: BagFormat, compress: bool = True, in_place: bool = False) -> None:
        if fmt not in FORMATS:
            raise SensorboxError(f"unknown bag format {fmt!r}; expected one of {', '.join(FORMATS)}")
        self.path = bag_path(Path(path), fmt)
        if self.path.exists():
            raise SensorboxError(f"{self.path} exists already; remove it or choose another --out")
        self.fmt = fmt
        self.ros_version: Literal[1, 2] = 1 if fmt == "bag" else 2
        self._tmp_dir = self.path.parent / f".{self.path.name}.partial"
        self._compress = compress
        self._in_place = in_place
        self._conns: dict[str, Any] = {}
        self.counts: dict[str, int] = {}
        self._writer: Writer1 | Writer2 | None = None

    def __enter__(self) -> Self:
        if self._in_place:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            target = self.path
        else:
            if self._tmp_dir.exists():
                shutil.rmtree(self._tmp_dir)  # debris of an earlier interrupted run
            self._tmp_dir.mkdir(parents=True)
            target = self._tmp_dir / self.path.name
        if self.fmt == "bag":
            w1 = Ros1Writer(target)
            if self._compress:
                w1.set_compression(Writer1.CompressionFormat.LZ4)
            self._writer = w1
        else:
            plugin = StoragePlugin.MCAP if self.fmt == "mcap" else StoragePlugin.SQLITE3
            w2 = Ros2Writer(target, version=8, storage_plugin=plugin)
            if self._compress:
                mode = CompressionMode.STORAGE if self.fmt == "mcap" else CompressionMode.MESSAGE
                w2.set_compression(mode, CompressionFormat.ZSTD)
            self._writer = w2
        self._writer.open()
        return self

    def add(self, topic: str, msgtype: str) -> None:
        assert self._writer is not None, "use BagWriter as a context manager"
        self._conns[topic] = self._writer.add_connection(
            topic, msgtype, typestore=typestore(self.ros_version)
        )
        self.counts[topic] = 0

    def write(self, topic: str, log_ns: int, raw: bytes) -> None:
        assert self._writer is not None, "use BagWriter as a context manager"
        self._writer.write(self._conns[topic], int(log_ns), raw)
        self.counts[topic] += 1

    def flush(self) -> None:
        """mcap: close the open chunk (if it holds messages) and flush the file to the OS.

        Everything written before a flush survives a SIGKILL of this process as
        complete chunks. Other formats: no-op.
        """
        storage = getattr(self._writer, "storage", None) if self.fmt == "mcap" else None
        if storage is None:
            return
        chunk = getattr(storage, "chunk", None)
        if chunk is not None and chunk.msgs:
            storage.close_chunk()
        storage.bio.flush()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if self._in_place:  # keep what was recorded, even after an error: close it readable
            if self._writer is not None:
                self._writer.close()
            return
        try:
            if self._writer is not None:
                self._writer.close()
        finally:
            if exc_type is None:
                (self._tmp_dir / self.path.name).rename(self.path)
            shutil.rmtree(self._tmp_dir, ignore_errors=True)

    @property
    def size_bytes(self) -> int:
        """Bytes on disk of the finished bag (a folder is summed)."""
        if self.path.is_dir():
            return sum(f.stat().st_size for f in self.path.rglob("*") if f.is_file())
        return self.path.stat().st_size if self.path.exists() else 0
