"""The PNG writer against libpng (OpenCV's decoder) and the PNG chunk rules."""

import struct
import zlib

import cv2
import numpy as np
import pytest

from ingest.dataset.png import LEVELS, encode_png, filtered_rows
from ingest.errors import PngError


def _decode(data: bytes) -> np.ndarray:
    out = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert out is not None, "libpng refused the file"
    return out


def _chunks(data: bytes) -> list[tuple[bytes, bytes]]:
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, out = 8, []
    while pos < len(data):
        (n,) = struct.unpack(">I", data[pos : pos + 4])
        kind, body = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + n]
        (crc,) = struct.unpack(">I", data[pos + 8 + n : pos + 12 + n])
        assert crc == zlib.crc32(kind + body), kind
        out.append((kind, body))
        pos += 12 + n
    return out


RNG = np.random.default_rng(7)
IMAGES: dict[str, np.ndarray] = {
    "bgr": RNG.integers(0, 256, (37, 53, 3), dtype=np.uint8),
    "grey8": RNG.integers(0, 256, (20, 31), dtype=np.uint8),
    "u16": np.array([[0, 1, 255, 256], [257, 4095, 65534, 65535]], np.uint16),
    "u16_sparse": np.where(RNG.random((64, 96)) < 0.05, RNG.integers(1, 65536, (64, 96)), 0).astype(
        np.uint16
    ),
    "one_pixel": np.array([[[1, 2, 3]]], np.uint8),
    "one_column": RNG.integers(0, 256, (9, 1, 3), dtype=np.uint8),
}


@pytest.mark.parametrize("name", sorted(IMAGES))
@pytest.mark.parametrize("level", LEVELS)
def test_libpng_reads_back_every_pixel(name, level):
    image = IMAGES[name]
    assert np.array_equal(_decode(encode_png(image, level)), image)


@pytest.mark.parametrize("row_filter", ["none", "sub"])
def test_both_row_filters_decode_to_the_same_pixels(row_filter):
    for image in IMAGES.values():
        assert np.array_equal(_decode(encode_png(image, 1, row_filter)), image)


@pytest.mark.parametrize("level", LEVELS)
def test_bgra_is_stored_as_the_same_rgb_file_as_its_bgr(level):
    """A bgra8 camera's pixels are written without their alpha: the file of the BGR image, byte for byte."""
    bgr = IMAGES["bgr"]
    bgra = np.concatenate([bgr, RNG.integers(0, 256, (*bgr.shape[:2], 1), dtype=np.uint8)], axis=2)
    data = encode_png(bgra, level)
    assert data == encode_png(bgr, level)
    assert np.array_equal(_decode(data), bgr)


def test_header_chunks_and_rgb_byte_order():
    bgr = np.zeros((2, 3, 3), np.uint8)
    bgr[..., 0] = 10  # blue
    bgr[..., 2] = 200  # red
    chunks = _chunks(encode_png(bgr, 1, "none"))
    assert [k for k, _ in chunks] == [b"IHDR", b"IDAT", b"IEND"]
    assert struct.unpack(">IIBBBBB", chunks[0][1]) == (3, 2, 8, 2, 0, 0, 0)  # width, height, 8-bit RGB
    raw = zlib.decompress(chunks[1][1])
    assert raw == bytes([0, 200, 0, 10] + [200, 0, 10] * 2) * 2  # filter byte 0, then R, G, B per pixel


def test_sub_filter_bytes_and_16_bit_big_endian():
    u16 = np.array([[0x0102, 0x0304]], np.uint16)
    rows = filtered_rows(u16, "sub")
    assert rows.tolist() == [[1, 0x01, 0x02, 0x03 - 0x01, 0x04 - 0x02]]
    wrap = np.array([[200, 10]], np.uint8)
    assert filtered_rows(wrap, "sub").tolist() == [[1, 200, (10 - 200) % 256]]


@pytest.mark.parametrize(
    ("image", "level", "match"),
    [
        (np.zeros((4, 4), np.float32), 1, "dtype float32"),
        (np.zeros((4, 4, 2), np.uint8), 1, r"shape \(4, 4, 2\)"),
        (np.zeros((0, 4), np.uint8), 1, "empty"),
        (np.zeros((4, 4), np.uint8), 9, "level 9"),
    ],
)
def test_bad_input_is_named(image, level, match):
    with pytest.raises(PngError, match=match):
        encode_png(image, level)
