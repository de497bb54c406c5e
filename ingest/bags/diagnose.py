"""Why a path is not a bag SensorBox can read, before and after rosbags tried: what the path is
(`ros_version`, special files), what its metadata or data holds that rosbags would fail on later
(`check_metadata`, `check_bare_db3`), and one line for rosbags' own failure (`explain`)."""

from __future__ import annotations

import contextlib
import sqlite3
import stat
import struct
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import yaml

from calibration.files import file_kind
from calibration.opencv_yaml import BoundedSafeLoader, yaml_error_line
from ingest.bags.decode import RosVersion
from ingest.bags.mcap_records import MCAP_MAGIC
from ingest.errors import BagError

SALVAGE_HINT = "rerun with --salvage to read its complete chunks"


def mcap_is_complete(path: Path) -> bool:
    """True when an MCAP file ends with the closing magic (it was closed properly)."""
    try:
        with path.open("rb") as f:
            if f.seek(0, 2) < 2 * len(MCAP_MAGIC):
                return False
            f.seek(-len(MCAP_MAGIC), 2)
            return f.read() == MCAP_MAGIC
    except OSError:
        return False


SUMMARY_OPCODES = {0x03, 0x04, 0x08, 0x0A, 0x0B, 0x0D, 0x0E}
"""What an MCAP summary section may start with: schema, channel, chunk index, attachment index,
statistics, metadata index, or summary offset records."""


def mcap_footer_problem(path: Path) -> str | None:
    """What is wrong with a complete MCAP file's footer, whose summary_start and summary_offset_start
    must each be 0 or the offset of a summary record (`SUMMARY_OPCODES`, a summary offset record), else
    None. A wrong offset makes the reader seek into the data and allocate what it reads there."""
    try:
        with path.open("rb") as f:
            size = f.seek(0, 2)
            if size < 2 * len(MCAP_MAGIC) + 29:
                return None
            f.seek(size - len(MCAP_MAGIC) - 29)
            footer = f.read(29)
            if footer[0] != 0x02:
                return None
            starts = struct.unpack_from("<QQ", footer, 9)
            for name, start, allowed in zip(
                ("summary_start", "summary_offset_start"), starts, (SUMMARY_OPCODES, {0x0E}), strict=True
            ):
                if start == 0:
                    continue
                opcode = b""
                if len(MCAP_MAGIC) <= start < size - len(MCAP_MAGIC) - 29:
                    f.seek(start)
                    opcode = f.read(1)
                if not opcode or opcode[0] not in allowed:
                    return (
                        f"its footer's {name} {start} points at no summary record (the file is {size} "
                        "bytes): its index is damaged"
                    )
    except OSError:
        return None
    return None


def refuse_special(path: Path) -> None:
    """Refuse a bag (or a rosbag2 folder's metadata.yaml or data file) that is no regular file.

    A FIFO named `x.mcap` made the reader wait forever; a link to /dev/zero
    would be read without end. Symlinks are followed.
    """
    items = [path / "metadata.yaml", *path.glob("*.mcap"), *path.glob("*.db3")] if path.is_dir() else [path]
    for item in items:
        try:
            mode = item.stat().st_mode
        except FileNotFoundError:
            continue  # a folder without metadata.yaml: said later, by what reads it
        if not stat.S_ISREG(mode):
            raise BagError(f"{item}: is {file_kind(mode)}, not a bag file or rosbag2 folder")


def bag_ros_version(paths: Sequence[Path]) -> RosVersion:
    """1 for `.bag` files, 2 for `.mcap`/`.db3` files and directories; mixing is an error."""
    kinds: set[RosVersion] = set()
    for path in paths:
        if not path.exists():
            raise BagError(f"{path}: no such file or directory")
        if path.name.endswith(".bag.active"):
            raise BagError(
                f"{path}: unfinished ROS 1 recording (.bag.active, the recorder was interrupted);"
                " run `rosbag reindex` on it and rename it to .bag"
            )
        refuse_special(path)
        if path.is_dir() or path.suffix in (".mcap", ".db3"):
            kinds.add(2)
        elif path.suffix == ".bag":
            check_ros1_magic(path)
            kinds.add(1)
        else:
            raise BagError(f"{path}: expected a ROS 1 .bag, a ROS 2 .mcap/.db3 file or a rosbag2 directory")
    if len(kinds) > 1:
        raise BagError(f"cannot read ROS 1 and ROS 2 bags together: {', '.join(map(str, paths))}")
    return kinds.pop() if kinds else 2


