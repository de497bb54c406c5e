"""Which frames a dataset folder holds, whether each finished sample is whole, which recording a bag is.

A frame is known by its content, not by the name of the bag it came from:
its two camera header stamps and `frame_digest`, a SHA-256 of both decoded
images, which every sample records in its metadata (`frames_sha256`). The
same recording given under another name (a rosbag2 folder, then its .mcap
file), two recordings given together after each on its own, or split bags
that overlap: a frame some sample of the folder holds is not written again.
Stamps alone would not do: recordings made by the simulator (or by a rig
whose clock starts at zero) share them, with other images.

Each sample's metadata also records every other file it wrote (`files`:
size and SHA-256), so a rerun checks each sample it would skip as finished
and writes a damaged one (a file deleted, cut short or overwritten, the
metadata unreadable or recording no files) again instead of keeping the damage.
"""

from __future__ import annotations

import hashlib
import stat
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from calibration.files import file_kind
from ingest.dataset.meta import SampleMeta, read_meta
from ingest.errors import DatasetError

Array = np.ndarray[Any, Any]
VERIFY_THREADS = 4
"""Finished samples checked at once on a rerun: a full-resolution sample is ~40 MB to read and hash."""


def frame_digest(upper: Array, lower: Array) -> str:
    """SHA-256 (hex) of the two decoded camera images of a frame: each one's shape, dtype and pixels.

    A BGRA image counts by its three colour channels, which is all the dataset stores of it: a raw
    bgra8 frame decoded as BGRA or converted to BGR first is the same frame.
    """
    digest = hashlib.sha256()
    for image in (upper, lower):
        if image.ndim == 3 and image.shape[2] == 4:
            image = image[..., :3]
        digest.update(f"{image.shape}:{image.dtype.str}:".encode())
        digest.update(np.ascontiguousarray(image).data)
    return digest.hexdigest()


def file_problem(path: Path, size: int, sha256: str) -> str:
    """Why `path` is not the file of `size` bytes and SHA-256 `sha256` that was written ('' when it is).

    Only a regular file of exactly `size` bytes is read, and no more than
    that: a file of another size is damaged by its size alone. A path that
    is no regular file (a device, a FIFO, a folder, or a symlink to one: a
    link to /dev/zero would be read until memory runs out) is no sample damage a
    rerun may write over: a `DatasetError` naming it.
    """
    try:
        st = path.stat()
    except FileNotFoundError:
        return f"{path}: missing"
    except OSError as err:
        return f"{path}: cannot be read ({err.strerror or err})"
    if not stat.S_ISREG(st.st_mode):
        raise DatasetError(
            f"{path}: is {file_kind(st.st_mode)}, not a file of the dataset; remove it, or give another --out"
        )
    if st.st_size != size:
        return f"{path}: {st.st_size} bytes, {size} were written"
    try:
        with path.open("rb") as f:
            data = f.read(size + 1)
    except OSError as err:
        return f"{path}: cannot be read ({err.strerror or err})"
    if len(data) != size:  # changed since the stat
        return f"{path}: {len(data)} bytes, {size} were written"
    if hashlib.sha256(data).hexdigest() != sha256:
        return f"{path}: not the file written (its SHA-256 differs)"
    return ""


def sample_problem(out: Path, sid: str, meta: SampleMeta) -> str:
    """Why written sample `sid` of dataset `out` is not whole, naming the file ('' when it is).

    Every file its metadata records must have the size and SHA-256 written.
    Metadata that records none (`files` absent or emptied) cannot vouch for
    any file: a PNG that decodes may still be zeroed or another sample's, so
    such a sample counts as damaged and is written again.
    """
    if not meta.files:
        return f"{out / 'meta' / f'{sid}.json'}: records no files (size and SHA-256) to check the sample by"
    for name, written in meta.files.items():
        problem = file_problem(out / name, written.bytes, written.sha256)
        if problem:
            return problem
    return ""


@dataclass(frozen=True)
class HeldFrame:
    """A sample of the dataset with the stamps of a frame a run is about to write: is it the same frame?"""

    sid: str
    frames_sha256: str
    problem: str = ""  # why its files are not whole ('' when they are): the frame is written again there

    @property
    def intact(self) -> bool:
        return not self.problem


@dataclass(frozen=True)
class Resume:
    """What a run finds in its output folder for its planned samples (by their ids in its range)."""

    done: dict[str, SampleMeta] = field(default_factory=dict)  # finished and whole (their metas): skipped
    damaged: dict[str, str] = field(default_factory=dict)  # finished but damaged (why): written again
    same_stamps: dict[str, tuple[HeldFrame, ...]] = field(default_factory=dict)  # other ids, same stamps


def _stamp(ns: int) -> str:
    sec, nsec = divmod(ns, 1_000_000_000)
    return f"{sec}.{nsec:09d} s"


