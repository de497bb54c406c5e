"""The renderer's settings and constants: every threshold and weight of its recipe, defined once.

`RenderParams` holds what a caller chooses (density, tolerances, clipping,
which stages run, the backend) as dataclass fields, and the recipe's fixed
thresholds and weights as named class constants (`ClassVar`): every backend
reads them from here, the numba kernels as arguments. The class constants
stay out of `dataclasses.asdict`, so scene.yaml, dataset.yaml and the meta
files, which record the settings, record only what a caller can choose.

The z-buffer key layout and the pixel neighbourhoods are module constants.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

RANGE_QUANTUM_M = 1e-4  # z-buffer key resolution


IDX_BITS = 28  # points per buffer per view < 2^28


IDX_MASK = (1 << IDX_BITS) - 1  # a key's point index


Q_MAX = (1 << 25) - 1  # ranges up to 3.3 km


# Keys sit above the bit pattern of 1.0 so, viewed as float64, they are normal positive numbers
# ordered like the integers; the empty key is the pattern of +inf.
KEY_BASE = 0x3FF0_0000_0000_0000


EMPTY_KEY = 0x7FF0_0000_0000_0000


AXES = ((0, 1), (1, 0), (1, 1), (1, -1))  # 4 axes through a pixel (drow, dcol): the leak test's sides


NB8 = ((0, 1), (0, -1), (1, 0), (-1, 0), (1, 1), (-1, -1), (1, -1), (-1, 1))  # opposite pairs adjacent


BACKENDS = ("numba", "numpy", "torch", "cuda")


def backend_problem(backend: str) -> str | None:
    """Why `backend` (`RenderParams.backend`) cannot render here, or None: torch for torch and cuda, a GPU
    for cuda.

    The GPU is looked for through NVML, without starting CUDA in this process,
    so that forked workers can still start it themselves.
    """
    if backend not in BACKENDS:
        return f"expected {', '.join(BACKENDS[:-1])} or {BACKENDS[-1]}"
    if backend in ("torch", "cuda"):
        try:
            import torch
        except ImportError:
            return "PyTorch is not installed (pip install torch)"
        os.environ.setdefault("PYTORCH_NVML_BASED_CUDA_CHECK", "1")
        if backend == "cuda" and not torch.cuda.is_available():
            return f"torch {torch.__version__} sees no CUDA GPU"
    return None


@dataclass(frozen=True)
class RenderParams:
    """Renderer settings (metres, pixels) and the recipe's fixed thresholds (class constants).

    Distances in pixels are measured between a point's sub-pixel position
    and a pixel centre; `tolerance` turns a distance into the largest range
    difference of one surface.
    """

    points_per_px: float | None = 2.0  # LOD density target; None = every point in the frustum
    splat_scale: float = 1.5  # footprint half-width = scale x point spacing in the image (random points)
    max_splat_px: int = 6
    near_m: float = 0.05  # points nearer to the camera centre are ignored
    tau_m: float = 0.01  # same-surface tolerance, see `tolerance`
    tau_rel: float = 0.01
    max_incidence_deg: float = 80.0
    clip_m: float | None = None
    clip_mode: Literal["invalid", "drop"] = "invalid"
    fill_passes: int = 3
    average_samples: bool = True  # mean of a pixel's same-surface samples, not just the nearest
    frustum_culling: bool = True  # False: project every point of every scan (the naive baseline)
    raw_fallback: bool = True  # a surface pixel with no own point and no planar fill takes the splat's range
    fit_gradient: bool = True  # False: points already lie on pixel-centre rays (dense GT snaps them there)
    colour: bool = True  # False: a black colour image, for callers that need only the ranges (dense GT)
    # compiled kernels, the numpy reference, or PyTorch on the CPU / a CUDA GPU (same output)
    backend: Literal["numba", "numpy", "torch", "cuda"] = "numba"

    HALF_PX: ClassVar[float] = 0.5
    """Pixels: how far a point may sit from its pixel's centre. Distances to a point measured from a pixel
    centre grow by it (leak test, masks), so a point anywhere in its pixel gets the same tolerance."""

    LEAK_MIN_PX: ClassVar[float] = 1.0
    """Pixels: an own point is a leak candidate only when the splat over it is nearer by more than the
    tolerance over this distance (then over the splat point's own distance plus `HALF_PX`): range noise
    between neighbouring samples of one surface never makes a candidate."""

    LEAK_RADIUS_PX: ClassVar[int] = 3
    """Pixels: the leak test looks this far at most (or the largest footprint half-width, if smaller, at
    least 1) for nearer own points on two opposite sides: a gap between a nearer surface's points is at
    most a footprint wide, and a wider search would reject background beside real silhouettes."""

    SAME_SURFACE_PX: ClassVar[float] = 1.0
    """Pixels: a pixel's points within the tolerance over this distance of its own (nearest) point belong
    to its surface and join its average."""

    GATE_DIRECT_PX: ClassVar[float] = 1.6
    """Pixels: the gradient fit takes a 4-neighbour's own point as on the same surface when their ranges
    differ by at most tau_m + range x `gate_slope` x this: a generous bound on the two points' distance
    (1 px between the pixel centres, each point up to `HALF_PX` off its own)."""

    GATE_DIAGONAL_PX: ClassVar[float] = 2.2
    """Pixels: `GATE_DIRECT_PX` for the diagonal neighbours (sqrt(2) px between the pixel centres), which
    join only where the 4-neighbours leave the gradient undetermined."""

    FIT_MIN_DET: ClassVar[float] = 0.25
    """Pixels^4: normal equations of the gradient fit with a smaller determinant leave it undetermined
    (neighbours along one axis only, or too close): the diagonal neighbours join, else one axis alone."""

    FIT_MIN_AXIS: ClassVar[float] = 0.25
    """Pixels^2: the sum of squared offsets along one axis that determines the gradient along it alone
    (when both together are not determined)."""

    FILL_TOLERANCE_PX: ClassVar[float] = 1.5
    """Pixels: a gap's neighbour predictions within the tolerance over this distance of the nearest (or,
    for the far group, of the far group's nearest) form one surface: a diagonal neighbour is sqrt(2) px
    away, plus a little."""

    FILL_DIAGONAL_WEIGHT: ClassVar[float] = 1.0 / math.sqrt(2.0)
    """Weight of a diagonal neighbour's prediction in a gap fill, against 1 for a 4-neighbour: one over its
    distance (sqrt(2) px)."""

    @property
    def incidence_slope(self) -> float:
        """tan(`max_incidence_deg`): range change per unit of lateral distance on the steepest surface."""
        return math.tan(math.radians(self.max_incidence_deg))

    @property
    def fill_weights(self) -> tuple[float, ...]:
        """The gap fill's weight of each neighbour in `NB8` order (four direct, then four diagonal)."""
        return (1.0,) * 4 + (self.FILL_DIAGONAL_WEIGHT,) * 4

    def tolerance(self, range_m: Any, dist_px: Any, ppr: Any) -> Any:
        """Largest range difference (m) between two samples of one surface ``dist_px`` apart.

        tau_m + range * (tau_rel + tan(max_incidence) * dist_px / ppr): the
        slope term admits surfaces up to `max_incidence_deg` from the view ray.
        """
        return self.tau_m + range_m * (self.tau_rel + self.incidence_slope * dist_px / ppr)

    def gate_slope(self, ppr: Any) -> Any:
        """The tolerance's part that grows with range and distance, per metre and pixel (float32 in, float32
        out): the gradient fit's gate is tau_m + range x this x `GATE_DIRECT_PX` (or `GATE_DIAGONAL_PX`)."""
        return self.tolerance(1.0, 1.0, ppr) - self.tau_m
