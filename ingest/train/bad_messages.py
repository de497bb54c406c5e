"""Undecodable messages during ingest: skipped and counted up to `--max-bad N`, an error beyond.

A message whose bytes do not match its type (an Image whose `step` is too
short for its width, a CompressedImage no decoder can read, a Livox CustomMsg
whose `point_num` disagrees with its bytes) is never lost silently: each one
is named by bag, topic and log time in a warning, counted per topic in the
summary and in `dataset.yaml`, and the run stops with a `MessageDecodeError`
as soon as there are more than the allowed number. With the default of 0 the
first one stops the run. The ingest passes read a message more than once
(plan, trajectory, stream) and the workers decode the camera images (`add`):
a message counts once, keyed by topic and log time.

What a skipped message costs: a camera frame makes its sample "skipped:
undecodable image"; a LiDAR sweep leaves its samples with fewer points (see
`PointMeta.thin_lidars`); an IMU reading is one gyro sample fewer.

A message that decodes goes through `ingest.train.plausible` (`dropped`):
IMU readings and LiDAR points no sensor can produce are dropped and
counted by reason, never skipped silently.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from ingest.bags.decode import Frame, ImuSample, Sweep
from ingest.bags.message import RawMessage
from ingest.errors import MessageDecodeError
from ingest.train.plausible import Dropped


@dataclass
class BadMessages:
    """The undecodable messages of one run: `limit` allowed, each reported once through `warn`."""

    limit: int = 0
    warn: Callable[[str], None] | None = None
    errors: dict[tuple[str, int], str] = field(default_factory=dict)  # (topic, log ns) -> message
    dropped: Dropped = field(default_factory=Dropped)  # implausible readings and points, by reason

    def decoded(self, msg: RawMessage, where: str) -> Sweep | Frame | ImuSample | None:
        """`msg.decoded(where)` without what no sensor measures (`Dropped.screen`), or None for a message
        skipped as undecodable or an implausible IMU reading."""
        try:
            decoded = msg.decoded(where)
        except MessageDecodeError as err:
            self._add(msg.topic, msg.log_ns, err)
            return None
        return self.dropped.screen(msg.topic, msg.log_ns, decoded)

    def stamp(self, msg: RawMessage, where: str) -> int | None:
        """`msg.stamp(where)` (header stamp, ns), or None for a message skipped as undecodable."""
        try:
            return msg.stamp(where)
        except MessageDecodeError as err:
            self._add(msg.topic, msg.log_ns, err)
            return None

    def add(self, topic: str, log_ns: int, why: str) -> None:
        """Count a message found undecodable elsewhere (workers decode the camera images); `why` names it."""
        self._add(topic, log_ns, MessageDecodeError(why))

    def _add(self, topic: str, log_ns: int, err: MessageDecodeError) -> None:
        key = (topic, log_ns)
        if key in self.errors:
            return
        self.errors[key] = str(err)
        if len(self.errors) > self.limit:
            raise MessageDecodeError(
                f"{err} (undecodable message {len(self.errors)}, more than --max-bad {self.limit}; "
                "--max-bad N skips and counts up to N)"
            ) from err
        if self.warn is not None:
            self.warn(f"skipped undecodable message {len(self.errors)}/{self.limit}: {err}")

    def by_topic(self) -> dict[str, int]:
        """Skipped messages per topic (sorted by topic)."""
        counts: dict[str, int] = {}
        for topic, _ in sorted(self.errors):
            counts[topic] = counts.get(topic, 0) + 1
        return counts
