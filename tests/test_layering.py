"""Imports flow one way (DESIGN.md section 1), between the packages and between the rooms inside them.

calibration <- ingest <- sensorbox. Inside ingest, train, render and eval share bags, dataset,
raster (the point renderer) and runtime but never import each other; those shared rooms import
none of the three. Inside train, the run imports the ground truth and the trajectory, the ground
truth the trajectory, and the trajectory neither; the modules every room reads messages with
(bad_messages, plausible, repeats, sync) import no room. Inside sensorbox,
live reaches the simulator only through the node registry (by name), and the CLI imports only
public names. No module of the packages imports itself back through others (an import inside a
function counts).
"""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("calibration", "ingest", "sensorbox")
# room -> rooms it must not import (dotted prefixes)
FORBIDDEN = {
    "calibration": {"ingest", "sensorbox"},
    "ingest": {"sensorbox"},
    "ingest.train": {"ingest.render", "ingest.eval", "ingest.inspect"},
    "ingest.train.trajectory": {"ingest.train.gt", "ingest.train.run"},
    "ingest.train.gt": {"ingest.train.run"},
    **{
        f"ingest.train.{m}": {"ingest.train.trajectory", "ingest.train.gt", "ingest.train.run"}
        for m in ("bad_messages", "plausible", "repeats", "sync")
    },
    "ingest.render": {"ingest.train", "ingest.eval", "ingest.inspect"},
    "ingest.eval": {"ingest.train", "ingest.render", "ingest.inspect"},
    "ingest.bags": {"ingest.train", "ingest.render", "ingest.eval", "ingest.dataset", "ingest.runtime"},
    "ingest.dataset": {"ingest.train", "ingest.render", "ingest.eval", "ingest.runtime"},
    "ingest.runtime": {"ingest.train", "ingest.render", "ingest.eval"},
    "ingest.raster": {"ingest.train", "ingest.render", "ingest.eval", "ingest.inspect", "ingest.runtime"},
    "sensorbox.live": {"sensorbox.sim", "sensorbox.cli", "sensorbox.analysis"},
    "sensorbox.livox": {"sensorbox.sim", "sensorbox.live", "sensorbox.cli", "sensorbox.analysis"},
    "sensorbox.sim": {"sensorbox.cli", "sensorbox.analysis"},
    "sensorbox.analysis": {"sensorbox.cli"},
}


def _module(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> list[tuple[str, list[str]]]:
    """(module, names imported from it) for every absolute import in the file."""
    tree = ast.parse(path.read_text(), filename=str(path))
    out: list[tuple[str, list[str]]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, []) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.append((node.module, [a.name for a in node.names]))
    return out


def _within(module: str, prefix: str) -> bool:
    return module == prefix or module.startswith(prefix + ".")


def _violations(room: str) -> dict[str, list[str]]:
    files = sorted((ROOT / Path(*room.split("."))).rglob("*.py"))
    if not files:
        file = (ROOT / Path(*room.split("."))).with_suffix(".py")
        files = [file] if file.is_file() else []
    assert files, f"no modules found for {room}"
    bad: dict[str, list[str]] = {}
    for f in files:
        hits = sorted({m for m, _ in _imports(f) for banned in FORBIDDEN[room] if _within(m, banned)})
        if hits:
            bad[str(f.relative_to(ROOT))] = hits
    return bad


@pytest.mark.parametrize("room", sorted(FORBIDDEN))
def test_import_direction(room):
    assert _violations(room) == {}, f"{room} must not import {sorted(FORBIDDEN[room])}"


def test_no_module_imports_another_modules_private_names():
    offenders = {}
    for package in PACKAGES:
        for f in sorted((ROOT / package).rglob("*.py")):
            private = [
                f"{m}.{n}" for m, names in _imports(f) if m.split(".")[0] in PACKAGES
                for n in names if n.startswith("_") and not n.startswith("__")
            ]  # fmt: skip
            if private:
                offenders[str(f.relative_to(ROOT))] = private
    assert offenders == {}


def test_the_cli_imports_only_public_names_of_the_library():
    for f in sorted((ROOT / "sensorbox" / "cli").glob("*.py")):
        for module, names in _imports(f):
            assert not any(n.startswith("_") for n in names), (f.name, module, names)


def _room_graph(room: str) -> dict[str, set[str]]:
    """Module -> the modules of ``room`` (a package or a room inside one) it imports (at the top or
    inside a function)."""
    files = sorted((ROOT / Path(*room.split("."))).rglob("*.py"))
    modules = {_module(f): f for f in files}
    graph: dict[str, set[str]] = {}
    for name, f in modules.items():
        deps: set[str] = set()
        for m, names in _imports(f):
            subs = {f"{m}.{n}" for n in names} & modules.keys()  # `from package import module`
            deps |= subs or ({m} & modules.keys())
        graph[name] = deps - {name}
    return graph


def _circle(graph: dict[str, set[str]]) -> list[str]:
    """One import circle of ``graph`` as the modules along it, first repeated at the end ([] when none)."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str]:
        state[node] = 1
        path.append(node)
        for dep in sorted(graph.get(node, ())):
            if state.get(dep) == 1:
                return [*path[path.index(dep) :], dep]
            if dep not in state and (found := visit(dep)):
                return found
        path.pop()
        state[node] = 2
        return []

    for node in sorted(graph):
        if node not in state and (found := visit(node)):
            return found
    return []


@pytest.mark.parametrize("package", PACKAGES)
def test_no_import_circle(package):
    assert _circle(_room_graph(package)) == []


def test_circle_finder_names_the_circle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a", "d"}, "d": set()}
    assert _circle(graph) == ["a", "b", "c", "a"]
    assert _circle({"a": {"b"}, "b": set(), "c": {"a", "b"}}) == []


def test_checker_detects_a_violation(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("from sensorbox.cli.main import app\nimport ingest.x\nfrom ingest.render.view import _z\n")
    assert _imports(bad) == [
        ("sensorbox.cli.main", ["app"]),
        ("ingest.x", []),
        ("ingest.render.view", ["_z"]),
    ]
    assert _within("ingest.render.view", "ingest.render") and not _within("ingest.renderer", "ingest.render")
