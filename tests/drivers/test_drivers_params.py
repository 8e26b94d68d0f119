"""Typed parameters: integers come back as int on both autopilots' encodings (ArduPilot's
C cast, PX4's byte-wise copy), and the parameter names of both ArduPilot generations."""

from __future__ import annotations

import pytest

from skyfix.datasets.sim import Simulator, SimulatorConfig
from skyfix.drivers.vehicle import Vehicle
from skyfix.errors import ConfigurationError, InputError


@pytest.mark.parametrize("flavour, name, default, new", [("ardupilot", "EK3_SRC1_POSXY", 3, 6),
                                                         ("px4", "EKF2_GPS_CTRL", 7, 5)])
def test_integer_parameters_round_trip(flavour, name, default, new):
    with Simulator(SimulatorConfig(vehicles=1, flavour=flavour, speed=5.0)) as sim:
        with Vehicle.connect(sim.url(0), timeout_s=5.0) as v:
            got = v.get_param(name)
            assert got == default and isinstance(got, int)
            assert v.set_param(name, new) == new
            # the autopilot stored the integer itself, not a float made of its bytes
            assert sim.vehicle(0).params[name] == new
            with pytest.raises(InputError, match="integer parameter"):
                v.set_param(name, 2.5)
            speed = "WPNAV_SPEED" if flavour == "ardupilot" else "MPC_XY_CRUISE"
            assert isinstance(v.get_param(speed), float)
            assert v.set_param(speed, 4.25) == pytest.approx(4.25)


def test_legacy_ardupilot_parameter_names_still_work():
    with Simulator(SimulatorConfig(vehicles=1, speed=5.0, legacy_params=True)) as sim:
        with Vehicle.connect(sim.url(0), timeout_s=5.0) as v:
            v.wait_until(lambda s: s.gps is not None and s.gps.fix_type >= 3, 5.0, what="fix")
            # the injection check names the generation's own parameter
            with pytest.raises(ConfigurationError, match=r"GPS_TYPE=1, GPS2_TYPE=0; set GPS_TYPE=14"):
                v.check_injection("gps")
            v.set_param("SIM_GPS_DISABLE", 1)  # the old way of switching the receiver off
            assert v.wait_until(lambda s: s.gps.fix_type <= 1, 5.0, what="receiver off").gps.fix_type <= 1
            v.set_param("GPS_TYPE", 14)
            v.check_injection("gps")