_MAGIC = {b"SQLite format 3\x00": "a SQLite database (a rosbag2 .db3)", b"#ROSBAG V2.0": "a ROS 1 bag (.bag)"}

ROS1_MAGIC = b"#ROSBAG V2.0\n"


def check_ros1_magic(path: Path) -> None:
    """Refuse a `.bag` file whose first 13 bytes are not the ROS 1 bag header line "#ROSBAG V2.0".

    rosbags reads the whole file before it looks at them: a 1 GB file of
    zeros took 28 s and 2.2 GB of memory to end in "File magic is invalid",
    a 5 GB one ran out of memory. One `BagError` line naming the file and
    what it starts like, from its first 16 bytes only.
    """
    try:
        with path.open("rb") as f:
            head = f.read(16)
    except OSError as err:
        raise BagError(f"{path}: cannot read: {err.strerror or err}") from err
    if head.startswith(ROS1_MAGIC):
        return
    if head.startswith(MCAP_MAGIC):
        raise BagError(
            f"{path}: not a ROS 1 bag: it starts like an MCAP file (renamed?); give it the .mcap suffix"
        )
    if (other := next((what for magic, what in _MAGIC.items() if head.startswith(magic)), None)) is not None:
        raise BagError(f"{path}: not a ROS 1 bag: it starts like {other} (renamed?); give it that suffix")
    what = "is empty" if not head else f"starts with {head[:13]!r}"
    raise BagError(f"{path}: not a ROS 1 bag: a .bag file starts with '#ROSBAG V2.0', this one {what}")


def other_format(path: Path) -> str | None:
    """What a file named .mcap is when its first bytes are another bag format's, else None."""
    try:
        with path.open("rb") as f:
            head = f.read(16)
    except OSError:
        return None
    if head.startswith(MCAP_MAGIC):
        return None
    return next((what for magic, what in _MAGIC.items() if head.startswith(magic)), None)


def _size(path: Path) -> int | None:
    try:
        return path.stat().st_size
    except OSError:
        return None


def explain(path: Path, err: BaseException) -> str:
    """A one-line diagnosis of why rosbags could not open `path`."""
    text = str(err)
    if path.suffix in (".mcap", ".db3") and path.is_file() and _size(path) == 0:
        return f"{path}: the file is empty (0 bytes): nothing was recorded into it, or it was cut to nothing"
    if path.suffix == ".mcap" and path.is_file() and (other := other_format(path)) is not None:
        return f"{path}: not an MCAP file: it starts like {other} (renamed?); give it that suffix"
    if path.suffix == ".mcap" and path.is_file() and not mcap_is_complete(path):
        return f"{path}: MCAP file is truncated or still being written (no closing magic); {SALVAGE_HINT}"
    if path.suffix == ".mcap" and path.is_file() and (footer := mcap_footer_problem(path)) is not None:
        return f"{path}: MCAP file: {footer}; {SALVAGE_HINT}"
    if path.suffix == ".mcap" and isinstance(err, KeyError) and (foreign := odd_mcap_encodings(path)):
        topic, encoding = foreign[0]
        return (
            f"{path}: {topic}: its schema is stored with encoding {encoding!r}, which rosbags cannot open "
            "(it reads ros2msg and ros2idl); leave the topic out of the recording (ros2 bag convert, "
            "exclude_topics) or record it in a bag of its own"
        )
    if (
        path.suffix == ".mcap"
        and isinstance(err, (TypeError, KeyError, AttributeError))
        and (qos := unreadable_qos(path))
    ):
        topic, text = qos
        shown = " ".join(text.split())
        return (
            f"{path}: {topic}: its channel's offered_qos_profiles metadata is not a list of ROS 2 QoS "
            "profiles "
            f"({shown[:80]!r}{'...' if len(shown) > 80 else ''}), which rosbags cannot read; rewrite the bag "
            "without it (ros2 bag convert) or drop the channel's metadata"
        )
    if path.is_dir():
        mcaps = sorted(path.glob("*.mcap"))
        if not (path / "metadata.yaml").exists():
            if mcaps:
                return (
                    f"{path}: rosbag2 directory has no metadata.yaml (the recording was interrupted"
                    f" or is still running); {SALVAGE_HINT}"
                )
            return f"{path}: not a rosbag2 directory (no metadata.yaml)"
        meta: Any = None
        try:
            meta = yaml.load((path / "metadata.yaml").read_bytes(), Loader=BoundedSafeLoader)
        except yaml.YAMLError as bad:
            return f"rosbag2 {yaml_error_line(path / 'metadata.yaml', bad)}"
        except OSError:
            pass  # rosbags' own error below names it
        if (other := _storage_mismatch(meta)) is not None:
            return f"{path / 'metadata.yaml'}: {other}"
        if isinstance(err, KeyError) and (odd := odd_definition_encodings(path)):
            name, msgtype, encoding = odd[0]
            return (
                f"{path}: {name}: the definition of {msgtype} is stored with encoding {encoding!r} (rosbag2 "
                "writes that for a type it could not find while recording), which rosbags cannot open; "
                "record with that type's package sourced, or leave its topic out (ros2 bag convert, "
                "exclude_topics)"
            )
        cut = [m.name for m in mcaps if not mcap_is_complete(m)]
        if cut:
            return f"{path}: {', '.join(cut)} truncated or still being written; {SALVAGE_HINT}"
        for m in mcaps:
            if (footer := mcap_footer_problem(m)) is not None:
                return f"{m}: MCAP file: {footer}; {SALVAGE_HINT}"
    if "not indexed" in text:
        return (
            f"{path}: ROS 1 bag is not indexed (recording was interrupted); run `rosbag reindex` on it first"
        )
    if "index looks damaged" in text:
        return (
            f"{path}: ROS 1 bag is truncated or its index is damaged ({text});"
            " run `rosbag reindex` on it first"
        )
    return f"{path}: cannot read bag: {type(err).__name__}: {' '.join(text.split())}"


