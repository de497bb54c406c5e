"""A parser of ROS 2 YAML launch files (`sensorbox.live.launch_run` runs what they describe).

The syntax is launch_yaml's (ros2/launch, launch_ros): a top-level `launch:`
list of entities, each a one-key mapping:

- `arg` (name, default, description, choices): a launch argument; `name:=value`
  on the command line (or an include's `arg`) wins over `default`; an argument
  without either is an error.
- `let` (name, value): sets a launch configuration.
- `node` (pkg, exec, name, namespace, param, remap, output): one SensorBox node.
  `param` entries are `{name, value}` (nested `{name, param: [...]}` gives
  dotted names) or `{from: FILE}` (a ROS 2 parameter file with
  `ros__parameters`); values keep their YAML type, and strings, after
  substitution, are read as YAML scalars (`"5"` -> 5) as launch_ros does.
  `remap` entries are `{from, to}`.
- `include` (file, arg): another launch file, relative to the including one
  unless absolute; it sees the current configurations plus its `arg` values.
- `group` (a list of entities, or {scoped, forwarding, keep, children}):
  `let`, namespaces and remaps set inside a scoped group (the default) end with it.
- `push_ros_namespace` (namespace), `set_remap` (from, to): for the rest of the
  enclosing group; `log` (message).
- Every entity takes `if` / `unless` (true/false/1/0 after substitution).

Substitutions in any string: `$(var NAME)`, `$(env NAME [DEFAULT])`,
`$(optenv NAME [DEFAULT])`, `$(eval EXPR)` (arithmetic, comparison and boolean
Python expressions, no names but `math.*`, min/max/abs/round/int/float/str),
`$(find-pkg-share sensorbox)` (`substitutions.package_share`), `$(dirname)`,
`$(filename)`, `$(not X)`, `$(and X Y)`, `$(or X Y)`, `$(equals A B)`,
`$(not-equals A B)`; they nest, and arguments may be quoted.

Differences from ROS 2, on purpose: an included file's `let`s do not leak into
the including file (ROS 2 scopes them only inside a group); an unknown key, a
command-line argument no `arg` declares, an unknown substitution or node type is
an error naming the file and line, never silently ignored.

Nodes: `pkg`/`exec` name a SensorBox node type (`sensorbox.live.nodes.NODE_TYPES`;
the real driver packages `livox_ros_driver2` and `zed_wrapper` are aliases); see
`sensorbox.live.nodes` for their parameters. `launch_run.run_launch` builds and runs them in
one process (`sensorbox.live.bus.run_graph`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import yaml

from calibration.files import resolved
from sensorbox.errors import GraphError, LaunchError
from sensorbox.live.bus import resolve_name
from sensorbox.live.launch_yaml import LineMap, join_ns, load_launch_yaml, param_file, ros_namespace
from sensorbox.live.substitutions import Scope, bool_word, evaluate_parts, parse_substitutions

if TYPE_CHECKING:
    pass

# ---------------------------------------------------------------- results


@dataclass(frozen=True)
class LaunchArgument:
    """A declared `arg`: its name, default (None = required), description, allowed values."""

    name: str
    default: str | None
    description: str
    choices: tuple[str, ...]
    file: Path


@dataclass(frozen=True)
class NodeSpec:
    """One `node` entity, fully substituted: what `sensorbox.live.nodes.build_node` needs."""

    pkg: str
    exec: str
    name: str | None
    namespace: str
    params: Mapping[str, Any]
    remaps: tuple[tuple[str, str], ...]
    where: str  # "file:line", for error messages

    @property
    def label(self) -> str:
        return f"node {self.name or self.exec!r} ({self.pkg}/{self.exec}) at {self.where}"


@dataclass
class LaunchPlan:
    """What a launch file describes once parsed: nodes to start, arguments, final configurations."""

    file: Path
    nodes: list[NodeSpec] = field(default_factory=list)
    arguments: list[LaunchArgument] = field(default_factory=list)
    configurations: dict[str, str] = field(default_factory=dict)
    messages: list[str] = field(default_factory=list)  # `log` entities


# ---------------------------------------------------------------- substitutions


# ---------------------------------------------------------------- entities


def _where(scope: Scope, item: Any) -> str:
    line = getattr(item, "line", 0)
    return f"{scope.file}:{line}" if line else str(scope.file)


def _one_source_per_target(remaps: list[tuple[str, str]], where: str) -> None:
    """A LaunchError at `where` when two of a node's remaps send different topics to one: two sensors'
    messages would be recorded interleaved as one (two LiDARs on one topic at twice its rate)."""
    source: dict[str, str] = {}
    for frm, to in remaps:
        if source.setdefault(to, frm) != frm:
            raise LaunchError(
                f"{where}: remaps {source[to]} -> {to} and {frm} -> {to} send two topics to one; their "
                "messages would be recorded as one topic: give each its own"
            )


def _remap(f: Mapping[str, Any], scope: Scope, where: str) -> tuple[str, str]:
    """A remap's (from, to), each a valid topic name (`resolve_name`'s rules), else LaunchError at `where`:
    the bus would refuse a bad one only when the node starts, naming neither file nor line."""
    pair = (_text(f["from"], scope, where, "from"), _text(f["to"], scope, where, "to"))
    for key, name in zip(("from", "to"), pair, strict=True):
        try:
            resolve_name(name, "/", "node")
        except GraphError as err:
            raise LaunchError(f"{where}: remap {key}: {err}") from err
    return pair


def _text(value: Any, scope: Scope, where: str, key: str) -> str:
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, int | float):
        return str(value)
    if not isinstance(value, str):
        raise LaunchError(f"{where}: {key!r} must be a string, got {type(value).__name__} {value!r}")
    return evaluate_parts(parse_substitutions(value, where), scope, where)


def _typed(text: str) -> Any:
    """A substituted parameter string read as a YAML scalar ("5" -> 5, "true" -> True), else itself."""
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError:
        return text
    if isinstance(value, bool | int | float) or (
        isinstance(value, list) and all(isinstance(v, bool | int | float | str) for v in value)
    ):
        return value
    return text


def _fields(
    entity: str, body: Any, where: str, allowed: Sequence[str], required: Sequence[str] = ()
) -> LineMap:
    if not isinstance(body, dict):
        raise LaunchError(f"{where}: `{entity}` expects a mapping of keys, got {type(body).__name__}")
    unknown = sorted(set(body) - set(allowed) - {"if", "unless"})
    if unknown:
        raise LaunchError(
            f"{where}: `{entity}` has unknown key(s) {', '.join(unknown)}; allowed: {', '.join(allowed)}"
        )
    for key in required:
        if key not in body:
            raise LaunchError(f"{where}: `{entity}` is missing its {key!r} key")
    out = LineMap(body)
    out.line = getattr(body, "line", 0)
    return out


def _entries(f: LineMap, key: str, entity: str, of: str, where: str) -> list[Any]:
    """The list under `key` of entity `f` ([] when absent or empty), or a LaunchError naming `entity`
    and `key` when it is a scalar (`param: 5`), a string or a mapping rather than a list."""
    raw = f.get(key)
    if raw is None:
        return []
    if not isinstance(raw, list):
        got = "a mapping" if isinstance(raw, dict) else repr(raw)
        raise LaunchError(f"{where}: {entity} `{key}` must be a list of {of}, got {got}")
    return raw


def _condition(body: Any, scope: Scope, where: str) -> bool:
    """False when the entity's `if` is false or its `unless` is true."""
    if not isinstance(body, dict):
        return True
    if "if" in body and "unless" in body:
        raise LaunchError(f"{where}: an entity takes `if` or `unless`, not both")
    for key, want in (("if", True), ("unless", False)):
        if key in body:
            value = body[key]
            flag = (
                value if isinstance(value, bool) else bool_word(_text(value, scope, where, key), where, key)
            )
            return flag == want
    return True


