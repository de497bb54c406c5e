"""Speed vs accuracy of the ingest alternatives, and equirect vs cubemap stereo (`sensorbox bench`).

Simulates two noise-free bags with exact truth (an indoor static room, where
the occlusion filter matters, and an outdoor walk, where motion compensation
does) unless `--bag` names simulator bags, ingests each with every alternative
of `sensorbox.analysis.tradeoff.ALTERNATIVES`, scores the GT against the truth
(`sensorbox.sim.score`) and writes into `--out`:

- `bench_tradeoff.csv`: one row per alternative and bag, then the pooled rows (bag "all");
- `bench_tradeoff.png`: samples/s (one worker) against the median depth error and
  the outlier share, with the Pareto front;
- `bench_projection.csv` / `.png`: SGBM on cam0's equirect vs on the cubemap faces.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from calibration.errors import SensorboxError

if TYPE_CHECKING:
    from sensorbox.analysis.projection import ProjectionResult
    from sensorbox.analysis.tradeoff import Alternative, Measurement
    from sensorbox.sim.config import SimConfig

FAMILY_COLORS = {
    "default": "black", "control": "tab:gray", "occlusion": "tab:red", "motion": "tab:blue",
    "resolution": "tab:green", "interpolation": "tab:purple", "encoder": "tab:orange",
}  # fmt: skip


def default_sims(scale: float, duration_s: float) -> list[tuple[str, SimConfig]]:
    """The bags the bench simulates: noise-free, jpeg images, fixed seeds."""
    from sensorbox.sim.config import SimConfig

    common: dict[str, Any] = {"duration_s": duration_s, "scale": scale, "image": "jpeg", "range_noise_m": 0.0}
    return [
        ("indoor_static", SimConfig(scene="indoor", seed=1, **common)),
        ("outdoor_walk", SimConfig(scene="outdoor", trajectory="walk", seed=2, **common)),
    ]


@dataclass
class BenchResult:
    """Everything one bench run measured and the files it wrote."""

    measurements: list[Measurement]
    pooled: list[Measurement]
    projection: list[ProjectionResult] = field(default_factory=list)
    projection_source: str = ""
    files: list[Path] = field(default_factory=list)


def run_bench(
    bags: Sequence[Path],
    out: Path,
    alternatives: Sequence[Alternative],
    workdir: Path,
    every: int = 1,
    projection: bool = True,
    repeats: int = 1,
    progress: Callable[[str], None] | None = None,
) -> BenchResult:
    """Run the alternatives on simulator bags (each with `<bag>.truth/`); write CSVs and charts to `out`.

    The files are made in memory and written as one set at the end: a full
    disk is one `OutputError` naming the file and leaves none of them.
    """
    from ingest.dataset.layout import write_atomic_set
    from ingest.train.run.settings import IngestConfig
    from sensorbox.analysis.tradeoff import csv_bytes, pool, run_alternatives
    from sensorbox.sim.score import score_dataset
    from sensorbox.sim.truth import Truth

    truths = {bag: Truth.load(bag) for bag in bags}
    keep = ("default",) if projection else ()
    measurements = run_alternatives(
        [(bag, truths[bag].path / "rig.yaml") for bag in bags], alternatives, workdir,
        lambda bag, ds: score_dataset(ds, truths[bag]),
        base=lambda rig, folder: IngestConfig(rig=rig, out=folder, workers=1, every=every),
        keep=keep, repeats=repeats, progress=progress,
    )  # fmt: skip
    pooled = pool(measurements)
    result = BenchResult(measurements, pooled)
    rows = [m.row() for m in measurements] + [m.row() for m in pooled]
    per_bag = [(bag.name, [m for m in measurements if m.bag == bag.name]) for bag in bags]
    files = [
        (out / "bench_tradeoff.csv", csv_bytes(rows)),
        (
            out / "bench_tradeoff.png",
            draw_tradeoff(per_bag, out / "bench_tradeoff.png", _title(bags, truths)),
        ),
    ]
    kept = [m for m in measurements if m.out is not None]
    if projection and kept:
        if progress is not None:
            progress("projections (SGBM)")
        first = next(m for m in kept if m.bag == bags[0].name)
        result.projection, result.projection_source = project(first.out, truths[bags[0]])  # type: ignore[arg-type]
        files.append((out / "bench_projection.csv", csv_bytes([r.row() for r in result.projection])))
        files.append(
            (out / "bench_projection.png", draw_projection(result.projection, out / "bench_projection.png"))
        )
    write_atomic_set(files)  # all four (two without the projection), or none: never a CSV without its chart
    result.files = [path for path, _ in files]
    return result


def _title(bags: Sequence[Path], truths: dict[Path, Any]) -> str:
    parts = []
    for bag in bags:
        p = truths[bag].params
        parts.append(f"{p['scene']} {p['trajectory'].get('kind', '')}".strip())
    rig = truths[bags[0]].rig.upper.model
    return f"{', '.join(parts)}; {rig.width}x{rig.height} fisheye, exact LiDAR"


def project(dataset: Path, truth: Any) -> tuple[list[ProjectionResult], str]:
    """Equirect vs cubemap SGBM on the middle sample of an ingested simulator dataset."""
    import cv2
    import numpy as np
    import yaml

    from ingest.dataset.meta import read_meta
    from ingest.dataset.png import read_image
    from sensorbox.analysis.projection import compare_projections

    sids = sorted(p.stem for p in (dataset / "meta").glob("*.json"))
    if not sids:
        raise SensorboxError(f"{dataset}: no samples were written, nothing to compare projections on")
    sid = sids[len(sids) // 2]
    stamp = read_meta(dataset, sid).stamp_ns
    upper = read_image(dataset / "left_fisheye" / f"{sid}.png", cv2.IMREAD_COLOR)
    lower = read_image(dataset / "right_fisheye" / f"{sid}.png", cv2.IMREAD_COLOR)
    if upper is None or lower is None:
        raise SensorboxError(f"{dataset}: cannot read the fisheye images of sample {sid}")
    height = int(yaml.safe_load((dataset / "dataset.yaml").read_text())["height_full"])

    def range_along(rays: Any) -> Any:
        return truth.range_along(np.asarray(rays), stamp)

    return compare_projections(upper, lower, truth.rig, height, range_along), f"sample {sid}, H_full {height}"


# -- tables and charts ------------------------------------------------------------------


def fronts(pooled: Sequence[Measurement]) -> tuple[list[bool], list[bool]]:
    """Pareto membership of each pooled alternative: (speed vs median mm, speed vs outlier %)."""
    from sensorbox.analysis.tradeoff import pareto_front

    rows = [m.row() for m in pooled]
    speed = [r["samples_per_s"] for r in rows]
    mm = pareto_front(speed, [r["depth_median_mm"] for r in rows])
    out = pareto_front(speed, [r["depth_outlier_pct"] for r in rows])
    return [bool(v) for v in mm], [bool(v) for v in out]


def tradeoff_table(pooled: Sequence[Measurement]) -> str:
    """Markdown table of the pooled alternatives, ratio of speed vs the default, Pareto marks."""
    rows = [m.row() for m in pooled]
    base = next((r for r in rows if r["alternative"] == "default"), rows[0])
    front_mm, front_out = fronts(pooled)
    head = (
        "| alternative | samples | samples/s | x default | ms/sample | depth median mm | outliers % "
        "| disp median px | disp >1 px % | kB/sample | Pareto |"
    )
    lines = [head, "|" + "---|" * 11]
    for r, a, b in zip(rows, front_mm, front_out, strict=True):
        marks = "/".join(m for m, on in (("mm", a), ("out", b)) if on) or "-"
        lines.append(
            f"| {r['alternative']} | {r['samples']} | {r['samples_per_s']:.2f} "
            f"| {r['samples_per_s'] / base['samples_per_s']:.2f} | {r['ms_per_sample']:.0f} "
            f"| {r['depth_median_mm']:.2f} | {r['depth_outlier_pct']:.3f} | {r['disp_median_px']:.3f} "
            f"| {r['disp_over_1px_pct']:.3f} | {r['kb_per_sample']:.0f} | {marks} |"
        )
    return "\n".join(lines)


def projection_table(results: Sequence[ProjectionResult]) -> str:
    """Markdown table of the projection comparison."""
    lines = [
        "| projection | pixels | warp s | SGBM s | EPE px | bad-1 % | bad-3 % | stereo coverage % "
        "| stable share % | fisheye coverage % | fisheye AbsRel | AbsRel on common pixels |",
        "|" + "---|" * 12,
    ]
    for res in results:
        r = res.row()
        lines.append(
            f"| {r['projection']} | {r['pixels']} | {r['warp_s']:.3f} | {r['sgbm_s']:.3f} "
            f"| {r['epe_px']:.3f} | {r['bad1_pct']:.2f} | {r['bad3_pct']:.2f} "
            f"| {r['stereo_coverage_pct']:.1f} "
            f"| {r['stable_share_pct']:.1f} | {r['fisheye_coverage_pct']:.1f} | {r['fisheye_abs_rel']:.4f} "
            f"| {r['common_abs_rel']:.4f} |"
        )
    return "\n".join(lines)


def draw_tradeoff(
    groups: Sequence[tuple[str, Sequence[Measurement]]], path: Path, subtitle: str = ""
) -> bytes:
    """Per bag (a row each): samples/s against median depth error and outlier share, with the Pareto front;
    the bytes of the chart file `path` (its suffix picks the format)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    from sensorbox.analysis.plots import figure_bytes

    n = len(groups)
    fig, axes = plt.subplots(
        n, 3, figsize=(17, 5 * n + 0.6), constrained_layout=True, width_ratios=[1, 1, 0.4], squeeze=False
    )
    plain = FuncFormatter(lambda v, _: f"{v:g}")
    for axrow, (bag, measurements) in zip(axes, groups, strict=True):
        rows = [m.row() for m in measurements]
        front_mm, front_out = fronts(measurements)
        speed = [r["samples_per_s"] for r in rows]
        panels = (
            ("depth_median_mm", "median |depth error| vs truth [mm]", front_mm),
            ("depth_outlier_pct", "outliers, |e| > max(5 cm, 3 %) [%]", front_out),
        )
        for ax, (key, label, front) in zip(axrow[:2], panels, strict=True):
            err = [r[key] for r in rows]
            seen: set[str] = set()
            for k, (r, x, e) in enumerate(zip(rows, speed, err, strict=True)):
                fam = r["family"]
                ax.scatter(x, e, s=60, color=FAMILY_COLORS.get(fam, "grey"), edgecolor="k", linewidth=0.5,
                           zorder=3, label=None if fam in seen else fam)  # fmt: skip
                seen.add(fam)
                # numbers, not names: alternatives that tie on accuracy sit on one line
                ax.annotate(str(k + 1), (x, e), textcoords="offset points", xytext=(4, 4 + 7 * (k % 3)),
                            fontsize=8)  # fmt: skip
            pts = sorted((x, e) for x, e, f in zip(speed, err, front, strict=True) if f)
            if pts:
                xs, ys = zip(*pts, strict=True)
                # the best error still reachable at this speed or faster: a staircase up and to the right
                ax.step(xs, ys, where="pre", color="k", lw=1, ls="--", zorder=2, label="Pareto front")
                ax.scatter(xs, ys, s=180, facecolor="none", edgecolor="k", lw=1.2, zorder=4)
            positive = [e for e in err if e > 0 and math.isfinite(e)]
            if positive and max(positive) / min(positive) > 20:
                ax.set_yscale("log")
                ax.yaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
                ax.yaxis.set_major_formatter(plain)
                ax.yaxis.set_minor_formatter(NullFormatter())
            ax.set_xlabel("samples/s (one worker; median of per-sample stage times)")
            ax.set_ylabel(label)
            ax.set_title(bag, fontsize=10)
            ax.grid(alpha=0.3, which="both")
            ax.legend(fontsize=8, loc="best")
        axrow[2].axis("off")
    lines = [f"{k + 1:>2}  {m.alternative}" for k, m in enumerate(groups[0][1])]
    axes[0][2].text(0.0, 1.0, "\n".join(lines), va="top", ha="left", family="monospace", fontsize=9,
                    transform=axes[0][2].transAxes)  # fmt: skip
    fig.suptitle(
        f"Ingest alternatives: speed vs GT accuracy (better: right and down)\n{subtitle}", fontsize=11
    )
    return figure_bytes(fig, path, dpi=100)


