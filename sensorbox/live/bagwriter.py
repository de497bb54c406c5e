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

A write that fails (the disk filled up between the recorder's free-space
checks) raises `BagWriteError` (an `OutputError`: the CLI prints one line naming
the bag and exits 3) with the messages per topic that are not in the
bag: those of the open chunk and of bytes the OS refused. For every format a
refused write or close (an OSError, or sqlite3's "database or disk is full")
is that one error; without `in_place` the hidden partial bag is removed, so the
requested path holds a complete bag or nothing. In place, the mcap is cut back
to its last complete chunk, so the bag still closes with a summary (or, when
even that no longer fits, is left as complete chunks that `ingest --salvage`
reads); `counts` then count exactly what the bag holds.
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import sqlite3
from collections import defaultdict
from dataclasses import dataclass
from io import BytesIO
from pathlib import Path
from types import TracebackType
from typing import Any, Literal, Self

from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode
from rosbags.rosbag2.storage_mcap import McapWriter, PendingChunk

from calibration.errors import SensorboxError
from ingest.bags.rostypes import typestore
from ingest.errors import OutputError
from sensorbox.live.interop import Ros1Writer, Ros2Writer

BagFormat = Literal["mcap", "db3", "bag"]
FORMATS: tuple[BagFormat, ...] = ("mcap", "db3", "bag")
NO_SPACE = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)


class BagWriteError(OutputError):
    """Writing a bag failed; `lost` = (messages, bytes) per topic that are not in the bag."""

    def __init__(self, message: str, lost: dict[str, tuple[int, int]], no_space: bool) -> None:
        super().__init__(message)
        self.lost = lost
        self.no_space = no_space


