"""Speed vs accuracy of the ingest pipeline's alternatives, and equirect vs cubemap stereo.

Alternatives are data (`ALTERNATIVES`): a name, a family and the
`IngestConfig` / `SampleParams` / `GtParams` fields they change. The runner
ingests each bag once per alternative into a scratch folder with one worker,
times every sample (the sum of `process_sample`'s stage times, so process
start-up and the planning pass do not count), and scores the written ground
truth with a callback (the simulator's exact truth lives in `sensorbox.sim`,
which `ingest` must not import). `pareto_front` marks the alternatives no
other one beats on both speed and error.

The projection comparison warps one stereo pair to cam0's rectified
equirect (a crop covering the fisheye) and to the cubemap faces that are
vertical stereo pairs (front, right, left; see
`sensorbox.analysis.stability.cubemap_stereo_faces`), runs the same SGBM on both, and
scores disparity in each projection's own pixels (EPE, bad-k) and range back
on cam0's fisheye pixels, where both are judged on the same rays. The face
size matches the equirect's pitch at the face centres (F = 2 H_full / pi).
A third variant pads every face above by the matcher's reach (a taller
pinhole with the same focal length), which removes the seam loss.
"""

from __future__ import annotations

import csv
import io
import itertools
import math
import shutil
import statistics
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from calibration.rig import read_rig
from calibration.types import ArrayLike, Bool
from calibration.warp import default_height_full
from ingest.train.run.pipeline import ingest
from ingest.train.run.settings import IngestConfig
from ingest.train.run.summary import IngestSummary

# -- alternatives as data ----------------------------------------------------------------

Changes = tuple[tuple[str, Any], ...]


@dataclass(frozen=True)
class Alternative:
    """One way to run the pipeline: what it changes relative to the default settings."""

    name: str
    family: str
    config: Changes = ()  # IngestConfig fields
    sample: Changes = ()  # SampleParams fields
    gt: Changes = ()  # GtParams fields
    height_scale: float = 1.0  # equirect rows relative to the rig's default (calibration.warp)

    def apply(self, cfg: IngestConfig) -> IngestConfig:
        """`cfg` with this alternative's changes (height_scale needs the rig's default height)."""
        gt = replace(cfg.sample.gt, **dict(self.gt))
        sample = replace(cfg.sample, **dict(self.sample), gt=gt)
        out = replace(cfg, **dict(self.config), sample=sample)
        if self.height_scale != 1.0:
            base = cfg.height_full
            if base is None:
                base = default_height_full(read_rig(cfg.rig).upper.model)
            out = replace(out, height_full=max(64, round(base * self.height_scale / 64) * 64))
        return out

    def describe(self) -> str:
        """The changes as text, e.g. 'gt.occlusion=False'."""
        parts = [f"{k}={v}" for k, v in self.config]
        parts += [f"{k}={v}" for k, v in self.sample] + [f"gt.{k}={v}" for k, v in self.gt]
        if self.height_scale != 1.0:
            parts.append(f"height_full x{self.height_scale:g}")
        return ", ".join(parts) or "defaults"


ALTERNATIVES: tuple[Alternative, ...] = (
    Alternative("default", "default"),
    Alternative("default, run again", "control"),  # A/A: how far timing noise alone moves a point
    Alternative("occlusion filter off", "occlusion", gt=(("occlusion", False),)),
    Alternative("occlusion window 1/3", "occlusion", gt=(("window_rad", 0.006), ("window_spacings", 0.67))),
    Alternative("occlusion window 2x", "occlusion", gt=(("window_rad", 0.036), ("window_spacings", 4.0))),
    Alternative("z-buffer order flipped", "occlusion", gt=(("zbuffer", "farthest"),)),
    Alternative(
        "filter off, z-buffer flipped", "occlusion", gt=(("occlusion", False), ("zbuffer", "farthest"))
    ),
    Alternative("motion: rotation only", "motion", sample=(("motion", "rotation"),)),
    Alternative("motion compensation off", "motion", sample=(("motion", "off"),)),
    Alternative("equirect 0.5x", "resolution", height_scale=0.5),
    Alternative("equirect 2x", "resolution", height_scale=2.0),
    Alternative("interpolation nearest", "interpolation", sample=(("interpolation", "nearest"),)),
    Alternative("interpolation cubic", "interpolation", sample=(("interpolation", "cubic"),)),
    Alternative("PNG level 0", "encoder", sample=(("png_level", 0),)),
    Alternative("PNG level 3", "encoder", sample=(("png_level", 3),)),
)
QUICK = ("default", "occlusion filter off", "motion compensation off", "equirect 0.5x", "PNG level 0")


