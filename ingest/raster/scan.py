"""A cloud the renderer draws: points in their own frame with colours, masks and a pose."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calibration.types import F32, F64, U8, Bool
from ingest.errors import ScanError


@dataclass(frozen=True, eq=False)
class Scan:
    """One scan: points in its scan frame (metres), colours, masks and pose."""

    name: str
    T_world_scan: F64
    xyz: F32  # (N, 3)
    rgb: U8  # (N, 3)
    masked: Bool | None = None  # (N,) True = reflective/transparent surface
    mask_xyz: F32 = field(default_factory=lambda: np.zeros((0, 3), np.float32))  # (M, 3) mask cloud
    source: str = ""
    dropped_points: int = 0  # read but not kept: not finite or at the scanner origin (no return)

    def __post_init__(self) -> None:
        n = len(self.xyz)
        if self.xyz.shape != (n, 3) or self.rgb.shape != (n, 3):
            raise ScanError(f"{self.source or self.name}: xyz {self.xyz.shape} and rgb {self.rgb.shape} "
                            "must both be (N, 3)")  # fmt: skip
        if self.masked is not None and self.masked.shape != (n,):
            raise ScanError(f"{self.source or self.name}: mask of shape {self.masked.shape}, expected ({n},)")

    @property
    def origin_world(self) -> F64:
        """The scanner centre in the world frame."""
        out: F64 = self.T_world_scan[:3, 3].copy()
        return out
