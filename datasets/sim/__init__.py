"""skyfix.datasets.sim: the multi-vehicle MAVLink simulator (ArduPilot Copter or PX4 flavour).

Each vehicle is a point-mass multirotor with attitude, speed limits, battery, wind and
GPS faults, speaking real MAVLink over UDP on 127.0.0.1.
"""

from skyfix.datasets.sim.gps import GpsFault, GpsReceiver
from skyfix.datasets.sim.simulator import DEFAULT_HOME, Simulator, SimulatorConfig
from skyfix.datasets.sim.vehicle import SimVehicle, SimVehicleConfig
from skyfix.datasets.sim.wind import WindField

__all__ = ["DEFAULT_HOME", "GpsFault", "GpsReceiver", "SimVehicle", "SimVehicleConfig", "Simulator",
           "SimulatorConfig", "WindField"]
