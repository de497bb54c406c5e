"""Benchmark views from dense laser scans, written in the WideDepth benchmark layout.

For every view (a scan centre of the site, a yaw and a height) the renderer
(`ingest.raster.view`) draws the scans of that centre's bundle (the central scan and
its nearest neighbours, the paper's bundle of three) through virtual cameras:

- CENTER: the reference camera, level at the scan centre (plus the view's
  height), looking along the view's yaw;
- DOWN: its vertical-stereo partner, the baseline below (+y of the camera);
- RIGHT: its horizontal-stereo partner, the baseline to the right (+x).

Layout (`<scene>` = `<site>_<centre scan>_<view>`, three digits each)::

    <scene>/scene.yaml                      every camera, pose, parameter and count (written last)
    <scene>/<FOV>FOV/<B>mm/CENTER/<image>.png
    <scene>/<FOV>FOV/<B>mm/CENTER/depth/<image>.png      uint16 mm (range; z for pinhole), 0 = invalid
    <scene>/<FOV>FOV/<B>mm/CENTER/disparity/<image>.png  uint16 px x 100, 0 = invalid
    <scene>/<FOV>FOV/<B>mm/DOWN/{fisheye,pano,pano_crop,pinhole,pinhole_crop}.png
    <scene>/<FOV>FOV/<B>mm/RIGHT/{fisheye,cassini_crop,pano,pano_crop,pinhole,pinhole_crop}.png
    (depth/ and disparity/ also hold float32 EXR copies, <image>.exr)

Images: `fisheye` (the virtual DS lens of that FOV), `pano` (the full-sphere
equirect, H_full x 2 H_full, showing what the fisheye sees), `pano_crop` (the
smallest window of it holding that), `cassini_crop` (the transverse equirect,
window likewise), `pinhole` (90 degrees wide, the fisheye's size) and
`pinhole_crop` (its centre). Disparity: `pano`/`pano_crop` for the vertical
pair CENTER-DOWN (DESIGN.md's angular formula, stability-masked);
`pinhole`/`pinhole_crop` (f B / z, the same for the vertical pinhole pair
CENTER-DOWN and the horizontal one CENTER-RIGHT: fx = fy) and `cassini_crop`
(the angular formula with the latitude from -x) for the horizontal pair. Both
partners get every image type, so each (image type, partner) pair the
WideDepth release loader reads has its images; `RIGHT/pano*` are exact images
of the RIGHT camera in CENTER's orientation, but a horizontal baseline has no
per-pixel disparity along an equirect's columns: that pair's exact disparity
is `cassini_crop`'s, and a loader that pairs `RIGHT/pano*` with
`disparity/pano*` gets the vertical pair's. The pinhole images go only to the
FOV folders of `pinhole_fovs` (120, as in the WideDepth release), the other
images to every folder.

Work is one task per rendered camera; tasks run in a local process pool
(forked, so the scans' level-of-detail index is shared, not copied). A scene
whose scene.yaml exists is skipped on a rerun when it was rendered with the
same cameras, baselines and render settings, from the same scans at the same
poses and view; otherwise the run is refused, naming what differs. scene.yaml
lists every file of its scene with its size and SHA-256: a finished scene
with a file deleted, cut short or overwritten is rendered again, as ingest
writes a damaged sample again.
"""

from __future__ import annotations

import multiprocessing
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import yaml

from calibration.camera import CameraModel
from ingest.dataset.layout import write_atomic
from ingest.dataset.lock import hold_folder
from ingest.errors import BenchmarkError, OutputError
from ingest.raster.lod import ScanIndex, build_index
from ingest.raster.scan import Scan
from ingest.raster.view import pixel_geometry
from ingest.render.plan import (
    BenchmarkConfig,
    Task,
    check_reference,
    fov_cameras,
    pinhole_camera,
    plan_tasks,
    plan_views,
    task_key,
)
from ingest.render.render_task import RenderState, run_task
from ingest.render.scans import frame_hint
from ingest.render.scene_doc import (
    check_same_setup,
    read_scene,
    scene_doc,
    scene_problem,
    setup_doc,
    source_doc,
)
from ingest.runtime.executor import Executor, share_cores

EMPTY_RENDER_FRACTION = 0.01  # a render drawing a surface in fewer of its pixels with a ray is empty


