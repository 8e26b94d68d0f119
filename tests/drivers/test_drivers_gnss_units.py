"""GNSS units: HDOP/VDOP are not metres, h_acc/v_acc are millimetres, alt is AMSL.

Checked three ways: a hand-built GPS_RAW_INT with known field values, skyfix's simulator
(which encodes the fields as autopilots do, with the real EGM96 geoid separation at its
home), and a telemetry log recorded from the real ArduPilot Copter SITL firmware.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import pytest

from skyfix.datasets.sim import Simulator, SimulatorConfig
from skyfix.drivers import units
from skyfix.drivers.mav import mavlink, mavutil
from skyfix.drivers.vehicle import Vehicle
from skyfix.errors import NotAvailableError
from skyfix.geo import Height, VerticalDatum
from skyfix.geoid import geoid_undulation_m

SITL_TLOG = Path(__file__).parent / "data" / "sitl_copter_takeoff.tlog"


def _raw(**kw):
    fields = dict(time_usec=5_000_000, fix_type=3, lat=465200000, lon=66300000, alt=372_000, eph=121,
                  epv=200, vel=0, cog=0, satellites_visible=10, alt_ellipsoid=0, h_acc=300, v_acc=450,
                  vel_acc=0, hdg_acc=0, yaw=0)
    fields.update(kw)
    return mavlink.MAVLink_gps_raw_int_message(**fields)


def test_gps_raw_int_fields_in_their_units():
    g = units.gnss_fix(_raw(), now_s=100.0)
    assert (g.h_acc_m, g.v_acc_m) == (0.3, 0.45)     # millimetres -> metres
    assert (g.hdop, g.vdop) == (1.21, 2.0)           # x100, unitless
    assert g.alt_amsl_m == 372.0
    n_m = float(geoid_undulation_m(46.52, 6.63))     # ~49.8 m at Lausanne
    assert g.alt_ellipsoid_source == "egm96"
    assert g.alt_ellipsoid_m == pytest.approx(372.0 + n_m, abs=0.02)  # cache grid: 0.001 deg
    assert g.autopilot_time_s == 5.0
    # the autopilot's own ellipsoid height wins; unknown values become NaN, not numbers
    g2 = units.gnss_fix(_raw(alt_ellipsoid=421_833, eph=65535, epv=65535, h_acc=0, v_acc=0), 0.0)
    assert g2.alt_ellipsoid_m == 421.833 and g2.alt_ellipsoid_source == "autopilot"
    assert all(math.isnan(x) for x in (g2.hdop, g2.vdop, g2.h_acc_m, g2.v_acc_m))
    nofix = units.gnss_fix(_raw(fix_type=1, lat=0, lon=0, alt=0), 0.0)
    assert nofix.alt_ellipsoid_source == "none" and math.isnan(nofix.alt_ellipsoid_m)


def test_records_give_heights_that_name_their_datum():
    """GPS_RAW_INT's alt is EGM96 AMSL and alt_ellipsoid WGS84: a caller asks for a datum and
    gets a Height that says which, never a float whose datum lives in its name."""
    n_m = float(geoid_undulation_m(46.52, 6.63))  # ~49.8 m: a misread datum is off by that much
    g = units.gnss_fix(_raw(), now_s=0.0)
    assert g.height("egm96") == Height(372.0, VerticalDatum.EGM96)
    assert g.height().datum is VerticalDatum.WGS84 and g.height().value_m == pytest.approx(372.0 + n_m, abs=0.01)
    # The autopilot's own ellipsoidal height is kept as sent; its AMSL stays the AMSL it sent.
    g2 = units.gnss_fix(_raw(alt_ellipsoid=421_833), 0.0)
    assert g2.height(VerticalDatum.WGS84) == Height(421.833, "wgs84") and g2.height("egm96").value_m == 372.0
    pos, _ = units.position_velocity(mavlink.MAVLink_global_position_int_message(
        1000, 465200000, 66300000, 380_000, 8_000, 0, 0, 0, 0), 0.0)
    assert pos.height().value_m == pytest.approx(380.0 + n_m, abs=0.01)
    assert pos.height().to("egm96", pos.lat_deg, pos.lon_deg).value_m == pytest.approx(380.0, abs=1e-9)
    with pytest.raises(NotAvailableError, match="no fix"):
        units.gnss_fix(_raw(fix_type=1, lat=0, lon=0, alt=0), 0.0).height()


def test_simulator_reports_like_an_autopilot_and_skyfix_reads_it():
    # the simulator's home (ArduPilot's CMAC field) has a geoid separation of +19.4 m and a
    # receiver with 0.8 m horizontal sigma at HDOP 1.2: reading HDOP as metres, or AMSL as
    # ellipsoidal height, fails the tolerances below
    with Simulator(SimulatorConfig(vehicles=1, speed=5.0, seed=4)) as sim:
        assert sim.geoid_m == pytest.approx(19.44, abs=0.05)
        with Vehicle.connect(sim.url(0), timeout_s=5.0) as v:
            st = v.wait_until(lambda s: s.gps is not None and s.gps.fix_type >= 3 and s.position
                              is not None and s.home is not None, 5.0, what="GPS fix")
            truth = sim.truth(0)
    g = st.gps
    assert g.h_acc_m == pytest.approx(0.8) and g.v_acc_m == pytest.approx(1.2)
    assert g.hdop == pytest.approx(1.2) and g.vdop == pytest.approx(1.9)
    assert g.alt_ellipsoid_source == "autopilot"
    # receiver error: 0.4 m Gauss-Markov bias + 0.15 m noise per axis -> within 2 m at 4 sigma
    assert g.alt_ellipsoid_m == pytest.approx(truth["alt_m"], abs=2.0)
    assert g.alt_amsl_m == pytest.approx(truth["alt_m"] - sim.geoid_m, abs=2.0)
    # GLOBAL_POSITION_INT and HOME_POSITION carry AMSL; skyfix adds the EGM96 geoid
    assert st.position.alt_ellipsoid_m == pytest.approx(truth["alt_m"], abs=2.0)
    assert st.home.alt_ellipsoid_m - st.home.alt_amsl_m == pytest.approx(sim.geoid_m, abs=0.05)


def test_sitl_telemetry_log_parses_with_real_units():
    """Replays a log recorded from ArduPilot Copter 4.7.0-dev SITL (arm, climb to 5 m)
    through the Vehicle's telemetry handlers."""
    # no link: the recorded messages are fed to the telemetry handlers directly
    vehicle = Vehicle(link=None, system_id=1, component_id=1, autopilot=mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA)
    log = mavutil.mavlink_connection(str(SITL_TLOG), dialect="ardupilotmega")
    n_raw = 0
    while (msg := log.recv_msg()) is not None:
        if msg.get_type() == "BAD_DATA" or msg.get_srcSystem() != 1 or msg.get_srcComponent() != 1:
            continue
        n_raw += msg.get_type() == "GPS_RAW_INT"
        vehicle._on_message(msg, 0.0)
    st = vehicle.state
    assert n_raw > 300 and st.autopilot == "ardupilot" and st.armed and st.mode == "GUIDED"
    g = st.gps
    # SITL's simulated u-blox: 10 satellites, RTK fixed, HDOP 1.21, 0.3 m accuracy
    assert g.fix_type == 6 and g.satellites == 10
    assert (g.hdop, g.vdop, g.h_acc_m, g.v_acc_m) == (1.21, 2.0, 0.3, 0.3)
    assert g.alt_ellipsoid_source == "autopilot"
    assert st.position.alt_rel_m == pytest.approx(5.0, abs=0.3)
    assert st.home.lat_deg == pytest.approx(46.52, abs=1e-5) and st.home.alt_amsl_m == pytest.approx(372.1, abs=0.5)


