"""Dense coloured terrestrial laser scans in: PLY and PCD (Open3D), E57 (pye57) and site manifests.

A `Scan` holds float32 xyz in its own scan frame (the scanner at the origin,
z up when levelled), uint8 RGB, an optional per-point mask (reflective or
transparent surfaces, from a label field) and an optional mask cloud in the
same frame, plus `T_world_scan` (p_world = T_world_scan @ p_scan). 20M points
take 300 MB: readers keep float32/uint8 throughout and E57 files are read in
chunks, so a scan never exists in float64.

Inputs (`read_scans` takes any mix):
- `site.yaml` manifest: ``scans: [{name, file, T_world_scan, mask?}]`` with
  paths relative to the manifest (what `sensorbox.sim.tls` writes);
- `.e57`: every scan in the file with its pose (``pose`` of each data3D);
  cartesian or spherical coordinates, invalid-state points dropped;
- `.pcd`: one scan, pose from the header's VIEWPOINT (tx ty tz qw qx qy qz);
- `.ply`: one scan in its own frame (T_world_scan = identity).
A label field (`mask_label`, default ``label``) marks masked points where it is
non-zero. Every scan must have colours (mask clouds need none); points that
are not finite or at the scanner origin are dropped with a logged warning
that counts them (`Scan.dropped_points`).
"""

from __future__ import annotations

import logging
import math
import os
import re
import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from calibration.errors import SensorboxError
from calibration.files import read_text
from calibration.opencv_yaml import BoundedSafeLoader, yaml_error_line
from calibration.transforms import as_transform
from calibration.types import F32, F64, U8, Bool
from ingest.errors import ScanError
from ingest.raster.scan import Scan
from ingest.render.cloud_files import check_cloud_file, short_file

E57_CHUNK = 1_000_000
SITE_VERSION = 1
log = logging.getLogger(__name__)


def read_scans(paths: Sequence[Path | str], mask_label: str | None = "label") -> list[Scan]:
    """Every scan in ``paths`` (manifests, E57, PCD, PLY), in order."""
    scans: list[Scan] = []
    for p in map(Path, paths):
        suffix = p.suffix.lower()
        if not p.exists():
            raise ScanError(f"{p}: no such scan file or site manifest")
        if suffix in (".yaml", ".yml"):
            scans += read_site(p, mask_label)
        elif suffix == ".e57":
            scans += read_e57(p)
        elif suffix in (".ply", ".pcd"):
            scans.append(read_cloud(p, None, mask_label))
        else:
            raise ScanError(f"{p}: unknown scan format {suffix!r}; expected .ply, .pcd, .e57 or a site .yaml")
    return _unique_names(scans)


def _unique_names(scans: list[Scan]) -> list[Scan]:
    """Scans with distinct names: a repeated name (scan.ply in two folders) gets a suffix _2, _3, ..."""
    seen: dict[str, int] = {}
    out = []
    for s in scans:
        k = seen.get(s.name, 0) + 1
        seen[s.name] = k
        out.append(s if k == 1 else replace(s, name=f"{s.name}_{k}"))
    return out


