"""Dense-scan renderer against the simulator's exact truth: range accuracy, leaks, holes, masks, clipping, LOD.

Scans are a simulated terrestrial scanner (0.25 deg grid, 0.87 M points each)
in the indoor scene; truth is the mesh's exact range along every pixel ray.
Metrics: median |error| away from depth edges (3 px band), "leaks" = pixels
showing something farther than the true first surface by > max(5 cm, 3 %).
"""

from dataclasses import asdict, replace

import numpy as np
import pytest

from calibration import CameraModel, read_rig
from calibration.spherical import Cassini, Equirectangular, pinhole_for_fov
from calibration.virtual import CroppedModel, R_up_cam, partner_pose, virtual_ds
from ingest.errors import ScanError
from ingest.eval.metrics import score_range
from ingest.raster.lod import build_index
from ingest.raster.params import RenderParams
from ingest.raster.scan import Scan
from ingest.raster.view import render_view
from sensorbox.sim.appearance import Texture
from sensorbox.sim.scenes import build_scene
from sensorbox.sim.tls import TlsParams, bundle_poses, simulate_scan, true_range
from tests.calibration.test_virtual import RIG

W, H = 256, 160
CENTRE = [-2.0, 0.0, 1.4]


def _index(s, **kw):
    return build_index(Scan(s.name, s.T_world_scan, s.xyz_scan, s.rgb, mask_xyz=s.mask_xyz_scan, **kw))


@pytest.fixture(scope="module")
def site():
    scene = build_scene("indoor", 0)
    tex = Texture(0)
    exact = [
        simulate_scan(scene, tex, T, TlsParams(step_deg=0.25), f"s{k}")
        for k, T in enumerate(bundle_poses(CENTRE))
    ]
    noisy = simulate_scan(
        scene, tex, exact[0].T_world_scan, TlsParams(step_deg=0.25, range_noise_m=0.0015), "n0"
    )
    T = np.array(exact[0].T_world_scan)
    T[:3, :3] = R_up_cam(0.0)
    return {
        "scene": scene,
        "sim": exact,
        "idx": [_index(s) for s in exact],
        "noisy": _index(noisy),
        "T": T,
        "ref": read_rig(RIG).camera("cam0").model,
    }


def _score(rend, truth):
    exact, _ = truth
    return {**asdict(score_range(rend.range_m, exact)), "holes": int(rend.holes.sum())}


@pytest.mark.parametrize("fov", [120, 195])
def test_bundle_view_matches_the_mesh(site, fov):
    m = virtual_ds(site["ref"], fov, W, H)
    rend = render_view(site["idx"], m, site["T"])
    s = _score(rend, true_range(site["scene"], m, site["T"]))
    assert s["median_mm"] <= 0.2 and s["p90_mm"] <= 1.0  # acceptance: median <= 1 mm off edges
    assert s["leak"] <= 1e-3  # acceptance: background through foreground <= 0.1 %
    assert s["holes"] <= 2 and s["valid"] > 0.9 * rend.rays.sum()
    assert rend.stats["points_touched"] < 0.4 * rend.stats["points_total"]  # LOD: the view needs few points


@pytest.mark.parametrize("partner", ["DOWN", "RIGHT"])
def test_neighbour_scans_fill_what_the_centre_could_not_see(site, partner):
    m = virtual_ds(site["ref"], 120, W, H)
    T = partner_pose(site["T"], partner, 0.3)
    truth = true_range(site["scene"], m, T)
    one = _score(render_view(site["idx"][:1], m, T), truth)
    three = _score(render_view(site["idx"], m, T), truth)
    assert one["holes"] > 300  # 0.3 m off the scan centre: disocclusions the central scan never saw
    assert three["holes"] <= one["holes"] / 50
    assert one["leak_off_silhouette"] <= 5e-4 and three["leak"] <= 1e-3
    assert one["median_mm"] <= 0.2 and three["median_mm"] <= 0.2


