"""Launch-file substitutions, $(var x), $(env X), $(eval ...), $(find-pkg-share sensorbox) and the
rest of ROS 2's YAML launch set: parsed once, evaluated in a scope."""

from __future__ import annotations

import ast
import importlib.resources
import math
import operator
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sensorbox.errors import LaunchError


def package_share() -> Path:
    """`$(find-pkg-share sensorbox)`: the package's share folder (launch/, calibration/)."""
    return Path(str(importlib.resources.files("sensorbox") / "share"))


TRUE_WORDS = ("true", "1")


FALSE_WORDS = ("false", "0")


@dataclass
class Substitution:
    name: str
    args: list[list[str | Substitution]]


def _parse_subst(text: str, pos: int, where: str) -> tuple[Substitution, int]:
    """Parse `$(name args...)` starting at text[pos] == '$'; return it and the index after ')'."""
    i = pos + 2
    start = i
    while i < len(text) and not text[i].isspace() and text[i] != ")":
        i += 1
    name = text[start:i]
    if not name:
        raise LaunchError(f"{where}: empty substitution '$()' in {text!r}")
    args: list[list[str | Substitution]] = []
    while True:
        while i < len(text) and text[i].isspace():
            i += 1
        if i >= len(text):
            raise LaunchError(f"{where}: unclosed substitution '$({name}' in {text!r}")
        if text[i] == ")":
            return Substitution(name, args), i + 1
        arg: list[str | Substitution] = []
        while i < len(text) and not text[i].isspace() and text[i] != ")":
            if text.startswith("$(", i):
                sub, i = _parse_subst(text, i, where)
                arg.append(sub)
            elif text[i] in "'\"":
                quoted, i = _scan(text, i + 1, where, stop=text[i])
                arg.extend(quoted or [""])
            else:
                arg.append(text[i])
                i += 1
        args.append(arg)


def _scan(text: str, i: int, where: str, stop: str | None) -> tuple[list[str | Substitution], int]:
    """Literals and substitutions from text[i] up to the closing `stop` character (or the end)."""
    parts: list[str | Substitution] = []
    lit = ""
    while True:
        if i >= len(text):
            if stop is not None:
                raise LaunchError(f"{where}: unclosed quote in substitution {text!r}")
            break
        if text[i] == stop:
            i += 1
            break
        if text.startswith("$(", i):
            if lit:
                parts.append(lit)
                lit = ""
            sub, i = _parse_subst(text, i, where)
            parts.append(sub)
        else:
            lit += text[i]
            i += 1
    if lit:
        parts.append(lit)
    return parts, i


def parse_substitutions(text: str, where: str) -> list[str | Substitution]:
    return _scan(text, 0, where, stop=None)[0]


MAX_INT_BITS = 4096  # $(eval) integers stay below this size ...
MAX_STR_LEN = 100_000  # ... and strings below this length, so no expression can take the time or memory


def _bounded_pow(a: Any, b: Any) -> Any:
    big = isinstance(a, int) and isinstance(b, int) and abs(a) > 1 and abs(a).bit_length() * b > MAX_INT_BITS
    if big:
        raise ValueError(f"{a} ** {b} is too large (more than {MAX_INT_BITS} bits)")
    return operator.pow(a, b)


def _bounded_mul(a: Any, b: Any) -> Any:
    if isinstance(a, int) and isinstance(b, int) and abs(a).bit_length() + abs(b).bit_length() > MAX_INT_BITS:
        raise ValueError(f"a product of more than {MAX_INT_BITS} bits")
    text, times = (a, b) if isinstance(a, str) else (b, a)
    if isinstance(text, str) and isinstance(times, int) and len(text) * times > MAX_STR_LEN:
        raise ValueError(f"a string of more than {MAX_STR_LEN} characters")
    return operator.mul(a, b)


