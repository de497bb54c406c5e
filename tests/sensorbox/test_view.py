"""`sensorbox view`: a dataset saved as a Rerun recording and read back with Rerun's own reader.

The train dataset is the indoor static fixture ingested with dense GT
(every 5th frame: 4 samples, a trajectory); the benchmark one is a small
`render-benchmark` run of simulated scans. No viewer is opened.
"""

from __future__ import annotations

import json
import os
import re
import shutil
from collections import defaultdict
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import yaml

from calibration import read_rig
from ingest.errors import DatasetError
from ingest.train.run.pipeline import ingest
from ingest.train.run.settings import IngestConfig
from sensorbox.analysis.view import display_problem, view_dataset, viewer_executable
from sensorbox.analysis.view_benchmark import benchmark_layout
from sensorbox.analysis.view_files import (
    downscale_factor,
    downscale_nearest_surface,
    meta_scalars,
    pose_at,
    read_tum,
)
from sensorbox.analysis.view_train import train_layout
from tests.faults.cli import run_here, sensorbox
from tests.paths import FIXTURES_DIR, ROOT

rerun_chunk = pytest.importorskip("rerun.chunk")

INDOOR = FIXTURES_DIR / "indoor_static_mcap"
IMAGE_ENTITIES = ("cam0/fisheye", "cam1/fisheye", "equirect/up", "equirect/down_virt")


pytestmark = pytest.mark.xdist_group("view")  # one worker builds the module's datasets once


