"""The renderer's recipe, written once over the stages a backend provides (numpy, numba, torch).

Recipe for one camera (any `CameraModel`: fisheye, equirect, Cassini, pinhole,
crops) at `T_world_cam`:

1. Gather: every scan of the bundle gives the points the view needs
   (`ingest.raster.lod.select`: frustum culling of voxel buckets and a prefix
   per bucket for about `points_per_px` points per pixel), projected into
   the camera (float32): range from the camera centre and each point's
   footprint in pixels along u and v (its spacing on the surface, the
   scanner's angular spacing times its range from its own scanner, over its
   range from the camera, times the camera's local pixels per radian).
2. Z-buffer: a point's key packs its range (`RANGE_QUANTUM_M` steps) above
   its index in one int64, so a per-pixel minimum yields both the nearest
   range and which point it is. Two buffers: "own", the nearest point inside
   each pixel, and "splat", the nearest point whose footprint (an ellipse of
   half-widths ku, kv) covers it.
3. Leaks: an own point is background leaking through a gap of a nearer
   surface when a splat covering it is nearer by more than the same-surface
   tolerance (`RenderParams.tolerance`) and nearer own points lie on two
   opposite sides of it within `LEAK_RADIUS_PX`; with nearer points on one
   side only it sits beside that surface's silhouette and stays (no
   foreground fattening).
4. Value on the pixel-centre ray: a point sits up to half a pixel off the
   centre, on an oblique surface half a pixel of range gradient. The gradient
   is fitted per pixel from its 4-neighbours' own points on the same surface
   (least squares on their sub-pixel offsets; the diagonal neighbours join
   where those leave it undetermined); every same-surface point in the pixel
   is moved to the centre along it and averaged (noise). Pixels with a
   surface but no own point take the planar prediction of their neighbours
   (`fill_passes` passes outwards), else the splat's raw range (or stay
   invalid: `raw_fallback` off, as ground truth wants).
5. Finish: mask points (a label) and mask clouds render into their own splat
   buffer; pixels whose mask surface is not behind the rendered one are
   invalid. Ranges beyond `clip_m` are invalid (`clip_mode="invalid"`, colour
   kept) or their points are not rendered at all (`"drop"`). RGB is the own
   point's colour, else the splat's.

Every pixel with a ray ends as a surface with a range, masked, clipped, or a
hole (no data). A backend (`ingest.raster.reference` in numpy, the oracle of
the tests; `compiled_view` in numba; `torch_view` in PyTorch) implements
`Stages` on its own arrays: flat (H*W,) images, the same numbers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from calibration.camera import CameraModel
from calibration.types import F64, Bool
from ingest.raster.geometry import PixelGeometry, Rendering, pixel_geometry
from ingest.raster.lod import ScanIndex
from ingest.raster.params import RenderParams


class InView(Protocol):
    """A backend's points of one view (and its mask points), as its `Stages.gather` made them."""

    @property
    def n(self) -> int:
        """Points in the image."""

    @property
    def k_max(self) -> int:
        """The largest footprint half-width (pixels) of a point in the image; 0 when there is none."""

    @property
    def stats(self) -> dict[str, int]:
        """points_total, points_touched, points_in_image."""


@dataclass(frozen=True, eq=False)
class Winners:
    """Per pixel (flat): the z-buffers' nearest points; index n and range inf where none."""

    own_ok: Any  # a point inside the pixel
    own_i: Any
    splat_i: Any
    r_own: Any
    r_splat: Any
    surface: Any  # a footprint covers the pixel


@dataclass(frozen=True, eq=False)
class OwnSamples:
    """Per pixel (flat): the own point left after the leak test, range (NaN: none), offset from the centre."""

    ok: Any
    R: Any
    U: Any
    V: Any


@dataclass(frozen=True, eq=False)
class Finished:
    """Per pixel (flat): the rendered view before it goes to the host."""

    surf: Any  # a surface, inside the rays
    masked: Any
    clipped: Any
    good: Any  # a valid range
    range_m: Any  # 0 where not good
    bgr: Any  # (H*W, 3)


