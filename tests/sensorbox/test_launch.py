"""The ROS 2 YAML launch parser: entities, substitutions, scoping, includes, parameters, errors."""

from __future__ import annotations

import textwrap
from pathlib import Path

import pytest

from sensorbox.errors import GraphError, LaunchError
from sensorbox.live.bus import Bus, Shutdown
from sensorbox.live.launch import parse_cli_args, parse_launch
from sensorbox.live.nodes import build_node
from sensorbox.live.substitutions import package_share, safe_eval, substitute

ROOT = Path(__file__).resolve().parents[2]


def write(path: Path, text: str) -> Path:
    path.write_text(textwrap.dedent(text))
    return path


# the ROS 2 documentation's example (different_formats_launch.yaml), with SensorBox's talker for turtlesim
EXAMPLE = """\
launch:
- arg: {name: background_r, default: "0"}
- arg: {name: chatter_ns, default: chatter/ns}
- arg: {name: use_extra, default: "false", description: start one more talker}
- let: {name: rate, value: "$(eval '$(var background_r) + 10')"}
- include:
    file: inner.launch.yaml
    arg:
    - {name: topic, value: from_parent}
- group:
  - push_ros_namespace: {namespace: $(var chatter_ns)}
  - let: {name: rate, value: "99"}
  - node: {pkg: sensorbox, exec: talker, name: sim, param: [{name: rate_hz, value: $(var rate)}]}
- node:
    pkg: sensorbox
    exec: talker
    name: sim
    namespace: turtlesim2
    param:
    - {name: rate_hz, value: $(var rate)}
    remap:
    - {from: /input/pose, to: /turtlesim1/turtle1/pose}
    - {from: chatter, to: /shared}
- node: {pkg: sensorbox, exec: talker, name: extra, if: $(var use_extra)}
- node: {pkg: sensorbox, exec: talker, name: not_extra, unless: $(var use_extra)}
"""
INNER = """\
launch:
- arg: {name: topic, default: inner_default}
- let: {name: leaked, value: "yes"}
- node:
    pkg: sensorbox
    exec: talker
    name: inner
    param:
    - {name: topic, value: $(var topic)}
    - {name: count, value: $(var background_r)}
"""


@pytest.fixture
def example(tmp_path):
    write(tmp_path / "inner.launch.yaml", INNER)
    return write(tmp_path / "example.launch.yaml", EXAMPLE)


def test_example_nodes_scoping_and_arguments(example):
    plan = parse_launch(example)
    nodes = {(n.namespace, n.name): n for n in plan.nodes}
    assert list(nodes) == [("/", "inner"), ("/chatter/ns", "sim"), ("/turtlesim2", "sim"), ("/", "not_extra")]
    assert dict(nodes["/", "inner"].params) == {"topic": "from_parent", "count": 0}  # "0" read as YAML: int
    assert dict(nodes["/chatter/ns", "sim"].params) == {"rate_hz": 99}  # the group's own `let`
    assert dict(nodes["/turtlesim2", "sim"].params) == {"rate_hz": 10}  # $(eval) of "0 + 10"
    assert nodes["/turtlesim2", "sim"].remaps == (
        ("/input/pose", "/turtlesim1/turtle1/pose"),
        ("chatter", "/shared"),
    )
    assert nodes["/", "inner"].where == f"{example.parent / 'inner.launch.yaml'}:4"
    # group and include scopes end with them: neither the group's rate nor the include's let leaks
    assert plan.configurations["rate"] == "10" and "leaked" not in plan.configurations
    assert [a.name for a in plan.arguments] == ["background_r", "chatter_ns", "use_extra", "topic"]
    assert plan.arguments[2].description == "start one more talker"


def test_command_line_arguments_override_defaults(example):
    plan = parse_launch(example, parse_cli_args(["use_extra:=true", "background_r:=5", "chatter_ns:=/abs"]))
    names = [(n.namespace, n.name) for n in plan.nodes]
    assert ("/", "extra") in names and ("/", "not_extra") not in names and ("/abs", "sim") in names
    assert dict(plan.nodes[0].params)["count"] == 5
    with pytest.raises(
        LaunchError, match=r"launch argument\(s\) colour not declared; its arguments: background_r"
    ):
        parse_launch(example, {"colour": "red"})


