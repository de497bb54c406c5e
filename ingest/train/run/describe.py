"""`dataset.yaml`: what a training set holds and how it was made, one entry per source recording.

The fingerprint (rectification, sizes, conventions, the configuration as
asked, versions) must match for a rerun or a second recording to write into
the same folder. `sources` lists every recording with its sample-id range and
the ground truth chosen for it (method, decision, window, trajectory) and,
when `--salvage` skipped corrupt chunks, the messages lost per topic and one
line per chunk (`lost_in_corrupt_chunks`), the undecodable messages skipped
per topic (`undecodable_messages`) and the IMU readings and LiDAR points no
sensor can produce, with the points the Livox tagged as noise, dropped per
topic and reason (`dropped_implausible`, `ingest.train.plausible`).
"""

from __future__ import annotations

import json
import tempfile
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml

from calibration.files import read_text
from ingest.dataset.compare import first_difference
from ingest.dataset.description import FORMAT, read_description
from ingest.dataset.identity import bag_identity
from ingest.dataset.layout import DEPTH_SCALE, DISP_SCALE, sample_id, write_atomic
from ingest.dataset.meta import read_meta
from ingest.errors import DatasetError, OutputError
from ingest.train.run.sample_job import Geometry

if TYPE_CHECKING:
    from ingest.train.run.resolved import ResolvedRun
    from ingest.train.run.settings import IngestConfig
    from ingest.train.run.summary import IngestSummary

HEADER = "# WideDepth training set written by SensorBox\n"
PER_SOURCE = ("gt", "overlap_images", "method", "decision", "gap_fallback", "window_ns")
"""SampleParams fields resolved per recording (dataset.yaml keeps them with each source), not config."""


def _fingerprint(cfg: IngestConfig, geometry: Geometry, bags: list[Path]) -> dict[str, Any]:
    from importlib.metadata import version

    import cv2

    rig = geometry.rig
    return {
        "format": FORMAT,
        "sensorbox_version": version("sensorbox"),
        "rig": {
            "name": rig.name,
            "source": str(Path(rig.source).resolve()) if rig.source else None,
            "camera_clock_offsets": _clock_offsets(rig, cfg.refine),
            "lidar_poses": _lidar_poses(rig, cfg.refine),
        },
        "R_cam0_rect": geometry.rect.R_cam0_rect.tolist(),
        "R_cam1_rect": geometry.rect.R_cam1_rect.tolist(),
        "baseline_m": geometry.rect.baseline_m,
        "height_full": geometry.equirect.height_full,
        "equirect_size": [geometry.equirect.height, geometry.equirect.width],
        "crop_offset": [geometry.equirect.row_offset, geometry.equirect.col_offset],
        "fisheye_size": [rig.upper.model.height, rig.upper.model.width],
        "conventions": {
            "depth_fisheye": f"uint16 PNG; range from cam0's centre, m = value / {DEPTH_SCALE:g}; 0 invalid",
            "disp_equirect": f"uint16 PNG; disparity, px (full sphere) = value / {DISP_SCALE:g}; 0 invalid",
            "disparity": "angular vertical stereo, reference = upper camera (DESIGN.md section 3)",
            "equirect": "row j: theta = (j + 0.5) pi / height_full from up (-y_rect); "
            "col i: phi = (i + 0.5) pi / height_full - pi from +z_rect towards +x_rect",
            "time": "int64 ns; meta stamp_ns = the upper camera's header stamp as recorded, exposure_ns = "
            "its mid-exposure on the LiDAR clock (stamp + the rig's timeshift_cam_imu), the GT's time",
        },
        "params": {
            "lidar_window_ns": cfg.lidar_window_ns,
            "stereo_tolerance_ns": cfg.stereo_tolerance_ns,
            "every": cfg.every,
            "ground_truth": cfg.gt,
            **{k: v for k, v in asdict(cfg.sample).items() if k not in PER_SOURCE},
            "gt": asdict(cfg.sample.gt),
        },
        "versions": {"numpy": np.__version__, "opencv": cv2.__version__, "rosbags": version("rosbags")},
    }


def _clock_offsets(rig: Any, refined: bool) -> dict[str, Any]:
    """Each camera's offset to the LiDAR clock as ingest applied it (ms), and where it came from."""
    chain = str(rig.camchain.source) if rig.camchain is not None and rig.camchain.source else "the rig"
    given = f"timeshift_cam_imu in {chain}"
    if refined:
        given = f"--refine: estimated from the recording where observable (see the summary), else {given}"
    return {
        c.name: {
            "timeshift_cam_imu_ms": (c.timeshift_cam_imu or 0.0) * 1e3,
            "from": given
            if c.timeshift_cam_imu is not None or refined
            else "none in the rig: header stamps taken as exposure times",
        }
        for c in rig.cameras
    }


