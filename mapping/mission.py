"""Survey plans as MAVLink mission items (plain data; :mod:`skyfix.drivers` uploads them).

:func:`mission_items` lays a plan out as the foundation's :class:`skyfix.mission.MissionItem`
(the one type drivers upload and the simulator stores): optional home (ArduPilot keeps
item 0 for it), take-off, optional speed change, one ``NAV_WAYPOINT`` per waypoint (with
the station hold time) and ``DO_SET_CAM_TRIGG_DIST`` wherever the camera starts or stops
triggering, then ``RETURN_TO_LAUNCH``. Altitudes are relative to home
(``MAV_FRAME_GLOBAL_RELATIVE_ALT_INT``), home's is AMSL (``MAV_FRAME_GLOBAL_INT``).
"""

from __future__ import annotations

from skyfix import validate
from skyfix.errors import InputError
from skyfix.mapping.survey import SurveyPart, SurveyPlan
from skyfix.mission import MissionItem, mavlink

__all__ = ["MissionItem", "mission_items"]

_NAN = float("nan")  # param4 (yaw) NaN: the autopilot keeps its heading behaviour


def mission_items(plan: SurveyPlan | SurveyPart, *, home_latlon_alt=None, takeoff: bool = True,
                  speed_mps: float | None = None, return_to_launch: bool = True) -> list[MissionItem]:
    """Mission items flying ``plan`` (or one drone's part); see the module docstring.

    ``home_latlon_alt``: (lat_deg, lon_deg, alt_m AMSL) written as item 0 (ArduPilot's home
    slot; omit for PX4). ``speed_mps``: ground speed set after take-off.

    Example:
        Take-off, speed, the 30 stations of a 28 m x 35 m grid, return to launch:

        >>> from skyfix.geo import destination
        >>> from skyfix.mapping.survey import plan_three_corners
        >>> a = (40.6303, -8.6575)
        >>> b, c = (tuple(float(x) for x in destination(*a, bearing, d)) for bearing, d in ((90.0, 28.0), (0.0, 35.0)))
        >>> items = mission_items(plan_three_corners(a, b, c, 7.0, 10.0), speed_mps=5.0)
        >>> names = {mavlink.MAV_CMD_NAV_TAKEOFF: "takeoff", mavlink.MAV_CMD_DO_CHANGE_SPEED: "speed",
        ...          mavlink.MAV_CMD_NAV_WAYPOINT: "waypoint", mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH: "rtl"}
        >>> [names[i.command] for i in items[:3]], len(items), names[items[-1].command], items[1].param2
        (['takeoff', 'speed', 'waypoint'], 33, 'rtl', 5.0)
    """
    if isinstance(plan, SurveyPart):
        plan = plan.plan
    if not isinstance(plan, SurveyPlan):
        raise InputError(f"plan must be a SurveyPlan or SurveyPart, got {type(plan).__name__}")
    items: list[MissionItem] = []
    if home_latlon_alt is not None:
        lat, lon, alt = (validate.finite_scalar(n, v) for n, v in zip(("home lat", "home lon", "home alt"),
                                                                     home_latlon_alt, strict=True))
        items.append(MissionItem.waypoint(lat, lon, alt, frame=mavlink.MAV_FRAME_GLOBAL_INT))
    latlon = plan.waypoints_latlon()
    alt = plan.altitude_m
    if takeoff:
        items.append(MissionItem.takeoff(alt, float(latlon[0, 0]), float(latlon[0, 1]), yaw_deg=_NAN))
    if speed_mps is not None:
        items.append(MissionItem.change_speed(speed_mps))
    triggering = False
    for k, (lat, lon) in enumerate(latlon):
        items.append(MissionItem.waypoint(float(lat), float(lon), alt, hold_s=plan.hold_s, yaw_deg=_NAN))
        want = bool(plan.trigger_on[k]) if k < len(plan.trigger_on) else False
        if want != triggering:
            # on: the first photo right here, then every trigger distance; off: distance 0
            items.append(MissionItem.camera_trigger_distance(plan.trigger_distance_m if want else 0.0,
                                                             trigger_now=want))
            triggering = want
    if return_to_launch:
        items.append(MissionItem.rtl())
    return items