def _no_copies(
    meta_dir: Path, done: dict[str, SampleMeta], others: dict[tuple[int, int], list[tuple[str, SampleMeta]]]
) -> None:
    """DatasetError when a sample of another id (`others`, by stamps) holds a done sample's very frames
    (`frames_sha256`): a sample copied within the folder, the same frame twice in the training set."""
    for sid, meta in done.items():
        for other, held in others.get((meta.stamp_ns, meta.lower_stamp_ns), []):
            if meta.frames_sha256 and held.frames_sha256 == meta.frames_sha256:
                digest = meta.frames_sha256[:12]
                raise DatasetError(
                    f"{meta_dir / f'{other}.json'}: sample {other} holds the same frames as sample {sid} "
                    f"(the frame at {_stamp(meta.stamp_ns)}, frames_sha256 {digest}...): the frame twice in "
                    f"the dataset, a sample copied within it; delete sample {other}'s files or choose a new "
                    "--out"
                )


def resume_state(out: Path, sids: list[str], stamps_ns: list[tuple[int, int]]) -> Resume:
    """The planned samples `sids` (upper and lower header stamps `stamps_ns`) against what `out` holds.

    A planned sample with metadata is done when it is whole, damaged
    otherwise; one that records other stamps is another frame's, which no
    run overwrites (DatasetError). One without is compared, by stamps,
    with every other sample of the folder (whose content the worker then
    compares: `frame_digest`). A sample with the same stamps that records no
    digest (an older SensorBox) cannot be told apart: DatasetError naming it;
    so is a sample of another id with a done sample's very frames (`_no_copies`).
    """
    meta_dir = out / "meta"
    if not meta_dir.is_dir():
        return Resume()
    own = dict(zip(sids, stamps_ns, strict=True))
    damaged: dict[str, str] = {}
    finished: dict[str, SampleMeta] = {}
    by_stamps: dict[tuple[int, int], list[tuple[str, SampleMeta]]] = {}
    for path in sorted(meta_dir.glob("*.json")):
        sid = path.stem
        try:
            meta = read_meta(out, sid)
        except DatasetError as err:
            if sid in own:
                damaged[sid] = str(err)
            continue
        if sid not in own:
            by_stamps.setdefault((meta.stamp_ns, meta.lower_stamp_ns), []).append((sid, meta))
            continue
        if (meta.stamp_ns, meta.lower_stamp_ns) != own[sid]:  # another recording's: never overwritten
            raise DatasetError(
                f"{path}: sample {sid} is the frame at {_stamp(meta.stamp_ns)}, but this recording's sample "
                f"{sid} is the frame at {_stamp(own[sid][0])}: dataset.yaml's id ranges do not describe "
                "the folder; choose a new --out"
            )
        finished[sid] = meta
    with ThreadPoolExecutor(VERIFY_THREADS) as pool:  # reads and hashes: hashlib and reads free the GIL
        checked = pool.map(lambda sid: sample_problem(out, sid, finished[sid]), finished)
        problems = dict(zip(finished, checked, strict=True))
    damaged.update({sid: problem for sid, problem in problems.items() if problem})
    done = {sid: finished[sid] for sid, problem in problems.items() if not problem}
    _no_copies(meta_dir, done, by_stamps)
    same: dict[str, tuple[HeldFrame, ...]] = {}
    for sid, key in own.items():
        if sid in done or sid in damaged or key not in by_stamps:
            continue
        held = []
        for other, meta in by_stamps[key]:
            if not meta.frames_sha256:
                raise DatasetError(
                    f"{meta_dir / f'{other}.json'}: the frame at {_stamp(key[0])} was written by an older "
                    f"SensorBox without frames_sha256, and this run's sample {sid} has its stamps; cannot "
                    "tell whether it is the same frame: choose a new --out"
                )
            held.append(HeldFrame(other, meta.frames_sha256, sample_problem(out, other, meta)))
        same[sid] = tuple(held)
    return Resume(done, dict(sorted(damaged.items())), same)


IDENTITY_HEAD_BYTES = 1 << 20


def bag_identity(bag: Path) -> dict[str, Any]:
    """What tells two recordings of the same name apart: their size and a hash of each file's first MiB.

    A bag is a file (ROS 1, MCAP) or a rosbag2 folder (its data files, by
    name; not `metadata.yaml`, which tools such as `ros2 bag reindex` rewrite).
    Reading a MiB per file costs milliseconds, and a different recording
    differs in its header or index within it, or in size.
    """
    if bag.is_dir():
        files = sorted(f for f in bag.rglob("*") if f.is_file() and f.name != "metadata.yaml")
    else:
        files = [bag]
    digest = hashlib.sha256()
    total = 0
    try:
        for f in files:
            size = f.stat().st_size
            total += size
            digest.update(f"{f.relative_to(bag) if bag.is_dir() else f.name}:{size}:".encode())
            with f.open("rb") as fh:
                digest.update(fh.read(IDENTITY_HEAD_BYTES))
    except OSError as err:
        raise DatasetError(f"{bag}: cannot read it to identify the recording: {err.strerror or err}") from err
    return {"bytes": total, "sha256_head": digest.hexdigest()}