@dataclass
class BenchmarkSummary:
    """What a run did: scenes, renders, files and per-render counts."""

    out: Path
    scenes: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    renders: int = 0
    files: int = 0
    seconds: float = 0.0
    index_seconds: float = 0.0
    stats: dict[str, dict[str, dict[str, int]]] = field(default_factory=dict)  # scene -> render key -> counts
    empty: dict[str, list[str]] = field(default_factory=dict)  # scene -> renders showing (almost) nothing
    warnings: list[str] = field(default_factory=list)  # one line per scene with empty renders
    stale_temporaries: int = 0  # left by a killed run, removed (`ingest.dataset.lock`)
    damaged: list[str] = field(default_factory=list)  # finished scenes found damaged, rendered again: why


def empty_renders(stats: dict[str, dict[str, int]]) -> list[str]:
    """Render keys of a scene drawing a surface in under EMPTY_RENDER_FRACTION of their pixels with a ray."""
    return [k for k, st in stats.items() if st["surface_px"] < EMPTY_RENDER_FRACTION * st["pixels_with_ray"]]


def _empty_warning(scene: str, empty: list[str], stats: dict[str, dict[str, int]], scan: Scan) -> str:
    worst = min(empty, key=lambda k: stats[k]["surface_px"] / max(stats[k]["pixels_with_ray"], 1))
    pct = 100.0 * stats[worst]["surface_px"] / max(stats[worst]["pixels_with_ray"], 1)
    limit = f"under {100 * EMPTY_RENDER_FRACTION:g} % of pixels drawn; {worst}: {pct:.2f} %"
    what = f"{len(empty)} of {len(stats)} renders show (almost) nothing ({limit})"
    return f"{scene}: {what}; {frame_hint(scan)}"


def without_disparity(stats: dict[str, dict[str, int]]) -> list[str]:
    """Render keys of a scene whose surface has depth but whose disparity maps hold no pixel."""
    return [k for k, st in stats.items() if st.get("disparity_px") == 0 and st["surface_px"] > 0]


def _disparity_warning(scene: str, keys: list[str], state: RenderState) -> str:
    rows = state.cfg.height_full
    at = f"at --height-full {rows} " if rows is not None else ""
    names = ", ".join(keys)
    return (
        f"{scene}: {len(keys)} renders draw a surface but their disparity maps hold no pixel ({names}): "
        f"{at}the baseline's disparity is too small a part of a pixel to keep (more --height-full rows or a "
        "longer --baseline keep it)"
    )


PASS_INDEX = "indexing the scans"
"""`run_benchmark`'s pass before the first view: each scan the views use sorted into its level-of-detail
index (unit: scans)."""


def refuse_training_set(out: Path) -> None:
    """BenchmarkError when `out` holds an ingest training set (a dataset.yaml or a meta/ folder): a
    benchmark's scenes written beside it are hidden from stats and eval, which take the folder for the
    training set."""
    held = [name for name in ("dataset.yaml", "meta") if (out / name).exists()]
    if held:
        raise BenchmarkError(
            f"{out}: holds a training set ({held[0]}: the ingest layout); render-benchmark would mix a "
            "benchmark into it: choose another --out"
        )


