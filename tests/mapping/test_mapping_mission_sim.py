"""Survey missions round-trip through the simulator's MAVLink mission protocol (real UDP, loopback)."""

from __future__ import annotations

import math

import pytest

from skyfix.camera import Camera
from skyfix.datasets.sim import Simulator, SimulatorConfig
from skyfix.drivers.vehicle import Vehicle
from skyfix.geo import destination
from skyfix.mapping.mission import mission_items
from skyfix.mapping.split import split_survey
from skyfix.mapping.survey import plan_polygon, plan_three_corners


@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
def test_survey_missions_round_trip(flavour):
    with Simulator(SimulatorConfig(vehicles=1, flavour=flavour, speed=5.0, seed=1)) as sim:
        v = Vehicle.connect(sim.url(0), timeout_s=5.0)
        try:
            home = v.wait_until(lambda s: s.home is not None, 5.0, what="home").home
            lat0, lon0 = home.lat_deg, home.lon_deg

            def at(b, d):
                la, lo = destination(lat0, lon0, b, d)
                return float(la), float(lo)

            photo = plan_polygon([(lat0, lon0), at(90, 120), at(45, 130), at(0, 90)], Camera.from_fov(1200, 900, 60),
                                 40.0, 0.7, 0.6)
            grid = plan_three_corners((lat0, lon0), at(90, 28), at(0, 35), 7.0, 10.0, hold_s=2.0)
            part = split_survey(grid, {"a": (lat0, lon0), "b": at(0, 40)})[1]
            for plan in (photo, part):
                items = mission_items(plan, speed_mps=5.0)
                stats = v.upload_mission(items)  # the same type: no conversion
                assert stats.items == len(items)
                back = v.download_mission()
                assert len(back) == len(items)
                for a, b in zip(back, items, strict=True):
                    assert a.command == b.command and a.frame == b.frame
                    # degE7 on the wire: 1e-7 deg (1 cm) is the resolution; alt_m is a float32 there
                    assert round(a.lat_deg * 1e7) == round(b.lat_deg * 1e7)
                    assert round(a.lon_deg * 1e7) == round(b.lon_deg * 1e7)
                    assert a.alt_m == pytest.approx(b.alt_m, abs=1e-4)
                    for name in ("param1", "param2", "param3"):
                        assert getattr(a, name) == pytest.approx(getattr(b, name))
                    assert (math.isnan(a.param4) and math.isnan(b.param4)) or a.param4 == pytest.approx(b.param4)
                v.clear_mission()
        finally:
            v.close()