def test_substitutions(tmp_path, monkeypatch):
    monkeypatch.setenv("SB_TEST_HOST", "10.0.0.5")
    monkeypatch.delenv("SB_TEST_MISSING", raising=False)
    cfg = {"which": "b", "b": "bee", "n": "3", "yes": "true"}
    f = tmp_path / "x.launch.yaml"
    cases = {
        "$(var $(var which))": "bee",
        "host=$(env SB_TEST_HOST)": "host=10.0.0.5",
        "$(env SB_TEST_MISSING 'fall back')": "fall back",
        "[$(optenv SB_TEST_MISSING)]": "[]",
        "$(eval '$(var n) * 2 + 1')": "7",
        "$(eval 'math.floor(math.pi * 100) / 100')": "3.14",
        "$(eval \"'$(var b)' if $(var n) > 2 else 'no'\")": "bee",
        "$(not $(var yes)) $(and true 1) $(or false 0) $(equals a a) $(not-equals a a)": "false true false true false",
        "$(find-pkg-share sensorbox)/launch": f"{package_share()}/launch",
        "$(dirname)/rig.yaml": f"{tmp_path}/rig.yaml",
        "no substitution (here)": "no substitution (here)",
    }
    for text, want in cases.items():
        assert substitute(text, cfg, f) == want, text


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("$(var nope)", "no launch configuration 'nope'"),
        ("$(foo x)", r"unknown substitution \$\(foo ...\); known: var, env"),
        ("$(var x", "unclosed substitution"),
        ("$(env SB_TEST_MISSING)", "environment variable 'SB_TEST_MISSING' is not set"),
        ("$(eval __import__('os'))", "eval"),
        ("$(find-pkg-share turtlesim)", "knows only the package 'sensorbox'"),
        ("$(not maybe)", "is not a boolean"),
        ("$(var)", r"takes 1 argument"),
    ],
)
def test_substitution_errors(text, message, monkeypatch):
    monkeypatch.delenv("SB_TEST_MISSING", raising=False)
    with pytest.raises(LaunchError, match=message):
        substitute(text, {}, Path("f.launch.yaml"))


def test_safe_eval():
    assert safe_eval("1 + 2 * 3") == 7
    assert safe_eval("max(2, 3) ** 2 - abs(-1)") == 8
    assert safe_eval("1 < 2 < 3 and not False") is True
    for bad in ("open('x')", "(1).__class__", "x + 1", "[1, 2]"):
        with pytest.raises(ValueError, match="unsupported"):
            safe_eval(bad)
    assert safe_eval("2 ** 100") == 2**100 and safe_eval("'ab' * 3") == "ababab"


def test_eval_refuses_what_would_not_end():
    """$(eval 9**9**9) used to hang even with --dry-run (issue 20, class 10)."""
    for bad, what in (
        ("9**9**9", "too large"),
        ("'x' * 10**9", "characters"),
        ("(10**1000) * (10**1000)", "bits"),
    ):
        with pytest.raises(ValueError, match=what):
            safe_eval(bad)


def test_parameters_types_nesting_and_files(tmp_path):
    write(tmp_path / "params.yaml", """\
        /**:
          ros__parameters: {count: 3, topic: everyone}
        talker:
          ros__parameters:
            rate: {hz: 20.0}
        other:
          ros__parameters: {count: 99}
        """)  # fmt: skip
    f = write(tmp_path / "p.launch.yaml", """\
        launch:
        - node:
            exec: talker
            name: talker
            param:
            - from: params.yaml
            - {name: code, value: "007", type: str}
            - {name: flag, value: "True"}
            - {name: ratio, value: "0.5"}
            - {name: ips, value: [127.0.0.12, "$(eval '6 * 2')"]}
            - name: outer
              param:
              - {name: inner, value: 1}
        """)  # fmt: skip
    node = parse_launch(f).nodes[0]
    assert node.pkg == "sensorbox"  # `pkg` may be left out
    assert dict(node.params) == {
        "count": 3, "topic": "everyone", "rate.hz": 20.0, "code": "007", "flag": True, "ratio": 0.5,
        "ips": ["127.0.0.12", 12], "outer.inner": 1,
    }  # fmt: skip