def read_site(manifest: Path, mask_label: str | None = "label") -> list[Scan]:
    """The scans of a site manifest (`site.yaml`)."""
    text = read_text(manifest, "site manifest", error=ScanError)  # a regular file of at most 4 MiB
    try:
        doc = yaml.load(text, Loader=BoundedSafeLoader)
    except yaml.YAMLError as err:
        raise ScanError(f"site manifest {yaml_error_line(manifest, err)}") from err
    if not isinstance(doc, dict) or doc.get("sensorbox_site") != SITE_VERSION:
        raise ScanError(f"{manifest}: not a site manifest (expected 'sensorbox_site: {SITE_VERSION}')")
    entries = doc.get("scans")
    if not isinstance(entries, list) or not entries:
        raise ScanError(f"{manifest}: 'scans' must be a non-empty list")
    named: dict[str, int] = {}
    for k, e in enumerate(entries):  # every entry checked before any scan is read
        _check_site_entry(manifest, k, e)
        if (name := e.get("name")) is not None:
            if name in named:  # a view is chosen by its scan's name (--center): two would be one
                raise ScanError(
                    f"{manifest}: scans[{k}].name {name!r} is also scans[{named[name]}]'s; expected a name "
                    "of its own for each scan"
                )
            named[name] = k
    scans = []
    for k, e in enumerate(entries):
        try:
            T = as_transform(
                e.get("T_world_scan", np.eye(4).tolist()), f"{manifest}: scans[{k}].T_world_scan"
            )
        except SensorboxError as err:
            raise ScanError(str(err)) from err
        path = manifest.parent / e["file"]
        if path.suffix.lower() == ".e57":  # each scan at the entry's pose composed with its own
            entry_scans = read_e57(path)
            if e.get("name") is not None:
                names = (
                    [e["name"]]
                    if len(entry_scans) == 1
                    else [f"{e['name']}_{i}" for i in range(len(entry_scans))]
                )
                entry_scans = [replace(sc, name=n) for sc, n in zip(entry_scans, names, strict=True)]
            entry_scans = [replace(sc, T_world_scan=T @ sc.T_world_scan) for sc in entry_scans]
        else:
            entry_scans = [read_cloud(path, T, mask_label, name=e.get("name"))]
        if e.get("mask") is not None:
            mask = read_mask_points(manifest.parent / e["mask"])
            entry_scans = [replace(sc, mask_xyz=mask) for sc in entry_scans]
        scans += entry_scans
    return scans


SITE_ENTRY_KEYS = ("name", "file", "T_world_scan", "mask")


def _check_site_entry(manifest: Path, k: int, entry: object) -> None:
    """Refuse a `scans[k]` entry that is not a mapping of the known keys with string name/file/mask.

    `T_world_scan` is checked by `as_transform`. An unknown key (a typo of
    `T_world_scan`) would otherwise leave the scan at the identity pose.
    """
    where = f"{manifest}: scans[{k}]"
    if not isinstance(entry, dict) or "file" not in entry:
        raise ScanError(f"{where} needs at least 'file'")
    unknown = [str(key) for key in entry if key not in SITE_ENTRY_KEYS]
    if unknown:
        raise ScanError(f"{where}: unknown key {unknown[0]!r}; expected {', '.join(SITE_ENTRY_KEYS)}")
    for key, optional in (("name", True), ("file", False), ("mask", True)):
        value = entry.get(key)
        if optional and value is None:
            continue
        if not isinstance(value, str) or not value.strip():
            raise ScanError(
                f"{where}.{key} is {value!r} ({type(value).__name__}); expected a non-empty string"
            )


def read_cloud(path: Path, T_world_scan: F64 | None, mask_label: str | None = "label",
               name: str | None = None) -> Scan:  # fmt: skip
    """One PLY/PCD scan through Open3D's tensor reader (float32 xyz, uint8 colours kept as stored).

    A scan without colours is refused: its renders would be uniform grey.
    Points that are not finite or lie at the scanner origin are dropped, with
    a logged warning and the count in `Scan.dropped_points`.
    """
    pc = _read_open3d(path)
    xyz = np.ascontiguousarray(pc.point.positions.numpy(), np.float32)
    n = len(xyz)
    if "colors" not in pc.point:
        raise ScanError(
            f"{path}: the scan has no colours; expected per-point colours (PLY red, green, blue; PCD rgb)"
        )
    rgb = _to_u8(pc.point.colors.numpy(), path)
    masked = None
    if mask_label and mask_label in pc.point:
        masked = np.ascontiguousarray(pc.point[mask_label].numpy().reshape(n) != 0)
    if T_world_scan is None:
        T_world_scan = _pcd_viewpoint(path) if path.suffix.lower() == ".pcd" else np.eye(4)
    keep = _returns(xyz, str(path))
    if not keep.all():
        xyz, rgb = xyz[keep], rgb[keep]
        masked = masked[keep] if masked is not None else None
    T = np.asarray(T_world_scan, np.float64)
    return Scan(name or path.stem, T, xyz, rgb, masked, source=str(path), dropped_points=n - len(xyz))