_BINOPS: dict[type, Callable[[Any, Any], Any]] = {
    ast.Add: operator.add, ast.Sub: operator.sub, ast.Mult: _bounded_mul, ast.Div: operator.truediv,
    ast.FloorDiv: operator.floordiv, ast.Mod: operator.mod, ast.Pow: _bounded_pow,
}  # fmt: skip


_CMPOPS: dict[type, Callable[[Any, Any], Any]] = {
    ast.Eq: operator.eq, ast.NotEq: operator.ne, ast.Lt: operator.lt, ast.LtE: operator.le,
    ast.Gt: operator.gt, ast.GtE: operator.ge,
}  # fmt: skip


_FUNCS: dict[str, Callable[..., Any]] = {
    "min": min, "max": max, "abs": abs, "round": round, "int": int, "float": float, "str": str,
}  # fmt: skip


def safe_eval(expr: str) -> Any:
    """Evaluate a small Python expression: literals, arithmetic, comparisons, `and/or/not`,
    `a if c else b`, `math.NAME`, and min/max/abs/round/int/float/str calls.

    Bounded: integers past `MAX_INT_BITS` and strings past `MAX_STR_LEN` are
    refused before they are built (`9**9**9` would otherwise run for hours).
    """

    def ev(node: ast.AST) -> Any:
        if isinstance(node, ast.Expression):
            return ev(node.body)
        if isinstance(node, ast.Constant) and isinstance(node.value, int | float | str | bool):
            return node.value
        if isinstance(node, ast.BinOp) and type(node.op) in _BINOPS:
            return _BINOPS[type(node.op)](ev(node.left), ev(node.right))
        if isinstance(node, ast.UnaryOp):
            v = ev(node.operand)
            if isinstance(node.op, ast.USub):
                return -v
            if isinstance(node.op, ast.UAdd):
                return +v
            if isinstance(node.op, ast.Not):
                return not v
        if isinstance(node, ast.BoolOp):
            values = [ev(v) for v in node.values]
            return all(values) if isinstance(node.op, ast.And) else any(values)
        if isinstance(node, ast.Compare) and all(type(o) in _CMPOPS for o in node.ops):
            left = ev(node.left)
            for op, comp in zip(node.ops, node.comparators, strict=True):
                right = ev(comp)
                if not _CMPOPS[type(op)](left, right):
                    return False
                left = right
            return True
        if isinstance(node, ast.IfExp):
            return ev(node.body) if ev(node.test) else ev(node.orelse)
        if (
            isinstance(node, ast.Attribute)
            and isinstance(node.value, ast.Name)
            and node.value.id == "math"
            and not node.attr.startswith("_")
            and hasattr(math, node.attr)
        ):
            return getattr(math, node.attr)
        if isinstance(node, ast.Name) and node.id in ("True", "False"):
            return node.id == "True"
        if isinstance(node, ast.Call) and not node.keywords:
            func = node.func
            fn = None
            if isinstance(func, ast.Name) and func.id in _FUNCS:
                fn = _FUNCS[func.id]
            elif isinstance(func, ast.Attribute):
                fn = ev(func)
            if callable(fn):
                return fn(*(ev(a) for a in node.args))
        raise ValueError(f"unsupported expression element {ast.dump(node)[:60]}")

    return ev(ast.parse(expr.strip(), mode="eval"))


def bool_word(value: str, where: str, what: str) -> bool:
    v = value.strip().lower()
    if v in TRUE_WORDS:
        return True
    if v in FALSE_WORDS:
        return False
    raise LaunchError(f"{where}: {what} {value!r} is not a boolean; expected true, false, 1 or 0")


@dataclass
class Scope:
    """Launch configurations, the pushed ROS namespace and remaps in effect, the current file."""

    file: Path
    configs: dict[str, str]
    namespace: str = "/"
    remaps: list[tuple[str, str]] = field(default_factory=list)
    used: set[str] = field(default_factory=set)  # configurations read by $(var ...), shared with children

    def child(self, keep_configs: bool = True) -> Scope:
        configs = dict(self.configs) if keep_configs else {}
        return Scope(self.file, configs, self.namespace, list(self.remaps), self.used)


