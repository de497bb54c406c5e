"""The helper thread of `ingest.runtime.background` and the sample's equirect warps that run in it."""

from __future__ import annotations

import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from calibration.errors import CalibrationError
from calibration.rig import read_rig
from calibration.warp import remap_spans, warp
from ingest.bags.reader import open_bags
from ingest.dataset.layout import prepare_dirs
from ingest.runtime.background import Background
from ingest.train.run import sample
from ingest.train.run.plan import plan
from ingest.train.run.resolved import resolve_run
from ingest.train.run.sample import process_sample, start_equirects
from ingest.train.run.sample_job import Geometry, SampleJob
from ingest.train.run.settings import IngestConfig, resolve_topics
from ingest.train.run.stream import Shared, StreamedJob, decode_images, stream_jobs
from tests.ingest.test_pipeline import INDOOR, _rig
from tests.live import HANG_S


def test_result_is_the_helpers_return_value_computed_in_another_thread():
    caller = threading.get_ident()
    go = threading.Event()

    def fn() -> tuple[int, bool]:
        started = go.wait(
            HANG_S
        )  # the caller sets it after Background() returned: only another thread sees it
        return threading.get_ident(), started

    bg = Background(fn)
    go.set()
    ident, started = bg.result()
    assert started and ident != caller
    assert bg.ms > 0.0 and bg.result() == (ident, True)  # a second result() returns the same value


def test_ms_is_the_helpers_wall_time_in_milliseconds():
    """`ms` is in milliseconds: a helper that sleeps 50 ms reports at least 50 (and not 50 000)."""
    bg = Background(lambda: time.sleep(0.05))
    bg.wait()
    assert 50.0 <= bg.ms < 5000.0


def test_an_error_in_the_helper_is_raised_by_result_not_by_wait():
    def fn() -> int:
        raise KeyError("no such lidar: lidar9")

    bg = Background(fn)
    bg.wait()  # only waits
    with pytest.raises(KeyError, match="lidar9"):
        bg.result()


def _jobs(tmp_path: Path, n: int) -> list[SampleJob]:
    cfg = IngestConfig(rig=_rig(INDOOR), out=tmp_path / "ds", workers=1, every=10)
    run = resolve_run(cfg)
    geometry = Geometry.from_rig(read_rig(cfg.rig), cfg.height_full)
    with open_bags([INDOOR]) as bags:
        topics = resolve_topics(geometry.rig, bags.topics(), str(INDOOR))
        jobs = [j for j in stream_jobs(bags, topics, plan(bags, topics, run), run)]
    shared = Shared(geometry)
    out = [j.sample_job(shared, *decode_images(j, shared)[0]) for j in jobs if isinstance(j, StreamedJob)][:n]
    assert len(out) == n
    prepare_dirs(cfg.out, exr=False)
    return out


def _helpers_alive() -> list[str]:
    return [t.name for t in threading.enumerate() if t.name.startswith("sensorbox-equirects")]


def test_equirects_equal_warp_and_reuse_the_calling_threads_buffers(tmp_path: Path):
    a, b = _jobs(tmp_path, 2)
    geo = a.geometry
    first = start_equirects(a).result()
    ref_up, _ = warp(a.upper_bgr, geo.rig.upper.model, geo.equirect, geo.rect.R_cam0_rect)
    ref_down, _ = warp(a.lower_bgr, geo.rig.lower.model, geo.equirect, geo.rect.R_cam1_rect)
    assert np.array_equal(first[0], ref_up) and np.array_equal(first[1], ref_down)
    assert ref_up.any() and not np.array_equal(ref_up, ref_down)
    second = start_equirects(b).result()  # this thread's buffers again, now holding b
    assert second[0] is first[0] and second[1] is first[1]
    assert np.array_equal(
        second[0], warp(b.upper_bgr, geo.rig.upper.model, geo.equirect, geo.rect.R_cam0_rect)[0]
    )
    other: list[tuple[np.ndarray, np.ndarray]] = []
    t = threading.Thread(target=lambda: other.append(start_equirects(a).result()))
    t.start()
    t.join()
    assert other[0][0] is not first[0]  # another calling thread (Dask runs several) has its own


def test_process_sample_waits_for_its_helper_also_when_a_stage_raises(tmp_path: Path):
    (job,) = _jobs(tmp_path, 1)
    ok = process_sample(job)
    assert ok.written and ok.overlapped_ms["equirect warps"] > 0.0 and not _helpers_alive()
    lp = job.lidars[0]
    broken = replace(job, lidars=(replace(lp, name="lidar9"), *job.lidars[1:]))
    with pytest.raises(CalibrationError, match="lidar9"):
        process_sample(broken)
    assert not _helpers_alive()
    bad = replace(job, lower_bgr=job.lower_bgr[:-1])
    with pytest.raises(ValueError, match="source model is"):
        process_sample(bad)  # the size is checked in the calling thread, before the helper starts
    assert not _helpers_alive()


def test_inline_runs_in_the_calling_thread_with_the_same_interface():
    bg = Background(threading.get_ident, inline=True)
    assert bg.result() == threading.get_ident() and bg.ms > 0.0

    def fn() -> int:
        raise ValueError("bad image")

    failed = Background(fn, inline=True)  # the error waits for result(), as from a thread
    failed.wait()
    with pytest.raises(ValueError, match="bad image"):
        failed.result()


def test_inline_warps_write_the_same_files_and_count_in_the_images_stage(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    (job,) = _jobs(tmp_path, 1)
    job.geometry.warm_maps()  # neither call builds the maps
    calls: list[tuple[int, float]] = []  # (thread, ms) of each remap
    remap = remap_spans

    def timed_remap(*args: Any, **kwargs: Any) -> None:
        t0 = time.perf_counter()
        remap(*args, **kwargs)
        calls.append((threading.get_ident(), (time.perf_counter() - t0) * 1e3))

    monkeypatch.setattr(sample, "remap_spans", timed_remap)
    threaded = process_sample(job)
    assert len(calls) == 2 and all(ident != threading.get_ident() for ident, _ in calls)
    names = sorted(p.relative_to(job.out) for p in job.out.rglob("*.png"))
    before = {n: (job.out / n).read_bytes() for n in names}
    calls.clear()
    inline_job = replace(job, out=tmp_path / "inline", params=replace(job.params, overlap_images=False))
    prepare_dirs(inline_job.out, exr=False)
    inline = process_sample(inline_job)
    assert len(calls) == 2 and all(ident == threading.get_ident() for ident, _ in calls)
    assert inline.overlapped_ms == {} and "equirect warps" in threaded.overlapped_ms
    # the inline warps run inside the interval that stage "images" times (no clock race: containment)
    assert inline.stage_ms["images"] >= sum(ms for _, ms in calls)
    assert len(names) == 6 and {n: (inline_job.out / n).read_bytes() for n in names} == before