MAX_INCLUDE_DEPTH = 32
"""Deepest chain of `include`s followed: each file is parsed recursively, as each nested group is
(whose depth the YAML reader bounds)."""


class _Parser:
    def __init__(self, plan: LaunchPlan) -> None:
        self.plan = plan
        self.stack: list[Path] = []

    def file(self, path: Path, scope: Scope) -> None:
        path = resolved(path, LaunchError, "a launch file")
        if path in self.stack:
            chain = " -> ".join(str(p) for p in [*self.stack, path])
            raise LaunchError(f"launch files include each other in a cycle: {chain}")
        if len(self.stack) >= MAX_INCLUDE_DEPTH:
            raise LaunchError(
                f"{path}: included more than {MAX_INCLUDE_DEPTH} files deep (from {self.stack[0]})"
            )
        doc = load_launch_yaml(path)
        if not isinstance(doc, dict) or set(doc) != {"launch"}:
            keys = ", ".join(map(str, doc)) if isinstance(doc, dict) else type(doc).__name__
            raise LaunchError(f"{path}: expected a single top-level key `launch:` (a list), got {keys}")
        entities = doc["launch"]
        if entities is None:
            entities = []
        if not isinstance(entities, list):
            raise LaunchError(f"{path}: `launch:` must be a list of entities, got {type(entities).__name__}")
        self.stack.append(path)
        scope.file = path
        try:
            self.entities(entities, scope)
        finally:
            self.stack.pop()

    def entities(self, items: list[Any], scope: Scope) -> None:
        for item in items:
            where = _where(scope, item)
            if not isinstance(item, dict) or len(item) != 1:
                raise LaunchError(
                    f"{where}: each entity is a mapping with one key (its type, e.g. `node:`), got {item!r}"
                )
            kind, body = next(iter(item.items()))
            handler = self.HANDLERS.get(kind)
            if handler is None:
                raise LaunchError(
                    f"{where}: unknown entity `{kind}`; known: {', '.join(sorted(set(self.HANDLERS)))}"
                )
            if not _condition(body, scope, where):
                continue
            handler(self, body, scope, where)

    # ---- entities

    def arg(self, body: Any, scope: Scope, where: str) -> None:
        f = _fields("arg", body, where, ("name", "default", "description", "choices", "choice"), ("name",))
        name = _text(f["name"], scope, where, "name")
        choices: list[str] = []
        for key in ("choices", "choice"):
            raw = f.get(key) or []
            if not isinstance(raw, list):
                raise LaunchError(f"{where}: arg {name!r}: {key!r} must be a list")
            for c in raw:
                choices.append(
                    _text(c["value"] if isinstance(c, dict) and "value" in c else c, scope, where, key)
                )
        default = None if f.get("default") is None else _text(f["default"], scope, where, "default")
        description = str(f.get("description", ""))
        self.plan.arguments.append(LaunchArgument(name, default, description, tuple(choices), scope.file))
        if name not in scope.configs:
            if default is None:
                raise LaunchError(
                    f"{where}: launch argument {name!r} is required ({description or 'no description'});"
                    f" pass {name}:=VALUE"
                )
            scope.configs[name] = default
        if choices and scope.configs[name] not in choices:
            raise LaunchError(
                f"{where}: launch argument {name}:={scope.configs[name]!r} is not one of {', '.join(choices)}"
            )

    def let(self, body: Any, scope: Scope, where: str) -> None:
        f = _fields("let", body, where, ("name", "value"), ("name", "value"))
        scope.configs[_text(f["name"], scope, where, "name")] = _text(f["value"], scope, where, "value")

    def log(self, body: Any, scope: Scope, where: str) -> None:
        f = _fields("log", body, where, ("message",), ("message",))
        self.plan.messages.append(_text(f["message"], scope, where, "message"))

    def push_ros_namespace(self, body: Any, scope: Scope, where: str) -> None:
        f = _fields("push_ros_namespace", body, where, ("namespace",), ("namespace",))
        ns = ros_namespace(_text(f["namespace"], scope, where, "namespace"), where)
        scope.namespace = ns if ns.startswith("/") else join_ns(scope.namespace, ns)

    def set_remap(self, body: Any, scope: Scope, where: str) -> None:
        f = _fields("set_remap", body, where, ("from", "to"), ("from", "to"))
        scope.remaps.append(_remap(f, scope, where))

    def group(self, body: Any, scope: Scope, where: str) -> None:
        if isinstance(body, list):
            self.entities(body, scope.child())
            return
        f = _fields("group", body, where, ("scoped", "forwarding", "keep", "children"), ("children",))
        scoped = self._flag(f, "scoped", True, scope, where)
        forwarding = self._flag(f, "forwarding", True, scope, where)
        children = f["children"]
        if not isinstance(children, list):
            raise LaunchError(f"{where}: group `children` must be a list of entities")
        if not scoped:
            self.entities(children, scope)
            return
        inner = scope.child(keep_configs=forwarding)
        for k in _entries(f, "keep", "group", "arguments", where):
            kf = _fields("keep", k, where, ("name", "value"), ("name", "value"))
            inner.configs[_text(kf["name"], scope, where, "name")] = _text(kf["value"], scope, where, "value")
        self.entities(children, inner)

    def include(self, body: Any, scope: Scope, where: str) -> None:
        if isinstance(body, str):
            body = LineMap(file=body)
        f = _fields("include", body, where, ("file", "arg"), ("file",))
        target = Path(_text(f["file"], scope, where, "file"))
        if not target.is_absolute():
            target = scope.file.parent / target
        if not target.exists():
            raise LaunchError(f"{where}: included launch file {target} not found")
        inner = scope.child()
        inner.used = set()  # what the included file reads, apart from what its includer does
        passed = []
        for a in _entries(f, "arg", "include", "arguments", where):
            af = _fields("include arg", a, where, ("name", "value"), ("name", "value"))
            passed.append(_text(af["name"], scope, where, "name"))
            inner.configs[passed[-1]] = _text(af["value"], scope, where, "value")
        first = len(self.plan.arguments)
        self.file(target, inner)
        scope.used |= inner.used
        known = {a.name for a in self.plan.arguments[first:]}
        if unknown := sorted(set(passed) - known - inner.used):
            declared = ", ".join(sorted(known)) or "none"
            raise LaunchError(
                f"{where}: include {target}: argument(s) {', '.join(unknown)} neither declared nor read "
                f"there (a misspelled name would be dropped without a word); its arguments: {declared}"
            )

    def node(self, body: Any, scope: Scope, where: str) -> None:
        allowed = ("pkg", "exec", "name", "namespace", "param", "remap", "output", "exec_name")
        f = _fields("node", body, where, allowed, ("exec",))
        pkg = _text(f.get("pkg", "sensorbox"), scope, where, "pkg")
        exe = _text(f["exec"], scope, where, "exec")
        from sensorbox.live.nodes import known_node_types, node_type

        if node_type(pkg, exe) is None:
            raise LaunchError(
                f"{where}: unknown node type pkg {pkg!r} exec {exe!r}; known: {', '.join(known_node_types())}"
            )
        name = _text(f["name"], scope, where, "name") if "name" in f else None
        ns = ros_namespace(_text(f.get("namespace", ""), scope, where, "namespace"), where)
        namespace = ns if ns.startswith("/") else join_ns(scope.namespace, ns)
        params: dict[str, Any] = {}
        for entry in _entries(f, "param", "node", "parameters", where):
            self._param(entry, "", params, scope, where, name or exe, namespace)
        remaps = list(scope.remaps)
        for entry in _entries(f, "remap", "node", "remappings", where):
            rf = _fields("remap", entry, where, ("from", "to"), ("from", "to"))
            remaps.append(_remap(rf, scope, where))
        _one_source_per_target(remaps, where)
        self.plan.nodes.append(NodeSpec(pkg, exe, name, namespace, params, tuple(remaps), where))

    def _param(
        self, entry: Any, prefix: str, out: dict[str, Any], scope: Scope, where: str, node: str, ns: str
    ) -> None:
        if isinstance(entry, dict) and "from" in entry:
            f = _fields("param", entry, where, ("from",))
            path = Path(_text(f["from"], scope, where, "from"))
            out.update(param_file(path if path.is_absolute() else scope.file.parent / path, node, ns, where))
            return
        f = _fields("param", entry, where, ("name", "value", "param", "type"), ("name",))
        name = prefix + _text(f["name"], scope, where, "name")
        if ("value" in f) == ("param" in f):
            raise LaunchError(f"{where}: param {name!r} needs exactly one of `value` or nested `param`")
        if "param" in f:
            for sub in _entries(f, "param", f"param {name!r}", "parameters", where):
                self._param(sub, name + ".", out, scope, where, node, ns)
            return
        kind = f.get("type")
        out[name] = _param_value(f["value"], scope, where, name, kind)

    @staticmethod
    def _flag(f: LineMap, key: str, default: bool, scope: Scope, where: str) -> bool:
        if key not in f:
            return default
        value = f[key]
        return value if isinstance(value, bool) else bool_word(_text(value, scope, where, key), where, key)

    HANDLERS: ClassVar[dict[str, Callable[[_Parser, Any, Scope, str], None]]] = {
        "arg": arg, "let": let, "log": log, "node": node, "include": include, "group": group,
        "push_ros_namespace": push_ros_namespace, "push-ros-namespace": push_ros_namespace,
        "set_remap": set_remap, "set-remap": set_remap,
    }  # fmt: skip