def _lidar_poses(rig: Any, refined: bool) -> dict[str, Any]:
    """Each LiDAR's pose in cam0 as ingest used it (4x4, m), and where it came from."""
    given = f"the rig file {rig.source}" if rig.source else "the rig"
    if refined:
        given = f"--refine: its points laid onto cam0's images where certain (see the summary), else {given}"
    return {lidar.name: {"T_cam0_lidar": lidar.T_cam0_lidar.tolist(), "from": given} for lidar in rig.lidars}


SETTINGS = ("R_cam0_rect", "height_full", "baseline_m", "params", "fisheye_size")
"""The keys of dataset.yaml a dataset is extended or resumed with only when equal; every sample's meta
records them too (`settings`), so that a folder whose dataset.yaml is lost still knows what made it."""


def sample_settings(asked: IngestConfig, geometry: Geometry, bags: list[Path]) -> dict[str, Any]:
    """`SETTINGS` of the configuration as asked, as JSON gives them back (for each sample's meta)."""
    doc = _fingerprint(asked, geometry, bags)
    settings: dict[str, Any] = json.loads(json.dumps({key: doc[key] for key in SETTINGS}))
    return settings


def _check_samples(
    asked: IngestConfig, geometry: Geometry, bags: list[Path], described: bool = False
) -> None:
    """DatasetError when a sample of `asked.out` was made with other settings than `asked` (its meta's
    `settings`; metadata without them, from an older SensorBox, by its sparse GT window alone).

    For a folder whose dataset.yaml is missing: a run must not describe samples it did not make. For one
    whose dataset.yaml agrees with the run (`described`): a sample copied in from another dataset would
    be taken as done, and the dataset would hold a sample its dataset.yaml does not describe.
    """
    want = sample_settings(asked, geometry, bags)
    window_ms = asked.lidar_window_ns / 1e6
    for path in sorted((asked.out / "meta").glob("*.json")):
        try:
            meta = read_meta(asked.out, path.stem)
        except DatasetError:
            continue  # damaged: the resume writes it again, or another recording's run does
        if meta.settings:
            differs = [(k, first_difference(meta.settings.get(k), want[k])) for k in SETTINGS]
        else:
            differs = [("gt", f" (window_ms: {meta.gt.window_ms:g} -> {window_ms:g})")]
            if meta.gt.method != "sparse" or meta.gt.window_ms == window_ms:
                continue
        key, where = next(((k, w) for k, w in differs if w), ("", ""))
        if not where:
            continue
        if described:
            yaml_path = asked.out / "dataset.yaml"
            raise DatasetError(
                f"{path}: this sample was made with a different {key!r}{where} than {yaml_path} describes "
                "and this run asks (a sample copied in from another dataset?); delete its files (the run "
                "writes it again) or choose a new --out"
            )
        raise DatasetError(
            f"{path}: the folder's samples were made with a different {key!r}{where} and "
            f"{asked.out / 'dataset.yaml'} is missing; choose a new --out or the settings they were made with"
        )


def check_format(out: Path) -> None:
    """DatasetError when `out` holds a benchmark (`<scene>/scene.yaml`) or a dataset.yaml that is not a
    training set's (`FORMAT`).

    Ingest replaces dataset.yaml with its own; another tool's, or a
    benchmark's, would be overwritten with no word, and a training set written
    beside a benchmark's scenes hides them from stats and eval (they take the
    folder for a training set). Checked before any work.
    """
    scenes = sorted(out.glob("*/scene.yaml"))
    if scenes:  # render-benchmark's layout: stats and eval would then see the training set alone
        raise DatasetError(
            f"{out}: holds a benchmark ({scenes[0].relative_to(out)}: the render-benchmark layout); "
            "ingest would mix a training set into it: choose another --out"
        )
    path = out / "dataset.yaml"
    if not path.exists():
        return
    doc = _read_dataset_yaml(path)
    if doc.get("format") != FORMAT:
        found = f"format {doc['format']!r}" if "format" in doc else "no 'format'"
        by = f" (SensorBox {doc['sensorbox_version']})" if "sensorbox_version" in doc else ""
        raise DatasetError(
            f"{path}: {found}{by}, expected format {FORMAT!r} (a SensorBox training set); "
            "ingest would overwrite it: choose another --out"
        )


