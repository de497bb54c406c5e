"""The per-sample function: one stereo pair + LiDAR points -> WideDepth files on disk.

`process_sample` is pure apart from writing its own files, takes only
picklable inputs and is what the local process pool or a Dask cluster runs.
"""

from __future__ import annotations

import time

import cv2

from calibration.warp import build_maps, check_source, remap_spans
from ingest.runtime.background import Background
from ingest.train.run.sample_dense import process_dense
from ingest.train.run.sample_job import SampleJob, SampleResult
from ingest.train.run.sample_parts import Equirects
from ingest.train.run.sample_sparse import process_sparse

INTERPOLATION = {"linear": cv2.INTER_LINEAR, "cubic": cv2.INTER_CUBIC, "nearest": cv2.INTER_NEAREST}


def start_equirects(job: SampleJob) -> Background[Equirects]:
    """Both images warped to cam0's rectified equirect, in a helper thread (see `ingest.runtime.background`).

    The sizes are checked and the output buffers taken here, in the calling
    thread: they are its reused per-thread buffers (`RemapMaps.scratch`, no
    25 MB allocation and fill per image), valid until its next sample. Inline
    instead when `SampleParams.overlap_images` is off.
    """
    geo = job.geometry
    interp = INTERPOLATION[job.params.interpolation]
    work = []
    for image, model, R in (
        (job.upper_bgr, geo.rig.upper.model, geo.rect.R_cam0_rect),
        (job.lower_bgr, geo.rig.lower.model, geo.rect.R_cam1_rect),
    ):
        check_source(image, model)
        maps = build_maps(model, geo.equirect, R)
        out = maps.scratch((geo.equirect.height, geo.equirect.width, *image.shape[2:]), image.dtype, 0.0)
        work.append((image, maps, out))

    def both() -> Equirects:
        for image, maps, out in work:
            remap_spans(image, maps, out, interp)
        return work[0][2], work[1][2]

    return Background(both, name=f"sensorbox-equirects-{job.sid}", inline=not job.params.overlap_images)


def process_sample(job: SampleJob) -> SampleResult:
    """Clouds -> motion compensation -> GT (fisheye range, equirect disparity) -> images -> files.

    The equirect warps run in a helper thread beside the clouds and GT
    stages; stage "images" is what the calling thread spends on them: starting
    them (building the remap maps, once per process) and waiting at the end.
    """
    if job.params.alignment_only:
        return process_sparse(job, None, 0.0)
    t0 = time.perf_counter()
    images = start_equirects(job)
    try:
        return _process(job, images, (time.perf_counter() - t0) * 1e3)
    finally:
        images.wait()  # never return while the helper still writes into this thread's buffers


def _process(job: SampleJob, images: Background[Equirects], start_ms: float) -> SampleResult:
    """`process_sample`'s stages, with its warps under way in `images` (starting them took `start_ms`)."""
    if job.params.method == "dense":
        return process_dense(job, images, start_ms)
    return process_sparse(job, images, start_ms)