def read_mask_points(path: Path) -> F32:
    """The points (M, 3) of a PLY/PCD mask cloud (no colours needed), without non-finite or origin points."""
    xyz = np.ascontiguousarray(_read_open3d(path).point.positions.numpy(), np.float32)
    out: F32 = xyz[_returns(xyz, str(path))]
    return out


def _read_open3d(path: Path) -> Any:
    """An Open3D tensor point cloud with at least one point, or a ScanError naming the file."""
    from ingest.runtime.o3d import o3d

    check_cloud_file(path)
    short = short_file(path)
    if short:  # Open3D zero-fills a short PLY
        raise ScanError(f"{path}: truncated: {short}")
    try:
        with _open3d_quiet():
            pc = o3d.t.io.read_point_cloud(path)
    except RuntimeError as err:  # Open3D raises for some malformed headers, warns for others
        raise ScanError(f"{path}: Open3D cannot read it: {_open3d_message(err)}") from err
    if "positions" not in pc.point or len(pc.point.positions) == 0:
        raise ScanError(f"{path}: no points (or not a PLY/PCD file Open3D can read)")
    return pc


@contextmanager
def _open3d_quiet() -> Iterator[None]:
    """Hold back Open3D's own warnings (stdout) and RPly's messages (C stdio, fd 2) during a read.

    They precede and repeat in other words ("Read PLY failed", "Unable to read
    magic number") the one ScanError line the caller raises. fd 2 points at
    /dev/null only for the call and is restored after it; scans are read before
    any progress display or worker starts, so nothing else writes there meanwhile.
    """
    from ingest.runtime.o3d import o3d

    sys.stderr.flush()
    saved_fd = os.dup(2)
    try:
        with Path(os.devnull).open("wb") as null:
            os.dup2(null.fileno(), 2)
            try:
                with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
                    yield
            finally:
                os.dup2(saved_fd, 2)
    finally:
        os.close(saved_fd)


def _returns(xyz: F32, source: str) -> Bool:
    """Points (N,) to keep: finite and not at the scanner origin; a warning counts the rest.

    NaN/inf or (0, 0, 0) is how most scanners write "no return"; those points
    carry no measurement, so they are dropped, and the user is told how many.
    """
    finite = np.isfinite(xyz).all(axis=1)
    with np.errstate(invalid="ignore", over="ignore"):  # NaN and 1e30 compare as they should
        keep: Bool = finite & (np.einsum("ij,ij->i", xyz, xyz) > 0.0)
    dropped = len(xyz) - int(keep.sum())
    if dropped:
        not_finite = int((~finite).sum())
        reasons = [f"{not_finite} not finite (NaN/inf)"] if not_finite else []
        if dropped > not_finite:
            reasons.append(f"{dropped - not_finite} at the scanner origin (no return)")
        log.warning("%s: dropped %d of %d points: %s", source, dropped, len(xyz), ", ".join(reasons))
    return keep


def _open3d_message(err: RuntimeError) -> str:
    """Open3D's error text without its colour codes and C++ source location."""
    text = re.sub(r"\x1b\[[0-9;]*m", "", str(err)).strip()
    return re.sub(r"^\[Open3D Error\] \(.*?\) \S+:\d+: ", "", text)