def check_existing(asked: IngestConfig, geometry: Geometry, bags: list[Path]) -> dict[str, Any]:
    """The existing dataset.yaml of `asked.out` ({} when none), or DatasetError naming what differs.

    A dataset is extended or resumed only with the same settings, rig and,
    for a recording ingested before, the same data. Ingest checks this first,
    before its passes over the bags (minutes with a trajectory), and again when
    it writes dataset.yaml. A dataset without a sample (a run that stopped
    before its first, say on images of another size than the rig's) has
    nothing to differ from: it is started afresh, as if `asked.out` were empty.
    Samples without a dataset.yaml (deleted) are checked against their
    metadata's settings instead: a new dataset.yaml describes them only when
    they were made as this run asks.
    """
    path = asked.out / "dataset.yaml"
    check_format(asked.out)
    if not any((asked.out / "meta").glob("*.json")):
        return {}
    if not path.exists():
        _check_samples(asked, geometry, bags)
        return {}
    doc = _fingerprint(asked, geometry, bags)
    old = _read_dataset_yaml(path)
    for key in SETTINGS:
        if old.get(key) != doc[key]:
            where = first_difference(old.get(key), doc[key])
            raise DatasetError(
                f"{path}: an existing dataset was made with a different {key!r}{where}; "
                "choose a new --out or delete it"
            )
    _check_samples(asked, geometry, bags, described=True)
    if not (asked.out / "rig" / "rig.yaml").is_file():  # written before the first sample: deleted since
        raise DatasetError(
            f"{asked.out / 'rig' / 'rig.yaml'}: missing, so the rig the dataset's samples were made with "
            "cannot be compared with this run's; put the dataset's rig/ back or choose a new --out"
        )
    rig_differs = _rig_difference(geometry, asked.out / "rig")
    if rig_differs:
        raise DatasetError(
            f"{asked.out / 'rig'}: the dataset was made with another rig ({rig_differs}); "
            "choose a new --out or delete it"
        )
    names = [p.name for p in bags]
    mine = next((s for s in old.get("sources") or [] if s.get("bags") == names), None)
    identity = [bag_identity(p) for p in bags] if mine is not None else []
    if mine is not None and mine.get("identity", identity) != identity:
        raise DatasetError(
            f"{path}: a recording named {', '.join(names)} was ingested here before, from other data "
            f"(bytes {[i['bytes'] for i in mine['identity']]} then, {[i['bytes'] for i in identity]} now, "
            "or other content); choose a new --out or rename the recording"
        )
    return old


def _first_id_held(out: Path, held: list[int], source: str, otherwise: int) -> int:
    """The first id of the samples in `out` made from the recording `source` (their meta's source_bag),
    or `otherwise` when none is: a dataset.yaml rebuilt after it was deleted gives a recording its own
    samples back, not new ids past them (the samples resume, and the file names where they are)."""
    ids = []
    for i in sorted(held):
        try:
            if read_meta(out, sample_id(i)).source_bag == source:
                ids.append(i)
        except DatasetError:
            continue  # a damaged meta is rewritten by the run (`ingest.dataset.identity`)
    return ids[0] if ids else otherwise


def write_dataset_yaml(
    resolved: ResolvedRun, geometry: Geometry, bags: list[Path], run: IngestSummary
) -> int:
    """dataset.yaml with this recording among its sources; the first sample id of this recording.

    `resolved.asked` is the configuration as given (it must match the
    dataset's); `resolved` has this recording's GT method and window.
    Sample ids are keyed by recording: a recording ingested before keeps its
    id range (a rerun resumes it), a new one is appended after the last.
    """
    asked = resolved.asked
    doc = _fingerprint(asked, geometry, bags)
    path = asked.out / "dataset.yaml"
    old = check_existing(asked, geometry, bags)
    sources: list[dict[str, Any]] = list(old.get("sources") or [])
    names = [p.name for p in bags]
    identity = [bag_identity(p) for p in bags]
    mine = next((s for s in sources if s.get("bags") == names), None)
    if mine is not None and mine.get("samples") != run.planned:
        raise DatasetError(
            f"{path}: {', '.join(names)} was ingested here before with {mine.get('samples')} planned "
            f"samples, now {run.planned}; choose a new --out or delete it"
        )
    gt_now = {"method": run.method, "window_ms": resolved.window_ns / 1e6}
    gt_then = {k: ((mine or {}).get("ground_truth") or {}).get(k, v) for k, v in gt_now.items()}
    if gt_then != gt_now:  # a resumed recording would mix samples of two kinds of GT
        raise DatasetError(
            f"{path}: {', '.join(names)} was ingested here before with {gt_then['method']} GT over "
            f"+-{gt_then['window_ms']:g} ms, now {run.method} GT over +-{gt_now['window_ms']:g} ms "
            f"({run.decision}); choose a new --out or delete it"
        )
    if mine is None:  # after every id in use: dataset.yaml's ranges, and the samples (it may be missing)
        held = [int(m.stem) for m in (asked.out / "meta").glob("*.json") if m.stem.isdigit()]
        first = max(
            [*(int(s["first_id"]) + int(s["samples"]) for s in sources), *(i + 1 for i in held)], default=0
        )
        if not sources:  # dataset.yaml lost: this recording's samples keep the ids they were written under
            first = _first_id_held(asked.out, held, ",".join(names), first)
        mine = {"bags": names, "first_id": first, "samples": run.planned}
        sources.append(mine)
    mine["identity"] = identity
    mine["paths"] = [str(p) for p in bags]
    mine["ground_truth"] = {
        "method": run.method,
        "decision": run.decision,
        "window_ms": resolved.window_ns / 1e6,
        "trajectory": run.trajectory.as_dict() if run.trajectory else None,
        "imu_check": run.imu_check.as_dict() if run.imu_check else None,
    }
    mine["undecodable_messages"] = dict(run.undecodable)  # per topic, skipped under --max-bad
    mine["dropped_implausible"] = {t: dict(c) for t, c in run.dropped.items()}  # per topic, reason
    if run.lost_chunks:
        mine["lost_in_corrupt_chunks"] = {"messages": run.lost, "chunks": run.lost_chunks}
    else:
        mine.pop("lost_in_corrupt_chunks", None)
    doc["sources"] = sources
    write_atomic(
        path,
        (HEADER + yaml.safe_dump(doc, sort_keys=False)).encode(),
    )
    copy_rig(geometry, asked.out / "rig")
    return int(mine["first_id"])


