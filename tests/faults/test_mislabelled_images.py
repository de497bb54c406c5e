"""Issue 49 (F18): raw image data of another encoding than its `encoding` says is an undecodable message.

bgra8 data (4 bytes a pixel, step 4 x width) labelled rgb8 passed as an rgb8
image whose rows carry a third of padding: every pixel read from the wrong
bytes, written into the dataset without a word. It must be skipped under
--max-bad and counted by topic like every undecodable message, naming the
topic and the message's log time, and refused beyond --max-bad.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from ingest.bags.decode import decode_image
from ingest.bags.reader import open_bags
from ingest.bags.rostypes import IMAGE_TYPE, typestore
from ingest.errors import MessageDecodeError
from ingest.train.run.pipeline import ingest
from ingest.train.run.settings import IngestConfig
from sensorbox.messages import image_msg
from tests.faults.bags import UPPER, raw_image, rewrite
from tests.faults.cli import sensorbox

FAST = {"workers": 1, "every": 3, "height_full": 64, "gt": "sparse"}
RELABELLED = (3, 9)  # upper frames of samples 1 and 3


def raw_image_header() -> bytes:
    """A small bgr8 `Image` (for its header)."""
    return image_msg(1, "cam0", np.zeros((2, 6, 3), np.uint8))


def _labelled(raw: bytes, encoding: str) -> bytes:
    ts = typestore(2)
    msg: Any = ts.deserialize_cdr(raw, IMAGE_TYPE)
    msg.encoding = encoding
    return bytes(ts.serialize_cdr(msg, IMAGE_TYPE))


@pytest.mark.parametrize(
    ("channels", "label", "line"),
    [
        (4, "rgb8", "Image rgb8 80x2: step 320 holds 4 bytes a pixel but rgb8 has 3"),
        (4, "mono8", "Image mono8 80x2: step 320 holds 4 bytes a pixel but mono8 has 1"),
        (3, "mono8", "Image mono8 80x2: step 240 holds 3 bytes a pixel but mono8 has 1"),
    ],
)
def test_image_data_of_more_bytes_a_pixel_than_its_encoding_is_undecodable(
    channels: int, label: str, line: str
) -> None:
    ts = typestore(2)
    data = np.arange(2 * 80 * channels, dtype=np.uint8)  # 2 rows of 80 pixels of `channels` bytes, packed
    small: Any = ts.deserialize_cdr(raw_image_header(), IMAGE_TYPE)
    msg = ts.types[IMAGE_TYPE](
        header=small.header, height=2, width=80, encoding=label, is_bigendian=0, step=80 * channels, data=data
    )
    raw = bytes(ts.serialize_cdr(msg, IMAGE_TYPE))
    with pytest.raises(MessageDecodeError) as err:
        decode_image(raw, 2)
    assert str(err.value) == (
        f"{line}; data of another encoding (bgra8 labelled rgb8?) would be read as wrong pixels"
    )


def test_bgra8_frames_labelled_rgb8_are_skipped_counted_and_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    def keep(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        if not topic.startswith("/zed_upper"):
            return [(topic, raw)]
        frame = raw_image(raw)
        return [(UPPER, _labelled(frame, "rgb8") if k in RELABELLED else frame)]

    bag, rig = rewrite(tmp_path / "bag", keep)
    with open_bags([bag]) as bags:
        log_ns = [m.log_ns for m in bags.messages(topics=[UPPER])]
    why = (
        "Image rgb8 480x300: step 1920 holds 4 bytes a pixel but rgb8 has 3; data of another encoding "
        "(bgra8 labelled rgb8?) would be read as wrong pixels"
    )
    at = [
        f"{bag}: {UPPER} at log time {log_ns[k] // 10**9}.{log_ns[k] % 10**9:09d} s: {why}"
        for k in RELABELLED
    ]
    summary = ingest([bag], IngestConfig(rig=rig, out=tmp_path / "ds", max_bad=5, **FAST))  # type: ignore[arg-type]
    assert (summary.written, summary.undecodable) == (5, {UPPER: 2})
    assert summary.skipped == {"undecodable image (--max-bad)": 2}
    source = yaml.safe_load((tmp_path / "ds" / "dataset.yaml").read_text())["sources"][0]
    assert source["undecodable_messages"] == {UPPER: 2}
    assert sorted(p.stem for p in (tmp_path / "ds" / "left_fisheye").glob("*.png")) == [
        "000000", "000002", "000004", "000005", "000006"
    ]  # fmt: skip

    args = ["ingest", str(bag), "--rig", str(rig), "--out", str(tmp_path / "cli"), "--workers", "1"]
    code, _, err = sensorbox(capsys, *args, "--every", "3", "--height-full", "64", "--no-preview")
    assert (code, err) == (
        2, [f"error: {at[0]} (undecodable message 1, more than --max-bad 0; --max-bad N skips and counts up to N)"]
    )  # fmt: skip
    code, _, err = sensorbox(capsys, *args[:-4], "--out", str(tmp_path / "cli2"), "--workers", "1",
                             "--every", "3", "--height-full", "64", "--no-preview", "--max-bad", "2")  # fmt: skip
    assert code == 0
    assert [e for e in err if "undecodable" in e] == [
        f"warning: skipped undecodable message {i}/2: {line}" for i, line in enumerate(at, 1)
    ]
