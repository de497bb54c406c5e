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


class OutputError(DatasetError, WriteError):
    """The operating system refused a write (disk full, read-only or missing folder, permissions).

    The message names the file or folder; the CLI exits 3 for it (a `WriteError`), as for an
    OSError that reaches the top unwrapped.
    """


class PngError(SensorboxError):
    """An array PNG cannot hold as given (shape, dtype) or a bad encoder setting."""


class OdometryError(SensorboxError):
    """The rig's trajectory cannot be estimated (too few LiDAR points, no overlap)."""
