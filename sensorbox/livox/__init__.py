"""Livox Mid-360 without the vendor SDK: the wire protocol (`protocol`) and a UDP driver (`driver`)."""

from sensorbox.errors import ProtocolError
from sensorbox.livox.config import DriverConfig, DriverStats, LidarEndpoint, LidarStats
from sensorbox.livox.driver import Mid360Driver, Publish
from sensorbox.livox.protocol import DeviceInfo, Ports

__all__ = [
    "DeviceInfo",
    "DriverConfig",
    "DriverStats",
    "LidarEndpoint",
    "LidarStats",
    "Mid360Driver",
    "Ports",
    "ProtocolError",
    "Publish",
]