class Stages(Protocol):
    """One backend's stage functions; images are flat (H*W,) arrays of the backend."""

    def gather(
        self, sources: list[ScanIndex], model: CameraModel, geo: PixelGeometry, T_world_cam: F64,
        params: RenderParams, pixel_mask: Bool | None,
    ) -> InView: ...  # fmt: skip

    def ppr(self, geo: PixelGeometry) -> Any:
        """Pixels per radian of every pixel (float32, flat), on the backend."""

    def winners(self, view: Any, H: int, W: int) -> Winners:
        """Both z-buffers of the view's points and their nearest points."""

    def leaking(self, view: Any, win: Winners, ppr: Any, params: RenderParams, W: int, K: int) -> Any:
        """Which own points are background seen through a gap (bool), nearer points looked for within K px."""

    def own_samples(self, view: Any, win: Winners, leak: Any, W: int) -> OwnSamples:
        """The own points that are not leaks."""

    def gradient_value(self, own: OwnSamples, ppr: Any, params: RenderParams, W: int) -> tuple[Any, Any, Any]:
        """(gu, gv, value): the range gradient per pixel (m per pixel along u, v; 0 without a fit) and
        the own point's range moved to the pixel-centre ray along it (NaN without an own point)."""

    def average(
        self, view: Any, own: OwnSamples, gu: Any, gv: Any, value: Any, ppr: Any, params: RenderParams, W: int
    ) -> Any:
        """Each pixel's value: the mean of its same-surface points moved to the centre (written into
        ``value`` or a new array)."""

    def nonzero(self, mask: Any) -> Any:
        """Flat indices where ``mask`` holds."""

    def fill(
        self, value: Any, own: OwnSamples, gu: Any, gv: Any, need: Any, ppr: Any, params: RenderParams, W: int
    ) -> tuple[Any, Any]:
        """(value, which pixels of ``need`` got one): gaps filled from their neighbours' planes."""

    def finish(
        self, view: Any, value: Any, win: Winners, own: OwnSamples, rays: Bool, ppr: Any,
        params: RenderParams, W: int,
    ) -> Finished:  # fmt: skip
        """Masks, clipping, the valid ranges and the colours of the pixels with a ray (``rays``, host)."""

    def host(self, a: Any) -> np.ndarray[Any, Any]:
        """A backend array as a numpy array on the host."""


class HostArrays:
    """The array stages of a backend whose arrays are numpy arrays on the host (numpy, numba)."""

    @staticmethod
    def ppr(geo: PixelGeometry) -> Any:
        return geo.ppr.reshape(-1)

    @staticmethod
    def nonzero(mask: Bool) -> Any:
        return np.flatnonzero(mask)

    @staticmethod
    def host(a: Any) -> np.ndarray[Any, Any]:
        return np.asarray(a)


def render(
    stages: Stages, sources: list[ScanIndex], model: CameraModel, T_world_cam: F64, params: RenderParams,
    pixel_mask: Bool | None = None,
) -> Rendering:  # fmt: skip
    """Render RGB + range of ``model`` at ``T_world_cam`` from ``sources`` with ``stages`` (module doc)."""
    H, W = model.height, model.width
    geo = pixel_geometry(model)
    ppr = stages.ppr(geo)
    view = stages.gather(sources, model, geo, T_world_cam, params, pixel_mask)
    win = stages.winners(view, H, W)
    K = min(RenderParams.LEAK_RADIUS_PX, max(1, view.k_max))
    leak = stages.leaking(view, win, ppr, params, W, K)
    own = stages.own_samples(view, win, leak, W)

    # values on the pixel-centre rays: own points moved along the fitted gradient, averaged, gaps filled
    gu, gv, value = stages.gradient_value(own, ppr, params, W)
    if params.average_samples and view.n:
        value = stages.average(view, own, gu, gv, value, ppr, params, W)
    need = stages.nonzero(win.surface & ~own.ok)
    value, got = stages.fill(value, own, gu, gv, need, ppr, params, W)
    raw_px = need[~got]  # a surface but no own point and no neighbour: the splat's nearest range
    value[raw_px] = win.r_splat[raw_px] if params.raw_fallback else math.nan

    rays = geo.valid if pixel_mask is None else geo.valid & pixel_mask
    out = stages.finish(view, value, win, own, rays, ppr, params, W)
    surf = out.surf
    shape = (H, W)
    surf_host = stages.host(surf).reshape(shape)
    stats = dict(view.stats)
    counts = {
        "pixels_with_ray": int(rays.sum()),
        "surface_px": surf.sum(),
        "own_px": (own.ok & surf).sum(),
        "filled_px": surf[need[got]].sum(),
        "raw_px": surf[raw_px].sum(),
        "leak_rejected_px": (leak & surf).sum(),
        "masked_px": out.masked.sum(),
        "clipped_px": out.clipped.sum(),
        "hole_px": (rays & ~surf_host).sum(),
        "valid_px": out.good.sum(),
    }
    stats.update({k: int(v) for k, v in counts.items()})
    return Rendering(
        stages.host(out.bgr).reshape(H, W, 3), stages.host(out.range_m).reshape(shape), surf_host,
        stages.host(out.masked).reshape(shape),
        stages.host(out.clipped).reshape(shape), rays, stats,
    )  # fmt: skip
