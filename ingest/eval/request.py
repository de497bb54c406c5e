"""`sensorbox eval`'s options as a user gives them -> `EvalOptions` and the comparison pair.

Group keys follow from what is asked: `--by` as given, the key of `--compare`'s
labels (195FOV -> fov, 200mm -> baseline), and every key for a heatmap over
FOV x baseline. Regions are all, edges (unless turned off) and each named
mask; the one `--compare` and `--heatmap` use must be among them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from ingest.errors import EvalError
from ingest.eval.evaluate import GROUP_KEYS, TASKS, EvalOptions
from ingest.eval.report import parse_config_label


@dataclass(frozen=True)
class EvalRequest:
    """The scoring run: options for `evaluate`, the pair to compare (labels) and the region they use."""

    options: EvalOptions
    pair: tuple[str, str] | None
    region: str


def parse_masks(items: Sequence[str]) -> tuple[tuple[str, Path], ...]:
    """NAME=DIR items -> ((name, folder), ...)."""
    out = []
    for item in items:
        name, sep, folder = item.partition("=")
        if not sep or not name or not folder:
            raise EvalError(f"--mask {item!r}: expected NAME=DIR (e.g. stable=out/stability)")
        out.append((name, Path(folder)))
    return tuple(out)


def _pair(compare: str | None) -> tuple[str, str] | None:
    if compare is None:
        return None
    a, sep, b = compare.partition(",")
    if not sep or not a.strip() or not b.strip():  # ',' named no configuration at all
        raise EvalError(f"--compare {compare!r}: expected A,B (e.g. 195FOV,120FOV)")
    return a.strip(), b.strip()


def eval_request(
    task: str, by: Sequence[str], compare: str | None, heatmap: bool, masks: Sequence[str], region: str,
    image_type: str | None, edges: bool, align: str,
) -> EvalRequest:  # fmt: skip
    """Check and combine the options of one `sensorbox eval` run."""
    if task not in TASKS:
        raise EvalError(f"--task {task!r}: expected one of {', '.join(TASKS)}")
    keys = list(dict.fromkeys(by))
    pair = _pair(compare)
    if pair is not None and (key := parse_config_label(pair[0])[0]) not in keys:
        keys.append(key)
    if heatmap:
        keys += [k for k in GROUP_KEYS if k not in keys]
    named = parse_masks(masks)
    regions = ("all", *(["edges"] if edges else []), *(name for name, _ in named))
    if region not in regions:
        raise EvalError(f"--region {region!r}: expected one of {', '.join(regions)}")
    asked = ([f"--by {'/'.join(by)}"] if by else []) + ([f"--compare {compare}"] if pair else [])
    options = EvalOptions(
        task=task, by=tuple(keys), image_type=image_type, edges=edges, masks=named,
        align=align,  # type: ignore[arg-type]
        asked_by=(*asked, *(["--heatmap"] if heatmap else [])),
    )  # fmt: skip
    return EvalRequest(options, pair, region)
