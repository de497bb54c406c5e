"""rosbags' writers, adjusted so that ROS's own readers check and read what we write.

- ROS 1: lz4 chunks in the LZ4 frame form that ROS 1's `rosbag` (roslz4)
  decompresses (`roslz4_compress`); rosbags' own lz4 chunks it rejects.
- ROS 2 mcap: every chunk carries the CRC-32 of its records, which rosbags
  leaves 0 ("not computed" in the MCAP spec), so readers that validate CRCs
  (Foxglove's `mcap`, `mcap doctor`, rosbags) detect a corrupted chunk instead
  of decoding damaged bytes.
"""

from __future__ import annotations

import os
import zlib
from collections.abc import Mapping
from typing import Any

import lz4.frame
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.rosbag2.storage_mcap import McapWriter

CHUNK_CRC_OFFSET = 1 + 8 + 8 + 8 + 8
"""Bytes from a Chunk record's opcode to its uncompressed_crc field: opcode,
record length, message_start_time, message_end_time, uncompressed_size."""


def roslz4_compress(chunk: bytes) -> bytes:
    """LZ4-frame-compress a ROS 1 bag chunk so that ROS 1's `rosbag` decompresses it.

    ROS 1 reads lz4 chunks with roslz4, which accepts only part of the LZ4 frame
    format: independent blocks, a content checksum, no content size field, no
    block checksums, no dictionary. rosbags' own lz4 writer uses python-lz4's
    defaults (linked blocks, a content size, no content checksum), which roslz4
    rejects with "malformed data to decompress". These settings give the frame
    header roslz4's own writer produces (1 MiB blocks); every LZ4 frame reader,
    rosbags' included, reads it too.
    """
    return bytes(
        lz4.frame.compress(
            chunk,
            compression_level=0,
            block_size=lz4.frame.BLOCKSIZE_MAX1MB,
            block_linked=False,
            content_checksum=True,
            block_checksum=False,
            store_size=False,
        )
    )


class Ros1Writer(Writer1):
    """rosbags' ROS 1 writer whose lz4 chunks ROS 1's `rosbag` reads (`roslz4_compress`)."""

    def set_compression(self, fmt: Writer1.CompressionFormat) -> None:
        super().set_compression(fmt)
        if fmt == Writer1.CompressionFormat.LZ4:
            self.compressor = roslz4_compress


class CrcMcapWriter(McapWriter):
    """rosbags' mcap storage that fills in each chunk's CRC-32 of its uncompressed records."""

    def close_chunk(self) -> None:
        crc = zlib.crc32(self.chunk.bio.getbuffer())
        chunk_start = self.bio.tell()
        super().close_chunk()
        self.bio.seek(chunk_start + CHUNK_CRC_OFFSET)
        self.bio.write(crc.to_bytes(4, "little"))
        self.bio.seek(0, os.SEEK_END)


class Ros2Writer(Writer2):
    """rosbags' rosbag2 writer whose mcap chunks carry CRCs (`CrcMcapWriter`)."""

    STORAGE_PLUGINS: Mapping[StoragePlugin, Any] = {
        **Writer2.STORAGE_PLUGINS,
        StoragePlugin.MCAP: CrcMcapWriter,
    }