def test_gps_input_comes_back_in_the_same_units():
    """GPS_INPUT (AMSL, accuracies in metres, DOPs) -> the autopilot's GPS_RAW_INT -> GnssFix."""
    with Simulator(SimulatorConfig(vehicles=1, speed=5.0, seed=4, params={"GPS1_TYPE": 14})) as sim:
        with Vehicle.connect(sim.url(0), timeout_s=5.0) as v:
            t = sim.truth(0)
            deadline = time.monotonic() + 5.0
            while time.monotonic() < deadline:  # a MAV GPS reports what was injected in the last second
                v.inject_gps(t["lat_deg"], t["lon_deg"], t["alt_amsl_m"] + 2.0, h_acc_m=0.6, v_acc_m=0.9)
                g = v.state.gps
                if g is not None and g.fix_type >= 3 and g.time_s > time.time() - 0.1:
                    break
                time.sleep(0.05)
    assert g is not None and g.fix_type >= 3
    assert (g.h_acc_m, g.v_acc_m) == pytest.approx((0.6, 0.9), abs=1e-3)
    assert (g.hdop, g.vdop) == pytest.approx((0.4, 0.6), abs=0.011)  # skyfix sends accuracy / 1.5
    assert g.alt_amsl_m == pytest.approx(t["alt_amsl_m"] + 2.0, abs=0.01)
    assert g.alt_ellipsoid_m == pytest.approx(t["alt_m"] + 2.0, abs=0.01)