def test_parameter_file_node_entry_overrides_the_wildcard_and_keeps_full_dotted_names(tmp_path):
    """As rcl reads a parameter file, the node's own entry wins over `/**` for a key both set (5, not 3),
    and a parameter nested two levels deep keeps its whole dotted name (`lidar.top.ip`)."""
    write(tmp_path / "params.yaml", """\
        /**:
          ros__parameters: {count: 3, lidar: {top: {ip: 10.0.0.1}}}
        talker:
          ros__parameters: {count: 5}
        """)  # fmt: skip
    f = write(tmp_path / "p.launch.yaml", """\
        launch:
        - node: {exec: talker, name: talker, param: [{from: params.yaml}]}
        """)  # fmt: skip
    assert dict(parse_launch(f).nodes[0].params) == {"count": 5, "lidar.top.ip": "10.0.0.1"}


def test_group_forms(tmp_path):
    f = write(tmp_path / "g.launch.yaml", """\
        launch:
        - let: {name: a, value: A}
        - group:
            scoped: false
            children:
            - let: {name: leaked, value: L}
            - push_ros_namespace: {namespace: outer}
        - group:
            forwarding: false
            keep: [{name: kept, value: $(var a)}]
            children:
            - set_remap: {from: chatter, to: /x}
            - node: {exec: talker, name: t, param: [{name: topic, value: "$(var kept)"}]}
        - node: {exec: talker, name: u, param: [{name: topic, value: $(var leaked)}]}
        """)  # fmt: skip
    plan = parse_launch(f)
    t, u = plan.nodes
    assert (t.namespace, dict(t.params), t.remaps) == ("/outer", {"topic": "A"}, (("chatter", "/x"),))
    assert (u.namespace, dict(u.params), u.remaps) == ("/outer", {"topic": "L"}, ())
    forwarding = write(tmp_path / "h.launch.yaml", """\
        launch:
        - let: {name: a, value: A}
        - group: {forwarding: false, children: [{node: {exec: talker, param: [{name: topic, value: $(var a)}]}}]}
        """)  # fmt: skip
    with pytest.raises(LaunchError, match="no launch configuration 'a'"):
        parse_launch(forwarding)


BAD = [
    ("nodes:\n- node: {exec: talker}\n", "expected a single top-level key `launch:`"),
    ("launch:\n- nodes: {exec: talker}\n", "unknown entity `nodes`; known: arg, group, include"),
    (
        "launch:\n- node: {pakage: sensorbox, exec: talker}\n",
        "`node` has unknown key.s. pakage; allowed: pkg, exec",
    ),
    ("launch:\n- node: {pkg: sensorbox}\n", "`node` is missing its 'exec' key"),
    (
        "launch:\n- node: {pkg: turtlesim, exec: turtlesim_node}\n",
        "unknown node type pkg 'turtlesim' exec 'turtlesim_node'; known: sensorbox/recorder, sensorbox/livox_driver",
    ),
    ("launch:\n- arg: {name: out}\n", "launch argument 'out' is required .no description.; pass out:=VALUE"),
    ("launch:\n- arg: {name: c, default: x, choices: [a, b]}\n", "c:='x' is not one of a, b"),
    ("launch:\n- node: {exec: talker, if: maybe}\n", "if 'maybe' is not a boolean"),
    ("launch:\n- node: {exec: talker, if: 'true', unless: 'false'}\n", "takes `if` or `unless`, not both"),
    ("launch:\n- node: {exec: talker, param: [{name: a, value: 1, param: []}]}\n", "exactly one of `value`"),
    ("launch:\n- node: {exec: talker, param: [{name: a, value: x, type: colour}]}\n", "type 'colour'"),
    (
        "launch:\n- include: {file: missing.launch.yaml}\n",
        "included launch file .*missing.launch.yaml not found",
    ),
    ("launch:\n- node: {exec: talker\n", "malformed YAML"),
    ("launch:\n- node: {exec: talker, exec: recorder}\n", "key 'exec' given twice"),
    ("launch: {node: {exec: talker}}\n", "`launch:` must be a list"),
    (  # sweep 6: both LiDARs' topics remapped onto one were recorded interleaved as one, without a word
        "launch:\n- node: {exec: talker, remap: [{from: /a, to: /lidar}, {from: /b, to: /lidar}]}\n",
        r":2: remaps /a -> /lidar and /b -> /lidar send two topics to one; their messages would be recorded "
        "as one topic: give each its own$",
    ),
]