def select(names: Iterable[str], alternatives: Sequence[Alternative] = ALTERNATIVES) -> list[Alternative]:
    """The alternatives with these names, in the given order (KeyError names the unknown one)."""
    by_name = {a.name: a for a in alternatives}
    out = []
    for name in names:
        if name not in by_name:
            raise KeyError(f"no alternative {name!r}; known: {', '.join(by_name)}")
        out.append(by_name[name])
    return out


# -- measuring ---------------------------------------------------------------------------


class SampleAccuracy(Protocol):
    """What the scoring callback reports per sample (e.g. sensorbox.sim.score.SampleScore)."""

    @property
    def depth_pixels(self) -> int: ...
    @property
    def depth_median_abs_m(self) -> float: ...
    @property
    def depth_outlier_rate(self) -> float: ...
    @property
    def disp_pixels(self) -> int: ...
    @property
    def disp_median_abs_px(self) -> float: ...
    @property
    def disp_over_1px_rate(self) -> float: ...


Scorer = Callable[[Path, Path], Sequence[SampleAccuracy]]
"""(bag, dataset folder) -> one accuracy per written sample."""


@dataclass(frozen=True)
class Measurement:
    """Per-sample times and accuracies of one alternative on one or more bags."""

    alternative: str
    family: str
    bag: str
    sample_ms: tuple[float, ...]
    stage_ms: Mapping[str, tuple[float, ...]]
    depth_median_m: tuple[float, ...]
    depth_pixels: tuple[int, ...]
    depth_outliers: tuple[float, ...]  # outlier pixels (rate x pixels)
    disp_median_px: tuple[float, ...]
    disp_pixels: tuple[int, ...]
    disp_over_1px: tuple[float, ...]
    bytes_written: int
    wall_s: float
    out: Path | None = None
    groups: tuple[int, ...] = ()  # samples per bag when pooled over bags

    @property
    def samples(self) -> int:
        return len(self.sample_ms)

    def row(self) -> dict[str, Any]:
        """Summary row: ms per sample and samples/s, median errors, outlier shares, size, stage medians.

        Times: the median over samples (one worker); errors: the median of the
        per-sample medians; pooled over bags, both are the mean of the bags'
        medians (a bag's samples are alike, two bags' are not). Outlier shares
        pool the pixels; kB per sample of the written images and GT.
        """
        n = max(self.samples, 1)
        ms = self._median_over_bags(self.sample_ms)
        return {
            "alternative": self.alternative,
            "family": self.family,
            "bag": self.bag,
            "samples": self.samples,
            "samples_per_s": 1000.0 / ms if ms > 0 else math.nan,
            "ms_per_sample": ms,
            "wall_samples_per_s": self.samples / self.wall_s if self.wall_s > 0 else math.nan,
            "depth_median_mm": self._median_over_bags(self.depth_median_m) * 1e3,
            "depth_outlier_pct": 100.0 * sum(self.depth_outliers) / max(sum(self.depth_pixels), 1),
            "disp_median_px": self._median_over_bags(self.disp_median_px),
            "disp_over_1px_pct": 100.0 * sum(self.disp_over_1px) / max(sum(self.disp_pixels), 1),
            "kb_per_sample": self.bytes_written / n / 1024.0,
            **{f"{k}_ms": _median(v) for k, v in sorted(self.stage_ms.items())},
        }

    def _median_over_bags(self, per_sample: Sequence[float]) -> float:
        """Median over samples; pooled over bags, the mean of the bags' medians (each bag counts once)."""
        if len(self.groups) < 2:
            return _median(per_sample)
        edges = np.cumsum((0, *self.groups)).tolist()
        return float(np.mean([_median(per_sample[a:b]) for a, b in itertools.pairwise(edges)]))

    def with_repeats(self, repeats: Sequence[Measurement]) -> Measurement:
        """This measurement with each sample's (and stage's) time the median over itself and `repeats`.

        Repeats of a deterministic ingest write the same samples, so only the
        times differ; with a different sample count the times are pooled instead.
        """
        runs = [self, *repeats]
        if any(r.samples != self.samples or set(r.stage_ms) != set(self.stage_ms) for r in runs):
            return replace(self, sample_ms=sum((r.sample_ms for r in runs), ()),
                           stage_ms={k: sum((tuple(r.stage_ms.get(k, ())) for r in runs), ())
                                     for k in self.stage_ms})  # fmt: skip
        med = np.median(np.array([r.sample_ms for r in runs]), axis=0)
        stages = {k: tuple(np.median(np.array([r.stage_ms[k] for r in runs]), axis=0).tolist())
                  for k in self.stage_ms}  # fmt: skip
        return replace(self, sample_ms=tuple(med.tolist()), stage_ms=stages,
                       wall_s=statistics.median(r.wall_s for r in runs))  # fmt: skip


