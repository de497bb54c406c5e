"""Point cloud files checked before Open3D reads them: a regular file (not a device or a FIFO, which
would be read without end), and no shorter than its PLY or PCD header promises (Open3D zero-fills a
short PLY)."""

from __future__ import annotations

import stat
from pathlib import Path
from typing import BinaryIO

from calibration.files import file_kind
from ingest.errors import ScanError


def check_cloud_file(path: Path) -> None:
    """Refuse a point cloud path that is missing or no regular file (symlinks followed).

    A link to /dev/zero given as `--mask` would be read line by line without
    end (a header that never ends) until memory runs out; a FIFO would wait
    forever. One `ScanError` line naming the path and what it is.
    """
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        raise ScanError(f"{path}: no such point cloud") from None
    except OSError as err:
        raise ScanError(f"{path}: cannot read the point cloud: {err.strerror or err}") from err
    if not stat.S_ISREG(mode):
        raise ScanError(f"{path}: is {file_kind(mode)}, not a point cloud file")


PLY_SIZES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2,
             "uint16": 2, "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4,
             "double": 8, "float64": 8}  # fmt: skip


MAX_HEADER_BYTES = 1 << 20
"""A PLY or PCD header ends within this (bytes): real ones take a few hundred; a file of zeros or of
another kind would otherwise be read whole as its header."""


def short_file(path: Path) -> str | None:
    """What is missing from a PLY/PCD whose header promises more data than the file holds, else None;
    `ScanError` when no header ends within `MAX_HEADER_BYTES`.

    Binary files: bytes (PLY with fixed-size rows only, uncompressed PCD);
    ASCII files: lines. Other layouts are left to Open3D.
    """
    header: list[list[str]] = []
    with path.open("rb") as f:
        while raw := f.readline(4096):
            if f.tell() > MAX_HEADER_BYTES:
                raise ScanError(
                    f"{path}: no end of a PLY or PCD header in its first {MAX_HEADER_BYTES >> 20} MiB "
                    "('end_header' or 'DATA'); expected a point cloud file"
                )
            header.append(raw.decode("ascii", "replace").split() or [""])
            if header[-1][0] not in ("end_header", "DATA"):
                continue
            rows = _pcd_row_bytes(header) if path.suffix.lower() == ".pcd" else _ply_row_bytes(header)
            if rows is None:
                return None
            if rows[1] == 0:  # ASCII: one line per point
                lines = _ascii_lines(f)
                short = lines < rows[0]
                return f"its header declares {rows[0]} points, the file has {lines} lines" if short else None
            need, have = f.tell() + rows[0] * rows[1], path.stat().st_size
            return f"its header promises {need} bytes, the file has {have}" if have < need else None
    return None


def _ascii_lines(f: BinaryIO) -> int:
    """Lines from the file position to its end, a last line without a newline included (PCL's own test
    files end so)."""
    lines, last = 0, b"\n"
    for chunk in iter(lambda: f.read(1 << 24), b""):
        lines += chunk.count(b"\n")
        last = chunk[-1:]
    return lines + (last != b"\n")


def _ply_row_bytes(header: list[list[str]]) -> tuple[int, int] | None:
    """(rows, bytes per row) of a PLY whose one non-empty element has scalar properties (0: ASCII)."""
    formats = [w[1] for w in header if w[0] == "format" and len(w) > 1]
    if formats not in (["ascii"], ["binary_little_endian"], ["binary_big_endian"]):
        return None
    rows, row_bytes, count = 0, 0, 0
    for w in header:
        if w[0] == "element":
            if len(w) != 3 or not w[2].isdigit() or (rows and int(w[2])):
                return None  # a second element with data is not worth modelling
            count = int(w[2])
            rows = rows or count
        elif w[0] == "property" and count:
            if len(w) != 3 or w[1] not in PLY_SIZES:
                return None  # a list property: rows of varying size
            row_bytes += PLY_SIZES[w[1]]
    return rows, 0 if formats == ["ascii"] else row_bytes


def _pcd_row_bytes(header: list[list[str]]) -> tuple[int, int] | None:
    """(rows, bytes per row) of an uncompressed PCD (0 bytes: ASCII, a line per row)."""
    fields = {w[0]: w[1:] for w in header}
    sizes, counts, points = fields.get("SIZE", []), fields.get("COUNT", []), fields.get("POINTS", [])
    data = fields.get("DATA")
    if (
        data not in (["binary"], ["ascii"])
        or len(points) != 1
        or not all(v.isdigit() for v in (*sizes, *counts, *points))
    ):
        return None
    counts = counts or ["1"] * len(sizes)
    row_bytes = sum(int(a) * int(b) for a, b in zip(sizes, counts, strict=False))
    return int(points[0]), 0 if data == ["ascii"] else row_bytes