@pytest.mark.parametrize(("text", "message"), BAD)
def test_errors_name_file_line_and_key(tmp_path, text, message):
    f = tmp_path / "bad.launch.yaml"
    f.write_text(text)
    with pytest.raises(LaunchError, match=message) as info:
        parse_launch(f)
    assert str(f) in str(info.value)


def test_error_line_numbers_and_include_cycles(tmp_path):
    f = write(tmp_path / "a.launch.yaml", """\
        launch:
        - arg: {name: x, default: "1"}

        - node:
            exec: talker
            param: [{name: rate_hz, value: $(var y)}]
        """)  # fmt: skip
    with pytest.raises(LaunchError, match=rf"{f}:4: .*no launch configuration 'y' .*known here: x"):
        parse_launch(f)
    write(tmp_path / "b.launch.yaml", "launch:\n- include: {file: c.launch.yaml}\n")
    write(tmp_path / "c.launch.yaml", "launch:\n- include: b.launch.yaml\n")
    with pytest.raises(
        LaunchError, match=r"include each other in a cycle: .*b\.launch\.yaml -> .*c\.launch\.yaml -> .*b"
    ):
        parse_launch(tmp_path / "b.launch.yaml")
    with pytest.raises(LaunchError, match="not found"):
        parse_launch(tmp_path / "none.launch.yaml")


def test_an_include_argument_the_file_neither_declares_nor_reads_is_refused(tmp_path):
    """Sweep 11: an include passing `durration` (a typo) to a file declaring `duration` (default 0: record
    until Ctrl-C) was dropped without a word. An argument the included files neither declare nor read as
    $(var ...) is refused, naming it and the file; one they read without declaring it is ROS 2's own use."""
    inc = write(tmp_path / "inc.launch.yaml", """\
        launch:
        - arg: {name: duration, default: "0"}
        - node: {exec: recorder, param: [{name: duration_s, value: $(var duration)}, {name: topics, value: $(var extra)}]}
        """)  # fmt: skip
    typo = write(tmp_path / "typo.launch.yaml", """\
        launch:
        - include:
            file: inc.launch.yaml
            arg: [{name: durration, value: "5"}, {name: extra, value: /a}]
        """)  # fmt: skip
    with pytest.raises(LaunchError) as info:
        parse_launch(typo)
    assert str(info.value) == (
        f"{typo}:2: include {inc}: argument(s) durration neither declared nor read there (a misspelled name "
        "would be dropped without a word); its arguments: duration"
    )
    right = write(tmp_path / "right.launch.yaml", """\
        launch:
        - include:
            file: inc.launch.yaml
            arg: [{name: duration, value: "5"}, {name: extra, value: /a}]
        """)  # fmt: skip
    (node,) = parse_launch(right).nodes
    assert node.params["duration_s"] == 5 and node.params["topics"] == "/a"


@pytest.mark.parametrize(("namespace", "part"), [("my ns", "my ns"), ("/rig/2nd", "2nd"), ("a-b", "a-b")])
def test_a_namespace_that_is_no_ros_name_is_refused(tmp_path, namespace, part):
    """Sweep 11: `push_ros_namespace: {namespace: 'my ns'}` recorded topics '/my ns/livox/...' (no ROS
    names), and the file's absolute remaps no longer reached them."""
    for entity in (
        f"push_ros_namespace: {{namespace: '{namespace}'}}",
        f"node: {{exec: talker, namespace: '{namespace}'}}",
    ):
        f = write(tmp_path / "ns.launch.yaml", f"launch:\n- {entity}\n")
        with pytest.raises(LaunchError) as info:
            parse_launch(f)
        assert str(info.value) == (
            f"{f}:2: namespace {namespace!r}: {part!r} is not a ROS name (letters, digits and _, not starting "
            "with a digit; parts joined by /)"
        )


@pytest.mark.parametrize("bad", ["out", "=x", "a b:=c"])
def test_cli_argument_syntax(bad):
    with pytest.raises(LaunchError, match="expected NAME:=VALUE"):
        parse_cli_args([bad])


