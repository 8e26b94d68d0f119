"""skyfix.datasets.sim: the multi-vehicle MAVLink simulator (ArduPilot Copter or PX4 flavour).

Each vehicle is a point-mass multirotor with attitude, speed limits, battery, wind and
GPS faults, speaking real MAVLink over UDP on 127.0.0.1. Names load on first use, so
that ``skyfix --help`` (which registers ``skyfix sim``) does not load pymavlink.
"""

from skyfix.lazy import lazy_exports

_EXPORTS = {
    "GpsFault": "skyfix.datasets.sim.gps",
    "GpsReceiver": "skyfix.datasets.sim.gps",
    "DEFAULT_HOME": "skyfix.datasets.sim.simulator",
    "Simulator": "skyfix.datasets.sim.simulator",
    "SimulatorConfig": "skyfix.datasets.sim.simulator",
    "SimVehicle": "skyfix.datasets.sim.vehicle",
    "SimVehicleConfig": "skyfix.datasets.sim.vehicle",
    "WindField": "skyfix.datasets.sim.wind",
}

__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)
