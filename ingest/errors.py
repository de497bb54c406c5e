"""Errors of the offline ingest layer, in the one `SensorboxError` tree.

`BagError` covers everything about a recording as a file: a path that does not
exist, a bag that is truncated, unindexed or still being written, a topic that
is not in it, a message type whose embedded definition SensorBox cannot trust.
Its message names the file or topic at fault and what was expected (for a
missing topic, the topics the bag does have). Malformed message *bytes* raise
`MessageDecodeError` instead. Every other ingest error is here too, one per
room: scans and benchmark layouts, evaluation, the dataset on disk, PNGs.
"""

from __future__ import annotations

import re
from collections.abc import Callable

from calibration.errors import SensorboxError, WriteError


class BagError(SensorboxError):
    """A bag cannot be opened or read, or lacks what was asked of it."""


class MessageDecodeError(SensorboxError):
    """A message's bytes do not match the layout its type promises."""


class BenchmarkError(SensorboxError):
    """A benchmark run cannot be set up or written."""


class ScanError(SensorboxError):
    """A scan file or site manifest cannot be read or is inconsistent."""


class EvalError(SensorboxError):
    """Ground truth or predictions cannot be found, read or matched."""


class DatasetError(SensorboxError):
    """The output folder cannot be written (disk full, permissions, a foreign dataset)."""


class SettingError(DatasetError):
    """A setting no run can start with, named as the library knows it.

    `setting` is the `IngestConfig` field as a dotted path
    (`sample.dense.window_ns`), `value` its value as given, `expected` what
    a run needs; `expected` may name other settings as `{field}` (e.g.
    `{lidar_window_ns}`), which `str()` fills with their field names. The
    CLI names its options instead (`sensorbox.cli.ingest`'s `OPTIONS`):
    the library does not know which flags set it.
    """

    def __init__(self, setting: str, value: object, expected: str) -> None:
        self.setting, self.value, self.expected = setting, value, expected
        super().__init__(self.line(lambda name: name, shown(value)))

    def line(self, name_of: Callable[[str], str], value: object) -> str:
        """The one line, each setting named by `name_of(field)` and this one's value shown as `value`."""
        expected = re.sub(r"\{([\w.]+)\}", lambda m: name_of(m.group(1)), self.expected)
        return f"{name_of(self.setting)} {value}: expected {expected}"


def shown(value: object) -> str:
    """A setting's value as an error line shows it: text quoted, numbers short (`:g`)."""
    if isinstance(value, str):
        return repr(value)
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


class OutputError(DatasetError, WriteError):
    """The operating system refused a write (disk full, read-only or missing folder, permissions).

    The message names the file or folder; the CLI exits 3 for it (a `WriteError`), as for an
    OSError that reaches the top unwrapped.
    """


class PngError(SensorboxError):
    """An array PNG cannot hold as given (shape, dtype) or a bad encoder setting."""


class OdometryError(SensorboxError):
    """The rig's trajectory cannot be estimated (too few LiDAR points, no overlap)."""
