"""Open3D, imported without its plotly viewer: `from ingest.runtime.o3d import o3d`.

`import open3d` imports `open3d.visualization.draw_plotly`, which imports dash,
plotly, IPython and pydantic: about 1.5 s of every process's start (Open3D's own
C++ module takes 0.7 s), for a viewer SensorBox never opens. Every command and
every ingest worker imports Open3D (the k-nearest-neighbour planes), so this
module puts a stand-in for that one submodule in place before the import; its
functions say why they are missing. The rest of Open3D is untouched.
"""

from __future__ import annotations

import sys
import types
from typing import Any, NoReturn

PLOTLY_VIEWER = "open3d.visualization.draw_plotly"


def _unavailable(*_args: Any, **_kwargs: Any) -> NoReturn:
    raise RuntimeError(
        f"{PLOTLY_VIEWER} is not loaded in SensorBox's processes (ingest.runtime.o3d keeps its dash and "
        "plotly imports out); import open3d in a process of your own to use it"
    )


def _without_plotly_viewer() -> None:
    """Register the stand-in, unless Open3D (or its viewer) is imported already."""
    if "open3d" in sys.modules or PLOTLY_VIEWER in sys.modules:
        return
    stub = types.ModuleType(PLOTLY_VIEWER, "stand-in: see ingest.runtime.o3d")
    for name in ("get_plotly_fig", "draw_plotly", "draw_plotly_server"):
        setattr(stub, name, _unavailable)
    sys.modules[PLOTLY_VIEWER] = stub


_without_plotly_viewer()

import open3d as o3d  # noqa: E402  (after the stand-in)

__all__ = ["o3d"]