def _rig_difference(geometry: Geometry, rig_dir: Path) -> str:
    """The first difference between `geometry`'s rig and the copy a dataset keeps in `rig_dir` ('' if none).

    Both files are compared as YAML (rig.yaml's poses and topics, camchain.yaml's
    intrinsics and extrinsics); the rig's name is not part of it. A dataset
    without a copy yet has nothing to differ from (`check_existing` refuses one
    whose samples lost theirs).
    """
    from calibration.rig import write_rig

    if not (rig_dir / "rig.yaml").is_file():
        return ""
    with tempfile.TemporaryDirectory(prefix="sensorbox-rig-") as tmp:
        write_rig(geometry.rig, Path(tmp) / "rig.yaml", camchain_name="camchain.yaml")
        for name in ("rig.yaml", "camchain.yaml"):
            new = yaml.safe_load((Path(tmp) / name).read_text())
            try:
                old = yaml.safe_load(read_text(rig_dir / name, "dataset rig", error=DatasetError))
            except (ValueError, yaml.YAMLError) as err:
                raise DatasetError(f"{rig_dir / name}: cannot read the dataset's rig: {err}") from err
            if isinstance(old, dict) and isinstance(new, dict):
                old.pop("name", None)
                new.pop("name", None)
            found = first_difference(old, new)
            if found:
                return f"{name}{found}"
    return ""


def copy_rig(geometry: Geometry, rig_dir: Path) -> None:
    """`rig_dir/rig.yaml` and `rig_dir/camchain.yaml`, both whole or neither.

    `calibration.rig.write_rig` writes them as one set, so a full disk or a
    read-only folder leaves no empty or cut file, and a target that is a
    device or FIFO is refused; the `OutputError` names the file.
    """
    from calibration.rig import write_rig

    write_rig(geometry.rig, rig_dir / "rig.yaml", camchain_name="camchain.yaml", error=OutputError)


def record_undecodable(
    out: Path, bags: list[Path], counts: dict[str, int], dropped: dict[str, dict[str, int]]
) -> None:
    """Set `undecodable_messages` (per topic) and `dropped_implausible` (per topic and reason) of the
    recording `bags` in `out/dataset.yaml`.

    The stream pass finds the undecodable images only after the description
    was written (the plan pass reads no pixels, and a sparse run decodes the
    IMU readings only there), so the counts are set again at the end of the run.
    """
    path = out / "dataset.yaml"
    doc = _read_dataset_yaml(path)
    names = [p.name for p in bags]
    for source in doc.get("sources") or []:
        if source.get("bags") == names:
            source["undecodable_messages"] = dict(counts)
            source["dropped_implausible"] = {t: dict(c) for t, c in dropped.items()}
    write_atomic(path, (HEADER + yaml.safe_dump(doc, sort_keys=False)).encode())


def record_calibration(out: Path, bags: list[Path], check: dict[str, Any]) -> None:
    """Set `calibration_check` of the recording `bags` in `out/dataset.yaml`: its samples' LiDAR points
    on cam0's images summed up (`ingest.train.gt.align.CalibrationCheck.as_yaml`), known only at the end."""
    path = out / "dataset.yaml"
    doc = _read_dataset_yaml(path)
    names = [p.name for p in bags]
    for source in doc.get("sources") or []:
        if source.get("bags") == names:
            source["calibration_check"] = check
    write_atomic(path, (HEADER + yaml.safe_dump(doc, sort_keys=False)).encode())


def _read_dataset_yaml(path: Path) -> dict[str, Any]:
    """`read_description`: the existing dataset.yaml, or one line why not (cut short: the line it ends at)."""
    return read_description(path, DatasetError)
