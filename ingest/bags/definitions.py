"""Which embedded message definitions SensorBox trusts, and a reader that sets the unparsable aside.

- `definition_problem(msgtype, msgdef, ros_version) -> str | None`: why an
  embedded definition cannot be parsed (None: it can, or there is none).
- `check_definition(where, topic, msgtype, msgdef, ros_version)`: `BagError`
  unless the topic's messages can be decoded without guessing (see
  `ingest.bags.reader`'s docstring for the rules).
- `TolerantAnyReader`: rosbags' `AnyReader`, except that a connection whose
  embedded definition cannot be parsed (e.g. rosbag2's service-event topics,
  whose schema is the raw `.srv` text) is left out of `connections` and listed
  in `unparsable` instead of failing the whole bag.
"""

from __future__ import annotations

from functools import cache
from typing import TYPE_CHECKING, Any

from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.interfaces import MessageDefinition, MessageDefinitionFormat
from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore

from ingest.bags.decode import DECODED_TYPES, RosVersion
from ingest.bags.rostypes import typestore
from ingest.errors import BagError

if TYPE_CHECKING:
    from rosbags.interfaces import Connection

__all__ = ["TolerantAnyReader", "check_definition", "definition_problem"]


@cache
def _our_hash(msgtype: str, ros_version: RosVersion) -> str:
    """RIHS01 (ROS 2) or MD5 (ROS 1) of SensorBox's own definition of `msgtype`."""
    store = typestore(ros_version)
    return store.hash_rihs01(msgtype) if ros_version == 2 else store.generate_msgdef(msgtype)[1]


@cache
def _embedded_hash(msgtype: str, msgdef: MessageDefinition, ros_version: RosVersion) -> str:
    """The same hash of a bag's embedded definition (parsed like AnyReader does)."""
    store = get_typestore(Stores.EMPTY)
    if msgdef.format == MessageDefinitionFormat.IDL:
        sep = "=" * 80 + "\n"
        if msgdef.data.startswith(f"{sep}IDL: "):
            for part in msgdef.data.split(sep)[1:]:
                store.register(get_types_from_idl(part.split("\n", 1)[1]))
        else:
            store.register(get_types_from_idl(msgdef.data))
    else:
        store.register(get_types_from_msg(msgdef.data, msgtype))
    return store.hash_rihs01(msgtype) if ros_version == 2 else store.generate_msgdef(msgtype)[1]


def _one_line(err: BaseException) -> str:
    """An exception as one short line; a quoted definition (rosbags quotes the whole text) is dropped."""
    text = " ".join(str(err).split())
    head, quoted = text.split(": '", 1) if ": '" in text else (text, "")
    text = head if len(quoted) > 60 else text
    text = text if len(text) <= 160 else text[:157] + "..."
    return f"{type(err).__name__}: {text}" if text else type(err).__name__


def definition_problem(msgtype: str, msgdef: MessageDefinition, ros_version: RosVersion) -> str | None:
    """Why `msgdef` cannot be parsed and hashed as `msgtype`; None when it can or is empty."""
    if msgdef.format == MessageDefinitionFormat.NONE or not msgdef.data.strip():
        return None
    try:
        _embedded_hash(msgtype, msgdef, ros_version)
    except Exception as err:  # rosbags' parsers raise several types on bad text
        lines = msgdef.data.splitlines()
        srv = any(ln.startswith("SRV: ") for ln in lines) or "---" in (ln.strip() for ln in lines)
        what = " (it is a service's .srv text, as rosbag2 records service-event topics)" if srv else ""
        return f"its embedded definition of {msgtype} cannot be parsed{what}: {_one_line(err)}"
    return None


def check_definition(
    where: str, topic: str, msgtype: str, msgdef: MessageDefinition, ros_version: RosVersion
) -> None:
    """Raise `BagError` unless the messages of `topic` can be decoded without guessing."""
    problem = definition_problem(msgtype, msgdef, ros_version)
    if problem is not None:
        raise BagError(f"{where}: topic {topic!r}: {problem}")
    if not msgdef.data.strip():
        if msgtype not in typestore(ros_version).types:
            raise BagError(
                f"{where}: topic {topic!r} has no embedded message definition for type {msgtype!r}"
                " and SensorBox does not know that type; refusing to guess its layout"
            )
        return  # decoded with SensorBox's typestore
    if msgtype not in DECODED_TYPES:
        return
    theirs = _embedded_hash(msgtype, msgdef, ros_version)
    ours = _our_hash(msgtype, ros_version)
    if theirs != ours:
        raise BagError(
            f"{where}: topic {topic!r}: the bag's definition of {msgtype} differs from the one"
            f" SensorBox decodes ({theirs} != {ours}); refusing to decode it"
        )


