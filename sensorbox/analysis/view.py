"""A SensorBox dataset as one Rerun recording (`sensorbox view`): images, GT, rig, trajectory, numbers.

Train layout (`sensorbox ingest`), one row per sample on the timeline
``time`` (the sample's `exposure_ns` from `meta/<id>.json`, else its
`stamp_ns`) and on ``sample`` (its id):

```
cam0/fisheye, cam1/fisheye          left_fisheye/, right_fisheye/ (JPEG-compressed RGB)
equirect/up, equirect/down_virt     equirect_up/, equirect_down_virt/
cam0/depth                          depth_fisheye/ as a depth image, 1000 units per metre (mm)
equirect/disparity                  disp_equirect/ as a depth image, 100 units per "metre" (px x 100)
meta/<key>/<key>...                 every number of meta/<id>.json as a scalar series
world/trajectory                    trajectories/<bag>.tum: T_world_cam0's positions (static line)
world/rig                           T_world_cam0 at the sample's time (the trajectory, interpolated)
world/rig/<cam1|lidar|imu>          the rig's frames in cam0 (rig/rig.yaml of the dataset, static)
```

Benchmark layout (`sensorbox render-benchmark`), one row per scene on
``scene`` (its index in name order): every image of every FOV, baseline and
camera under `<FOV>FOV/<B>mm/<CAMERA>/<image>`, CENTER's depth and disparity
as depth images beside them, `world/center` (T_world_center) with
`world/center/<B>mm/<PARTNER>` and every number of scene.yaml's `stats` and
`scans` as scalars (`scene/stats/<FOV>FOV/<B>mm/<CAMERA>/<image>/<field>`,
`scene/scans/<scan>/points`).

Images are shrunk by a whole factor until their longest side is at most
`max_side_px` (960 by default; `None` keeps them whole): colour by area
averaging, depth and disparity by the nearest surface of each block (the
smallest non-zero value), so sparse GT keeps its pixels and no value is
made up between two surfaces. Accumulated clouds are not stored in a
dataset and are not shown. Rerun is imported here, not at the top, so the
CLI starts without it.
"""

from __future__ import annotations

import errno
import os
import shutil
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

from ingest.errors import OutputError
from ingest.eval.evaluate import detect_layout
from sensorbox.errors import ViewerError

if TYPE_CHECKING:
    import rerun as rr

from sensorbox.analysis.view_benchmark import log_benchmark
from sensorbox.analysis.view_files import (
    MAX_SIDE_PX,
    VIEWER_FLUSH_S,
    Progress,
    ViewSummary,
)
from sensorbox.analysis.view_train import log_train


def view_dataset(
    root: Path,
    save: Path | None = None,
    max_side_px: int | None = MAX_SIDE_PX,
    progress: Progress | None = None,
) -> ViewSummary:
    """`root` (train or benchmark layout) as a Rerun recording: written to `save` (.rrd), else streamed
    to a Rerun viewer spawned for it.

    The .rrd is written to a temporary name beside `save` and renamed when
    complete, so a failed run leaves no partial recording. A folder that is
    neither layout is an `EvalError` naming it; a damaged file a `DatasetError`;
    a viewer that cannot be started (no display, no `rerun` executable) or
    does not take the recording within `VIEWER_FLUSH_S` a `ViewerError`,
    before any file is read in the first two cases.
    """
    import rerun

    layout = detect_layout(root)
    rec = rerun.RecordingStream("sensorbox")  # a fresh recording id: a second view is not merged in
    tmp = _staging(save) if save is not None else None
    if tmp is None:
        _spawn(rec)
    try:
        if tmp is not None:
            rec.save(tmp)
        rec.send_recording_name(root.resolve().name)
        log = log_train if layout == "train" else log_benchmark
        summary = log(rec, root, max_side_px, progress)
        _flush(rec, streamed=tmp is None)
    except BaseException as err:
        rec.disconnect()
        if tmp is not None:
            tmp.unlink(missing_ok=True)
            if _write_failed(err):
                raise OutputError(f"cannot write {save}: {_write_problem(err, tmp.parent)}") from err
        raise
    rec.disconnect()
    if save is not None and tmp is not None:
        try:
            tmp.replace(save)
        except OSError as err:
            tmp.unlink(missing_ok=True)
            raise OutputError(f"cannot write {save}: {err.strerror or err}") from err
    return summary


