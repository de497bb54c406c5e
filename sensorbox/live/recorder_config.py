"""What the live recorder is told (`RecorderConfig`, checked by `validate`), what it counts per topic
(`TopicCounters`), and the file system facts it needs (free bytes, a bag name for now)."""

from __future__ import annotations

import math
import re
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

from sensorbox.errors import RecorderError

MiB = 1 << 20
NAME_PATTERN = r"[A-Za-z0-9_.+-]+"  # a bag name prefix: one folder name, nothing a shell or path reads
DiskFree = Callable[[Path], int]


def disk_free_bytes(path: Path) -> int:
    """Free bytes on the file system holding `path` (its nearest existing parent)."""
    p = Path(path).absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    return shutil.disk_usage(p).free


def default_bag_name() -> str:
    """`capture_YYYYmmdd-HHMMSS`, local time (bags of one run are `<name>_000`, `<name>_001`, ...)."""
    return datetime.now().strftime("capture_%Y%m%d-%H%M%S")


MAX_MIB = (1e9, "MiB (about a petabyte)")
"""The largest size a recorder parameter in MiB may state."""
MAX_S = (1e8, "s (about three years)")
"""The largest time a recorder parameter in seconds may state (`sensorbox.sim.config.MAX_DURATION_S`)."""


@dataclass(frozen=True)
class RecorderConfig:
    """Where and how to record; sizes in bytes, times in seconds (0 = off)."""

    out: Path
    name: str = ""  # bag folder prefix; "" = capture_<local time>
    topics: tuple[str, ...] = ()  # () = every topic on the bus
    split_bytes: int = 0  # start the next bag once the mcap file is this large
    split_s: float = 0.0  # start the next bag after this much receive time
    duration_s: float = 0.0  # ask the graph to stop after recording this long
    queue_msgs: int = 4096  # per topic: 20 s of a 200 Hz IMU while the writer is starved
    queue_bytes: int = 512 * MiB  # per topic
    min_free_bytes: int = 1024 * MiB  # stop before the disk has less than this free
    compress: bool = True  # zstd mcap chunks
    flush_s: float = 1.0  # close and flush the open chunk at least this often
    disk_check_s: float = 1.0

    def validate(self) -> None:
        if self.name and not re.fullmatch(NAME_PATTERN, self.name):
            raise RecorderError(f"recorder name {self.name!r}: use letters, digits and _ . + - only")
        for key in ("split_bytes", "split_s", "duration_s", "min_free_bytes", "flush_s"):
            value = getattr(self, key)
            if not (value >= 0 and math.isfinite(value)):
                raise RecorderError(f"recorder {key} must be a finite number >= 0, got {value}")
        if self.queue_msgs < 1 or self.queue_bytes < 1:
            raise RecorderError(
                f"recorder queue_msgs ({self.queue_msgs}) and queue_bytes ({self.queue_bytes}) must be >= 1"
            )
        if self.disk_check_s <= 0:
            raise RecorderError(f"recorder disk_check_s must be > 0, got {self.disk_check_s}")


@dataclass
class TopicCounters:
    msgtype: str
    received: int = 0  # handed to enqueue
    written: int = 0
    bytes: int = 0  # serialised bytes written
    queue_drops: int = 0
    disk_drops: int = 0
    write_drops: int = 0
    stopped_drops: int = 0
    queued_bytes: int = 0
    queue_peak: int = 0
    first_ns: int = 0  # receive time of the first and last message written
    last_ns: int = 0

    def rate_hz(self) -> float:
        """Mean rate written: (messages - 1) / (last - first receive time)."""
        span = self.last_ns - self.first_ns
        return (self.written - 1) * 1e9 / span if self.written > 1 and span > 0 else 0.0
