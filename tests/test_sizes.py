"""Modules of at most 500 lines and functions of at most 80 in calibration/, ingest/ and sensorbox/, as a ratchet.

The code written before the limits has exceptions, listed below with their line counts today. An
exception may not grow, a module or function not listed may not pass its limit, and one listed that
is now within it (or gone) must leave the list: the list only shrinks, as modules are split.
"""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("calibration", "ingest", "sensorbox")
MODULE_LINES = 500
FUNCTION_LINES = 80

# path -> lines, of the modules over MODULE_LINES
MODULE_EXCEPTIONS: dict[str, int] = {}
# path:qualified name -> lines (from `def` to its last line), of the functions over FUNCTION_LINES
FUNCTION_EXCEPTIONS: dict[str, int] = {}


def _files() -> list[Path]:
    return [f for package in PACKAGES for f in sorted((ROOT / package).rglob("*.py"))]


def _functions(tree: ast.AST, prefix: str = "") -> list[tuple[str, int]]:
    """(qualified name, lines from `def` to its last line) of every function in ``tree``, nested ones too."""
    out: list[tuple[str, int]] = []
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            name = f"{prefix}{node.name}"
            out.append((name, (node.end_lineno or node.lineno) - node.lineno + 1))
            out += _functions(node, f"{name}.<locals>.")
        elif isinstance(node, ast.ClassDef):
            out += _functions(node, f"{prefix}{node.name}.")
        else:
            out += _functions(node, prefix)
    return out


def module_sizes() -> dict[str, int]:
    """path -> lines of every module of the packages."""
    return {str(f.relative_to(ROOT)): len(f.read_text().splitlines()) for f in _files()}


def function_sizes() -> dict[str, int]:
    """path:qualified name -> lines of every function of the packages."""
    sizes: dict[str, int] = {}
    for f in _files():
        path = f.relative_to(ROOT)
        for name, lines in _functions(ast.parse(f.read_text(), filename=str(f))):
            sizes[f"{path}:{name}"] = max(lines, sizes.get(f"{path}:{name}", 0))
    return sizes


def ratchet(sizes: dict[str, int], limit: int, exceptions: dict[str, int]) -> list[str]:
    """One line per breach: over ``limit`` and not listed, listed and grown, or listed and now within it."""
    problems = []
    for name, lines in sorted(sizes.items()):
        allowed = exceptions.get(name)
        if lines > limit and allowed is None:
            problems.append(f"{name}: {lines} lines, over the limit of {limit}")
        elif allowed is not None and lines > allowed:
            problems.append(f"{name}: {lines} lines, grown past its listed {allowed}")
    for name, allowed in sorted(exceptions.items()):
        if sizes.get(name, 0) <= limit:
            problems.append(
                f"{name}: listed at {allowed} lines but now within the limit of {limit}: unlist it"
            )
    return problems


def test_no_module_over_the_limit():
    assert ratchet(module_sizes(), MODULE_LINES, MODULE_EXCEPTIONS) == []


def test_no_function_over_the_limit():
    assert ratchet(function_sizes(), FUNCTION_LINES, FUNCTION_EXCEPTIONS) == []


def test_ratchet_names_each_breach():
    sizes = {"a.py": 600, "b.py": 520, "c.py": 400, "d.py": 510, "e.py": 505}
    exceptions = {"b.py": 510, "c.py": 530, "d.py": 510, "e.py": 507, "gone.py": 700}
    assert ratchet(sizes, 500, exceptions) == [
        "a.py: 600 lines, over the limit of 500",
        "b.py: 520 lines, grown past its listed 510",
        "c.py: listed at 530 lines but now within the limit of 500: unlist it",
        "gone.py: listed at 700 lines but now within the limit of 500: unlist it",
    ]


def test_functions_are_named_by_class_and_enclosing_function():
    tree = ast.parse(
        "def f():\n    def g():\n        pass\n    return g\n\n\nclass C:\n    def m(self):\n        pass\n"
    )
    assert _functions(tree) == [("f", 4), ("f.<locals>.g", 2), ("C.m", 2)]
