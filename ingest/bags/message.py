"""One stored message as read from a bag, and its decoding with the bag, topic and time named on failure."""

from __future__ import annotations

from typing import NamedTuple

from ingest.bags.chunks import DeferredData
from ingest.bags.decode import Frame, ImuSample, Raw, RosVersion, Sweep, decode, header_stamp_ns
from ingest.errors import MessageDecodeError


class RawMessage(NamedTuple):
    """One stored message: topic, type (`pkg/msg/Type`), log time (ns), bytes, ROS version.

    `raw` is a memoryview into its decompressed chunk for a large message
    (an image), bytes otherwise (`ingest.bags.chunks.COPY_BELOW_BYTES`).
    When the read asked for it (`BagSet.messages(defer=...)`), a large
    message may still be in its compressed chunk: `deferred` holds that
    chunk, `raw` only the data's first bytes (its header), and `data()`
    decompresses it. `damage` says why a message stored on its own (a
    rosbag2 .db3's zstd-compressed message) could not be read; `raw` is
    then empty and every decoding raises `MessageDecodeError` with it.
    """

    topic: str
    msgtype: str
    log_ns: int
    raw: Raw
    ros_version: RosVersion
    deferred: DeferredData | None = None
    damage: str = ""

    def __reduce__(
        self,
    ) -> tuple[type[RawMessage], tuple[str, str, int, bytes, RosVersion, DeferredData | None, str]]:
        """Pickled (a Dask job, a process pipe) with `raw` as bytes: a view of its chunk does not pickle."""
        return RawMessage, (
            self.topic,
            self.msgtype,
            self.log_ns,
            bytes(self.raw),
            self.ros_version,
            self.deferred,
            self.damage,
        )

    def data(self) -> Raw:
        """The message's bytes (a deferred chunk decompressed: `MessageDecodeError` if it fails or the
        message is damaged)."""
        if self.damage:
            raise MessageDecodeError(self.damage)
        return self.raw if self.deferred is None else self.deferred.data()

    def decoded(self, where: str, keep_bgra: bool = False) -> Sweep | Frame | ImuSample:
        """`ingest.bags.decode.decode` of this message; a failure names `where`, the topic and log time."""
        try:
            return decode(self.msgtype, self.data(), self.ros_version, keep_bgra)
        except MessageDecodeError as err:
            raise MessageDecodeError(f"{where}: {self.topic} at log time {self.log_time}: {err}") from err

    def stamp(self, where: str) -> int:
        """The message's header stamp (ns); a failure names `where`, topic and log time."""
        try:
            if self.damage:
                raise MessageDecodeError(self.damage)
            return header_stamp_ns(self.raw, self.ros_version)
        except MessageDecodeError as err:
            raise MessageDecodeError(f"{where}: {self.topic} at log time {self.log_time}: {err}") from err

    @property
    def log_time(self) -> str:
        sec, nsec = divmod(self.log_ns, 1_000_000_000)
        return f"{sec}.{nsec:09d} s"
