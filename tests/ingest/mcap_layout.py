"""The record layout of an mcap file, read by hand for tests that damage particular records."""

from __future__ import annotations


def chunk_offsets(data: bytes | bytearray) -> list[int]:
    """Byte offsets of the top-level Chunk records (opcode 0x06) of an intact mcap file."""
    pos, found = 8, []
    while pos + 9 <= len(data) and data[pos] != 0x02:  # up to the Footer
        if data[pos] == 0x06:
            found.append(pos)
        pos += 9 + int.from_bytes(data[pos + 1 : pos + 9], "little")
    return found
