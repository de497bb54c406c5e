"""The renderer's thresholds and weights are defined once, in `RenderParams`, and read by every backend."""

from __future__ import annotations

import ast
from pathlib import Path

from ingest.raster.params import RenderParams

RASTER = Path(__file__).resolve().parents[2] / "ingest" / "raster"
# the recipe and every backend's stages: no bare threshold may stand in them
RECIPE_MODULES = ("recipe", "reference", "visibility", "compiled_view", "pixel_kernels", "point_kernels",
                  "torch_view", "geometry", "view")  # fmt: skip
NAMES = ("GATE_DIRECT_PX", "GATE_DIAGONAL_PX", "FIT_MIN_DET", "FIT_MIN_AXIS", "FILL_TOLERANCE_PX",
         "FILL_DIAGONAL_WEIGHT")  # fmt: skip
THRESHOLDS = {name: getattr(RenderParams, name) for name in NAMES}


def bare_thresholds(folder: Path) -> list[str]:
    """'module:line value' of every float literal in the recipe's modules that equals a named threshold,
    and of every 1 / sqrt(2) written out (the diagonal weight)."""
    values = set(THRESHOLDS.values())
    found = []
    for name in RECIPE_MODULES:
        path = folder / f"{name}.py"
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Constant) and isinstance(node.value, float) and node.value in values:
                found.append(f"{name}:{node.lineno} {node.value}")
            elif isinstance(node, ast.Call) and ast.unparse(node) == "math.sqrt(2.0)":
                found.append(f"{name}:{node.lineno} sqrt(2)")
    return found


def test_the_recipe_thresholds_stand_only_in_render_params() -> None:
    assert bare_thresholds(RASTER) == []
    params = (RASTER / "params.py").read_text()
    for name in THRESHOLDS:  # each defined there once, with its docstring
        assert params.count(f"    {name}: ClassVar") == 1, name


def test_the_thresholds_keep_their_values() -> None:
    assert THRESHOLDS == {
        "GATE_DIRECT_PX": 1.6, "GATE_DIAGONAL_PX": 2.2, "FIT_MIN_DET": 0.25, "FIT_MIN_AXIS": 0.25,
        "FILL_TOLERANCE_PX": 1.5, "FILL_DIAGONAL_WEIGHT": 0.7071067811865475,
    }  # fmt: skip
    assert (RenderParams.HALF_PX, RenderParams.LEAK_MIN_PX, RenderParams.SAME_SURFACE_PX) == (0.5, 1.0, 1.0)
    assert RenderParams.LEAK_RADIUS_PX == 3


def test_the_thresholds_stay_out_of_the_recorded_settings() -> None:
    """scene.yaml, dataset.yaml and meta/*.json record `asdict(RenderParams)`: the class constants are not
    settings, and recording them would change those files and refuse to resume older outputs."""
    from dataclasses import asdict

    assert not set(asdict(RenderParams())) & {"HALF_PX", *THRESHOLDS}
