"""The PyTorch renderer (RenderParams.backend "torch"/"cuda") against the compiled one, on the CPU.

The same device-agnostic code runs on a GPU with backend "cuda"; CI has none,
so the CPU build of torch runs it here on small synthetic scans: the same
holes, masks, clipping, colours and counts, ranges within 0.1 mm.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from calibration.spherical import Equirectangular, pinhole_for_fov  # noqa: E402
from calibration.virtual import partner_pose, virtual_ds  # noqa: E402
from ingest.raster import torch_view  # noqa: E402
from ingest.raster.geometry import ViewPoints  # noqa: E402
from ingest.raster.lod import point_index  # noqa: E402
from ingest.raster.params import RenderParams  # noqa: E402
from ingest.raster.view import render_view  # noqa: E402
from ingest.raster.visibility import zbuffer  # noqa: E402
from tests.ingest.test_render_compiled import CASES, H, W, assert_same, scans  # noqa: E402, F401

TORCH = RenderParams(backend="torch")


@pytest.fixture(autouse=True)
def one_torch_thread() -> Iterator[None]:
    """torch's CPU thread pool stalls for seconds on a loaded 2-core machine; these views are tiny."""
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


@pytest.mark.parametrize("case", list(CASES))
def test_torch_backend_renders_what_the_compiled_one_renders(scans, case):  # noqa: F811
    params = CASES[case]
    model = virtual_ds(scans["ref"], 150, W, H)
    T = partner_pose(scans["T"], "DOWN", 0.3)
    a = render_view(scans["idx"], model, T, params)
    b = render_view(scans["idx"], model, T, replace(params, backend="torch"))
    assert a.stats["valid_px"] > 0.3 * W * H
    assert_same(a, b)


@pytest.mark.parametrize("fill_passes", [0, 1])
def test_torch_backend_keeps_the_raw_fallback_of_unfilled_pixels(scans, fill_passes):  # noqa: F811
    """Surface pixels that no point and no fill reached take the splat's range (`raw_fallback`), as the
    compiled renderer gives them; a sparse scan at a fine resolution leaves many such pixels."""
    params = RenderParams(fill_passes=fill_passes)
    model = virtual_ds(scans["ref"], 120, 2 * W, 2 * H)
    a = render_view(scans["idx"], model, scans["T"], params)
    b = render_view(scans["idx"], model, scans["T"], replace(params, backend="torch"))
    assert a.stats["raw_px"] > (0.05 * a.stats["surface_px"] if fill_passes == 0 else 0), a.stats
    assert_same(a, b)


def test_torch_other_models_masks_and_dense_gt_settings(scans):  # noqa: F811
    pano = Equirectangular(128).crop(40, 90, 60, 160)
    keep = np.zeros((pano.height, pano.width), bool)
    keep[5:40, 10:150] = True
    T = scans["T"]
    assert_same(render_view(scans["idx"], pano, T, pixel_mask=keep),
                render_view(scans["idx"], pano, T, TORCH, pixel_mask=keep))  # fmt: skip
    pin = pinhole_for_fov(np.radians(80), W, H)  # not Double Sphere: projected on the host
    assert_same(render_view(scans["idx"][:1], pin, T), render_view(scans["idx"][:1], pin, T, TORCH))
    dense = RenderParams(points_per_px=None, frustum_culling=False, raw_fallback=False, fill_passes=0,
                         fit_gradient=False)  # fmt: skip
    idx = [point_index(scans["scans"][1])]
    model = virtual_ds(scans["ref"], 120, W, H)
    assert_same(
        render_view(idx, model, T, dense), render_view(idx, model, T, replace(dense, backend="torch"))
    )
    grey = replace(dense, colour=False)  # no colour: a black image, the same ranges
    assert_same(render_view(idx, model, T, grey), render_view(idx, model, T, replace(grey, backend="torch")))
    assert not render_view(idx, model, T, replace(grey, backend="torch")).bgr.any()
    T_away = T.copy()
    T_away[:3, 3] += [500.0, 0.0, 0.0]
    empty = render_view(scans["idx"], model, T_away, TORCH)
    assert empty.stats["valid_px"] == 0 and empty.holes.sum() == empty.rays.sum()


def test_torch_zbuffer_gives_the_numpy_keys():
    rng = np.random.default_rng(3)
    n = 5000
    pix = rng.integers(0, H * W, n)
    r = rng.uniform(0.5, 3.0, n).astype(np.float32)
    r[: n // 4] = r[n // 4 : n // 2]  # ties resolve by index
    ku, kv = (rng.integers(0, 4, n).astype(np.int16) for _ in range(2))
    f = np.zeros(n, np.float32)
    pts = ViewPoints(pix, f, f, r, ku, kv, np.zeros((n, 3), np.uint8), np.zeros(n, bool))
    own, splat = zbuffer(pts, H, W)
    t = {k: torch.from_numpy(getattr(pts, k)) for k in ("pix", "r", "ku", "kv")}
    t_own, t_splat = torch_view.zbuffer(t, H, W)
    assert np.array_equal(t_own.numpy(), own) and np.array_equal(t_splat.numpy(), splat)


def test_dense_gt_with_the_torch_backend_is_the_compiled_gt(scans):  # noqa: F811
    """`--backend torch|cuda` reaches the dense-GT renders: the same fisheye range and equirect disparity."""
    from ingest.train.gt.dense import DenseParams, dense_ground_truth

    scan = scans["scans"][0]
    T_world_cam = scans["T"]
    xyz_world = scan.xyz.astype(np.float64) @ scan.T_world_scan[:3, :3].T + scan.T_world_scan[:3, 3]
    pts_cam = (xyz_world - T_world_cam[:3, 3]) @ T_world_cam[:3, :3]
    model = virtual_ds(scans["ref"], 150, W, H)
    eq = Equirectangular(384)
    numba_params = DenseParams(free_space=False)
    torch_params = replace(numba_params, render=replace(numba_params.render, backend="torch"))
    a = dense_ground_truth(model, eq, np.eye(3), 0.1, pts_cam, numba_params)
    b = dense_ground_truth(model, eq, np.eye(3), 0.1, pts_cam, torch_params)
    assert a.range_img.count > 0.2 * W * H and a.disp_img.count > 2000, (a.range_img.count, a.disp_img.count)
    for x, y in ((a.range_img, b.range_img), (a.disp_img, b.disp_img)):
        assert np.array_equal(x.pixel, y.pixel)
        np.testing.assert_allclose(y.value, x.value, rtol=1e-5, atol=1e-4)
    assert a.unstable == b.unstable