def _median(values: Sequence[float]) -> float:
    finite = [v for v in values if math.isfinite(v)]
    return statistics.median(finite) if finite else math.nan


def pool(measurements: Sequence[Measurement], bag: str = "all") -> list[Measurement]:
    """One measurement per alternative over all bags (samples concatenated), first-seen order."""
    groups: dict[str, list[Measurement]] = {}
    for m in measurements:
        groups.setdefault(m.alternative, []).append(m)
    out = []
    for name, ms in groups.items():
        stages: dict[str, tuple[float, ...]] = {}
        for m in ms:
            for k, v in m.stage_ms.items():
                stages[k] = stages.get(k, ()) + tuple(v)
        out.append(
            Measurement(
                name, ms[0].family, bag,
                sum((m.sample_ms for m in ms), ()), stages,
                sum((m.depth_median_m for m in ms), ()), sum((m.depth_pixels for m in ms), ()),
                sum((m.depth_outliers for m in ms), ()), sum((m.disp_median_px for m in ms), ()),
                sum((m.disp_pixels for m in ms), ()), sum((m.disp_over_1px for m in ms), ()),
                sum(m.bytes_written for m in ms), sum(m.wall_s for m in ms),
                groups=tuple(len(m.depth_median_m) for m in ms),
            )
        )  # fmt: skip
    return out


def _folder_bytes(path: Path, subdirs: Iterable[str]) -> int:
    return sum(f.stat().st_size for d in subdirs for f in (path / d).glob("*") if f.is_file())


def measure(
    bag: Path, cfg: IngestConfig, alternative: Alternative, score: Scorer | None, keep: bool = False
) -> Measurement:
    """Ingest `bag` with `alternative` applied to `cfg` (into cfg.out, replaced); score it unless None."""
    cfg = alternative.apply(cfg)
    if cfg.out.exists():
        shutil.rmtree(cfg.out)
    t0 = time.perf_counter()
    summary: IngestSummary = ingest([bag], cfg)
    wall = time.perf_counter() - t0
    scores = list(score(bag, cfg.out)) if score is not None else []
    stage_ms = {k: tuple(v) for k, v in summary.stage_ms.items()}
    per_sample = tuple(float(sum(vals)) for vals in zip(*stage_ms.values(), strict=True)) if stage_ms else ()
    written = _folder_bytes(cfg.out, ("left_fisheye", "right_fisheye", "equirect_up", "equirect_down_virt",
                                      "disp_equirect", "depth_fisheye"))  # fmt: skip
    m = Measurement(
        alternative.name, alternative.family, bag.name, per_sample, stage_ms,
        tuple(s.depth_median_abs_m for s in scores), tuple(s.depth_pixels for s in scores),
        tuple(s.depth_outlier_rate * s.depth_pixels if s.depth_pixels else 0.0 for s in scores),
        tuple(s.disp_median_abs_px for s in scores), tuple(s.disp_pixels for s in scores),
        tuple(s.disp_over_1px_rate * s.disp_pixels if s.disp_pixels else 0.0 for s in scores), written, wall,
        cfg.out if keep else None,
    )  # fmt: skip
    if not keep:
        shutil.rmtree(cfg.out, ignore_errors=True)
    return m