def test_node_parameters_are_checked_when_built(tmp_path):
    f = write(tmp_path / "n.launch.yaml", """\
        launch:
        - node: {exec: talker, name: t, param: [{name: rate_hz, value: 5.0}, {name: colour, value: red}]}
        - node: {exec: talker, name: u, param: [{name: rate_hz, value: fast}]}
        - node: {exec: recorder, param: [{name: split_size_mb, value: -1}]}
        - node: {exec: recorder, param: [{name: duration_s, value: .nan}]}
        - node: {exec: recorder, param: [{name: out, value: ''}]}
        """)  # fmt: skip
    t, u, r, nan, empty = parse_launch(f).nodes
    with pytest.raises(
        GraphError, match=r"parameter\(s\) colour not used by this node .*it reads: count, payload_bytes"
    ):
        build_node(t, Bus(), Shutdown())
    with pytest.raises(GraphError, match="parameter 'rate_hz' = 'fast': expected a finite number"):
        build_node(u, Bus(), Shutdown())
    with pytest.raises(
        GraphError, match=r"at .*n.launch.yaml:4: parameter 'split_size_mb' = -1: expected at least 0$"
    ):
        build_node(
            r, Bus(), Shutdown()
        )  # said 'recorder split_bytes ... got -1048576', a key the file has not
    with pytest.raises(
        GraphError, match=r"parameter 'out' = '': expected a path \(an empty one would be the current"
    ):
        build_node(empty, Bus(), Shutdown())  # sweep 8: recorded into the current folder
    with pytest.raises(GraphError, match=r"parameter 'duration_s' = nan: expected a finite number"):
        build_node(nan, Bus(), Shutdown())  # NaN passed '>= 0' and recorded forever


def test_shipped_launch_files_parse_with_their_defaults():
    sim = parse_launch(ROOT / "launch" / "sim.launch.yaml")
    assert [(n.pkg, n.exec) for n in sim.nodes] == [
        ("sensorbox", "mid360_emulator"), ("sensorbox", "mid360_emulator"),
        ("livox_ros_driver2", "livox_ros_driver2_node"), ("sensorbox", "sim_camera"), ("sensorbox", "recorder"),
    ]  # fmt: skip
    assert dict(sim.nodes[-1].params) == {
        "out": "bags/sim", "name": "", "duration_s": 0, "split_size_mb": 0, "min_free_mb": 1024,
    }  # fmt: skip
    real = parse_launch(ROOT / "launch" / "sensorbox.launch.yaml", {"camera": "opencv"})
    assert [n.name for n in real.nodes] == ["livox_lidar_publisher", "v4l2_stereo", "recorder"]
    with pytest.raises(LaunchError, match="camera:='usb' is not one of zed, opencv"):
        parse_launch(ROOT / "launch" / "sensorbox.launch.yaml", {"camera": "usb"})


@pytest.mark.parametrize(
    ("entity", "message"),
    [
        ("node: {exec: talker, param: 5}", "node `param` must be a list of parameters, got 5"),
        ("node: {exec: talker, param: rate}", "node `param` must be a list of parameters, got 'rate'"),
        ("node: {exec: talker, remap: {from: a, to: b}}", "node `remap` must be a list of remappings, got a mapping"),
        ("node: {exec: talker, param: [{name: a, param: 5}]}", "param 'a' `param` must be a list of parameters, got 5"),
        ("group: {keep: 5, children: []}", "group `keep` must be a list of arguments, got 5"),
        ("include: {file: b.launch.yaml, arg: 5}", "include `arg` must be a list of arguments, got 5"),
    ],
)  # fmt: skip
def test_a_scalar_where_a_list_belongs_is_one_line_naming_the_key(tmp_path, entity, message):
    """`param: 5` was `TypeError: 'int' object is not iterable`; `param: rate` was iterated by character."""
    write(tmp_path / "b.launch.yaml", "launch: []\n")
    f = write(tmp_path / "a.launch.yaml", f"launch:\n- {entity}\n")
    with pytest.raises(LaunchError) as info:
        parse_launch(f)
    assert str(info.value) == f"{f}:2: {message}"