def run_benchmark(
    scans: list[Scan],
    reference: CameraModel,
    out: Path,
    cfg: BenchmarkConfig,
    progress: Callable[[int, int], None] | None = None,
    passes: Callable[[str, int, int], None] | None = None,
) -> BenchmarkSummary:
    """Render every view of the site into ``out`` (see the module doc); resumable per scene.

    `progress(done, total)` after each view; `passes(PASS_INDEX, done, total)` before the first
    view, per scan indexed (seconds to minutes each for a large scan).
    """
    cfg.validate()
    refuse_training_set(out)
    ds = check_reference(reference)
    if not scans:
        raise BenchmarkError("no scans given")
    t0 = time.perf_counter()
    fovs = {f: fov_cameras(ds, f, cfg) for f in cfg.fovs_deg}  # first: refuses an equirect too big
    summary = BenchmarkSummary(out)
    views = plan_views(scans, cfg)
    ph = pinhole_camera(cfg)
    setup = setup_doc(cfg, fovs, ph)
    done_before: set[str] = set()
    for view in views:  # a finished scene is skipped only when it was rendered as asked now, and is whole
        path = out / view.scene / "scene.yaml"
        if not path.exists():
            continue
        doc = read_scene(path)
        check_same_setup(path, doc, setup, source_doc(view, scans, cfg))
        problem = scene_problem(path.parent, doc)
        if problem:
            summary.damaged.append(problem)
        else:
            done_before.add(view.scene)
    todo = [v for v in views if v.scene not in done_before]
    summary.skipped = [v.scene for v in views if v.scene in done_before]
    used = sorted({i for v in todo for i in v.bundle})
    indexes: list[ScanIndex] = [None] * len(scans)  # type: ignore[list-item]
    t_index = time.perf_counter()
    for k, i in enumerate(used):
        if passes:
            passes(PASS_INDEX, k, len(used))
        indexes[i] = build_index(scans[i], cfg.voxel_m)
    if passes:
        passes(PASS_INDEX, len(used), len(used))
    summary.index_seconds = time.perf_counter() - t_index
    for fc in fovs.values():  # warm the per-model caches before forking
        for m in (fc.fisheye.model, fc.pano, fc.cassini):
            pixel_geometry(m)
    pixel_geometry(ph[0])
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise OutputError(f"cannot create {out}: {err.strerror or err}") from err
    with hold_folder(out) as stale:  # one run at a time into `out`; a killed run's temporaries are removed
        summary.stale_temporaries = stale
        state = RenderState(out, cfg, indexes, {v.scene: v for v in todo}, fovs, ph)
        summary.stats = _render_tasks(state, scans, plan_tasks(todo, cfg), summary, progress)
    summary.seconds = time.perf_counter() - t0
    return summary


def _render_tasks(
    state: RenderState,
    scans: list[Scan],
    tasks: list[Task],
    summary: BenchmarkSummary,
    progress: Callable[[int, int], None] | None,
) -> dict[str, dict[str, dict[str, int]]]:
    """Every render task of `state`'s views; each scene's scene.yaml once its last render is written.

    Returns the per-render counts of each scene.
    """
    out = state.out
    stats: dict[str, dict[str, dict[str, int]]] = {scene: {} for scene in state.views}
    written: dict[str, dict[str, dict[str, Any]]] = {scene: {} for scene in state.views}
    remaining = {scene: sum(t.scene == scene for t in tasks) for scene in state.views}
    done = 0

    def finished(task: Task, st: dict[str, int], files: dict[str, dict[str, Any]]) -> None:
        nonlocal done
        done += 1
        summary.renders += 1
        summary.files += len(files)
        stats[task.scene][task_key(task)] = st
        written[task.scene].update(files)
        remaining[task.scene] -= 1
        if remaining[task.scene] == 0:  # scene.yaml last: it marks the scene finished
            view = state.views[task.scene]
            doc = scene_doc(state, view, scans, dict(sorted(stats[task.scene].items())), written[task.scene])
            empty = empty_renders(stats[task.scene])
            if empty:
                summary.empty[task.scene] = empty
                doc["warnings"] = [_empty_warning(task.scene, empty, stats[task.scene], scans[view.center])]
            if no_disparity := without_disparity(stats[task.scene]):
                doc.setdefault("warnings", []).append(_disparity_warning(task.scene, no_disparity, state))
            summary.warnings += doc.get("warnings", [])
            text = "# SensorBox benchmark scene (WideDepth layout)\n" + yaml.safe_dump(
                doc, sort_keys=False, default_flow_style=None
            )
            write_atomic(out / task.scene / "scene.yaml", text.encode())
            summary.files += 1
            summary.scenes.append(task.scene)
        if progress:
            progress(done, len(tasks))

    # workers share the scans' index by fork; without fork the run stays in this process (no copies)
    # OpenCV's threads are set before the fork (`Executor`): reconfiguring a forked OpenCV pool deadlocks
    workers = state.cfg.workers if len(tasks) > 1 and "fork" in multiprocessing.get_all_start_methods() else 1
    results = Executor(workers, worker_init=partial(share_cores, workers)).run(run_task, tasks, shared=state)
    try:
        for result in results:
            finished(*result)
    finally:
        results.close()
    return stats
