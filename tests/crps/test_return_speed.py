"""The lost drone returns no faster than its helpers fly (crps/return_speed.py), over real MAVLink to the simulator.

Stock ArduPilot Copter returns at WPNAV_SPEED, 1000 cm/s (read back from the SITL firmware in ../shared/sitl);
helpers plan at 5 m/s. ReturnSpeed lowers RTL_SPEED for the recovery and writes the old value back after.
"""

from __future__ import annotations

import math
import time

import pytest

from skyfix.crps.return_speed import ReturnSpeed
from skyfix.datasets.sim.simulator import Simulator, SimulatorConfig
from skyfix.drivers.vehicle import Vehicle
from skyfix.errors import InputError
from skyfix.geo import destination

SPEED = 4.0  # simulated seconds per wall second


def _now(kind: str, what: str, fn) -> None:
    fn()  # the help loop's worker runs these; here, at once


def _fly_out_and_return(sim, v: Vehicle) -> float:
    """Take off, fly 120 m north, RTL: the largest horizontal ground speed (truth, m/s) on the way back."""
    v.set_mode("GUIDED")
    v.arm()
    v.takeoff(10.0)
    home = v.state.home
    lat, lon = destination(home.lat_deg, home.lon_deg, 0.0, 120.0)
    v.goto(float(lat), float(lon), 15.0, wait=True)
    v.set_mode("RTL")
    fastest = 0.0
    while True:
        time.sleep(0.05)
        t = sim.truth(0)
        fastest = max(fastest, math.hypot(t["vel_east_mps"], t["vel_north_mps"]))
        if t["alt_rel_m"] < 0.3 or math.hypot(t["east_m"], t["north_m"]) < 2.0:
            break
    return fastest


@pytest.mark.parametrize("helpers_mps, expected_mps", [(5.0, 5.0), (None, 10.0)])
def test_a_stock_ardupilot_return_is_slowed_to_the_helpers_speed_and_restored(helpers_mps, expected_mps):
    with Simulator(SimulatorConfig(vehicles=1, speed=SPEED, seed=5)) as sim:
        v = Vehicle.connect(sim.url(0), timeout_s=5.0)
        try:
            v.wait_until(lambda st: st.position is not None and st.home is not None, 5.0, what="first telemetry")
            v.set_param("WPNAV_SPEED", 1000)  # ArduPilot Copter's own default (the simulator's is 500)
            speed = ReturnSpeed(helpers_mps, _now)
            speed.limit(v, "ardupilot")
            assert v.get_param("RTL_SPEED") == (0 if helpers_mps is None else 500)
            note = speed.take_note()
            assert (note is None) if helpers_mps is None else ("helpers' 5 m/s" in note and "was 1000" in note)
            fastest = _fly_out_and_return(sim, v)
            assert fastest == pytest.approx(expected_mps, abs=0.6)  # the simulator's speed control
            speed.restore(v)
            assert v.get_param("RTL_SPEED") == 0  # as found: "0, the cruise speed"
            assert (speed.take_note() is None) == (helpers_mps is None)
        finally:
            v.close()


def test_a_return_already_slow_enough_is_left_alone():
    with Simulator(SimulatorConfig(vehicles=1, speed=SPEED, seed=6)) as sim:
        v = Vehicle.connect(sim.url(0), timeout_s=5.0)
        try:
            v.wait_until(lambda st: st.position is not None, 5.0, what="first telemetry")
            v.set_param("RTL_SPEED", 300)
            speed = ReturnSpeed(5.0, _now)
            speed.limit(v, "ardupilot")
            assert v.get_param("RTL_SPEED") == 300 and speed.take_note() is None
            speed.restore(v)
            assert v.get_param("RTL_SPEED") == 300
        finally:
            v.close()


def test_px4_is_left_alone_and_says_so():
    speed = ReturnSpeed(5.0, _now)
    speed.limit(object(), "px4")
    assert "px4 has no RTL speed" in speed.take_note()


@pytest.mark.parametrize("bad", [0.0, -1.0, math.nan, math.inf])
def test_a_return_speed_must_be_a_positive_number(bad):
    with pytest.raises(InputError, match="return speed"):
        ReturnSpeed(bad, _now)


def test_an_autopilot_without_the_parameter_leaves_the_speed_and_says_why():
    """A PX4 reached as if it were ArduPilot: RTL_SPEED is not there; the failure is the timeline's, not a crash."""
    from skyfix.errors import SkyfixError

    with Simulator(SimulatorConfig(vehicles=1, speed=SPEED, seed=7, flavour="px4")) as sim:
        v = Vehicle.connect(sim.url(0), timeout_s=5.0)
        try:
            speed = ReturnSpeed(5.0, _now)
            with pytest.raises(SkyfixError):  # the help loop's worker logs it and goes on
                speed.limit(v, "ardupilot")
            assert speed.take_note().startswith("return speed not limited: ")
            speed.restore(v)  # nothing was changed: nothing written
            assert speed.take_note() is None
        finally:
            v.close()