@pytest.fixture(scope="module")
def dense_ds(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("view") / "ds"
    rig = FIXTURES_DIR / "indoor_static_mcap.truth" / "rig.yaml"
    summary = ingest([INDOOR], IngestConfig(rig=rig, out=out, workers=1, every=5, gt="dense"))
    assert summary.written == 4
    return out


def _rows(rrd: Path, index: str) -> dict[str, list[tuple[int | None, dict[str, Any]]]]:
    """Every logged row of the recording by entity: (its `index` timeline value or None if static, its
    components)."""
    out: dict[str, list[tuple[int | None, dict[str, Any]]]] = defaultdict(list)
    for chunk in rerun_chunk.RrdReader(rrd).stream():
        batch = chunk.to_record_batch()
        names = batch.schema.names
        data = {n: batch.column(n).to_pylist() for n in names if ":" in n and not n.startswith("rerun.")}
        keys = batch.column(index).cast("int64").to_pylist() if index in names else [None] * batch.num_rows
        for r in range(batch.num_rows):
            out[chunk.entity_path.lstrip("/")].append((keys[r], {n: v[r] for n, v in data.items()}))
    return out


def _one_per_sample(rows: list[tuple[int | None, dict[str, Any]]]) -> dict[int, dict[str, Any]]:
    """The rows on the timeline (static ones left out), by sample; none logged twice."""
    on_timeline = [(k, v) for k, v in rows if k is not None]
    by_sample = dict(on_timeline)
    assert len(by_sample) == len(on_timeline), "an entity logged twice for one sample"
    return by_sample


def _u16(row: dict[str, Any], archetype: str) -> np.ndarray[Any, Any]:
    fmt = row[f"{archetype}:format"][0]
    buf = np.asarray(row[f"{archetype}:buffer"][0], np.uint8).view("<u2")
    return buf.reshape(fmt["height"], fmt["width"])


def _png(path: Path) -> np.ndarray[Any, np.dtype[np.uint16]]:
    """A uint16 GT PNG as written."""
    values = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert values is not None and values.dtype == np.uint16, path
    return np.asarray(values, np.uint16)


def _jpeg_shape(row: dict[str, Any]) -> tuple[int, ...]:
    """The shape of a logged JPEG image, decoded."""
    assert row["EncodedImage:media_type"] == ["image/jpeg"]
    image = cv2.imdecode(np.asarray(row["EncodedImage:blob"][0], np.uint8), cv2.IMREAD_COLOR)
    assert image is not None
    return tuple(image.shape)


def test_train_dataset_saved_and_read_back(
    dense_ds: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rrd = tmp_path / "ds.rrd"
    res = run_here(capsys, "view", str(dense_ds), "--save", str(rrd))
    assert res.returncode == 0, res.stderr
    lines = res.stdout.strip().splitlines()
    assert len(lines) == 1
    assert lines[0].startswith(
        f"{dense_ds} (train layout): 4 samples; 16 images; 8 depth images; 149 series (544 values); "
        "4 on the trajectory; 5 rig frames; saved "
    )
    assert not list(tmp_path.glob(".*.tmp"))
    assert len(rerun_chunk.RrdReader(rrd).blueprints()) == 1  # the default layout travels with the data
    rows = _rows(rrd, "sample")
    metas = {int(p.stem): json.loads(p.read_text()) for p in sorted((dense_ds / "meta").glob("*.json"))}
    assert sorted(metas) == [0, 1, 2, 3]
    times = _rows(rrd, "time")
    for entity in (*IMAGE_ENTITIES, "cam0/depth", "equirect/disparity", "world/rig"):
        assert sorted(_one_per_sample(rows[entity])) == sorted(metas), entity
    # one timeline: every sample at its exposure time
    stamps = sorted(k for k, _ in times["meta/gt/density"] if k is not None)
    assert stamps == sorted(m["exposure_ns"] for m in metas.values())
    for sid, meta in metas.items():
        fisheye = _one_per_sample(rows["cam0/fisheye"])[sid]
        assert _jpeg_shape(fisheye) == (300, 480, 3)  # under 960 px: as written
        depth = _one_per_sample(rows["cam0/depth"])[sid]
        png = _png(dense_ds / "depth_fisheye" / f"{sid:06d}.png")
        np.testing.assert_array_equal(_u16(depth, "DepthImage"), png)
        assert depth["DepthImage:meter"] == [1000.0]
        disp = _one_per_sample(rows["equirect/disparity"])[sid]
        assert disp["DepthImage:meter"] == [100.0]
        full = _png(dense_ds / "disp_equirect" / f"{sid:06d}.png")
        assert full.shape == (512, 1024)  # longest side over 960: halved
        np.testing.assert_array_equal(_u16(disp, "DepthImage"), downscale_nearest_surface(full, 2))
        series = {
            "meta/gt/density": meta["gt"]["density"],
            "meta/gt/depth_pixels": meta["gt"]["depth_pixels"],
            "meta/gt/trajectory_residual_mm": meta["gt"]["trajectory_residual_mm"],
            "meta/gt/accumulated_points": meta["gt"]["accumulated_points"],
            "meta/points/kept": meta["points"]["kept"],
            "meta/points/total": meta["points"]["total"],
            "meta/points/silent_lidars": 0,
            "meta/motion/applied": 1.0,
            "meta/motion/predicted_motion_px": meta["motion"]["predicted_motion_px"],
            "meta/stereo_dt_ms": meta["stereo_dt_ms"],
            "meta/twist_cam0/linear_z": meta["twist_cam0"][5],
            "meta/points/range_ratio/lidar_bottom/scatter": meta["points"]["range_ratio"]["lidar_bottom"][2],
            "meta/stereo_offset/across_px": meta["stereo_offset"][0],
        }
        for name in ("lidar_top", "lidar_bottom"):
            for field in ("shift_deg", "correlation", "points"):
                series[f"meta/alignment/{name}/{field}"] = meta["alignment"][name][field]
            series[f"meta/alignment/{name}/rotation_deg/y"] = meta["alignment"][name]["rotation_deg"][1]
        for entity, value in series.items():
            assert _one_per_sample(rows[entity])[sid]["Scalars:scalars"] == [pytest.approx(value)], entity
    # the rig's frames, static, from the dataset's rig/
    rig = read_rig(dense_ds / "rig" / "rig.yaml")
    for lidar in rig.lidars:
        (key, frame), *more = rows[f"world/rig/{lidar.name}"]
        assert key is None and not more
        np.testing.assert_allclose(frame["Transform3D:translation"][0], lidar.T_cam0_lidar[:3, 3], atol=1e-6)
    (key, traj), *more = rows["world/trajectory/indoor_static_mcap"]
    stamps_ns, _ = read_tum(dense_ds / "trajectories" / "indoor_static_mcap.tum")
    assert key is None and not more and len(traj["LineStrips3D:strips"][0]) == len(stamps_ns)


def test_full_res_keeps_the_equirect_whole(dense_ds: Path, tmp_path: Path) -> None:
    summary = view_dataset(dense_ds, tmp_path / "full.rrd", max_side_px=None)
    assert (summary.samples, summary.images, summary.depth_images) == (4, 16, 8)
    rows = _rows(tmp_path / "full.rrd", "sample")
    for sid, row in _one_per_sample(rows["equirect/disparity"]).items():
        full = _png(dense_ds / "disp_equirect" / f"{sid:06d}.png")
        np.testing.assert_array_equal(_u16(row, "DepthImage"), full)
    for row in _one_per_sample(rows["equirect/up"]).values():
        assert _jpeg_shape(row) == (512, 1024, 3)


def test_not_a_dataset_is_one_line_and_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "empty").mkdir()
    res = run_here(capsys, "view", str(tmp_path / "empty"), "--save", str(tmp_path / "x.rrd"))
    assert res.returncode == 2 and res.stdout == ""
    assert res.stderr.strip().splitlines() == [
        f"error: {tmp_path / 'empty'}: neither the WideDepth train layout (disp_equirect/, depth_fisheye/) "
        "nor the benchmark layout (<scene>/<FOV>FOV/<B>mm/CENTER/) is there"
    ]
    (tmp_path / "unfinished" / "depth_fisheye").mkdir(parents=True)
    res = run_here(capsys, "view", str(tmp_path / "unfinished"), "--save", str(tmp_path / "x.rrd"))
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == [
        f"error: {tmp_path / 'unfinished'}: no finished sample (meta/<id>.json); nothing to view"
    ]
    assert not list(tmp_path.glob("*.rrd")) and not list(tmp_path.glob(".*.tmp"))


def test_a_damaged_image_is_named_and_no_recording_is_left(
    dense_ds: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    broken = tmp_path / "ds"
    shutil.copytree(dense_ds, broken)
    (broken / "depth_fisheye" / "000002.png").write_bytes(b"\x89PNG\r\n\x1a\n cut")
    res = run_here(capsys, "view", str(broken), "--save", str(tmp_path / "out" / "x.rrd"))
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == [
        f"error: {broken / 'depth_fisheye' / '000002.png'}: cannot be decoded "
        "(12 bytes: empty, cut short or not an image)"
    ]
    assert list((tmp_path / "out").iterdir()) == []


def test_a_missing_image_is_counted_and_named(
    dense_ds: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    thin = tmp_path / "ds"
    shutil.copytree(dense_ds, thin)
    (thin / "right_fisheye" / "000001.png").unlink()
    res = run_here(capsys, "view", str(thin), "--save", str(tmp_path / "x.rrd"))
    assert res.returncode == 0, res.stderr
    assert ": 4 samples; 15 images; 8 depth images; " in res.stdout
    assert "; missing files: 1 (first: right_fisheye/000001.png); saved " in res.stdout
    assert sorted(_one_per_sample(_rows(tmp_path / "x.rrd", "sample")["cam1/fisheye"])) == [0, 2, 3]


def test_a_sample_whose_metadata_is_not_json_is_named(dense_ds: Path, tmp_path: Path) -> None:
    broken = tmp_path / "ds"
    shutil.copytree(dense_ds, broken)
    (broken / "meta" / "000003.json").write_text('{"gt": ')
    with pytest.raises(
        DatasetError, match=r"^.*/meta/000003\.json: cannot be read as JSON \(Expecting value"
    ):
        view_dataset(broken, tmp_path / "x.rrd")
    assert not (tmp_path / "x.rrd").exists() and not (tmp_path / ".x.rrd.tmp").exists()


def test_a_sample_whose_metadata_is_a_fifo_is_named_not_read(dense_ds: Path, tmp_path: Path) -> None:
    """Sweep 9: a FIFO as meta/000001.json blocked `view` until it was killed (60 s), no line."""
    broken = tmp_path / "ds"
    shutil.copytree(dense_ds, broken)
    (broken / "meta" / "000001.json").unlink()
    os.mkfifo(broken / "meta" / "000001.json")
    with pytest.raises(DatasetError) as err:
        view_dataset(broken, tmp_path / "x.rrd")
    assert str(err.value) == f"{broken}/meta/000001.json: is a FIFO (named pipe), not a sample metadata file"
    assert not (tmp_path / "x.rrd").exists() and not (tmp_path / ".x.rrd.tmp").exists()


def test_a_writer_that_dies_of_a_full_disk_is_one_line_and_exit_3(
    dense_ds: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Sweep 10: `view --save` onto a full file system ended in a traceback ('RuntimeError: File-writer
    thread shut down prematurely', from Rerun's flush: its writer thread died of the full disk first and
    says only that). It is the output refused (exit 3, one line naming the file and the space left), and
    no partial recording is left."""
    import rerun

    def died(self: object, *args: object, **kwargs: object) -> None:
        raise RuntimeError("File-writer thread shut down prematurely")

    monkeypatch.setattr(rerun.RecordingStream, "flush", died)
    code, _, lines = sensorbox(capsys, "view", str(dense_ds), "--save", str(tmp_path / "out" / "v.rrd"))
    assert code == 3
    assert len(lines) == 1 and re.fullmatch(
        rf"error: cannot write {re.escape(str(tmp_path / 'out' / 'v.rrd'))}: Rerun's file writer stopped "
        r"\(File-writer thread shut down prematurely\); [\d,]+ bytes free on its file system",
        lines[0],
    ), lines
    assert list((tmp_path / "out").iterdir()) == []


def test_save_onto_a_folder_is_refused(
    dense_ds: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    res = run_here(capsys, "view", str(dense_ds), "--save", str(tmp_path))
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == [f"error: --save {tmp_path}: is a folder; give a file path"]


def test_nearest_surface_downscale_keeps_sparse_pixels_and_takes_the_nearest() -> None:
    depth = np.zeros((5, 7), np.uint16)
    depth[0, 1] = 3000  # block (0, 0): alone
    depth[2, 2], depth[3, 3] = 5000, 4000  # block (1, 1): the nearer wins, no mean (4500)
    depth[4, 6] = 65535  # the last, partial block: kept, 65535 is a range, not padding
    out = downscale_nearest_surface(depth, 2)
    expected = np.zeros((3, 4), np.uint16)
    expected[0, 0], expected[1, 1], expected[2, 3] = 3000, 4000, 65535
    np.testing.assert_array_equal(out, expected)
    assert downscale_factor((2048, 4096), 960) == 5 and downscale_factor((600, 960), 960) == 1
    assert downscale_factor((2048, 4096), None) == 1


def test_meta_scalars_names_every_number() -> None:
    meta = {
        "id": "000001", "exposure_ns": 5, "files": {"a.png": {"bytes": 3}}, "settings": {"every": 5},
        "gt": {"density": 0.25, "method": "dense", "trajectory_residual_mm": None},
        "motion": {"applied": True, "velocity_cam0_mps": [1.0, 2.0, 3.0]},
        "points": {"silent_lidars": ["lidar_top"], "kept": 7},
        "twist_cam0": [0.0, 0.1, 0.2, 1.0, 1.1, 1.2],
        "alignment": {"lidar_top": {"shift_deg": 0.5, "information": [[1.0, 0.0], [0.0, 1.0]]}},
    }  # fmt: skip
    assert meta_scalars(meta) == {
        ("gt", "density"): 0.25,
        ("motion", "applied"): 1.0,
        ("motion", "velocity_cam0_mps", "x"): 1.0,
        ("motion", "velocity_cam0_mps", "y"): 2.0,
        ("motion", "velocity_cam0_mps", "z"): 3.0,
        ("points", "silent_lidars"): 1.0,
        ("points", "kept"): 7.0,
        ("twist_cam0", "angular_x"): 0.0,
        ("twist_cam0", "angular_y"): 0.1,
        ("twist_cam0", "angular_z"): 0.2,
        ("twist_cam0", "linear_x"): 1.0,
        ("twist_cam0", "linear_y"): 1.1,
        ("twist_cam0", "linear_z"): 1.2,
        ("alignment", "lidar_top", "shift_deg"): 0.5,
    }


def test_pose_at_interpolates_between_knots(tmp_path: Path) -> None:
    tum = tmp_path / "t.tum"
    s = np.sqrt(0.5)
    tum.write_text(f"# header\n10.000000000 0 0 0 0 0 0 1\n10.100000000 2 0 0 0 0 {s} {s}\n")
    stamps, T = read_tum(tum)
    assert stamps.tolist() == [10_000_000_000, 10_100_000_000]
    mid = pose_at(stamps, T, 10_050_000_000)
    assert mid is not None
    np.testing.assert_allclose(mid[:3, 3], [1.0, 0.0, 0.0], atol=1e-12)
    angle_deg = np.degrees(np.arctan2(mid[1, 0], mid[0, 0]))
    assert angle_deg == pytest.approx(45.0)
    assert pose_at(stamps, T, 9_999_999_999) is None and pose_at(stamps, T, 10_100_000_001) is None


def _write_benchmark(root: Path) -> dict[str, Any]:
    """A two-scene benchmark folder in render-benchmark's layout: one FOV and baseline, CENTER with a
    fisheye, its depth and the pano's disparity, DOWN with a fisheye; scene.yaml with its poses and stats."""
    rng = np.random.default_rng(0)
    written: dict[str, Any] = {}
    for k, scene in enumerate(("000_000_000", "000_001_000")):
        base = root / scene / "120FOV" / "65mm"
        for cam in ("CENTER", "DOWN"):
            (base / cam).mkdir(parents=True)
            cv2.imwrite(str(base / cam / "fisheye.png"), rng.integers(0, 255, (40, 64, 3), np.uint8))
        (base / "CENTER" / "depth").mkdir()
        (base / "CENTER" / "disparity").mkdir()
        depth = rng.integers(0, 9000, (40, 64)).astype(np.uint16)
        disp = rng.integers(0, 3000, (32, 64)).astype(np.uint16)
        cv2.imwrite(str(base / "CENTER" / "depth" / "fisheye.png"), depth)
        cv2.imwrite(str(base / "CENTER" / "disparity" / "pano.png"), disp)
        T = np.eye(4)
        T[:3, 3] = [float(k), 0.0, 1.4]
        doc = {
            "sensorbox_benchmark": 1, "scene": scene,
            "view": {"center_scan": f"s{k}", "T_world_center": T.tolist()},
            "scans": [{"name": f"s{k}", "points": 1000 + k, "dropped_points": k}],
            "T_center_partner": {"DOWN": {"65mm": [[1, 0, 0, 0], [0, 1, 0, 0.065], [0, 0, 1, 0], [0, 0, 0, 1]]}},
            "stats": {"120FOV/65mm/DOWN/fisheye": {"hole_px": 10 + k, "valid_px": 2000 - k}},
        }  # fmt: skip
        (root / scene / "scene.yaml").write_text(yaml.safe_dump(doc))
        written[scene] = {"depth": depth, "disp": disp, "doc": doc}
    return written


def test_benchmark_dataset_saved_and_read_back(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    written = _write_benchmark(tmp_path / "bench")
    rrd = tmp_path / "b.rrd"
    res = run_here(capsys, "view", str(tmp_path / "bench"), "--save", str(rrd))
    assert res.returncode == 0, res.stderr
    assert res.stdout.startswith(
        f"{tmp_path / 'bench'} (benchmark layout): 2 scenes; 4 images; 4 depth images; "
        "6 series (8 values); 2 rig frames; saved "
    )
    rows = _rows(rrd, "scene")
    for n, scene in enumerate(written.values()):
        depth = _one_per_sample(rows["120FOV/65mm/CENTER/depth/fisheye"])[n]
        np.testing.assert_array_equal(_u16(depth, "DepthImage"), scene["depth"])
        assert depth["DepthImage:meter"] == [1000.0]
        disp = _one_per_sample(rows["120FOV/65mm/CENTER/disparity/pano"])[n]
        np.testing.assert_array_equal(_u16(disp, "DepthImage"), scene["disp"])
        assert disp["DepthImage:meter"] == [100.0]
        for cam in ("CENTER", "DOWN"):
            assert n in _one_per_sample(rows[f"120FOV/65mm/{cam}/fisheye"])
        stats = scene["doc"]["stats"]["120FOV/65mm/DOWN/fisheye"]
        for field in ("hole_px", "valid_px"):
            entity = f"scene/stats/120FOV/65mm/DOWN/fisheye/{field}"
            assert _one_per_sample(rows[entity])[n]["Scalars:scalars"] == [float(stats[field])], entity
        scan = scene["doc"]["scans"][0]
        assert _one_per_sample(rows[f"scene/scans/{scan['name']}/points"])[n]["Scalars:scalars"] == [
            float(scan["points"])
        ]
        centre = _one_per_sample(rows["world/center"])[n]
        np.testing.assert_allclose(centre["Transform3D:translation"][0], [float(n), 0.0, 1.4])
        down = _one_per_sample(rows["world/center/65mm/DOWN"])[n]
        np.testing.assert_allclose(down["Transform3D:translation"][0], [0.0, 0.065, 0.0], atol=1e-7)


@pytest.fixture(scope="module")
def rendered(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A real `render-benchmark` run: three coarse simulated scans, one centre, 64x40 fisheyes (2 s)."""
    from ingest.render.benchmark import run_benchmark
    from ingest.render.plan import BenchmarkConfig
    from ingest.render.scans import read_scans
    from sensorbox.sim.appearance import Texture
    from sensorbox.sim.scenes import build_scene
    from sensorbox.sim.tls import TlsParams, bundle_poses, simulate_scan, write_site
    from tests.calibration.test_virtual import RIG

    root = tmp_path_factory.mktemp("rendered")
    scene, params = build_scene("indoor", 0), TlsParams(step_deg=1.0)
    scans = [
        simulate_scan(scene, Texture(0), T, params, f"s{k}")
        for k, T in enumerate(bundle_poses([-2.0, 0.0, 1.4]))
    ]
    manifest = write_site(root / "site", scene, scans, "ply", params)
    cfg = BenchmarkConfig(
        fovs_deg=(120.0,), baselines_mm=(120.0,), width=64, height=40, height_full=64, centers=("s0",)
    )
    run_benchmark(read_scans([manifest]), read_rig(RIG).camera("cam0").model, root / "out", cfg)
    return root / "out"


def test_a_rendered_benchmark_has_every_view_and_number(rendered: Path, tmp_path: Path) -> None:
    summary = view_dataset(rendered, tmp_path / "r.rrd")
    assert len(rerun_chunk.RrdReader(tmp_path / "r.rrd").blueprints()) == 1
    scene = rendered / "000_000_000"
    pngs = sorted(p.relative_to(scene).with_suffix("").as_posix() for p in scene.rglob("*.png"))
    gt = [p for p in pngs if "/depth/" in p or "/disparity/" in p]
    # 120FOV: CENTER 6 views, DOWN 5, RIGHT 6; CENTER's depth of its 6 views, disparity of 5 (no fisheye)
    assert len(pngs) == 28 and len(gt) == 11
    rows = _rows(tmp_path / "r.rrd", "scene")
    for rel in pngs:
        (row,) = _one_per_sample(rows[rel]).values()
        if rel in gt:
            meter = 1000.0 if "/depth/" in rel else 100.0
            png = _png(scene / f"{rel}.png")
            np.testing.assert_array_equal(_u16(row, "DepthImage"), png)
            assert row["DepthImage:meter"] == [meter]
        else:
            assert row["EncodedImage:media_type"] == ["image/jpeg"]
    doc = yaml.safe_load((scene / "scene.yaml").read_text())
    numbers = sum(len(v) for v in doc["stats"].values()) + 2 * len(doc["scans"])
    assert (summary.samples, summary.images, summary.depth_images) == (1, 17, 11)
    assert summary.scalars == len(summary.series) == numbers
    valid = _one_per_sample(rows["scene/stats/120FOV/120mm/DOWN/fisheye/valid_px"])[0]
    assert valid["Scalars:scalars"] == [float(doc["stats"]["120FOV/120mm/DOWN/fisheye"]["valid_px"])]


def test_without_a_display_the_viewer_is_refused_in_one_line(
    dense_ds: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    for name in ("DISPLAY", "WAYLAND_DISPLAY"):
        monkeypatch.delenv(name, raising=False)
    res = run_here(capsys, "view", str(dense_ds))
    assert res.returncode == 2 and res.stdout == ""
    assert res.stderr.strip().splitlines() == [
        "error: no display for the Rerun viewer (DISPLAY and WAYLAND_DISPLAY are unset); save the recording "
        "with --save FILE.rrd and open it where there is one ('rerun FILE.rrd')"
    ]
    assert display_problem({"DISPLAY": ":0"}, "linux") is None
    assert display_problem({"WAYLAND_DISPLAY": "wayland-0"}, "linux") is None
    assert display_problem({}, "darwin") is None


def test_the_viewer_executable_is_found_beside_the_python_running(tmp_path: Path) -> None:
    venv_bin = tmp_path / "venv" / "bin"
    venv_bin.mkdir(parents=True)
    (venv_bin / "rerun").write_text("#!/bin/sh\n")
    (venv_bin / "rerun").chmod(0o755)
    assert viewer_executable("/nonexistent", venv_bin / "python") == venv_bin / "rerun"
    assert viewer_executable("", tmp_path / "python") is None


def test_the_default_layout_charts_density_misalignment_points_and_motion() -> None:
    series = {
        "/meta/gt/density", "/meta/gt/depth_pixels", "/meta/alignment/lidar_top/shift_deg",
        "/meta/alignment/lidar_top/correlation", "/meta/alignment/lidar_bottom/shift_deg",
        "/meta/points/kept", "/meta/points/zero", "/meta/motion/predicted_motion_px",
    }  # fmt: skip
    assert train_layout(series) == [
        ("GT density", ["/meta/gt/density"]),
        (
            "misalignment per LiDAR (shift_deg)",
            ["/meta/alignment/lidar_bottom/shift_deg", "/meta/alignment/lidar_top/shift_deg"],
        ),
        ("points per filter", ["/meta/points/kept", "/meta/points/zero"]),
        ("motion and trajectory residual", ["/meta/motion/predicted_motion_px"]),
    ]
    assert train_layout({"/meta/stereo_dt_ms"}) == []


def test_help_and_a_missing_argument(capsys: pytest.CaptureFixture[str]) -> None:
    res = run_here(capsys, "view", "--help")
    assert res.returncode == 0 and "--save" in res.stdout and "--full-res" in res.stdout
    res = run_here(capsys, "view")
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == [
        "error: Missing argument 'dataset'. (see 'sensorbox view --help')"
    ]
    res = run_here(capsys, "view", str(ROOT), "--save", "")
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == [
        "error: --save '': empty path (that is the current folder); give a path"
    ]


def test_the_benchmark_layout_has_a_view_per_image_with_the_depth_over_centers() -> None:
    images = [
        "120FOV/65mm/CENTER/fisheye", "120FOV/65mm/CENTER/depth/fisheye", "120FOV/65mm/CENTER/disparity/pano",
        "120FOV/65mm/CENTER/pano", "120FOV/65mm/DOWN/fisheye", "195FOV/65mm/RIGHT/cassini_crop",
    ]  # fmt: skip
    assert benchmark_layout(images) == {
        "120FOV/65mm": [
            ("CENTER fisheye + depth", ["120FOV/65mm/CENTER/fisheye", "120FOV/65mm/CENTER/depth/fisheye"]),
            ("CENTER pano", ["120FOV/65mm/CENTER/pano"]),
            ("CENTER pano disparity", ["120FOV/65mm/CENTER/disparity/pano"]),
            ("DOWN fisheye", ["120FOV/65mm/DOWN/fisheye"]),
        ],
        "195FOV/65mm": [("RIGHT cassini_crop", ["195FOV/65mm/RIGHT/cassini_crop"])],
    }
