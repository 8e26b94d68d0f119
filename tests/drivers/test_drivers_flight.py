"""A full flight over real UDP against the simulator: connect, arm, takeoff, goto, mission,
GPS loss with GPS_INPUT injection, geofence breach -> RTL, land, disarm."""

from __future__ import annotations

import time

import numpy as np
import pytest

from skyfix.drivers.mission import MissionItem
from skyfix.drivers.safety import Geofence, SafetyGate
from skyfix.errors import SafetyViolation
from skyfix.geo import destination, inverse
from skyfix.types import GeoFix


def _offset(lat, lon, bearing_deg, dist_m):
    la, lo = destination(lat, lon, bearing_deg, dist_m)
    return float(la), float(lo)


def _dist(lat1, lon1, lat2, lon2) -> float:
    return float(inverse(lat1, lon1, lat2, lon2)[1])


def test_full_flight(sim, vehicle):
    v = vehicle
    st = v.state
    assert st.autopilot == "ardupilot" and st.mode == "STABILIZE" and not st.armed
    home = st.home
    # --- arm and take off in GUIDED
    v.set_mode("GUIDED")
    v.arm()
    v.takeoff(10.0)
    assert abs(sim.truth(0)["alt_rel_m"] - 10.0) < 1.0  # within the 0.5 m wait band + overshoot
    # --- goto 40 m north-east: arrives within the 1.5 m tolerance; truth agrees to GPS accuracy
    lat, lon = _offset(home.lat_deg, home.lon_deg, 45.0, 40.0)
    v.goto(lat, lon, 15.0, wait=True)
    t = sim.truth(0)
    assert _dist(t["lat_deg"], t["lon_deg"], lat, lon) < 1.5 + 2.0  # tolerance + GPS bias (< 2 m)
    assert abs(t["alt_rel_m"] - 15.0) < 1.5
    # --- mission: upload, download identical, fly it with camera triggers and progress events
    pts = [_offset(home.lat_deg, home.lon_deg, b, 25.0) for b in (0.0, 90.0, 180.0)]
    items = [MissionItem.camera_trigger_distance(10.0)] + [MissionItem.waypoint(a, b, 12.0) for a, b in pts]
    progress = []
    stats = v.upload_mission(items, progress=lambda done, total: progress.append((done, total)))
    assert stats.items == 4 and progress[-1] == (5, 5)  # ArduPilot: home item 0 + 4
    back = v.download_mission()
    assert len(back) == 4 and back[1].command == items[1].command
    assert all(abs(a.lat_deg - b.lat_deg) < 1e-7 and abs(a.alt_m - b.alt_m) < 1e-3
               for a, b in zip(back, items, strict=True))
    v.start_mission()
    v.wait_until(lambda s: s.mission_seq >= 4 and any(e.kind == "mission_item_reached" and e.data["seq"] == 4
                                                      for e in list(v.events)), 60.0, what="mission end")
    reached = [e.data["seq"] for e in v.events if e.kind == "mission_item_reached"]
    assert reached[-4:] == [1, 2, 3, 4]
    # legs 25 m + 35 m + 35 m flown with a 10 m trigger distance: at least 8 pictures
    assert sum(e.kind == "camera_trigger" for e in v.events) >= 8
    t = sim.truth(0)
    assert _dist(t["lat_deg"], t["lon_deg"], *pts[-1]) < 2.0 + 2.0  # WPNAV_RADIUS + GPS bias
    # --- GPS loss: with GPS2_TYPE=14 and GPS_INPUT the vehicle holds; 0.5 m noise injected
    v.set_param("GPS2_TYPE", 14)
    v.set_mode("GUIDED")
    hold = sim.truth(0)
    rng = np.random.default_rng(0)

    def external_fix():
        tr = sim.truth(0)
        e, n = rng.normal(0.0, 0.5, 2)
        la, lo, al = sim.world.to_geodetic(tr["east_m"] + e, tr["north_m"] + n, tr["up_m"])
        return GeoFix(float(la), float(lo), float(al), np.diag([0.25, 0.25, 0.5]), time.time(), "test")

    injector = v.start_gps_injection(external_fix, rate_hz=5.0 * sim.config.speed)  # 5 Hz sim time
    v.set_param("SIM_GPS1_ENABLE", 0)  # cut the real receiver, as in SITL
    t_end = sim.time_s + 15.0
    worst = 0.0
    while sim.time_s < t_end:
        tr = sim.truth(0)
        worst = max(worst, np.hypot(tr["east_m"] - hold["east_m"], tr["north_m"] - hold["north_m"]))
        time.sleep(0.02)
    assert v.state.gps.fix_type <= 1  # GPS1 reports no fix
    assert v.state.mode == "GUIDED"  # no EKF failsafe
    # the hold point was taken on the real GPS (bias <= ~1.5 m); injected noise 0.5 m 1-sigma
    assert worst < 3.0, f"drifted {worst:.1f} m while injecting"
    assert injector.sent >= 0.8 * 15.0 * 5.0
    injector.stop()
    v.set_param("SIM_GPS1_ENABLE", 1)
    # --- geofence: out-of-fence goto refused; velocity breach -> RTL within one telemetry step
    v.set_safety(SafetyGate(Geofence.circle(home.lat_deg, home.lon_deg, 60.0, max_alt_rel_m=40.0),
                            max_speed_mps=12.0, action="rtl"))
    far = _offset(home.lat_deg, home.lon_deg, 90.0, 80.0)
    with pytest.raises(SafetyViolation, match="outside the geofence"):
        v.goto(*far, 15.0)
    v.velocity(0.0, 6.0, 0.0)
    v.wait_until(lambda s: s.mode == "RTL", 30.0, what="RTL after breach")
    latency_s, reason = v.safety_log[-1]
    assert "outside the geofence" in reason and latency_s < 0.05
    # --- RTL lands at home and disarms
    v.wait_until(lambda s: not s.armed, 90.0, what="landed and disarmed")
    t = sim.truth(0)
    assert t["alt_rel_m"] < 0.1 and _dist(t["lat_deg"], t["lon_deg"], home.lat_deg, home.lon_deg) < 3.0
    v.disarm()  # already disarmed: accepted, no error
