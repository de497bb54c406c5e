"""An ingest run as decided, once: the user's settings (`IngestConfig`) stay as given; `ResolvedRun` is
what the passes and the samples read.

The run decides three things the settings leave open: the GT method (`--gt
auto` chooses after the trajectory pass), dense GT's window (a static rig's
default window is widened) and whether a worker warps its images in a helper
thread (not when every core already runs a worker). `resolve_run` makes
those decisions into one frozen value, with every window in it: no stage
rebuilds the settings while the run is under way.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

from ingest.train.gt.block_planes import FreeSpaceSettings
from ingest.train.gt.dense import DenseParams, free_space_settings
from ingest.train.run.sample_job import SampleParams
from ingest.train.run.settings import IngestConfig
from ingest.train.trajectory.estimate import STATIC_WINDOW_NS

STATIC_WINDOW_NOTE = f"rig static: window +-{STATIC_WINDOW_NS / 1e6:.0f} ms"
"""What `resolve_run` adds to the decision when it widens dense GT's window for a static rig."""


@dataclass(frozen=True)
class ResolvedRun:
    """One run's settings and decisions (times in ns), frozen.

    `sample` is what every sample reads: the GT method and why
    (`sample.method`, `sample.decision`), sparse GT's window
    (`sample.window_ns`, the user's `--window-ms`), dense GT's parameters
    with their resolved window (`sample.dense.window_ns`), the gap fallback
    (`--gt auto`: sparse GT for frames in trajectory gaps) and the image
    overlap. `window_ns` is how far around a frame a sample's job holds
    points: dense GT's window for a dense run, sparse GT's otherwise.
    """

    asked: IngestConfig
    sample: SampleParams
    window_ns: int

    @property
    def out(self) -> Path:
        return self.asked.out

    @property
    def every(self) -> int:
        return self.asked.every

    @property
    def stereo_tolerance_ns(self) -> int | None:
        return self.asked.stereo_tolerance_ns

    @property
    def free_space(self) -> FreeSpaceSettings | None:
        """Dense GT's free-space test as the stream pass's blocks run it (None when it is off)."""
        dense = self.sample.dense
        return free_space_settings(dense) if dense.free_space else None


def resolve_run(
    asked: IngestConfig,
    method: str | None = None,
    decision: str = "asked",
    static: bool = False,
    every_core_busy: bool = False,
) -> ResolvedRun:
    """The run of `asked` with GT `method` (None: `asked.sample.method`) chosen for `decision`.

    `static`: the trajectory pass found the rig standing still; with `--gt
    auto`, dense GT and the default window (not one the user gave), the
    window widens to `STATIC_WINDOW_NS` and the decision says so.
    `every_core_busy`: every core runs a worker, so a worker warps its images
    inline (a helper thread per worker would only add thread switches).
    """
    chosen = method or asked.sample.method
    if chosen not in ("sparse", "dense"):
        raise ValueError(f"GT method {chosen!r}: expected sparse or dense")
    dense = asked.sample.dense
    default_window = asked.widen_static and dense.window_ns == DenseParams().window_ns
    if asked.gt == "auto" and chosen == "dense" and static and default_window:
        dense = replace(dense, window_ns=STATIC_WINDOW_NS)
        decision = f"{decision}; {STATIC_WINDOW_NOTE}"
    sample = replace(
        asked.sample,
        method=chosen,  # type: ignore[arg-type]  # checked above
        decision=decision,
        window_ns=asked.lidar_window_ns,
        dense=dense,
        gap_fallback=asked.gt == "auto",
        overlap_images=asked.sample.overlap_images and not every_core_busy,
    )
    window = dense.window_ns if chosen == "dense" else asked.lidar_window_ns
    return ResolvedRun(asked, sample, window)