def _param_value(value: Any, scope: Scope, where: str, name: str, kind: Any) -> Any:
    if isinstance(value, list):
        return [_param_value(v, scope, where, name, kind) for v in value]
    if isinstance(value, bool | int | float) and kind is None:
        return value
    if value is None:
        raise LaunchError(f"{where}: param {name!r} has no value")
    text = _text(value, scope, where, name)
    if kind is None:
        return _typed(text)
    casts: dict[str, Callable[[str], Any]] = {
        "str": str,
        "int": int,
        "float": float,
        "bool": lambda t: bool_word(t, where, f"param {name!r}"),
    }
    if kind not in casts:
        raise LaunchError(f"{where}: param {name!r}: type {kind!r}; expected one of {', '.join(casts)}")
    try:
        return casts[kind](text)
    except ValueError as err:
        raise LaunchError(f"{where}: param {name!r}: {text!r} is not a {kind}") from err


# ---------------------------------------------------------------- public API


def parse_cli_args(items: Sequence[str]) -> dict[str, str]:
    """`["out:=bags", "duration:=5"]` -> {"out": "bags", "duration": "5"}."""
    out: dict[str, str] = {}
    for item in items:
        name, sep, value = item.partition(":=")
        if not sep or not name or any(c.isspace() for c in name):
            raise LaunchError(f"launch argument {item!r}: expected NAME:=VALUE, e.g. duration:=10")
        if name in out:  # the last would win without a word
            raise LaunchError(
                f"launch argument {name} given twice ({name}:={out[name]}, {item}); give it once"
            )
        out[name] = value
    return out


