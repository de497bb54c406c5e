"""Errors of the offline ingest layer, in the one `SensorboxError` tree.

`BagError` covers everything about a recording as a file: a path that does not
exist, a bag that is truncated, unindexed or still being written, a topic that
is not in it, a message type whose embedded definition SensorBox cannot trust.
Its message names the file or topic at fault and what was expected (for a
missing topic, the topics the bag does have). Malformed message *bytes* raise
`ingest.bags.livox_msg.MessageDecodeError` instead.
"""

from __future__ import annotations

from calibration.errors import SensorboxError


class BagError(SensorboxError):
    """A bag cannot be opened or read, or lacks what was asked of it."""
