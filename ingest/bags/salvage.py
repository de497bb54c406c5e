"""MCAP files read record by record (`salvage_mcap`, and `BagSet` with `salvage=True`): every intact
message of a truncated, unclosed or damaged file, with what was lost logged, never raised, and the
channels whose messages cannot be decoded safely named (`channel_problem`)."""

from __future__ import annotations

import logging
from collections.abc import Collection, Iterator
from dataclasses import dataclass
from functools import cache
from pathlib import Path

from rosbags.interfaces import MessageDefinition, MessageDefinitionFormat

from ingest.bags.chunks import LostChunk
from ingest.bags.decode import RosVersion
from ingest.bags.definitions import check_definition
from ingest.bags.mcap_records import McapChannel, SalvageReport, mcap_messages
from ingest.bags.message import RawMessage
from ingest.errors import BagError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SalvageChannel:
    topic: str
    msgtype: str
    msgdef: MessageDefinition
    ros_version: RosVersion | None  # None: a message encoding SensorBox cannot decode
    encoding: str


_SCHEMA_FORMATS = {
    "ros2msg": MessageDefinitionFormat.MSG,
    "ros1msg": MessageDefinitionFormat.MSG,
    "ros2idl": MessageDefinitionFormat.IDL,
    "omgidl": MessageDefinitionFormat.IDL,
}
_ENCODING_VERSIONS: dict[str, RosVersion] = {"cdr": 2, "ros1": 1}


@cache
def _channel(mc: McapChannel) -> SalvageChannel:
    fmt = _SCHEMA_FORMATS.get(mc.schema_encoding, MessageDefinitionFormat.NONE)
    msgdef = MessageDefinition(fmt, mc.schema_data if mc.schema_name else "")
    version = _ENCODING_VERSIONS.get(mc.message_encoding)
    return SalvageChannel(mc.topic, mc.schema_name, msgdef, version, mc.message_encoding)


def mcap_channel_messages(
    path: Path, quiet: bool = False, lost: list[LostChunk] | None = None
) -> Iterator[tuple[SalvageChannel, int, bytes]]:
    """(channel, log_ns, data) of every intact message record of an MCAP file; logs what was lost.

    The chunks it lost are appended to `lost` and logged, one line each, once the file is read.
    """
    report = SalvageReport()
    for mc, log_ns, data in mcap_messages(path, report):
        yield _channel(mc), log_ns, data
    if not report.has_magic and not report.intact_records:
        raise BagError(f"{path}: not an MCAP file (no MCAP magic at its start and no intact record)")
    level = logging.INFO if report.intact or quiet else logging.WARNING
    log.log(level, "%s: %s", path, report.summary())
    for chunk in report.lost_chunks:
        log.log(
            logging.INFO if quiet else logging.WARNING,
            "%s; its messages are counted as lost",
            chunk.describe(),
        )
    if lost is not None:
        lost.extend(report.lost_chunks)


def salvage_mcap(path: str | Path, topics: Collection[str] | None = None) -> Iterator[RawMessage]:
    """Messages of every intact record of a truncated, unclosed or damaged MCAP file, in file order.

    Walks the file record by record (`ingest.bags.mcap_records`); what is cut
    or damaged is skipped and logged, never raised. A complete file yields all
    its messages. `topics` limits the output (None: all). With `topics=None`
    a topic that cannot be decoded safely (schema unparsable or missing,
    foreign encoding, see the module docstring) is skipped with a warning
    naming it; asked for by name it raises `BagError` when reached, as does a
    missing or non-MCAP file.
    """
    path = Path(path)
    if not path.is_file():
        raise BagError(f"{path}: no such MCAP file")
    wanted = None if topics is None else set(topics)
    return salvage_messages(path, wanted)


def salvage_messages(path: Path, wanted: set[str] | None, quiet: bool = False) -> Iterator[RawMessage]:
    usable: dict[SalvageChannel, bool] = {}
    for channel, log_ns, data in mcap_channel_messages(path, quiet):
        if wanted is not None and channel.topic not in wanted:
            continue
        if channel not in usable:
            problem = channel_problem(path, channel)
            if problem is not None and wanted is not None:
                raise BagError(problem)
            if problem is not None and not quiet:
                log.warning("%s; skipping that topic, the others are read", problem)
            usable[channel] = problem is None
        if usable[channel]:
            assert channel.ros_version is not None  # channel_problem
            yield RawMessage(channel.topic, channel.msgtype, log_ns, data, channel.ros_version)


def channel_problem(path: Path, channel: SalvageChannel) -> str | None:
    """Why a salvaged channel's messages cannot be decoded safely (a `BagError` text), or None."""
    if channel.ros_version is None:
        return (
            f"{path}: topic {channel.topic!r} uses message encoding {channel.encoding!r};"
            " expected 'cdr' (ROS 2) or 'ros1'"
        )
    if not channel.msgtype:
        return f"{path}: topic {channel.topic!r} has no schema, so its message type is unknown"
    try:
        check_definition(str(path), channel.topic, channel.msgtype, channel.msgdef, channel.ros_version)
    except BagError as err:
        return str(err)
    return None


def salvage_targets(path: Path) -> list[Path]:
    """The MCAP files of `path` (a file or a rosbag2 directory); `--salvage` walks them record by record."""
    if path.is_file():
        return [path] if path.suffix == ".mcap" else []
    return sorted(path.glob("*.mcap"))