def _match_folder_qos(folder: Any) -> list[str]:
    """Let a rosbag2 folder's storage files yield the messages of topics whose QoS or serialization
    format in metadata.yaml differs from what the file stores; the topics and what differs, for a
    warning (the file's bytes are read, as the file stores them).

    rosbags pairs a folder's metadata topics with its files' channels by topic, type and QoS, so a
    difference (rosbag2's own test bags have them: the file's QoS written by a newer recorder)
    silently dropped every message of the topic. A channel with no equal metadata entry takes the
    QoS of the metadata entry of its topic and type.
    """
    topics: set[str] = set()
    for storage in getattr(folder, "storages", ()):  # a rosbag2 folder's files (a single file: none)
        conns = storage.connections
        for idx, x in enumerate(conns):
            same = [y for y in folder.connections if y.topic == x.topic and y.msgtype == x.msgtype]
            if same and all(y.ext != x.ext for y in same):
                conns[idx] = x._replace(ext=same[0].ext)
                given, stored = same[0].ext, x.ext
                formats = (
                    getattr(given, "serialization_format", None),
                    getattr(stored, "serialization_format", None),
                )
                if formats[0] != formats[1]:  # which field differs, named
                    topics.add(f"{x.topic} (serialization format {formats[0]!r}, the file's {formats[1]!r})")
                else:
                    topics.add(f"{x.topic} (QoS profiles)")
    return sorted(topics)


class TolerantAnyReader(AnyReader):
    """`AnyReader` whose `open()` sets aside connections with unparsable definitions.

    `unparsable` holds (connection, reason) for them after `open()`. The
    connections kept have their embedded hash checked against the digest the
    bag recorded, as AnyReader does. Messages are never deserialised through
    this reader (SensorBox decodes raw bytes itself), so `typestore` is
    SensorBox's own.
    """

    unparsable: list[tuple[Connection, str]]
    qos_mismatches: list[str]
    """Topics of a rosbag2 folder whose metadata.yaml QoS or serialization format differs from their storage
    file's, each with what differs (read anyway)."""
    message_compressed: set[int]
    """`id` of each rosbag2 storage (a connection's `owner`) whose messages are zstd-compressed one by
    one (compression_mode 'message'): this reader yields them compressed, and `BagSet` decompresses
    each itself, so that one corrupt message is that message's failure, not the end of the read."""

    def _open(self) -> None:
        assert self.stack is not None
        for reader in self.readers:
            self.stack.enter_context(reader)
        self.qos_mismatches = []
        for reader in self.readers:
            self.qos_mismatches += _match_folder_qos(getattr(reader, "storage", None))
        self.message_compressed = set()
        for reader in self.readers:
            storage = getattr(reader, "storage", None)  # a rosbag2 reader's; a ROS 1 reader has none
            metadata = getattr(storage, "metadata", None)
            if getattr(metadata, "compression_mode", None) == "message":
                storage.metadata = metadata._replace(compression_mode=None)  # type: ignore[union-attr]
                self.message_compressed.add(id(storage))
        ros_version: RosVersion = 2 if self.is2 else 1
        kept: list[Connection] = []
        self.unparsable = []
        for conn in (c for reader in self.readers for c in reader.connections):
            problem = definition_problem(conn.msgtype, conn.msgdef, ros_version)
            if problem is not None:
                self.unparsable.append((conn, problem))
                continue
            if conn.digest and conn.msgdef.format != MessageDefinitionFormat.NONE:
                have = _embedded_hash(conn.msgtype, conn.msgdef, ros_version)
                if have != conn.digest:
                    msg = f"Message type {conn.msgtype!r} hash mismatch {have} != {conn.digest}"
                    raise AnyReaderError(msg)
            kept.append(conn)
        self.connections = kept
        self.typestore = typestore(ros_version)