def test_range_noise_is_averaged_not_biased(site):
    m = virtual_ds(site["ref"], 120, W, H)
    truth = true_range(site["scene"], m, site["T"])
    avg = _score(render_view([site["noisy"]], m, site["T"]), truth)
    near = _score(render_view([site["noisy"]], m, site["T"], RenderParams(average_samples=False)), truth)
    assert avg["median_mm"] <= 1.0 and abs(avg["bias_mm"]) <= 0.3  # 1.5 mm scanner noise
    assert avg["median_mm"] < 0.9 * near["median_mm"]
    assert near["bias_mm"] < avg["bias_mm"] - 0.1  # the nearest sample alone is pulled towards the camera


def test_glass_is_masked_and_keeps_its_colour(site):
    m = virtual_ds(site["ref"], 120, W, H)
    rend = render_view(site["idx"], m, site["T"])
    _, glass = true_range(site["scene"], m, site["T"])
    assert glass.sum() > 500  # the pane is in view
    assert (rend.masked & glass).sum() >= 0.95 * glass.sum()
    assert (rend.masked & ~glass).sum() <= 0.015 * rend.rays.sum()  # a px or two around the pane
    assert (rend.range_m[rend.masked] == 0).all()
    assert (rend.bgr[rend.masked].max(axis=1) > 0).mean() > 0.99  # the camera sees through: colour kept
    bare = render_view([replace(site["idx"][0], mask_xyz=np.zeros((0, 3), np.float32))], m, site["T"])
    assert bare.masked.sum() == 0


def test_labelled_points_are_masked(site):
    s = site["sim"][0]
    x = s.xyz_scan @ s.T_world_scan[:3, :3].T + s.T_world_scan[:3, 3]
    label = x[:, 2] < 0.01  # the floor, as if it were a mirror
    idx = _index(replace(s, mask_xyz_scan=np.zeros((0, 3), np.float32)), masked=label)
    m = virtual_ds(site["ref"], 120, W, H)
    rend = render_view([idx], m, site["T"])
    rays, _ = m.unproject(m.pixel_grid().reshape(-1, 2))
    exact, _ = true_range(site["scene"], m, site["T"])
    z = site["T"][2, 3] + (rays @ site["T"][:3, :3].T)[:, 2].reshape(H, W) * exact
    on_floor = np.isfinite(z) & (z < 0.005)
    assert on_floor.sum() > 3000
    assert (rend.masked & on_floor).sum() >= 0.97 * on_floor.sum()
    assert (rend.masked & ~on_floor).sum() <= 0.02 * rend.rays.sum()


def test_clipping_far_ranges(site):
    m = virtual_ds(site["ref"], 120, W, H)
    exact, _ = true_range(site["scene"], m, site["T"])
    far = np.isfinite(exact) & (exact > 3.05)
    near = np.isfinite(exact) & (exact < 2.95)
    assert far.sum() > 1000 and near.sum() > 1000
    inv = render_view(site["idx"], m, site["T"], RenderParams(clip_m=3.0))
    assert inv.range_m.max() <= 3.0
    assert inv.clipped[far & ~inv.masked].mean() > 0.99 and not inv.clipped[near].any()
    assert (inv.bgr[far].max(axis=1) > 0).mean() > 0.99  # colour kept
    drop = render_view(site["idx"], m, site["T"], RenderParams(clip_m=3.0, clip_mode="drop"))
    # dropped points leave no surface; what remains beyond are nearer objects' silhouettes (splats
    # reach 1-2 px into the void) and sub-pixel legs and cables the exact centre ray misses
    beyond = np.isfinite(exact) & (exact > 3.3)
    assert drop.holes[beyond].mean() > 0.97 and (drop.bgr[drop.holes] == 0).all()
    assert drop.range_m.max() <= 3.0 and drop.clipped.sum() < 0.05 * inv.clipped.sum()  # fills at the rim