def run_alternatives(
    bags: Sequence[tuple[Path, Path]],
    alternatives: Sequence[Alternative],
    workdir: Path,
    score: Scorer,
    base: Callable[[Path, Path], IngestConfig] | None = None,
    keep: Iterable[str] = ("default",),
    repeats: int = 1,
    progress: Callable[[str], None] | None = None,
) -> list[Measurement]:
    """Every alternative on every (bag, rig) pair; datasets of `keep` (first round) stay in workdir.

    `base(rig, out)` gives the default settings (one worker by default, so a
    sample's time is not shared with a sibling process). With `repeats` > 1
    the whole list runs that many rounds (interleaved, so a busy spell on a
    shared machine hits every alternative alike), the first is scored and
    each sample's time is the median over the rounds.
    """
    make = base or (lambda rig, out: IngestConfig(rig=rig, out=out, workers=1))
    keep_set = set(keep)
    first: list[Measurement] = []
    later: list[list[Measurement]] = []
    for rep in range(max(1, repeats)):
        for a, alt in enumerate(alternatives):
            for b, (bag, rig) in enumerate(bags):
                if progress is not None:
                    progress(f"{alt.name} on {bag.name}" + (f" (round {rep + 1})" if repeats > 1 else ""))
                folder = workdir / f"{rep}_{a:02d}_{b}_{_slug(alt.name)}"
                if rep == 0:
                    first.append(measure(bag, make(rig, folder), alt, score, keep=alt.name in keep_set))
                    later.append([])
                else:
                    later[a * len(bags) + b].append(measure(bag, make(rig, folder), alt, None))
    return [m.with_repeats(rest) for m, rest in zip(first, later, strict=True)]


def _slug(name: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in name.lower()).strip("_")


# -- Pareto front and CSV ----------------------------------------------------------------


def pareto_front(speed: ArrayLike, error: ArrayLike) -> Bool:
    """True for points that no other point dominates (speed >= and error <=, one of them strictly).

    Higher speed and lower error are better; points with a NaN are never on
    the front, and of identical points all are.
    """
    s = np.asarray(speed, dtype=np.float64)
    e = np.asarray(error, dtype=np.float64)
    if s.shape != e.shape or s.ndim != 1:
        raise ValueError(f"pareto_front: speed {s.shape} and error {e.shape} must be equal 1-D shapes")
    ok = np.isfinite(s) & np.isfinite(e)
    better_eq = (s[None, :] >= s[:, None]) & (e[None, :] <= e[:, None])
    strictly = (s[None, :] > s[:, None]) | (e[None, :] < e[:, None])
    dominated = (better_eq & strictly & ok[None, :]).any(axis=1)
    out: Bool = ok & ~dominated
    return out


def csv_bytes(rows: Sequence[Mapping[str, Any]]) -> bytes:
    """Rows as CSV text (columns of the first row, then any new ones in order; floats to 6 digits)."""
    columns: list[str] = []
    for row in rows:
        columns += [k for k in row if k not in columns]
    buf = io.StringIO()
    writer = csv.DictWriter(buf, columns, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
    return buf.getvalue().encode()
