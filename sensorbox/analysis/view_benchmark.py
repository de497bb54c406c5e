"""`sensorbox view` of a benchmark (`sensorbox render-benchmark`): every scene's images of every FOV,
baseline and camera, CENTER's depth and disparity, the scene's poses and numbers on the timeline
`scene`, and the layout of the viewer's panels."""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ingest.dataset.layout import DEPTH_SCALE, DISP_SCALE
from ingest.errors import DatasetError

if TYPE_CHECKING:
    import rerun as rr

from sensorbox.analysis.view_files import (
    BENCHMARK_FOLDER,
    F64,
    TIMELINE_SCENE,
    Logger,
    Progress,
    ViewSummary,
    meta_scalars,
    read_yaml,
    rerun_transform,
)


def _benchmark_scenes(root: Path) -> list[Path]:
    """Scene folders (those with a `<FOV>FOV/<B>mm/CENTER` folder), in name order."""
    return sorted(p for p in root.iterdir() if p.is_dir() and any(p.glob("*FOV/*mm/CENTER")))


def _benchmark_folders(scene: Path) -> Iterator[tuple[str, Path]]:
    """(`<FOV>FOV/<B>mm/<CAMERA>`, folder) of every camera of a scene, in name order."""
    for folder in sorted(scene.glob("*FOV/*mm/*")):
        rel = folder.relative_to(scene).as_posix()
        if folder.is_dir() and BENCHMARK_FOLDER.match(rel):
            yield rel, folder


def benchmark_scalars(doc: Mapping[str, Any]) -> dict[tuple[str, ...], float]:
    """The numbers of a scene.yaml: each view's render `stats` and each scan's point counts."""
    out: dict[tuple[str, ...], float] = {}
    stats = doc.get("stats")
    for view, counts in (stats or {}).items() if isinstance(stats, Mapping) else ():
        if isinstance(counts, Mapping):  # "120FOV/65mm/DOWN/fisheye" as four levels of the entity tree
            out.update(meta_scalars(counts, ("stats", *str(view).split("/"))))
    for scan in doc.get("scans") or []:
        if isinstance(scan, Mapping) and isinstance(scan.get("name"), str):
            counts = {k: scan[k] for k in ("points", "dropped_points") if k in scan}
            out.update(meta_scalars(counts, ("scans", scan["name"])))
    return out


def _matrix(value: object, where: str) -> F64:
    T = np.asarray(value, np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise DatasetError(f"{where}: expected a finite 4x4 matrix, found {value!r}")
    return T


def _log_scene_poses(log: Logger, doc: Mapping[str, Any], where: Path) -> None:
    """`world/center` (T_world_center) and each partner in it, per baseline, as in scene.yaml."""
    view = doc.get("view")
    if isinstance(view, Mapping) and "T_world_center" in view:
        log.rec.log(
            "world/center", rerun_transform(log.rr, _matrix(view["T_world_center"], f"{where}: view"))
        )
    partners = doc.get("T_center_partner")
    if not isinstance(partners, Mapping):
        return
    for partner, by_baseline in partners.items():
        for baseline, T in (by_baseline or {}).items():
            entity = log.rr.new_entity_path(["world", "center", str(baseline), str(partner)])
            T_c = _matrix(T, f"{where}: T_center_partner.{partner}.{baseline}")
            log.rec.log(entity, rerun_transform(log.rr, T_c), log.rr.TransformAxes3D(0.05))
            log.summary.frames += 1


def log_benchmark(
    rec: rr.RecordingStream, root: Path, max_side_px: int | None, progress: Progress | None
) -> ViewSummary:
    """Every scene of a benchmark-layout dataset onto `rec` (module doc); returns what was logged."""
    summary = ViewSummary(layout="benchmark")
    log = Logger(rec, summary, max_side_px)
    scenes = _benchmark_scenes(root)
    for n, scene in enumerate(scenes):
        rec.set_time(TIMELINE_SCENE, sequence=n)
        for rel, folder in _benchmark_folders(scene):
            for png in sorted(folder.glob("*.png")):
                log.colour(f"{rel}/{png.stem}", png, root)
            for kind, scale in (("depth", DEPTH_SCALE), ("disparity", DISP_SCALE)):
                for png in sorted((folder / kind).glob("*.png")):
                    log.depth(f"{rel}/{kind}/{png.stem}", png, root, scale)
        scene_yaml = scene / "scene.yaml"
        if scene_yaml.is_file():
            doc = read_yaml(scene_yaml)
            _log_scene_poses(log, doc, scene_yaml)
            log.scalars("scene", benchmark_scalars(doc))
        else:
            summary.missing_files.append(scene_yaml.relative_to(root).as_posix())
        summary.samples += 1
        if progress is not None:
            progress(n + 1, len(scenes))
    _send_benchmark_blueprint(log)
    return summary


BENCHMARK_CHARTS = ("hole_px", "valid_px", "masked_px", "filled_px")  # render stats charted per view


def benchmark_layout(images: Iterable[str]) -> dict[str, list[tuple[str, list[str]]]]:
    """The image panels of the benchmark layout's default viewer layout: per `<FOV>FOV/<B>mm`, (title,
    entity paths) of each camera image, CENTER's with its depth over it, and of each disparity map."""
    logged = set(images)
    tabs: dict[str, list[tuple[str, list[str]]]] = {}
    for entity in sorted(logged):
        parts = entity.split("/")  # <FOV>FOV, <B>mm, <CAMERA>, then <image> or depth|disparity, <image>
        pair, camera, rest = "/".join(parts[:2]), parts[2], parts[3:]
        if len(rest) == 1:  # a camera's image: <pair>/<CAMERA>/<image>
            depth = f"{pair}/{camera}/depth/{rest[0]}"
            title = f"{camera} {rest[0]}" + (" + depth" if depth in logged else "")
            tabs.setdefault(pair, []).append((title, [entity] + ([depth] if depth in logged else [])))
        elif rest[0] == "disparity":
            tabs.setdefault(pair, []).append((f"{camera} {rest[1]} disparity", [entity]))
    # per camera its images first, then its disparity maps
    return {
        pair: sorted(panels, key=lambda p: (p[0].split()[0], p[0].endswith(" disparity")))
        for pair, panels in tabs.items()
    }


def _send_benchmark_blueprint(log: Logger) -> None:
    """The default layout of a benchmark recording: a tab per FOV and baseline with a view per image
    (`benchmark_layout`), one with the scene's cameras in 3D and one with the render stats' charts."""
    import rerun.blueprint as rrb

    tabs: list[Any] = [
        rrb.Grid(*(rrb.Spatial2DView(origin="/", contents=c, name=t) for t, c in panels), name=pair)
        for pair, panels in benchmark_layout(log.summary.image_entities).items()
    ]
    tabs.append(rrb.Spatial3DView(origin="world", name="cameras"))
    charts = [
        rrb.TimeSeriesView(origin="/", contents=entities, name=field)
        for field in BENCHMARK_CHARTS
        if (entities := sorted(e for e in log.summary.series if e.endswith(f"/{field}")))
    ]
    if charts:
        tabs.append(rrb.Grid(*charts, name="render stats"))
    log.rec.send_blueprint(rrb.Blueprint(rrb.Tabs(*tabs), auto_views=False, collapse_panels=True))
