"""ArduPilot Copter SITL loses its GNSS receiver in flight and flies home on positions a
companion injects as a second GPS (the mechanics the collaborative recovery relies on).

On the loss the companion switches the autopilot to its injected GPS (GPS2_TYPE 14 set in
flight, GPS_PRIMARY 1, EKF source set 2) and injects an external positioning source: here a
second GNSS-class sensor model (skyfix's simulated receiver: Gauss-Markov bias 0.4 m / 60 s
+ 0.15 m noise) on the firmware's true state. The camera-based source is
tests/crps/test_recovery_sitl.py. Speed-up 5, ~30 s; skipped with the reason where the
firmware is absent.
"""

from __future__ import annotations

import numpy as np
import pytest

from skyfix.datasets import sitl
from skyfix.datasets.sim.gps import GpsReceiver
from skyfix.drivers.injection import ARDUPILOT_INJECTED_GPS2_PARAMS
from skyfix.drivers.vehicle import Vehicle
from skyfix.geo import LocalFrame, destination, inverse
from skyfix.types import GeoFix

pytestmark = [pytest.mark.sitl, pytest.mark.slow,
              pytest.mark.skipif(bool(sitl.missing_reason()), reason=sitl.missing_reason() or "-")]

SPEEDUP = 5.0


def test_receiver_lost_in_flight_rtl_on_injected_gps2_lands_home():
    with sitl.SitlFleet(1, speedup=SPEEDUP, params=ARDUPILOT_INJECTED_GPS2_PARAMS) as fleet:
        lat0, lon0, alt0_amsl, _ = fleet.homes[0]
        v = Vehicle.connect(fleet[0].url, timeout_s=30.0)
        truth = sitl.SitlTruth.connect(fleet[0].url_secondary, alt0_amsl, speedup=SPEEDUP)
        try:
            _fly(v, truth, LocalFrame(lat0, lon0, 0.0))
        finally:
            truth.close()
            v.close()


def _fly(v: Vehicle, truth: sitl.SitlTruth, world: LocalFrame) -> None:
    sensor = GpsReceiver(seed=3)

    def source() -> GeoFix:
        t = truth.truth(world)
        sensor.step(1.0 / 5.0)
        r = sensor.read(0.0, np.array([t["east_m"], t["north_m"], t["up_m"]]), np.zeros(3))
        lat, lon, alt = world.to_geodetic(*r.pos_enu_m)
        return GeoFix(float(lat), float(lon), float(alt), np.diag([0.8 ** 2, 0.8 ** 2, 1.2 ** 2]))

    home = v.wait_until(lambda s: s.home is not None and s.gps is not None and s.gps.fix_type >= 3, 60.0,
                        what="GPS fix and home").home
    assert v.get_param("GPS2_TYPE") == 0  # no second GPS in normal flight: arming needs no companion
    v.set_mode("GUIDED")
    sitl.arm_when_ready(v, 60.0)
    v.takeoff(12.0, timeout_s=40.0)
    lat, lon = destination(home.lat_deg, home.lon_deg, 60.0, 40.0)
    v.goto(float(lat), float(lon), 12.0, wait=True, tolerance_m=1.5, timeout_s=40.0)
    t_loss = v.state.position.time_s
    v.set_param("SIM_GPS1_ENABLE", 0)
    v.wait_until(lambda s: s.gps.fix_type <= 1, 5.0, what="receiver loss flagged")
    v.use_injected_gps(True)  # GPS2_TYPE 14 in flight, GPS_PRIMARY 1, EKF source set 2
    assert v.gps_input_id == 1  # GPS_INPUT addressed to GPS2
    v.start_gps_injection(source, rate_hz=5.0 * SPEEDUP)  # 5 Hz of the firmware's time
    v.rtl()
    v.wait_until(lambda s: not s.armed, 120.0, what="RTL landing on the injected GPS")
    t = truth.truth(world)
    landing_m = float(inverse(t["lat_deg"], t["lon_deg"], home.lat_deg, home.lon_deg)[1])
    failsafes = [e.text for e in v.events if e.kind == "statustext" and e.time_s > t_loss
                 and ("Failsafe" in e.text or "Glitch" in e.text)]
    assert not failsafes, failsafes  # the EKF took the injected fixes without complaint
    assert v.state.gps.fix_type <= 1  # GPS_RAW_INT is still the dead receiver: it flew on GPS2
    assert landing_m <= 3.0  # the sensor's 0.4 m bias + the firmware's landing spread
    v.injector.stop()
    v.use_injected_gps(False)
    assert v.get_param("GPS_PRIMARY") == 0 and v.get_param("GPS2_TYPE") == 0
