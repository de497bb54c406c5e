"""Reading an evaluation: markdown tables, A-vs-B comparisons, FOV x baseline heatmaps of an `EvalReport`."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ingest.errors import EvalError
from ingest.eval.evaluate import CONFIG_LABEL, GROUP_KEYS, EvalReport, GroupRow, config_component
from ingest.eval.metrics import (
    HIGHER_IS_BETTER,
    LOWER_IS_BETTER,
)

_HEAD = {
    "epe_px": "EPE [px]", "median_px": "median [px]", "p95_px": "p95 [px]",
    "bad1": "bad-1 [%]", "bad2": "bad-2 [%]", "bad3": "bad-3 [%]",
    "abs_rel": "AbsRel", "mae_m": "MAE [m]", "rmse_m": "RMSE [m]",
    "delta1": "δ<1.25 [%]", "delta2": "δ<1.25² [%]", "delta3": "δ<1.25³ [%]",
    "coverage": "coverage [%]",
}  # fmt: skip


_PERCENT = frozenset({"bad1", "bad2", "bad3", "delta1", "delta2", "delta3", "coverage"})


def format_metric(name: str, value: float | int | None) -> str:
    """A metric as the tables print it (shares in percent)."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    if name in _PERCENT:
        return f"{100.0 * value:.2f}"
    if name in ("abs_rel", "mae_m", "rmse_m"):
        return f"{value:.4f}"
    return f"{value:.3f}"


def _md(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def markdown_table(report: EvalReport, region: str = "all") -> str:
    """Markdown table of one region: a row per group (when grouped) and the pooled total."""
    cols = report.columns
    header = ["group", "samples", "GT px", _HEAD["coverage"], *(_HEAD[c] for c in cols)]
    rows = []
    for g in (*report.groups, report.overall):
        m = g.metrics[region]
        rows.append(
            [
                g.label,
                str(g.samples),
                str(m["n_gt"]),
                format_metric("coverage", m["coverage"]),
                *(format_metric(c, m[c]) for c in cols),
            ]
        )
    return _md(header, rows)


@dataclass(frozen=True)
class CompareRow:
    """One metric of configuration A vs B; change = 100 (A - B) / |B|."""

    other: str | None  # the other grouping key's value (e.g. '65mm') when grouped by both
    metric: str
    a: float
    b: float
    change_pct: float
    better: str  # "A", "B", "=" or "-" (not comparable)


def parse_config_label(label: str) -> tuple[str, float]:
    """'195FOV' -> ('fov', 195.0); '65mm' -> ('baseline', 65.0)."""
    m = CONFIG_LABEL.match(label.strip())
    if m is None:
        raise EvalError(f"configuration {label!r}: expected <FOV>FOV (e.g. 195FOV) or <B>mm (e.g. 65mm)")
    return ("fov" if m["unit"] == "FOV" else "baseline"), float(m["value"])


def compare(report: EvalReport, a: str, b: str, region: str = "all") -> list[CompareRow]:
    """Percentage change of every metric between configurations `a` and `b` (e.g. '195FOV', '120FOV').

    Both must name the same grouping key, which must be one of the report's
    `by` keys; when the report is grouped by the other key too, A and B are
    paired within each of its values.
    """
    key_a, va = parse_config_label(a)
    key_b, vb = parse_config_label(b)
    if key_a != key_b:
        raise EvalError(f"--compare {a},{b}: both must be FOVs or both baselines")
    if key_a not in report.options.by:
        raise EvalError(f"--compare {a},{b}: the report is not grouped by {key_a}")
    other = next((k for k in report.options.by if k != key_a), None)

    def value(g: GroupRow, key: str) -> float | None:
        return g.fov_deg if key == "fov" else g.baseline_mm

    side: dict[tuple[float | None, float | None], GroupRow] = {}
    for g in report.groups:
        side[(value(g, key_a), value(g, other) if other else None)] = g
    others = sorted({o for _, o in side}, key=lambda o: -math.inf if o is None else o)
    rows: list[CompareRow] = []
    for o in others:
        ga, gb = side.get((va, o)), side.get((vb, o))
        if ga is None or gb is None:
            continue
        label = config_component(other, o) if other else None
        for metric in (*report.columns, "coverage"):
            x, y = float(ga.metrics[region][metric]), float(gb.metrics[region][metric])
            rows.append(CompareRow(label, metric, x, y, _change(x, y), _better(metric, x, y)))
    if not rows:
        have = ", ".join(g.label for g in report.groups) or "none"
        raise EvalError(f"--compare {a},{b}: no group holds both (groups: {have})")
    return rows


def _change(a: float, b: float) -> float:
    if not (math.isfinite(a) and math.isfinite(b)) or b == 0.0:
        return 0.0 if a == b else math.nan
    return 100.0 * (a - b) / abs(b)


def _better(metric: str, a: float, b: float) -> str:
    if not (math.isfinite(a) and math.isfinite(b)):
        return "-"
    if a == b:
        return "="
    lower_wins = metric in LOWER_IS_BETTER
    assert lower_wins or metric in HIGHER_IS_BETTER
    return "A" if (a < b) == lower_wins else "B"


def markdown_compare(rows: Sequence[CompareRow], a: str, b: str) -> str:
    """Markdown table of `compare` rows: A, B, change in %, which is better."""
    grouped = any(r.other is not None for r in rows)
    header = [*(["config"] if grouped else []), "metric", f"A = {a}", f"B = {b}", "change [%]", "better"]
    body = [
        [
            *([r.other or ""] if grouped else []),
            _HEAD[r.metric],
            format_metric(r.metric, r.a),
            format_metric(r.metric, r.b),
            "-" if not math.isfinite(r.change_pct) else f"{r.change_pct:+.1f}",
            r.better,
        ]
        for r in rows
    ]
    return _md(header, body)


@dataclass(frozen=True)
class Heatmap:
    """A metric over FOV (rows) x baseline (columns); NaN where no sample had that configuration."""

    metric: str
    region: str
    fovs_deg: tuple[float, ...]
    baselines_mm: tuple[float, ...]
    values: np.ndarray[Any, np.dtype[np.float64]]


def heatmap(report: EvalReport, metric: str, region: str = "all") -> Heatmap:
    """The grid of pooled `metric` per (FOV, baseline) group; needs `by` = fov and baseline."""
    if set(report.options.by) != set(GROUP_KEYS):
        raise EvalError("a heatmap needs the report grouped by fov and baseline")
    if metric not in (*report.columns, "coverage"):
        raise EvalError(f"metric {metric!r}: expected one of {', '.join((*report.columns, 'coverage'))}")
    fovs = tuple(sorted({g.fov_deg for g in report.groups if g.fov_deg is not None}))
    bases = tuple(sorted({g.baseline_mm for g in report.groups if g.baseline_mm is not None}))
    grid = np.full((len(fovs), len(bases)), np.nan)
    for g in report.groups:
        assert g.fov_deg is not None and g.baseline_mm is not None
        grid[fovs.index(g.fov_deg), bases.index(g.baseline_mm)] = float(g.metrics[region][metric])
    return Heatmap(metric, region, fovs, bases, grid)