_STORAGE_SUFFIX = {"mcap": ".mcap", "sqlite3": ".db3"}


def _storage_mismatch(meta: Any) -> str | None:
    """What disagrees when metadata.yaml's storage_identifier names another format than its files'
    suffix (a metadata.yaml copied from another recording), else None."""
    info = meta.get("rosbag2_bagfile_information") if isinstance(meta, dict) else None
    if not isinstance(info, dict):
        return None
    storage, files = info.get("storage_identifier"), info.get("relative_file_paths")
    suffix = _STORAGE_SUFFIX.get(storage) if isinstance(storage, str) else None
    if suffix is None or not isinstance(files, list):
        return None
    odd = [
        f
        for f in files
        if isinstance(f, str) and Path(f).suffix in _STORAGE_SUFFIX.values() and Path(f).suffix != suffix
    ]
    if not odd:
        return None
    return (
        f"storage_identifier {storage!r} (files {suffix}) but it lists {odd[0]}; expected the storage of its "
        "files (a metadata.yaml of another recording?)"
    )


def odd_mcap_encodings(path: Path) -> list[tuple[str, str]]:
    """(topic, schema encoding) of each channel of an .mcap whose schema rosbags cannot read (not
    ros2msg/ros2idl: a JSON or protobuf topic beside the ROS ones); [] when the summary cannot be read."""
    from mcap.reader import make_reader

    try:
        with path.open("rb") as f:
            summary = make_reader(f).get_summary()
    except Exception:  # any failure: rosbags' own error stands
        return []
    if summary is None:
        return []
    odd = {
        sid: sc.encoding for sid, sc in summary.schemas.items() if sc.encoding not in ("ros2msg", "ros2idl")
    }
    return [(ch.topic, odd[ch.schema_id]) for ch in summary.channels.values() if ch.schema_id in odd]


def unreadable_qos(path: Path) -> tuple[str, str] | None:
    """(topic, its offered_qos_profiles metadata) of the first channel of an .mcap whose QoS profiles
    rosbags cannot parse (a recorder that wrote something else there); None when every one parses or the
    summary cannot be read."""
    from mcap.reader import make_reader
    from rosbags.rosbag2.metadata import parse_qos

    try:
        with path.open("rb") as f:
            summary = make_reader(f).get_summary()
    except Exception:  # any failure: rosbags' own error stands
        return None
    for ch in summary.channels.values() if summary is not None else []:
        text = ch.metadata.get("offered_qos_profiles", "")
        if not text:
            continue
        try:
            parse_qos(yaml.load(text, Loader=BoundedSafeLoader))
        except Exception:  # rosbags' parser fails on any odd shape: that is what we look for
            return ch.topic, text
    return None


