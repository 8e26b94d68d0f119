"""Mission export: the foundation's MissionItem on the wire, commands and camera triggering; GeoJSON/KML/PNG files."""

from __future__ import annotations

import json
import math

import pytest
from pymavlink.dialects.v20 import common as mavlink  # the definition, not skyfix's copy of it

from skyfix.camera import Camera
from skyfix.geo import destination
from skyfix.mapping.export import write_all
from skyfix.mapping.mission import mission_items
from skyfix.mapping.split import split_survey
from skyfix.mapping.survey import plan_polygon, plan_three_corners
from skyfix.mission import MissionItem

LAT0, LON0 = 40.6303, -8.6575


def _at(bearing_deg, dist_m):
    lat, lon = destination(LAT0, LON0, bearing_deg, dist_m)
    return float(lat), float(lon)


def test_station_mission_items_pack_as_mavlink_messages():
    plan = plan_three_corners((LAT0, LON0), _at(90, 28), _at(0, 35), 7.0, 10.0, hold_s=2.0)
    items = mission_items(plan, home_latlon_alt=(LAT0, LON0, 30.0), speed_mps=3.0)
    assert items[0].frame == mavlink.MAV_FRAME_GLOBAL_INT and items[0].alt_m == 30.0
    assert items[1].command == mavlink.MAV_CMD_NAV_TAKEOFF and items[1].alt_m == 10.0
    assert items[2].command == mavlink.MAV_CMD_DO_CHANGE_SPEED and items[2].param2 == 3.0
    nav = [it for it in items if it.command == mavlink.MAV_CMD_NAV_WAYPOINT][1:]
    assert len(nav) == 30 and all(it.param1 == 2.0 and it.alt_m == 10.0 for it in nav)
    assert all(it.frame == mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT and math.isnan(it.param4) for it in nav)
    latlon = plan.waypoints_latlon()
    assert [(it.lat_deg, it.lon_deg) for it in nav] == [(a, b) for a, b in latlon]
    assert items[-1].command == mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH
    mav = mavlink.MAVLink(None, srcSystem=255)
    for seq, it in enumerate(items):  # every item is a valid MISSION_ITEM_INT on the wire, and comes back
        decoded = mav.decode(bytearray(it.to_message(seq, 1, 1).pack(mav)))
        assert decoded.seq == seq and decoded.x == round(it.lat_deg * 1e7) and decoded.command == it.command
        back = MissionItem.from_message(decoded)
        assert (back.command, back.frame, back.param1, back.param2) == (it.command, it.frame, it.param1, it.param2)
        assert back.lat_deg == pytest.approx(it.lat_deg, abs=0.6e-7)  # degE7 resolution


def test_photo_mission_switches_camera_trigger_per_line():
    cam = Camera.from_fov(1200, 900, 60.0)
    plan = plan_polygon([(LAT0, LON0), _at(90, 200), _at(45, 200), _at(0, 150)], cam, 60, 0.7, 0.6)
    items = mission_items(plan, takeoff=False, return_to_launch=False)
    trig = [it for it in items if it.command == mavlink.MAV_CMD_DO_SET_CAM_TRIGG_DIST]
    n_lines = int(plan.trigger_on.sum())
    assert len(trig) == 2 * n_lines
    assert all(t.param1 == pytest.approx(plan.trigger_distance_m) and t.param3 == 1 for t in trig[::2])
    assert all(t.param1 == 0 for t in trig[1::2])


def test_files_for_a_split_plan(tmp_path):
    plan = plan_three_corners((LAT0, LON0), _at(90, 28), _at(0, 35), 7.0, 10.0)
    parts = split_survey(plan, {"A": (LAT0, LON0), "B": _at(0, 40)})
    files = write_all(tmp_path, parts)
    gj = json.loads((tmp_path / "plan.geojson").read_text())
    paths = [f for f in gj["features"] if f["properties"]["role"] == "path"]
    assert {f["properties"]["drone_id"] for f in paths} == {"A", "B"}
    lon, lat = gj["features"][0]["geometry"]["coordinates"][0][0]
    assert (lat, lon) == pytest.approx((LAT0, LON0), abs=1e-9)
    assert "<LineString" in (tmp_path / "plan.kml").read_text()
    assert (tmp_path / "plan.png").read_bytes()[:4] == b"\x89PNG"
    lines = (tmp_path / "plan_A.waypoints").read_text().splitlines()
    assert lines[0] == "QGC WPL 110" and len(files) == 5
    assert not any(math.isnan(float(v)) for row in lines[1:] for v in row.split("\t")[4:11])
