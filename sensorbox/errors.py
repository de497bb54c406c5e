"""Errors of the box (drivers, protocol, graphs, launch files, recorder, viewer); the root: `calibration`."""

from calibration.errors import CalibrationError, SensorboxError


class DriverError(SensorboxError):
    """A live device (LiDAR, camera) misbehaved or could not be reached."""


class ProtocolError(DriverError):
    """A datagram does not follow the Mid-360 protocol (bad CRC, length, field value)."""


class GraphError(SensorboxError):
    """A node graph could not be built, started or run (names the node and what failed)."""


class LaunchError(SensorboxError):
    """A launch file or argument is malformed; the message names the file, line and key."""


class RecorderError(SensorboxError):
    """The recorder's configuration or output folder is unusable."""


class ViewerError(SensorboxError):
    """The Rerun viewer `sensorbox view` streams to cannot be started or does not take the recording."""


__all__ = [
    "CalibrationError",
    "DriverError",
    "GraphError",
    "LaunchError",
    "ProtocolError",
    "RecorderError",
    "SensorboxError",
    "ViewerError",
]