def _write_failed(err: BaseException) -> bool:
    """Whether Rerun's binding failed writing the .rrd: it reports an OS error (a full disk) as a plain
    RuntimeError whose text names it ("... No space left on device (os error 28)"), or, when its writer
    thread died of one first, as "File-writer thread shut down prematurely"."""
    return isinstance(err, RuntimeError) and ("(os error " in str(err) or "File-writer" in str(err))


def _write_problem(err: BaseException, folder: Path) -> str:
    """What stopped the .rrd's writer in `folder`: Rerun's own words, and the space left there when its
    words name no OS error (a writer thread that died of a full disk says only that it stopped)."""
    if "(os error " in str(err):
        return str(err)
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        return f"Rerun's file writer stopped ({err})"
    return f"Rerun's file writer stopped ({err}); {free:,} bytes free on its file system"


def display_problem(env: Mapping[str, str], platform: str) -> str | None:
    """Why no viewer window can open here (Linux without X11 or Wayland), or None when one can."""
    if platform.startswith("linux") and not (env.get("DISPLAY") or env.get("WAYLAND_DISPLAY")):
        return "no display for the Rerun viewer (DISPLAY and WAYLAND_DISPLAY are unset)"
    return None


def viewer_executable(path_env: str, python: Path) -> Path | None:
    """The `rerun` viewer rerun-sdk installs: on PATH, else beside the Python running this (a virtual
    environment used without activating it); None when neither has one."""
    found = shutil.which("rerun", path=os.pathsep.join(p for p in (path_env, str(python.parent)) if p))
    return Path(found) if found else None


def _spawn(rec: rr.RecordingStream) -> None:
    """Start a Rerun viewer and stream `rec` to it; refused in one line where it cannot start."""
    hint = "; save the recording with --save FILE.rrd and open it where there is one ('rerun FILE.rrd')"
    if (problem := display_problem(os.environ, sys.platform)) is not None:
        raise ViewerError(problem + hint)
    exe = viewer_executable(os.environ.get("PATH", ""), Path(sys.executable))
    if exe is None:
        raise ViewerError(f"no Rerun viewer executable 'rerun' on PATH nor beside {sys.executable}{hint}")
    path_env = os.environ.get("PATH", "")
    os.environ["PATH"] = os.pathsep.join(p for p in (str(exe.parent), path_env) if p)  # rerun looks there
    try:
        rec.spawn()
    finally:
        os.environ["PATH"] = path_env


def _flush(rec: rr.RecordingStream, streamed: bool) -> None:
    """Wait until everything logged is written (a file) or taken by the viewer (at most VIEWER_FLUSH_S)."""
    if not streamed:
        rec.flush()
        return
    try:
        rec.flush(timeout_sec=VIEWER_FLUSH_S)
    except Exception as err:  # the binding raises a plain RuntimeError-like error on its timeout
        raise ViewerError(
            f"the Rerun viewer did not take the recording within {VIEWER_FLUSH_S:g} s ({err})"
        ) from err


def _staging(save: Path) -> Path:
    """The temporary file beside `save` that the recording goes to first (its folders made); a folder
    that cannot be made or written is an `OutputError` naming `save`."""
    tmp = save.with_name(f".{save.name}.tmp")
    try:
        if save.is_dir():
            raise IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR), str(save))
        save.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_bytes(b"")  # a refused write shows here, not in Rerun's writer thread
    except OSError as err:
        raise OutputError(f"cannot write {save}: {err.strerror or err}") from err
    return tmp