KNOWN_SUBSTITUTIONS = (
    "var", "env", "optenv", "eval", "find-pkg-share", "dirname", "filename",
    "not", "and", "or", "equals", "not-equals",
)  # fmt: skip


def evaluate_parts(parts: Sequence[str | Substitution], scope: Scope, where: str) -> str:
    """The text of `parts`, each substitution applied; refused past `MAX_STR_LEN` characters.

    Counted as the pieces come, before they are joined: `let`s that each
    double the last (`$(var a)$(var a)`) reach gigabytes in 35 steps.
    """
    pieces: list[str] = []
    length = 0
    for p in parts:
        piece = p if isinstance(p, str) else _apply(p, scope, where)
        length += len(piece)
        if length > MAX_STR_LEN:
            raise LaunchError(
                f"{where}: a substituted value longer than {MAX_STR_LEN} characters "
                "(a substitution that grows with each use?)"
            )
        pieces.append(piece)
    return "".join(pieces)


def _apply(sub: Substitution, scope: Scope, where: str) -> str:
    args = [evaluate_parts(a, scope, where) for a in sub.args]

    def need(lo: int, hi: int) -> None:
        if not lo <= len(args) <= hi:
            want = str(lo) if lo == hi else f"{lo}..{hi}"
            raise LaunchError(f"{where}: $({sub.name} ...) takes {want} argument(s), got {len(args)}")

    name = sub.name
    if name == "var":
        need(1, 1)
        if args[0] not in scope.configs:
            known = ", ".join(sorted(scope.configs)) or "none"
            raise LaunchError(
                f"{where}: $(var {args[0]}): no launch configuration {args[0]!r}"
                f" (declare it with `arg` or `let`; known here: {known})"
            )
        scope.used.add(args[0])
        return scope.configs[args[0]]
    if name in ("env", "optenv"):
        need(1, 2)
        if args[0] in os.environ:
            return os.environ[args[0]]
        if len(args) == 2:
            return args[1]
        if name == "optenv":
            return ""
        raise LaunchError(f"{where}: $(env {args[0]}): environment variable {args[0]!r} is not set")
    if name == "eval":
        expr = " ".join(args)
        try:
            value = safe_eval(expr)
        except Exception as err:
            raise LaunchError(f"{where}: $(eval {expr!r}) failed: {err}") from err
        return str(value)
    if name == "find-pkg-share":
        need(1, 1)
        if args[0] != "sensorbox":
            raise LaunchError(
                f"{where}: $(find-pkg-share {args[0]}): SensorBox knows only the package 'sensorbox'"
                " (its share folder); give a path instead"
            )
        return str(package_share())
    if name == "dirname":
        need(0, 0)
        return str(scope.file.parent)
    if name == "filename":
        need(0, 0)
        return str(scope.file)
    if name == "not":
        need(1, 1)
        return str(not bool_word(args[0], where, "$(not) argument")).lower()
    if name in ("and", "or"):
        need(2, 64)
        values = [bool_word(a, where, f"$({name}) argument") for a in args]
        return str(all(values) if name == "and" else any(values)).lower()
    if name in ("equals", "not-equals"):
        need(2, 2)
        same = args[0] == args[1]
        return str(same if name == "equals" else not same).lower()
    raise LaunchError(f"{where}: unknown substitution $({name} ...); known: {', '.join(KNOWN_SUBSTITUTIONS)}")


def substitute(text: str, configs: Mapping[str, str], file: Path = Path("<string>")) -> str:
    """Expand every substitution in `text` with launch configurations `configs`."""
    where = str(file)
    return evaluate_parts(parse_substitutions(text, where), Scope(file, dict(configs)), where)
