"""The GT z-buffer keeps exactly the nearest (or, as an ablation, the farthest) point of each pixel."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from calibration.rig import REFERENCE_RIG, read_rig
from ingest.train.groundtruth import GtParams, in_view, splat_to_pixels
from ingest.train.planes import Normals

MODEL = read_rig(REFERENCE_RIG).upper.model.scaled(0.125)  # 240 x 150: many points per pixel


@pytest.mark.parametrize("zbuffer", ["nearest", "farthest"])
def test_splat_keeps_the_nearest_point_per_pixel_like_a_lexsort(zbuffer):
    rng = np.random.default_rng(6)
    rays, ok = MODEL.unproject(rng.uniform(0, [MODEL.width, MODEL.height], (100_000, 2)))
    pts = rays[ok] * rng.uniform(0.5, 30.0, ok.sum())[:, None]
    pts[:50] = pts[50:100]  # exact ties: the earlier point wins, as a stable sort keeps it
    no_planes = Normals(np.zeros_like(pts), np.zeros(len(pts), bool))  # ranges stay the points' own
    params = replace(GtParams(), zbuffer=zbuffer)
    splat = splat_to_pixels(MODEL, pts, no_planes, params)

    seen, cols, rows = in_view(MODEL, pts)
    idx = np.nonzero(seen)[0]
    flat = rows[idx].astype(np.int64) * MODEL.width + cols[idx].astype(np.int64)
    r = np.linalg.norm(pts[idx], axis=1)
    order = np.lexsort((r if zbuffer == "nearest" else -r, flat))
    first = np.r_[True, flat[order][1:] != flat[order][:-1]]
    assert len(splat.pixel) < len(idx) / 2  # ~3 candidates per pixel
    np.testing.assert_array_equal(splat.pixel, flat[order][first])
    np.testing.assert_array_equal(splat.point, idx[order][first])
    np.testing.assert_allclose(splat.range_m, r[order][first], rtol=1e-12)