def parse_launch(path: str | Path, args: Mapping[str, str] | None = None) -> LaunchPlan:
    """Parse a launch file with command-line arguments `args` into the nodes it starts."""
    path = Path(path)
    args = dict(args or {})
    plan = LaunchPlan(path)
    scope = Scope(path, dict(args))
    _Parser(plan).file(path, scope)
    declared = {a.name for a in plan.arguments}
    extra = sorted(set(args) - declared)
    if extra:
        known = ", ".join(sorted(declared)) or "none"
        raise LaunchError(
            f"{path}: launch argument(s) {', '.join(extra)} not declared; its arguments: {known}"
        )
    _refuse_emptied(path, args, plan.arguments)
    plan.configurations = scope.configs
    return plan


def _refuse_emptied(path: Path, args: Mapping[str, str], declared: Sequence[LaunchArgument]) -> None:
    """Refuse `NAME:=` (empty) for an argument whose default is not empty.

    Such a value is a path or a setting left out by mistake: sim.launch.yaml's
    `out:=` made the recorder's folder "" and the rig "/rig.yaml", at the
    filesystem root. An argument whose default is empty (`name`) may be given empty.
    """
    for arg in declared:
        if args.get(arg.name) == "" and arg.default:
            raise LaunchError(
                f"{path}: launch argument {arg.name}:= is empty (its default is {arg.default!r}); "
                "give a value, or leave it out for the default"
            )