def draw_projection(results: Sequence[ProjectionResult], path: Path) -> bytes:
    """Each projection's image and its SGBM error map with the stability mask's outline; the bytes of
    the chart file `path`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from sensorbox.analysis.plots import figure_bytes

    fig, axes = plt.subplots(len(results), 2, figsize=(14, 3.0 * len(results)), constrained_layout=True,
                             gridspec_kw={"width_ratios": [1, 1]})  # fmt: skip
    axes = np.atleast_2d(axes)
    cmap = plt.get_cmap("magma").with_extremes(bad="0.8")
    for row, res in zip(axes, results, strict=True):
        image, stable = res.maps["image"], res.maps["stable"]
        err = np.abs(res.maps["disp"] - res.maps["gt"])
        if res.name.startswith("cubemap"):  # show the faces as a panorama: left | front | right
            F = image.shape[0]
            order = [3, 0, 1]
            image, err, stable = (np.concatenate([a[:, k * F : (k + 1) * F] for k in order], axis=1)
                                  for a in (image, err, stable))  # fmt: skip
        visible = np.any(image > 0, axis=(0, 2)) if image.ndim == 3 else np.ones(image.shape[1], bool)
        cols = slice(int(np.argmax(visible)), int(len(visible) - np.argmax(visible[::-1])))
        grey = image[:, cols] @ np.array([0.114, 0.587, 0.299]) if image.ndim == 3 else image[:, cols]
        row[0].imshow(grey, cmap="gray", vmin=0, vmax=255)  # grey keeps the committed chart small
        r = res.row()
        row[0].set_title(f"{res.name}: {r['pixels']} px, EPE {r['epe_px']:.3f} px, "
                         f"bad-1 {r['bad1_pct']:.2f} %", fontsize=9)  # fmt: skip
        shown = row[1].imshow(err[:, cols], vmin=0, vmax=3, cmap=cmap)
        row[1].contour(stable[:, cols].astype(float), [0.5], colors="cyan", linewidths=0.8)
        row[1].set_title(f"|SGBM - exact disparity| [px] (grey: no match or unseen); cyan: stability mask; "
                         f"fisheye coverage {r['fisheye_coverage_pct']:.1f} %", fontsize=9)  # fmt: skip
        fig.colorbar(shown, ax=row[1], fraction=0.02)
        for ax in row:
            ax.set_xticks([])
            ax.set_yticks([])
    return figure_bytes(fig, path, dpi=64)


def bench_bags(
    bags: Sequence[Path], workdir: Path, scale: float, duration_s: float, progress: Callable[[str], None]
) -> list[Path]:
    """The given simulator bags, or the two default ones simulated into `workdir`."""
    if bags:
        return list(bags)
    from sensorbox.sim.run import simulate

    out = []
    for name, cfg in default_sims(scale, duration_s):
        progress(f"simulating {name}")
        out.append(simulate(cfg, workdir / name).bag)
    return out


def bench_report(result: BenchResult, bags: Sequence[Path]) -> str:
    """The markdown a person reads after a bench run: trade-off table, projection table, files."""
    lines = [
        f"# Ingest alternatives on {', '.join(b.name for b in bags)} (pooled over the bags)",
        "",
        tradeoff_table(result.pooled),
        "",
        "samples/s: one worker, 1000 / median per-sample stage time; Pareto: on the front of",
        "speed vs median error (mm) and/or speed vs outlier share (out).",
    ]
    if result.projection:
        lines += ["", f"# Stereo on equirect vs cubemap faces (SGBM, {result.projection_source})", ""]
        lines.append(projection_table(result.projection))
    lines += ["", "Written: " + ", ".join(str(p) for p in result.files)]
    return "\n".join(lines)


def bench_settings(
    only: Sequence[str], quick: bool, every: int | None, repeats: int, duration_s: float
) -> tuple[list[Alternative], int]:
    """The alternatives to run (all, `--quick`'s five, or `--only` these) and the frame step."""
    from sensorbox.analysis.tradeoff import ALTERNATIVES, QUICK, select

    try:
        alternatives = select(list(only) or ([*QUICK] if quick else [a.name for a in ALTERNATIVES]))
    except KeyError as err:
        raise SensorboxError(f"--only: {err.args[0]}") from err
    step = every if every is not None else (3 if quick else 1)
    if step < 1 or repeats < 1 or duration_s <= 0:
        raise SensorboxError(
            f"--every and --repeats must be >= 1 and --duration > 0 (got {step}, {repeats}, {duration_s})"
        )
    return alternatives, step
