"""skyfix.drivers: MAVLink connection, telemetry, commands, missions, position injection
and the safety gate, on pymavlink, for ArduPilot and PX4.

    from skyfix.drivers import Vehicle, MissionItem, SafetyGate, Geofence
    v = Vehicle.connect("udpin:127.0.0.1:14550")

Names are imported lazily so that ``skyfix --help`` does not load pymavlink.
"""

from __future__ import annotations

import os

from skyfix.lazy import lazy_exports

os.environ.setdefault("MAVLINK20", "1")  # before any pymavlink import: ODOMETRY needs MAVLink 2

_EXPORTS = {
    "Vehicle": "skyfix.drivers.vehicle",
    "MavlinkLink": "skyfix.drivers.link",
    "MissionItem": "skyfix.drivers.mission",
    "TransferStats": "skyfix.drivers.mission",
    "Geofence": "skyfix.drivers.safety",
    "SafetyGate": "skyfix.drivers.safety",
    "PositionInjector": "skyfix.drivers.injection",
    "VehicleState": "skyfix.drivers.state",
    "VehicleEvent": "skyfix.drivers.state",
    "Position": "skyfix.drivers.state",
    "Velocity": "skyfix.drivers.state",
    "Attitude": "skyfix.drivers.state",
    "GnssFix": "skyfix.drivers.state",
    "Battery": "skyfix.drivers.state",
    "Home": "skyfix.drivers.state",
}

__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)
