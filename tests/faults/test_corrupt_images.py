"""Issue 49: a JPEG whose data libjpeg finds corrupt is an undecodable message named by bag, topic and time.

Bytes flipped inside a chunk whose CRC was written over them reach the
decoder intact as far as the bag can tell; OpenCV decodes such a JPEG with
grey or smeared blocks and libjpeg's only trace was a bare line on stderr
(`Corrupt JPEG data: premature end of data segment`). Now it stops the run
in one line, or with `--max-bad` is skipped with its sample and counted.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from ingest.bags.decode import decode_compressed_image
from ingest.bags.reader import open_bags
from ingest.bags.rostypes import COMPRESSED_IMAGE_TYPE, IMAGE_TYPE, typestore
from ingest.dataset.layout import IMAGE_DIRS
from ingest.errors import BagError, MessageDecodeError
from ingest.train.run.pipeline import ingest
from ingest.train.run.settings import IngestConfig
from ingest.train.run.stream import UNDECODABLE_IMAGE
from sensorbox.messages import compressed_image_msg
from tests.faults.bags import INDOOR, LOWER, UPPER, rewrite

RAW_LOWER = LOWER.removesuffix("/compressed")
FAST = {"workers": 1, "every": 4, "height_full": 64}


def _flipped(raw: bytes, seed: int, flips: int) -> bytes:
    """The CompressedImage with `flips` bytes of its JPEG data inverted, at places drawn from `seed`."""
    ts = typestore(2)
    msg: Any = ts.deserialize_cdr(raw, COMPRESSED_IMAGE_TYPE)
    data = np.asarray(msg.data, np.uint8).copy()
    for i in np.random.default_rng(seed).integers(1000, len(data) - 10, flips):
        data[i] ^= 0xFF
    bad = ts.types[COMPRESSED_IMAGE_TYPE](header=msg.header, format=msg.format, data=data)
    return bytes(ts.serialize_cdr(bad, COMPRESSED_IMAGE_TYPE))


def _lower(k: int) -> bytes:
    with open_bags([INDOOR]) as bags:
        return next(bytes(m.raw) for j, m in enumerate(bags.messages(topics=[LOWER])) if j == k)


@pytest.mark.parametrize(
    ("seed", "flips", "warning"),
    [
        (4, 5, "Corrupt JPEG data: premature end of data segment"),
        (0, 1, "Corrupt JPEG data: 71 extraneous bytes before marker 0xd9"),
    ],
)
def test_a_corrupt_jpeg_raises_with_libjpegs_words_and_prints_nothing(
    seed: int, flips: int, warning: str, capfd: pytest.CaptureFixture[str]
) -> None:
    raw = _flipped(_lower(16), seed, flips)
    with pytest.raises(MessageDecodeError) as err:
        decode_compressed_image(raw)
    assert str(err.value).endswith(f" bytes): {warning}")
    assert capfd.readouterr().err == ""  # libjpeg's bare line is the error's now
    decode_compressed_image(_lower(16))  # the intact one decodes


def _log_time(bag: Path, topic: str, k: int) -> tuple[int, int]:
    """(seconds, nanoseconds) of the log time of message `k` of `topic` in `bag`."""
    with open_bags([bag]) as bags:
        log_ns = next(m.log_ns for j, m in enumerate(bags.messages(topics=[topic])) if j == k)
    sec, nsec = divmod(log_ns, 1_000_000_000)
    return sec, nsec


def test_a_corrupt_jpeg_in_a_bag_is_named_and_skipped_under_max_bad(tmp_path: Path) -> None:
    def keep(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        return [(topic, _flipped(raw, 4, 5) if topic == LOWER and k == 16 else raw)]

    bag, rig = rewrite(tmp_path / "bag", keep)
    sec, nsec = _log_time(bag, LOWER, 16)
    with pytest.raises(MessageDecodeError) as err:
        ingest([bag], IngestConfig(rig=rig, out=tmp_path / "ds0", **FAST))  # type: ignore[arg-type]
    line = str(err.value)
    assert line.startswith(f"{bag}: {LOWER} at log time {sec}.{nsec:09d} s: CompressedImage (format ")
    assert (
        "Corrupt JPEG data: premature end of data segment (undecodable message 1, more than --max-bad 0"
        in line
    )
    summary = ingest([bag], IngestConfig(rig=rig, out=tmp_path / "ds", max_bad=1, **FAST))  # type: ignore[arg-type]
    assert summary.undecodable == {LOWER: 1}
    assert summary.skipped == {UNDECODABLE_IMAGE: 1}  # frame 16: sample 4
    assert not (tmp_path / "ds" / "meta" / "000004.json").exists()


def test_a_frame_that_shrinks_mid_bag_is_refused_naming_bag_topic_and_time(tmp_path: Path) -> None:
    def keep(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        if topic != LOWER or k != 8:
            return [(topic, raw)]
        frame = decode_compressed_image(raw)
        half = np.asarray(cv2.resize(frame.image, (240, 150), interpolation=cv2.INTER_AREA), np.uint8)
        return [(topic, compressed_image_msg(frame.stamp_ns, frame.frame_id, half))]

    bag, rig = rewrite(tmp_path / "bag", keep)
    sec, nsec = _log_time(bag, LOWER, 8)
    with pytest.raises(BagError) as err:
        ingest([bag], IngestConfig(rig=rig, out=tmp_path / "ds", **FAST))  # type: ignore[arg-type]
    assert str(err.value) == (
        f"{bag}: {LOWER} at log time {sec}.{nsec:09d} s: the image is 240x150 but the rig's cam1 is 480x300 "
        "(the wrong rig file for this bag, or a camera whose resolution changed during the recording)"
    )


def _mono(raw: bytes, encoding: str) -> bytes:
    """The fixture's CompressedImage as a raw mono8 or mono16 `Image` of its grey."""
    frame = decode_compressed_image(raw)
    grey = cv2.cvtColor(frame.image, cv2.COLOR_BGR2GRAY)
    pixels = grey if encoding == "mono8" else grey.astype(np.uint16) * 257  # the grey in both bytes
    h, w = grey.shape
    ts = typestore(2)
    msg: Any = ts.deserialize_cdr(raw, COMPRESSED_IMAGE_TYPE)
    image = ts.types[IMAGE_TYPE](
        header=msg.header, height=h, width=w, encoding=encoding, is_bigendian=0,
        step=w * pixels.itemsize, data=np.frombuffer(pixels.tobytes(), np.uint8),
    )  # fmt: skip
    return bytes(ts.serialize_cdr(image, IMAGE_TYPE))


