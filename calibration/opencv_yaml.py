"""OpenCV's YAML dialect (``cv::FileStorage``): the ``%YAML:1.0`` header and ``!!opencv-matrix`` nodes.

OpenCV starts its files with ``%YAML:1.0``, a directive YAML itself does not
allow (YAML writes ``%YAML 1.1``), and stores matrices as tagged mappings::

    T_cam_imu: !!opencv-matrix
       rows: 4
       cols: 4
       dt: d
       data: [ 16 numbers, row-major ]

Kalibr camchains written by OpenVINS and other OpenCV-based tools carry the
header and sometimes such matrices; PyYAML refuses both. `load_opencv_yaml`
reads them: the header line is blanked (so line numbers in later errors stay
right) and a matrix becomes nested lists of rows, or a flat list when it has
one row or one column (a vector such as intrinsics or distortion coefficients).
"""

from __future__ import annotations

import re
import sys
from typing import Any

import yaml

_OPENCV_DIRECTIVE = re.compile(r"\A(?:\ufeff)?%YAML:\d+\.\d+[ \t]*(?:#[^\r\n]*)?(?=\r?\n|\Z)")
_FLOAT_DT = frozenset("fdh")  # float32, float64, float16
_INT_DT = frozenset("ucwsi")  # uint8, int8, uint16, int16, int32
OPENCV_MATRIX_TAG = "tag:yaml.org,2002:opencv-matrix"


def strip_opencv_directive(text: str) -> str:
    """Blank out a leading ``%YAML:1.0`` line (and a comment after it, as OpenVINS writes:
    ``%YAML:1.0 # need to specify the file type at the top!``), keeping the line count."""
    return _OPENCV_DIRECTIVE.sub("", text, count=1)


MAX_YAML_DEPTH = 64
"""Deepest nesting of mappings and lists read: the reference camchain nests 4 levels, the rig file 5,
the shipped launch files 7 and 8. PyYAML composes recursively; a RecursionError came between 400
and 500 levels."""


class BoundedSafeLoader(yaml.SafeLoader):
    """`yaml.SafeLoader` that refuses nesting deeper than `MAX_YAML_DEPTH` as a YAML error at its line."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._depth = 0

    def compose_node(self, parent: yaml.Node | None, index: int) -> yaml.Node | None:
        self._depth += 1
        try:
            if self._depth > MAX_YAML_DEPTH:
                mark = self.peek_event().start_mark  # type: ignore[no-untyped-call]
                raise yaml.composer.ComposerError(
                    None, None, f"nested more than {MAX_YAML_DEPTH} levels deep", mark
                )
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_yaml_int(self, node: yaml.ScalarNode) -> int:
        """An integer, or a YAML error at its line when it has more digits than Python converts
        (`sys.get_int_max_str_digits`, 4300 by default), where PyYAML lets the ValueError escape."""
        try:
            return super().construct_yaml_int(node)
        except ValueError as err:
            digits = sum(c.isdigit() for c in str(node.value))
            limit = sys.get_int_max_str_digits()
            problem = (
                f"an integer of {digits} digits; at most {limit} are read"
                if digits > limit
                else f"not an integer: {str(node.value)[:40]!r}"
            )
            raise yaml.constructor.ConstructorError(None, None, problem, node.start_mark) from err


BoundedSafeLoader.add_constructor("tag:yaml.org,2002:int", BoundedSafeLoader.construct_yaml_int)


class OpenCvSafeLoader(BoundedSafeLoader):
    """`yaml.SafeLoader` that also constructs ``!!opencv-matrix`` nodes (see the module doc).

    Two more differences from PyYAML's YAML 1.1 reading, for files other
    tools write: a number in exponent form without a dot (``1e-04``,
    ``5000693e-4``, as C++ and YAML 1.2 writers print them) is a float, not
    the string YAML 1.1 makes of it; and a key given twice in one mapping is
    an error instead of the last copy silently winning.
    """

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: set[Any] = set()
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":  # `<<: *anchor`, which super() flattens
                continue
            key = self.construct_object(key_node, deep=deep)
            try:
                hash(key)
            except TypeError:  # super() refuses it in one line ("found unhashable key")
                continue
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"key {key!r} given twice in one mapping", key_node.start_mark
                )
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


OpenCvSafeLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
    list("-+0123456789."),
)


def _matrix_error(node: yaml.Node, problem: str) -> yaml.constructor.ConstructorError:
    return yaml.constructor.ConstructorError(None, None, f"!!opencv-matrix: {problem}", node.start_mark)


def _construct_opencv_matrix(loader: yaml.SafeLoader, node: yaml.Node) -> list[Any]:
    """Rows as nested lists (floats for dt f/d/h, ints for integer dt); a vector as one flat list."""
    if not isinstance(node, yaml.MappingNode):
        raise _matrix_error(node, "expected a mapping with rows, cols, dt and data")
    fields = loader.construct_mapping(node, deep=True)
    missing = [k for k in ("rows", "cols", "dt", "data") if k not in fields]
    if missing:
        raise _matrix_error(node, f"missing {', '.join(missing)}")
    rows, cols, dt, data = fields["rows"], fields["cols"], fields["dt"], fields["data"]
    if not all(isinstance(n, int) and not isinstance(n, bool) and n > 0 for n in (rows, cols)):
        raise _matrix_error(node, f"rows and cols must be positive integers, got {rows!r} and {cols!r}")
    if not isinstance(dt, str) or dt not in _FLOAT_DT | _INT_DT:
        known = "".join(sorted(_FLOAT_DT | _INT_DT))
        raise _matrix_error(node, f"dt must be one single-channel type letter of {known!r}, got {dt!r}")
    if not isinstance(data, list) or not all(
        isinstance(v, int | float) and not isinstance(v, bool) for v in data
    ):
        raise _matrix_error(node, "data must be a list of numbers")
    if len(data) != rows * cols:
        raise _matrix_error(node, f"data has {len(data)} numbers, expected rows x cols = {rows * cols}")
    if dt in _INT_DT and not all(isinstance(v, int) for v in data):
        raise _matrix_error(node, f"dt {dt!r} is an integer type but data holds non-integers")
    values = [float(v) for v in data] if dt in _FLOAT_DT else list(data)
    if rows == 1 or cols == 1:
        return values
    return [values[r * cols : (r + 1) * cols] for r in range(rows)]


OpenCvSafeLoader.add_constructor(OPENCV_MATRIX_TAG, _construct_opencv_matrix)


def load_opencv_yaml(text: str) -> Any:
    """Parse YAML text that may be in OpenCV's dialect; raises `yaml.YAMLError` like `yaml.safe_load`."""
    return yaml.load(strip_opencv_directive(text), Loader=OpenCvSafeLoader)


def yaml_error_line(path: object, err: yaml.YAMLError) -> str:
    """One line for a YAML syntax error in `path`: "PATH: line L, column C: malformed YAML: PROBLEM".

    PyYAML's own message spans several lines (the context, a caret, the problem).
    """
    mark = getattr(err, "problem_mark", None)
    where = f" line {mark.line + 1}, column {mark.column + 1}:" if mark is not None else ""
    problem = getattr(err, "problem", None) or " ".join(str(err).split())
    return f"{path}:{where} malformed YAML: {problem}"
