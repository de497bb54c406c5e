"""The pixels of a `sensor_msgs/Image`: the encodings SensorBox reads, the (H, W, C) view of its data
(honouring `step` and byte order, refusing data of another encoding), and the conversion to the BGR or
mono image the rest of SensorBox takes."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from ingest.errors import MessageDecodeError

Array = np.ndarray[Any, np.dtype[Any]]

_BAYER_CODES: dict[str, int] = {
    # ROS names the pattern from the top-left pixel; OpenCV's classic names are
    # shifted by one (cv_bridge's mapping): rggb -> BayerBG, etc.
    "rggb": cv2.COLOR_BayerBG2BGR,
    "bggr": cv2.COLOR_BayerRG2BGR,
    "gbrg": cv2.COLOR_BayerGR2BGR,
    "grbg": cv2.COLOR_BayerGB2BGR,
}

_COLOUR_CODES: dict[str, int] = {
    "rgb8": cv2.COLOR_RGB2BGR,
    "bgra8": cv2.COLOR_BGRA2BGR,
    "rgba8": cv2.COLOR_RGBA2BGR,
}

IMAGE_ENCODINGS: dict[str, tuple[int, str]] = {
    "bgr8": (3, "u1"),
    "rgb8": (3, "u1"),
    "bgra8": (4, "u1"),
    "rgba8": (4, "u1"),
    "mono8": (1, "u1"),
    "mono16": (1, "u2"),
    **{f"bayer_{p}8": (1, "u1") for p in _BAYER_CODES},
    **{f"bayer_{p}16": (1, "u2") for p in _BAYER_CODES},
}
"""Supported `sensor_msgs/Image` encodings -> (channels, numpy base type)."""


ROW_ALIGN_BYTES = 64
"""Row padding (`step` beyond a row's pixels) aligns rows to at most this many bytes (SIMD, DMA). Padding
of this much and of a byte a pixel or more is no alignment: data of an encoding with more bytes a pixel
(bgra8 data labelled rgb8 reads every pixel from the wrong bytes)."""


def image_pixels(msg: Any) -> Array:
    """The image data as an (H, W, C) view honouring `step` and byte order."""
    encoding = str(msg.encoding)
    if encoding not in IMAGE_ENCODINGS:
        raise MessageDecodeError(
            f"Image encoding {encoding!r} is not supported; expected one of {sorted(IMAGE_ENCODINGS)}"
        )
    channels, base = IMAGE_ENCODINGS[encoding]
    dtype = np.dtype((">" if msg.is_bigendian else "<") + base)
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    if height <= 0 or width <= 0:
        raise MessageDecodeError(f"Image {encoding} is empty ({width}x{height})")
    row_bytes = width * channels * dtype.itemsize
    if step < row_bytes:
        raise MessageDecodeError(
            f"Image {encoding} {width}x{height}: step {step} < {row_bytes} bytes per row"
        )
    pixel_bytes = channels * dtype.itemsize
    if step - row_bytes >= max(width, ROW_ALIGN_BYTES):  # padding aligns rows: it adds no byte a pixel
        raise MessageDecodeError(
            f"Image {encoding} {width}x{height}: step {step} holds {step / width:g} bytes a pixel but "
            f"{encoding} has {pixel_bytes}; data of another encoding (bgra8 labelled rgb8?) would be "
            "read as wrong pixels"
        )
    need = (height - 1) * step + row_bytes  # the last row's padding may be left out
    if not need <= msg.data.size <= height * step:
        expected = f"{need}" if need == height * step else f"{need}..{height * step}"
        raise MessageDecodeError(
            f"Image {encoding} {width}x{height} step {step} needs {expected} data bytes, has {msg.data.size}"
        )
    return np.ndarray(
        (height, width, channels),
        dtype,
        buffer=msg.data,
        strides=(step, channels * dtype.itemsize, dtype.itemsize),
    )


def to_bgr(pixels: Array, encoding: str) -> Array:
    """Convert an (H, W, C) view in `encoding` to BGR uint8 HxWx3 or mono HxW."""
    out: Array
    if encoding == "bgr8":
        out = pixels
    elif encoding in _COLOUR_CODES:  # cv2 reads row-padded views directly, ~20x faster than numpy
        out = cv2.cvtColor(pixels, _COLOUR_CODES[encoding])
    elif encoding.startswith("mono"):
        out = pixels[:, :, 0]
    else:  # bayer_<pattern><bits>
        pattern = encoding[len("bayer_") : len("bayer_") + 4]
        mosaic = np.ascontiguousarray(pixels[:, :, 0], dtype=pixels.dtype.newbyteorder("="))
        out = cv2.cvtColor(mosaic, _BAYER_CODES[pattern])
        if out.dtype == np.uint16:
            out = np.right_shift(out, 8).astype(np.uint8)
    return np.ascontiguousarray(out, dtype=out.dtype.newbyteorder("="))


def grey_as_bgr(image: Array) -> Array:
    """A mono image (HxW uint8, or uint16 scaled to its high byte as bayer16 is) as grey BGR uint8 HxWx3;
    a colour image as it is. The dataset's image folders hold RGB PNGs, whatever the camera sent."""
    if image.ndim == 3:
        return image
    grey = np.right_shift(image, 8).astype(np.uint8) if image.dtype == np.uint16 else image
    out: Array = cv2.cvtColor(np.ascontiguousarray(grey), cv2.COLOR_GRAY2BGR)
    return out
