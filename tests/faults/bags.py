"""Fixture bags with one fault each, rewritten from `indoor_static_mcap` message by message."""

from __future__ import annotations

import shutil
import struct
from collections.abc import Callable, Collection
from pathlib import Path
from typing import Any

import numpy as np

from ingest.bags.decode import decode_compressed_image
from ingest.bags.livox_msg import decode_custom_msg, encode_custom_msg
from ingest.bags.reader import open_bags
from ingest.bags.rostypes import IMAGE_TYPE, typestore
from sensorbox.live.bagwriter import BagWriter
from sensorbox.messages import image_msg
from sensorbox.sim.truth import truth_dir
from tests.paths import FIXTURES_DIR

INDOOR = FIXTURES_DIR / "indoor_static_mcap"
UPPER = "/zed_upper/zed_node/rgb/color/rect/image"  # the rig's topic; the fixture has `/compressed`
LOWER = "/zed_lower/zed_node/rgb/color/rect/image/compressed"
LIDAR_TOP = "/livox/lidar_192_168_1_12"
LIDAR_BOTTOM = "/livox/lidar_192_168_1_13"

Keep = Callable[[str, int, bytes], list[tuple[str, bytes]]]
"""keep(topic, index on its topic, raw) -> the (topic, raw) messages to write in its place."""


def rewrite(
    dst: Path, keep: Keep, src: Path = INDOOR, declare: dict[str, str] | None = None,
    flush_after: Collection[str] = (),
) -> tuple[Path, Path]:  # fmt: skip
    """The fixture rewritten through `keep` into the mcap `dst`, its truth beside it; (bag, rig).

    `declare` (topic -> type) adds topics to the bag even when no message is written on them, and sets the
    type of a topic `keep` writes to.
    A message on a topic of `flush_after` closes its mcap chunk (it is the chunk's last).
    """
    types: dict[str, str] = dict(declare or {})
    with open_bags([src]) as bags:
        messages = [(m.topic, m.msgtype, m.log_ns, bytes(m.raw)) for m in bags.messages()]
    seen: dict[str, int] = {}
    out_msgs = []
    for topic, msgtype, log_ns, raw in messages:
        k = seen[topic] = seen.get(topic, -1) + 1
        for new_topic, new_raw in keep(topic, k, raw):
            declared = (declare or {}).get(new_topic)
            types[new_topic] = declared or (IMAGE_TYPE if new_topic == UPPER else msgtype)
            out_msgs.append((new_topic, log_ns, new_raw))
    with BagWriter(dst, "mcap") as out:
        for topic, msgtype in types.items():
            out.add(topic, msgtype)
        for topic, log_ns, raw in out_msgs:
            out.write(topic, log_ns, raw)
            if topic in flush_after:
                out.flush()
    shutil.copytree(truth_dir(src), truth_dir(dst))
    return dst, truth_dir(dst) / "rig.yaml"


def frames_swapped(src: Path, topic: str, first: int, second: int) -> Keep:
    """The `first` and `second` messages of `topic` in `src` with each other's image, each under its own
    stamp (a raw or compressed image's header stamp is its bytes 4..12)."""
    with open_bags([src]) as bags:
        raws = [bytes(m.raw) for m in bags.messages() if m.topic == topic]

    def keep(on: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        if on != topic or k not in (first, second):
            return [(on, raw)]
        other = raws[second if k == first else first]
        return [(on, raw[:12] + other[12:])]

    return keep


def raw_image(compressed: bytes, short_step: bool = False) -> bytes:
    """The fixture's CompressedImage as a raw bgra8 `Image`; `short_step`: a row `step` 4 bytes short."""
    frame = decode_compressed_image(compressed)
    raw = image_msg(frame.stamp_ns, frame.frame_id, np.ascontiguousarray(frame.image))
    if not short_step:
        return raw
    ts = typestore(2)
    msg: Any = ts.deserialize_cdr(raw, IMAGE_TYPE)
    h, w = int(msg.height), int(msg.width)
    step = 4 * w - 4
    bad = ts.types[IMAGE_TYPE](
        header=msg.header, height=h, width=w, encoding=msg.encoding, is_bigendian=0, step=step,
        data=np.asarray(msg.data)[: h * step],
    )  # fmt: skip
    return bytes(ts.serialize_cdr(bad, IMAGE_TYPE))


def cut_compressed(raw: bytes) -> bytes:
    """A CompressedImage whose data sequence claims 100 bytes more than the message holds."""
    return raw[:-100]


def wrong_point_num(raw: bytes) -> bytes:
    """A CustomMsg whose `point_num` says 7 points more than its points array holds."""
    msg = decode_custom_msg(raw)
    good = encode_custom_msg(msg.stamp_ns, msg.frame_id, msg.timebase_ns, msg.points, msg.lidar_id)
    pos = len(good) - (len(msg.points) * 20 - 1) - 20  # the <QIB3xI> block before the points (CDR)
    timebase, n, lidar_id, count = struct.unpack_from("<QIB3xI", good, pos)
    assert (timebase, count) == (msg.timebase_ns, len(msg.points))
    return good[:pos] + struct.pack("<QIB3xI", timebase, n + 7, lidar_id, count) + good[pos + 20 :]
