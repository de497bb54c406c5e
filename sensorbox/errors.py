"""Errors of the live box (drivers, recorder); the tree's root lives in `calibration`."""

from calibration.errors import CalibrationError, SensorboxError


class DriverError(SensorboxError):
    """A live device (LiDAR, camera) misbehaved or could not be reached."""


__all__ = ["CalibrationError", "DriverError", "SensorboxError"]
