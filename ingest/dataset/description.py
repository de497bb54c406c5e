"""Reading a training set's `dataset.yaml` back: whole, or one line saying where it was cut.

Ingest writes dataset.yaml whole (`ingest.dataset.layout.write_atomic`), but a
copy, a sync or an editor can cut it, and YAML cut at a line end still parses:
a file cut inside `R_cam0_rect` read as a dataset "made with a different
'R_cam0_rect'" and `stats` as one without a `fisheye_size`. A training set's
description holds every key `TOP_KEYS` names, `sources` last, and each source
the keys `SOURCE_KEYS` names: a file that lacks one ends before it, and is
refused naming the line it ends at, not taken for a dataset made otherwise.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from calibration.errors import SensorboxError
from calibration.files import read_text
from calibration.opencv_yaml import yaml_error_line

FORMAT = "widedepth-train"
"""dataset.yaml's `format`: what marks a folder as a training set ingest wrote (and may extend)."""
TOP_KEYS = (
    "format", "sensorbox_version", "rig", "R_cam0_rect", "R_cam1_rect", "baseline_m", "height_full",
    "equirect_size", "crop_offset", "fisheye_size", "conventions", "params", "versions", "sources",
)  # fmt: skip
"""The keys of a training set's dataset.yaml, in the order ingest writes them."""
SOURCE_KEYS = ("bags", "first_id", "samples", "identity", "paths", "ground_truth", "undecodable_messages",
               "dropped_implausible")  # fmt: skip
"""The keys every source of it holds, in the order ingest writes them (optional ones follow)."""


def cut_before(doc: dict[str, Any]) -> str | None:
    """What a training set's description `doc` ends before ("'sources'", "source 2's 'paths'"), or None
    when it holds every key ingest writes (or is no training set's: `format` is not `FORMAT`)."""
    if doc.get("format") != FORMAT:
        return None
    missing = [k for k in TOP_KEYS if k not in doc]
    if missing:
        return repr(missing[0])
    sources = doc["sources"]
    if not isinstance(sources, list) or not sources:
        return "its first source"
    last = sources[-1]
    if not isinstance(last, dict):
        return f"source {len(sources)}'s keys"
    gone = [k for k in SOURCE_KEYS if k not in last]
    return f"source {len(sources)}'s {gone[0]!r}" if gone else None


def read_description(path: Path, error: type[SensorboxError]) -> dict[str, Any]:
    """The mapping dataset.yaml `path` holds, or `error` with one line: not a regular file (a device, a
    FIFO), not YAML (naming line and column), not a mapping, or cut short (naming the line it ends at)."""
    text = read_text(path, "dataset description", error=error)
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise error(f"existing dataset description {yaml_error_line(path, err)}") from err
    if not isinstance(doc, dict):
        raise error(f"{path}: not a SensorBox dataset description (expected a mapping)")
    if (clash := sources_clash(doc)) is not None:
        raise error(
            f"{path}: {clash}: not what ingest writes; delete it (a rerun of ingest checks the samples "
            "against their meta and writes it anew) or restore it"
        )
    missing = cut_before(doc)
    if missing is not None:
        lines = text.count("\n") + (0 if text.endswith("\n") else 1)
        raise error(
            f"{path}: truncated or unreadable at line {lines}: the file ends there, before {missing}, which "
            "ingest writes; delete it (a rerun of ingest checks the samples against their meta and writes "
            "it anew) or restore it"
        )
    return doc


def sources_clash(doc: dict[str, Any]) -> str | None:
    """Two sources of a training set's description that ingest would never write side by side, in words:
    one recording's bags listed twice (ingest finds a recording's entry by its bags' names; a second entry
    is never checked, its samples never resumed), or sample-id ranges that overlap; else None (also when
    the sources cannot be read as such: `cut_before` and the readers name that). The same data under
    other names is a source of its own, whose frames the first one's samples hold."""
    sources = doc.get("sources") if doc.get("format") == FORMAT else None
    if not isinstance(sources, list):
        return None
    seen: list[tuple[int, Any, int, int]] = []
    for k, source in enumerate(sources):
        try:
            first, count, bags = int(source["first_id"]), int(source["samples"]), source["bags"]
        except (KeyError, TypeError, ValueError):
            return None
        for j, other, lo, n in seen:
            if bags == other:
                return f"sources[{k}] lists the bags of sources[{j}] again ({', '.join(map(str, bags))})"
            if first < lo + n and lo < first + count:
                return (
                    f"sources[{k}]'s samples {first}..{first + count - 1} overlap sources[{j}]'s "
                    f"{lo}..{lo + n - 1}"
                )
        seen.append((k, bags, first, count))
    return None