def _to_u8(c: np.ndarray[Any, Any], path: Path) -> U8:
    if c.dtype == np.uint8:
        return np.ascontiguousarray(c)
    if c.dtype == np.uint16:
        return (c >> 8).astype(np.uint8)
    if np.issubdtype(c.dtype, np.floating):  # Open3D float colours are in [0, 1]
        return np.clip(np.round(c * 255.0), 0, 255).astype(np.uint8)
    raise ScanError(f"{path}: colours of type {c.dtype} are not supported (expected uint8, uint16 or float)")


def _pcd_viewpoint(path: Path) -> F64:
    """T_world_scan from a PCD header's VIEWPOINT line (identity when absent)."""
    with path.open("rb") as f:
        for raw in f:
            line = raw.decode("ascii", "replace").strip()
            if line.startswith("VIEWPOINT"):
                vals = [float(v) for v in line.split()[1:]]
                if len(vals) != 7 or not all(math.isfinite(v) for v in vals):
                    raise ScanError(f"{path}: VIEWPOINT needs 7 numbers (tx ty tz qw qx qy qz), got {line!r}")
                return _pose(vals[3:], vals[:3], f"{path}: VIEWPOINT")
            if line.startswith("DATA"):
                break
    return np.eye(4)


def _pose(q_wxyz: Sequence[float], t: Sequence[float], where: str) -> F64:
    w, x, y, z = q_wxyz
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if not n > 0.0:
        raise ScanError(f"{where}: zero quaternion")
    w, x, y, z = w / n, x / n, y / n, z / n
    T = np.eye(4)
    T[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    T[:3, 3] = t
    return T


def read_e57(path: Path, chunk: int = E57_CHUNK) -> list[Scan]:
    """Every scan of an E57 file with its pose, read ``chunk`` points at a time (float32 out)."""
    try:
        import pye57
        from pye57 import libe57
    except ImportError as err:  # pragma: no cover - a declared dependency
        raise ScanError(f"{path}: reading E57 needs the 'pye57' package") from err
    try:
        e57 = pye57.E57(str(path))
    except Exception as err:  # libE57Format raises its own exception types
        raise ScanError(f"{path}: not a readable E57 file: {_first_line(err)}") from err
    scans = []
    where = f"{path}: the header"
    try:
        for i in range(e57.scan_count):
            where = f"{path}: data3D[{i}]"
            header = e57.get_header(i)
            name = header["name"].value() if "name" in header.scan_fields else f"scan_{i:03d}"
            T = (
                _pose(header.rotation, header.translation, f"{where}.pose")
                if header.has_pose()
                else np.eye(4)
            )
            xyz, rgb = _read_e57_points(e57, libe57, header, chunk, where)
            keep = _returns(xyz, where)
            scan = Scan(str(name), T, xyz[keep], rgb[keep], source=f"{path}#{i}")
            scans.append(replace(scan, dropped_points=len(xyz) - len(scan.xyz)))
    except libe57.E57Exception as err:  # corrupt records, bad sections: libE57Format's own exception
        raise ScanError(f"{where}: libE57 cannot read it: {_first_line(err)}") from err
    finally:
        e57.close()
    if not scans:  # libE57's empty.e57, or an E57 of images alone (PinholeImageWithDistortionParameters)
        raise ScanError(f"{path}: holds no scan (no data3D section; an E57 of images alone?)")
    return scans


def _first_line(err: BaseException) -> str:
    """The first line of an exception's text: pye57 appends libE57's multi-line debug report to it."""
    lines = [line for line in str(err).splitlines() if line.strip()]
    return lines[0] if lines else type(err).__name__


def _read_e57_points(e57: Any, libe57: Any, header: Any, chunk: int, where: str) -> tuple[F32, U8]:
    fields = set(header.point_fields)
    cart = ("cartesianX", "cartesianY", "cartesianZ")
    sph = ("sphericalRange", "sphericalAzimuth", "sphericalElevation")
    coords = cart if set(cart) <= fields else sph if set(sph) <= fields else None
    if coords is None:
        raise ScanError(f"{where}: no cartesian or spherical coordinates (fields: {sorted(fields)})")
    colours = ("colorRed", "colorGreen", "colorBlue")
    if not set(colours) <= fields:
        raise ScanError(f"{where}: the scan has no colours; expected per-point {', '.join(colours)}")
    invalid_field = "cartesianInvalidState" if coords is cart else "sphericalInvalidState"
    names = [*coords, *colours, *((invalid_field,) if invalid_field in fields else ())]
    n_total = int(header.point_count)
    cap = max(1, min(chunk, n_total))
    # float64 for coordinates and colours (any colour limits), int8 for the invalid state; libE57's
    # binding misreads 64-bit integer buffers
    bufs = {n: np.empty(cap, np.int8 if n == invalid_field else np.float64) for n in names}
    vec = libe57.VectorSourceDestBuffer()
    for n in names:
        vec.append(libe57.SourceDestBuffer(e57.image_file, n, bufs[n], cap, True, True))
    scale = 255.0 / _colour_max(header)
    xyz_parts, rgb_parts = [], []
    reader = header.points.reader(vec)
    try:
        while True:
            got = int(reader.read())
            if got == 0:
                break
            b = {n: a[:got] for n, a in bufs.items()}
            ok = b[invalid_field] == 0 if invalid_field in b else np.ones(got, bool)
            if coords is cart:
                p = np.stack([b[c][ok] for c in cart], axis=1)
            else:
                r, az, el = (b[c][ok] for c in sph)
                ce = np.cos(el)
                p = np.stack([r * ce * np.cos(az), r * ce * np.sin(az), r * np.sin(el)], axis=1)
            xyz_parts.append(p.astype(np.float32))
            c = np.stack([b[k][ok] for k in colours], axis=1) * scale
            rgb_parts.append(np.clip(np.round(c), 0, 255).astype(np.uint8))
    finally:
        reader.close()
    xyz = np.concatenate(xyz_parts) if xyz_parts else np.zeros((0, 3), np.float32)
    if len(xyz) == 0:
        raise ScanError(f"{where}: no valid points")
    return xyz, np.concatenate(rgb_parts)


def _colour_max(header: Any) -> float:
    try:
        return float(header["colorLimits"]["colorRedMaximum"].value()) or 255.0
    except Exception:  # colorLimits is optional in E57
        return 255.0


def frame_hint(scan: Scan, samples: int = 100_000) -> str:
    """Why views at a scan's centre may show nothing: its scale and up axis as its points suggest.

    The renderer puts cameras at the scanner origin, level in the scan frame
    (z up, metres). A median range far beyond a building's (hundreds of m)
    suggests millimetres or points in a world frame; a smallest extent (2-98 %
    of the points) along x or y rather than z, a frame that is not z-up (most
    sites are wider than they are tall).
    """
    xyz = scan.xyz[:: max(1, len(scan.xyz) // samples)].astype(np.float64)
    median_m = float(np.median(np.linalg.norm(xyz, axis=1))) if len(xyz) else 0.0
    extent = np.percentile(xyz, 98, axis=0) - np.percentile(xyz, 2, axis=0) if len(xyz) else np.zeros(3)
    sizes = f"extent x {extent[0]:.3g} y {extent[1]:.3g} z {extent[2]:.3g} m, median range {median_m:.3g} m"
    hints = []
    if median_m > 300.0:
        hints.append("wrong scale (millimetres?) or points in a world frame rather than the scanner's")
    elif 0.0 < median_m < 0.05:
        hints.append("wrong scale (kilometres?)")
    smallest = int(np.argmin(extent))
    if smallest != 2:
        hints.append(f"frame not z-up (the smallest extent is along {'xy'[smallest]}; a levelled scan "
                     "has z up: set its T_world_scan in a site.yaml)")  # fmt: skip
    cause = "; ".join(hints) or "the view may be outside the scanned space (check --height, --yaw)"
    return f"scan {scan.name} ({sizes}): likely {cause}"