def odd_definition_encodings(path: Path) -> list[tuple[str, str, str]]:
    """(file, type, encoding) of each .db3 message definition rosbags cannot read (not ros2msg/ros2idl)."""
    found: list[tuple[str, str, str]] = []
    for db3 in sorted(path.glob("*.db3")):
        try:
            with contextlib.closing(sqlite3.connect(f"file:{db3}?mode=ro", uri=True)) as db:
                rows = db.execute(
                    "SELECT topic_type, encoding FROM message_definitions "
                    "WHERE encoding NOT IN ('ros2msg', 'ros2idl')"
                ).fetchall()
        except sqlite3.Error:  # no such table (an older rosbag2), not a database: rosbags' own error stands
            continue
        found += [(db3.name, str(t), str(e)) for t, e in rows]
    return found


_METADATA_INTEGERS = (
    "message_count", "duration.nanoseconds", "starting_time.nanoseconds_since_epoch",
    "files[].message_count", "files[].duration.nanoseconds", "files[].starting_time.nanoseconds_since_epoch",
    "topics_with_message_count[].message_count",
)  # fmt: skip
"""Keys of rosbag2's metadata.yaml (under `rosbag2_bagfile_information`) that hold integers."""


def _metadata_values(node: Any, key: str, where: str) -> Iterator[tuple[str, Any]]:
    """(dotted name with list indexes, value) of each value at `key` ("a.b", "list[].c") below `node`."""
    head, _, rest = key.partition(".")
    if head.endswith("[]"):
        items = node.get(head[:-2]) if isinstance(node, dict) else None
        for i, item in enumerate(items if isinstance(items, list) else []):
            yield from _metadata_values(item, rest, f"{where}.{head[:-2]}[{i}]")
    elif isinstance(node, dict) and head in node:
        if rest:
            yield from _metadata_values(node[head], rest, f"{where}.{head}")
        else:
            yield f"{where}.{head}", node[head]


def check_metadata(path: Path) -> None:
    """`BagError` naming the key and value when a rosbag2 folder's metadata.yaml holds a non-integer
    count, duration or start time (rosbags would fail later with a bare TypeError). Keys that are
    missing, and a file that is missing or not YAML, are left to rosbags' own errors (`explain`)."""
    meta = path / "metadata.yaml"
    try:
        doc = yaml.load(meta.read_bytes(), Loader=BoundedSafeLoader)
    except (OSError, yaml.YAMLError):
        return
    info = doc.get("rosbag2_bagfile_information") if isinstance(doc, dict) else None
    if not isinstance(info, dict):
        return
    for key in _METADATA_INTEGERS:
        for name, value in _metadata_values(info, key, "rosbag2_bagfile_information"):
            if not isinstance(value, int) or isinstance(value, bool):
                raise BagError(f"{meta}: {name} is {value!r}, expected an integer")


ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"


def check_bare_db3(path: Path) -> None:
    """`BagError` when the .db3 file `path`, given without its rosbag2 folder, holds zstd-compressed
    messages: only the folder's metadata.yaml says so (compression_mode 'message'), and read without
    it every message would fail to decode as CDR."""
    try:
        with contextlib.closing(sqlite3.connect(f"file:{path}?mode=ro", uri=True)) as db:
            row = db.execute("SELECT data FROM messages LIMIT 1").fetchone()
    except sqlite3.Error:  # not a database, no messages table: rosbags' own error names it
        return
    if row is not None and bytes(row[0][:4]) == ZSTD_MAGIC:
        folder = path.parent
        known = (folder / "metadata.yaml").is_file()
        where = f"pass the folder {folder}" if known else "pass its rosbag2 folder"
        raise BagError(
            f"{path}: its messages are zstd-compressed, which only the rosbag2 folder's metadata.yaml "
            f"declares (compression_mode 'message'); {where}, not the .db3 file"
        )
