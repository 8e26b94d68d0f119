"""skyfix.drivers: MAVLink connection, telemetry, commands, missions, position injection
and the safety gate, on pymavlink, for ArduPilot and PX4."""

from skyfix.drivers import mav as _mav  # noqa: F401  (pins MAVLink 2 before any pymavlink import)