def _read(png: Path) -> Any:
    image = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
    assert image is not None, png
    return image


def test_mono8_and_mono16_cameras_give_grey_rgb_pngs(tmp_path: Path) -> None:
    greys: dict[str, list[Any]] = {"upper": [], "lower": []}

    def keep(topic: str, k: int, raw: bytes) -> list[tuple[str, bytes]]:
        if topic.startswith("/zed_upper"):
            greys["upper"].append(cv2.cvtColor(decode_compressed_image(raw).image, cv2.COLOR_BGR2GRAY))
            return [(UPPER, _mono(raw, "mono8"))]
        if topic == LOWER:
            greys["lower"].append(cv2.cvtColor(decode_compressed_image(raw).image, cv2.COLOR_BGR2GRAY))
            return [(RAW_LOWER, _mono(raw, "mono16"))]
        return [(topic, raw)]

    bag, rig = rewrite(tmp_path / "bag", keep, declare={RAW_LOWER: IMAGE_TYPE})
    out = tmp_path / "ds"
    summary = ingest([bag], IngestConfig(rig=rig, out=out, **FAST))  # type: ignore[arg-type]
    assert summary.written == 6
    for folder in IMAGE_DIRS:
        for png in sorted((out / folder).glob("*.png")):
            image = _read(png)
            assert image.dtype == np.uint8 and image.shape[2] == 3, (png, image.shape, image.dtype)
            assert (image[..., 0] == image[..., 1]).all() and (image[..., 1] == image[..., 2]).all()
    for side, folder in (("upper", "left_fisheye"), ("lower", "right_fisheye")):
        written = _read(out / folder / "000001.png")
        assert np.array_equal(written[..., 0], greys[side][4])  # frame 4 is sample 1; mono16's high byte
