"""The compiled renderer (RenderParams.backend="numba") against the numpy recipe it replaces.

Synthetic numpy scans (`ingest.raster.synthetic`: a box room with a box in
it, exact ranges) rendered by both backends: the same pixels with and without
a surface, the same masks and clipping, the same colours and counts, and
ranges within 0.1 mm (on x86-64 they are the same bits). The compiled
z-buffer must give the numpy z-buffer's keys bit for bit, including the
classes it spreads by a min filter instead of point by point.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from calibration import read_rig
from calibration.spherical import Equirectangular, pinhole_for_fov
from calibration.virtual import R_up_cam, partner_pose, virtual_ds
from ingest.raster import compiled_view
from ingest.raster.geometry import ViewPoints
from ingest.raster.lod import build_index, point_index
from ingest.raster.params import RenderParams
from ingest.raster.synthetic import room_scan
from ingest.raster.view import Rendering, render_view
from ingest.raster.visibility import zbuffer
from tests.calibration.test_virtual import RIG

W, H = 160, 96
NUMPY = RenderParams(backend="numpy")


@pytest.fixture(scope="module")
def scans():
    centre = room_scan(150_000, seed=1, label_wall=True, glass=True, name="c")
    side = room_scan(60_000, origin_world=(0.5, 1.0, 0.2), seed=2, noise_m=0.002, name="s")
    T = np.array(centre.T_world_scan)
    T[:3, :3] = R_up_cam(0.0)
    return {"idx": [build_index(centre), build_index(side)], "scans": [centre, side], "T": T,
            "ref": read_rig(RIG).camera("cam0").model}  # fmt: skip


def assert_same(a: Rendering, b: Rendering) -> None:
    for name in ("rays", "surface", "masked", "clipped"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert np.array_equal(a.range_m > 0, b.range_m > 0)  # the same valid pixels and holes
    assert float(np.abs(a.range_m - b.range_m).max()) <= 1e-4
    assert np.array_equal(a.bgr, b.bgr)
    assert a.stats == b.stats


CASES = {
    "default": RenderParams(),
    "clip invalid": RenderParams(clip_m=4.0),
    "clip drop, no raw fallback": RenderParams(clip_m=4.0, clip_mode="drop", raw_fallback=False),
    "naive all points": RenderParams(points_per_px=None, frustum_culling=False),
    "sparse LOD, no averaging": RenderParams(points_per_px=0.3, average_samples=False, fill_passes=5),
    "no gradient, no fill": RenderParams(fit_gradient=False, fill_passes=0, raw_fallback=False),
}


@pytest.mark.parametrize("case", list(CASES))
def test_compiled_backend_renders_what_numpy_renders(scans, case):
    params = CASES[case]
    model = virtual_ds(scans["ref"], 150, W, H)
    for T in (scans["T"], partner_pose(scans["T"], "DOWN", 0.3)):
        a = render_view(scans["idx"], model, T, replace(params, backend="numpy"))
        b = render_view(scans["idx"], model, T, params)
        assert a.stats["valid_px"] > 0.3 * W * H
        assert_same(a, b)
    assert a.stats["masked_px"] > 0 or case.startswith("clip drop")  # labelled wall and glass are in view


def test_other_models_pixel_masks_and_dense_gt_settings(scans):
    pano = Equirectangular(128).crop(40, 90, 60, 160)
    keep = np.zeros((pano.height, pano.width), bool)
    keep[5:40, 10:150] = True
    T = scans["T"]
    assert_same(render_view(scans["idx"], pano, T, NUMPY, pixel_mask=keep),
                render_view(scans["idx"], pano, T, pixel_mask=keep))  # fmt: skip
    pin = pinhole_for_fov(np.radians(80), W, H)
    assert_same(render_view(scans["idx"][:1], pin, T, NUMPY), render_view(scans["idx"][:1], pin, T))
    # dense ground truth draws every point of an unsorted cloud, each its own voxel
    dense = RenderParams(points_per_px=None, frustum_culling=False, raw_fallback=False, fill_passes=0,
                         fit_gradient=False)  # fmt: skip
    idx = [point_index(scans["scans"][1])]
    model = virtual_ds(scans["ref"], 120, W, H)
    numpy_dense = replace(dense, backend="numpy")
    assert_same(render_view(idx, model, T, numpy_dense), render_view(idx, model, T, dense))
    # ... and without colour: the same ranges and masks, a black image, in both backends
    coloured = render_view(idx, model, T, dense)
    assert coloured.bgr.any()
    for params in (dense, numpy_dense):
        grey = render_view(idx, model, T, replace(params, colour=False))
        assert not grey.bgr.any() and grey.bgr.shape == coloured.bgr.shape
        assert_same(replace(grey, bgr=coloured.bgr), coloured)


def test_a_full_panorama_renders_as_numpy_renders_it(scans):
    """An equirect projects with numpy's float32 arctan2 in every backend. A numba kernel's (libm's) is an
    ulp off numpy's for ~40 % of points and moved some across pixel edges: here the ranges of ~20 000
    pixels changed (up to 1.2 mm) and 2 colours, in bench_gpu --check up to 2.7 m at depth edges."""
    pano = Equirectangular(192)
    for T in (scans["T"], partner_pose(scans["T"], "DOWN", 0.3)):
        a = render_view(scans["idx"], pano, T, NUMPY)
        b = render_view(scans["idx"], pano, T)
        assert_same(a, b)
        assert np.array_equal(a.range_m, b.range_m)  # the same bits, not only within 0.1 mm


def test_nothing_in_view(scans):
    model = virtual_ds(scans["ref"], 120, W, H)
    T_away = scans["T"].copy()
    T_away[:3, 3] += [500.0, 0.0, 0.0]
    a = render_view(scans["idx"], model, T_away, NUMPY)
    b = render_view(scans["idx"], model, T_away)
    assert_same(a, b)
    assert b.stats["valid_px"] == 0 and b.holes.sum() == b.rays.sum()


def _rows_packed(rng: np.random.Generator, n: int, k_max: int) -> tuple[ViewPoints, ViewPoints, Any, Any]:
    """Random points; the same packed by row group as `compiled_view._gather` packs them, their order
    (selection index of each packed point) and the group starts."""
    pix = rng.integers(0, H * W, n)
    group = pix // W // 8
    pos = np.argsort(group, kind="stable")  # packed position -> selection order
    r = rng.uniform(0.5, 3.0, n).astype(np.float32)
    r[: n // 4] = r[n // 4 : n // 2]  # equal ranges: ties resolve by selection order
    ku = rng.integers(0, k_max + 1, n).astype(np.int16)
    kv = rng.integers(0, k_max + 1, n).astype(np.int16)
    ku[: n // 2] = kv[: n // 2] = 2  # one class dense enough for the min filter
    f = np.zeros(n, np.float32)
    pts = ViewPoints(pix, f, f, r, ku, kv, np.zeros((n, 3), np.uint8), np.zeros(n, bool))
    packed = ViewPoints(pix[pos], f, f, r[pos], ku[pos], kv[pos], pts.rgb, pts.masked)
    seg = np.searchsorted(group[pos], np.arange(-(-H // 8) + 1))[None, :]
    return pts, packed, pos, seg


@pytest.mark.parametrize("k_max", [0, 3, 6])
def test_compiled_zbuffer_gives_the_numpy_keys(k_max):
    pts, packed, order, seg = _rows_packed(np.random.default_rng(k_max), 20_000, k_max)
    own, splat = zbuffer(pts, H, W)
    k1 = int(max(pts.ku.max(), pts.kv.max())) + 1
    classes = np.bincount(pts.ku.astype(np.int64) * k1 + pts.kv, minlength=k1 * k1).reshape(k1, k1)
    layer_of, _ = compiled_view._dense_classes(classes, k1 - 1, H * W)
    assert (layer_of >= 0).any()  # the min-filter path is exercised
    for bands in (None, 1):
        c_own, c_splat = compiled_view.zbuffer(packed, order, seg, classes, H, W, bands=bands)
        assert np.array_equal(c_own, own) and np.array_equal(c_splat, splat)


@pytest.mark.parametrize(("k_max", "H", "W"), [(1, 9, 1), (2, 40, 33), (3, 70, 2), (6, 101, 77)])
def test_layer_dilation_is_the_min_over_each_points_footprint(k_max: int, H: int, W: int) -> None:
    """`dilate_layers` (row minima built width by width) against the plain definition: every layer pixel's
    key spread over its class's ellipse offsets, clipped to the image."""
    from ingest.raster import point_kernels as pk
    from ingest.raster.kernels import ellipse_offsets

    start, drow, dcol = ellipse_offsets(k_max)
    span_start, span_dr, _, span_w = pk.ellipse_spans(start, drow, dcol)
    rng = np.random.default_rng(k_max)
    n_cls = (k_max + 1) ** 2
    layer_cls = np.sort(rng.choice(n_cls, size=min(3, n_cls), replace=False)).astype(np.int64)
    empty = np.iinfo(np.int64).max
    layers = rng.integers(0, 1 << 40, size=(len(layer_cls), H * W)).astype(np.int64)
    layers[rng.random(layers.shape) < 0.9] = empty
    got = np.full(H * W, empty, np.int64)
    pk.dilate_layers(layers, layer_cls, span_start, span_dr, span_w, H, W, got)

    want = np.full((H, W), empty, np.int64)
    for layer, cls in zip(layers, layer_cls, strict=True):
        rows, cols = np.divmod(np.flatnonzero(layer != empty), W)
        for dr, dc in zip(drow[start[cls] : start[cls + 1]], dcol[start[cls] : start[cls + 1]], strict=True):
            r, c = rows + dr, cols + dc
            ok = (r >= 0) & (r < H) & (c >= 0) & (c < W)
            np.minimum.at(want, (r[ok], c[ok]), layer[rows[ok] * W + cols[ok]])
    assert np.array_equal(got, want.reshape(-1))


def test_compiled_atan2_matches_numpy_to_1e15_with_its_signed_zeros_and_infinities() -> None:
    rng = np.random.default_rng(3)
    n = 200_000
    y = rng.normal(size=n) * 10.0 ** rng.uniform(-6, 6, n)
    x = rng.normal(size=n) * 10.0 ** rng.uniform(-6, 6, n)
    special = np.array([0.0, -0.0, 1.0, -1.0, np.inf, -np.inf, np.nan, 1e-300, -1e-300, 1e300])
    y = np.concatenate([y, np.repeat(special, len(special)), [1.0, -1.0, 1.0, -1.0]])
    x = np.concatenate([x, np.tile(special, len(special)), [1.0, 1.0, -1.0, -1.0]])  # the octants' edges
    got = _atan2_all(y, x)
    want = np.arctan2(y, x)
    assert np.array_equal(np.isnan(got), np.isnan(want))
    assert np.array_equal(np.signbit(got), np.signbit(want))  # atan2(-0, -1) = -pi, atan2(+0, -1) = +pi
    assert np.nanmax(np.abs(got - want)) < 1e-15


def _atan2_all(y: np.ndarray[Any, Any], x: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    from numba import njit

    from ingest.raster.point_kernels import atan2

    @njit(cache=False)
    def run(y: Any, x: Any, out: Any) -> None:  # pragma: no cover
        for i in range(len(y)):
            out[i] = atan2(y[i], x[i])

    out = np.empty_like(y)
    run(y, x, out)
    return out


def test_compiled_sphere_cells_count_what_numpy_counts() -> None:
    from ingest.raster.lod import SPHERE_CELLS, angular_spacing, cell_spacing
    from ingest.raster.point_kernels import sphere_cells
    from tests.ingest.oracles import sphere_cells_numpy

    rng = np.random.default_rng(4)
    xyz = (rng.normal(size=(300_000, 3)) * 10.0 ** rng.uniform(-3, 3, (300_000, 1))).astype(np.float32)
    xyz[:1000, 0] = 0.0  # on the azimuth cells' edges at +-90 deg ...
    xyz[1000:2000, 1] = 0.0  # ... at 0 and 180 deg (cell 0 or the last by the sign of zero)
    xyz[2000:3000, 1] = -0.0
    xyz[3000:3100] = 0.0  # at the scanner: on the equator, at azimuth 0
    xyz[3100:3200, 2] = np.nan  # the first row of cells, as numpy's cast and clip put it
    n_u, n_az = SPHERE_CELLS
    cell = np.empty(len(xyz), np.int64)
    counts = np.zeros(n_u * n_az, np.int64)
    sphere_cells(xyz, n_u, n_az, cell, counts)
    cell_np, counts_np = sphere_cells_numpy(xyz)
    assert np.array_equal(cell, cell_np)
    assert np.array_equal(counts, counts_np)
    assert (cell[3000:3100] == n_u // 2 * n_az + n_az // 2).all()
    assert (cell[3100:3200] < n_az).all()
    for smooth in (1, 5):
        assert np.array_equal(
            angular_spacing(xyz, smooth=smooth), cell_spacing(cell_np, counts_np, SPHERE_CELLS, smooth)
        )
