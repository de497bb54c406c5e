"""Render a view of dense scans: RGB + range per pixel, with splats, a z-buffer and masks.

`render_view` runs the recipe of `ingest.raster.recipe` with the stages of
`RenderParams.backend`: "numba" (`ingest.raster.compiled_view`, the
default), "numpy" (`ingest.raster.reference`, the reference), "torch" or
"cuda" (`ingest.raster.torch_view`, PyTorch on the CPU or a GPU). All give
the same view.
"""

from __future__ import annotations

from calibration.camera import CameraModel
from calibration.types import F64, Bool
from ingest.raster import recipe
from ingest.raster.geometry import PixelGeometry, Rendering, pixel_geometry, pixel_rays
from ingest.raster.lod import ScanIndex
from ingest.raster.params import RenderParams
from ingest.raster.reference import NumpyStages

__all__ = ["PixelGeometry", "Rendering", "pixel_geometry", "pixel_rays", "render_view"]


def render_view(
    sources: list[ScanIndex],
    model: CameraModel,
    T_world_cam: F64,
    params: RenderParams | None = None,
    pixel_mask: Bool | None = None,
) -> Rendering:
    """Render RGB + range of ``model`` at ``T_world_cam`` from the scans ``sources`` (`ingest.raster.recipe`).

    ``pixel_mask`` (H, W) limits the output to some pixels (e.g. the part of an
    equirect crop a fisheye sees); outside it everything is 0.
    """
    params = params or RenderParams()
    if params.backend == "numba":
        from ingest.raster.compiled_view import render_compiled

        return render_compiled(sources, model, T_world_cam, params, pixel_mask)
    if params.backend in ("torch", "cuda"):  # torch is optional: imported only when asked for
        from ingest.raster.torch_view import render_torch

        device = "cuda" if params.backend == "cuda" else "cpu"
        return render_torch(sources, model, T_world_cam, params, pixel_mask, device)
    return recipe.render(NumpyStages(), sources, model, T_world_cam, params, pixel_mask)