@dataclass(frozen=True)
class _Checkpoint:
    """An mcap writer's state when everything written so far was in complete chunks, handed to the OS."""

    offset: int  # file size then
    chunks: int
    channel_stats: dict[int, int]
    time_range: tuple[int, int]
    counts: dict[int, int]  # the rosbag2 writer's per-connection counts (metadata.yaml)
    writer_range: tuple[int, int]

    @staticmethod
    def take(writer: Writer2, storage: McapWriter) -> _Checkpoint:
        return _Checkpoint(
            storage.bio.tell(), len(storage.chunks), dict(storage.channel_stats),
            (storage.message_start_time, storage.message_end_time), dict(writer.counts),
            (writer.min_timestamp, writer.max_timestamp),
        )  # fmt: skip

    def restore(self, writer: Writer2, storage: McapWriter) -> None:
        """Cut the file back to this state: the partial chunk and any refused bytes are gone."""
        with contextlib.suppress(OSError):
            storage.bio.close()  # its buffer cannot be written; the descriptor is closed regardless
        os.truncate(storage.path, self.offset)
        storage.bio = storage.path.open("r+b")  # type: ignore[assignment]  # a BufferedRandom writes as well
        storage.bio.seek(self.offset)
        del storage.chunks[self.chunks :]
        storage.channel_stats = {cid: self.channel_stats.get(cid, 0) for cid in storage.channel_stats}
        storage.message_start_time, storage.message_end_time = self.time_range
        storage.chunk = PendingChunk(2**63 - 1, 0, BytesIO(), defaultdict(list))
        writer.counts = {cid: self.counts.get(cid, 0) for cid in writer.counts}
        writer.min_timestamp, writer.max_timestamp = self.writer_range


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
        self.counts: dict[str, int] = {}  # messages per topic in the bag (or in its open mcap chunk)
        self.pending: dict[str, tuple[int, int]] = {}  # mcap: (messages, bytes) not yet in a complete chunk
        self._checkpoint: _Checkpoint | None = None
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
        try:
            self._writer.open()  # writes the file's header: a full disk can refuse it already
        except (OSError, sqlite3.Error) as err:
            self._writer = None
            if not self._in_place:
                shutil.rmtree(self._tmp_dir, ignore_errors=True)
            raise BagWriteError(
                f"{self.path}: cannot create the bag: {_why(err)}", {}, _no_space(err)
            ) from None
        storage = self._mcap()
        if storage is not None:
            self._checkpoint = _Checkpoint.take(w2, storage)  # the header is in the buffer: flush() writes it
        return self

    def add(self, topic: str, msgtype: str) -> None:
        assert self._writer is not None, "use BagWriter as a context manager"
        self._conns[topic] = self._writer.add_connection(
            topic, msgtype, typestore=typestore(self.ros_version)
        )
        self.counts[topic] = 0

    def write(self, topic: str, log_ns: int, raw: bytes) -> None:
        """Write one message; BagWriteError (mcap) when it or earlier ones could not be written."""
        assert self._writer is not None, "use BagWriter as a context manager"
        self.counts[topic] += 1
        n, size = self.pending.get(topic, (0, 0))
        self.pending[topic] = (n + 1, size + len(raw))
        storage = self._mcap()
        try:
            self._writer.write(self._conns[topic], int(log_ns), raw)
            if storage is not None and len(storage.chunks) != self._checkpoint_chunks():
                self._sync(storage)  # rosbags closed a full chunk: hand it to the OS now
        except (OSError, sqlite3.Error) as err:  # sqlite3 (db3): "database or disk is full"
            self._fail(err, "cannot write")

    def flush(self) -> None:
        """mcap: close the open chunk (if it holds messages) and flush the file to the OS.

        Everything written before a flush survives a SIGKILL of this process as
        complete chunks. Other formats: no-op.
        """
        storage = self._mcap()
        if storage is None:
            return
        try:
            if storage.chunk.msgs:
                storage.close_chunk()
            self._sync(storage)
        except OSError as err:
            self._fail(err, "cannot write")

    def _mcap(self) -> McapWriter | None:
        storage = getattr(self._writer, "storage", None) if self.fmt == "mcap" else None
        return storage if isinstance(storage, McapWriter) else None

    def _checkpoint_chunks(self) -> int:
        return self._checkpoint.chunks if self._checkpoint is not None else 0

    def _sync(self, storage: McapWriter) -> None:
        """Flush the file; every message written so far is then in the bag."""
        storage.bio.flush()
        assert isinstance(self._writer, Writer2)
        self._checkpoint = _Checkpoint.take(self._writer, storage)
        self.pending = {}

    def _fail(self, err: OSError | sqlite3.Error, doing: str) -> None:
        """Cut the mcap back to its last complete chunk and raise BagWriteError naming what is lost.

        Not in place (any format) the hidden partial bag is removed on exit, so
        nothing is written, which the message says.
        """
        lost, self.pending = self.pending, {}
        for topic, (n, _) in lost.items():
            self.counts[topic] -= n
        storage = self._mcap()
        if storage is not None and self._checkpoint is not None:
            assert isinstance(self._writer, Writer2)
            self._checkpoint.restore(self._writer, storage)
        n_lost = sum(n for n, _ in lost.values())
        if self._in_place:  # the bag stays: say what it lacks
            what = f"{n_lost} message{'s' if n_lost != 1 else ''} of the open chunk not in it"
        else:  # the hidden partial bag is removed on exit
            what = "no bag written"
        raise BagWriteError(
            f"{self.path}: {doing} the bag: {_why(err)}; {what}", lost, _no_space(err)
        ) from None

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if self._in_place:  # keep what was recorded, even after an error: close it readable
            if self._writer is not None:
                self._close_in_place()
            return
        closed = False
        try:
            if self._writer is not None:
                writer, self._writer = self._writer, None
                writer.close()
            closed = True
        except (OSError, sqlite3.Error) as err:
            if exc_type is None:  # after an error of its own the bag is dropped anyway: that one stands
                raise BagWriteError(
                    f"{self.path}: cannot close the bag: {_why(err)}; no bag written", {}, _no_space(err)
                ) from None
        finally:
            try:
                if exc_type is None and closed:
                    (self._tmp_dir / self.path.name).rename(self.path)
            finally:
                shutil.rmtree(self._tmp_dir, ignore_errors=True)

    def _close_in_place(self) -> None:
        """Close with summary and metadata.yaml; without room for them, leave the complete chunks."""
        assert self._writer is not None
        storage = self._mcap()
        writer, self._writer = self._writer, None
        try:
            writer.close()
        except OSError as err:
            meta = self.path / "metadata.yaml.tmp"
            with contextlib.suppress(OSError):
                meta.unlink(missing_ok=True)  # never a partial metadata file
            if isinstance(writer, Writer2) and writer.storage is not None and storage is not None:
                assert self._checkpoint is not None
                self._checkpoint.restore(writer, storage)  # the summary failed: cut it off
                storage.bio.close()
                chunks = self._checkpoint.chunks
                lost, self.pending = self.pending, {}
                for topic, (n, _) in lost.items():
                    self.counts[topic] -= n
                raise BagWriteError(
                    f"{self.path}: cannot write the bag's summary: {err.strerror or err}; its {chunks} "
                    "complete chunk(s) stay readable with `sensorbox ingest --salvage`",
                    lost,
                    err.errno in NO_SPACE,
                ) from None
            raise BagWriteError(
                f"{self.path}: cannot write metadata.yaml: {err.strerror or err}; the mcap is complete",
                {},
                err.errno in NO_SPACE,
            ) from None

    @property
    def size_bytes(self) -> int:
        """Bytes on disk of the finished bag (a folder is summed)."""
        if self.path.is_dir():
            return sum(f.stat().st_size for f in self.path.rglob("*") if f.is_file())
        return self.path.stat().st_size if self.path.exists() else 0


def _why(err: OSError | sqlite3.Error) -> str:
    """The OS's words for a refused write (sqlite3 has only its message)."""
    return (err.strerror if isinstance(err, OSError) else None) or str(err)


def _no_space(err: OSError | sqlite3.Error) -> bool:
    """Whether the write failed for want of room (sqlite3 says "database or disk is full")."""
    if isinstance(err, OSError):
        return err.errno in NO_SPACE
    return isinstance(err, sqlite3.OperationalError) and "full" in str(err)