def test_sparse_level_of_detail_still_closes_surfaces(site):
    m = virtual_ds(site["ref"], 120, W, H)
    truth = true_range(site["scene"], m, site["T"])
    sparse = render_view(site["idx"][:1], m, site["T"], RenderParams(points_per_px=0.5))
    s = _score(sparse, truth)
    assert s["holes"] <= 20 and s["leak_off_silhouette"] <= 5e-4  # splats close a 1.4 px point spacing
    assert s["median_mm"] <= 1.0
    assert sparse.stats["points_in_image"] < 0.4 * W * H * 2  # and it really drew fewer points


def test_lod_render_agrees_with_the_all_points_render(site):
    m = virtual_ds(site["ref"], 140, W, H)
    truth = true_range(site["scene"], m, site["T"])
    lod = render_view(site["idx"][:1], m, site["T"])
    naive = render_view(
        site["idx"][:1], m, site["T"], RenderParams(points_per_px=None, frustum_culling=False)
    )
    assert naive.stats["points_touched"] == site["idx"][0].n_points
    assert lod.stats["points_touched"] < 0.2 * naive.stats["points_touched"]
    a, b = _score(lod, truth), _score(naive, truth)
    assert (
        a["median_mm"] <= 0.2 and b["median_mm"] <= 0.2 and abs(a["valid"] - b["valid"]) < 0.01 * a["valid"]
    )


@pytest.mark.parametrize("kind", ["pano_crop", "cassini", "pinhole"])
def test_other_projections_match_the_mesh(site, kind):
    m: CameraModel
    if kind == "pano_crop":
        m = Equirectangular(512).crop(150, 330, 200, 360)
    elif kind == "cassini":
        m = CroppedModel(Cassini(512), 100, 380, 300, 260)
    else:
        m = pinhole_for_fov(np.radians(90), W, H)
    rend = render_view(site["idx"], m, site["T"])
    s = _score(rend, true_range(site["scene"], m, site["T"]))
    assert s["median_mm"] <= 0.2 and s["leak"] <= 1e-3 and s["holes"] <= 0.001 * m.width * m.height


def test_pixel_mask_and_empty_input(site):
    m = virtual_ds(site["ref"], 120, W, H)
    keep = np.zeros((H, W), bool)
    keep[40:120, 60:200] = True
    rend = render_view(site["idx"][:1], m, site["T"], pixel_mask=keep)
    assert (rend.range_m[~keep] == 0).all() and (rend.bgr[~keep] == 0).all()
    assert rend.stats["pixels_with_ray"] == keep.sum() and rend.surface[keep].all()
    T_away = site["T"].copy()
    T_away[:3, 3] += [500.0, 0.0, 0.0]  # far outside the room, looking at nothing
    T_away[:3, :3] = R_up_cam(0.0)
    empty = render_view(site["idx"][:1], m, T_away)
    assert empty.stats["valid_px"] == 0 and empty.holes.sum() == empty.rays.sum()


def test_a_scan_with_absurd_coordinates_is_one_line_without_numpy_warnings():
    """Every 1000th point at 1e30 gave two RuntimeWarnings (an int32 cast) and "use a larger voxel
    size", which no CLI option sets."""
    import warnings

    xyz = np.random.default_rng(0).uniform(-5, 5, (5000, 3)).astype(np.float32)
    xyz[::1000] = 1e30
    scan = Scan("far", np.eye(4), xyz, np.zeros((5000, 3), np.uint8), source="far.ply")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ScanError) as err:
            build_index(scan)
    assert str(err.value) == (
        "far.ply: coordinates up to 1e+30 m (bounding box 1e+30 x 1e+30 x 1e+30 m), more than the renderer's "
        "index of 0.25 m voxels holds (about 1625 m a side); expected the scan in metres in its scanner frame "
        "(far outliers, another unit or a world frame?)"
    )
    small_but_far = replace(
        scan, xyz=(xyz[1:1000] + np.float32(1e9)).astype(np.float32), rgb=scan.rgb[1:1000]
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(
            ScanError, match=r"^far\.ply: coordinates up to 1e\+09 m \(bounding box 0 x 0 x 0 m\)"
        ):
            build_index(small_but_far)
