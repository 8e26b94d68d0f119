"""Survey plans as MAVLink mission items (plain data; :mod:`skyfix.drivers` uploads them).

:class:`MissionItemInt` carries exactly the fields of MAVLink's ``MISSION_ITEM_INT``
message; :func:`mission_items` lays a plan out as: optional home (ArduPilot keeps item 0
for it), take-off, optional speed change, one ``NAV_WAYPOINT`` per waypoint (with the
station hold time) and ``DO_SET_CAM_TRIGG_DIST`` wherever the camera starts or stops
triggering, then ``RETURN_TO_LAUNCH``. Altitudes are relative to home
(``MAV_FRAME_GLOBAL_RELATIVE_ALT_INT``).
"""

from __future__ import annotations

from dataclasses import dataclass

from skyfix import validate
from skyfix.errors import InputError
from skyfix.mapping.survey import SurveyPart, SurveyPlan

__all__ = ["MAV_CMD", "MAV_FRAME", "MissionItemInt", "mission_items"]


class MAV_FRAME:  # noqa: N801 - MAVLink's enum name
    """MAV_FRAME values used here (MAVLink common.xml)."""

    GLOBAL_INT = 5
    GLOBAL_RELATIVE_ALT_INT = 6
    MISSION = 2


class MAV_CMD:  # noqa: N801 - MAVLink's enum name
    """MAV_CMD values used here (MAVLink common.xml)."""

    NAV_WAYPOINT = 16
    NAV_RETURN_TO_LAUNCH = 20
    NAV_TAKEOFF = 22
    DO_CHANGE_SPEED = 178
    DO_SET_CAM_TRIGG_DIST = 206


MAV_MISSION_TYPE_MISSION = 0


@dataclass(frozen=True)
class MissionItemInt:
    """The fields of MAVLink ``MISSION_ITEM_INT``.

    ``x``/``y``: latitude/longitude in degrees x 1e7 (int32) for global frames; ``z``:
    altitude in metres in ``frame`` (relative to home here). ``param1..4`` as defined by
    ``command``.
    """

    seq: int
    frame: int
    command: int
    current: int
    autocontinue: int
    param1: float
    param2: float
    param3: float
    param4: float
    x: int
    y: int
    z: float
    target_system: int = 1
    target_component: int = 1
    mission_type: int = MAV_MISSION_TYPE_MISSION


def _deg_e7(value: float) -> int:
    return int(round(value * 1e7))


def mission_items(plan: SurveyPlan | SurveyPart, *, home_latlon_alt=None, takeoff: bool = True,
                  speed_mps: float | None = None, return_to_launch: bool = True,
                  target_system: int = 1, target_component: int = 1) -> list[MissionItemInt]:
    """Mission items flying ``plan`` (or one drone's part); see the module docstring.

    ``home_latlon_alt``: (lat_deg, lon_deg, alt_m AMSL) written as item 0 (ArduPilot's home
    slot; omit for PX4). ``speed_mps``: ground speed set after take-off.
    """
    if isinstance(plan, SurveyPart):
        plan = plan.plan
    if not isinstance(plan, SurveyPlan):
        raise InputError(f"plan must be a SurveyPlan or SurveyPart, got {type(plan).__name__}")
    items: list[tuple] = []
    if home_latlon_alt is not None:
        lat, lon, alt = (validate.finite_scalar(n, v) for n, v in zip(("home lat", "home lon", "home alt"),
                                                                     home_latlon_alt, strict=True))
        items.append((MAV_FRAME.GLOBAL_INT, MAV_CMD.NAV_WAYPOINT, (0, 0, 0, 0), lat, lon, alt))
    latlon = plan.waypoints_latlon()
    alt = plan.altitude_m
    if takeoff:
        items.append((MAV_FRAME.GLOBAL_RELATIVE_ALT_INT, MAV_CMD.NAV_TAKEOFF, (0, 0, 0, float("nan")),
                      latlon[0, 0], latlon[0, 1], alt))
    if speed_mps is not None:
        items.append((MAV_FRAME.MISSION, MAV_CMD.DO_CHANGE_SPEED,
                      (1, validate.positive_scalar("speed_mps", speed_mps), -1, 0), 0.0, 0.0, 0.0))
    triggering = False
    for k, (lat, lon) in enumerate(latlon):
        items.append((MAV_FRAME.GLOBAL_RELATIVE_ALT_INT, MAV_CMD.NAV_WAYPOINT,
                      (plan.hold_s, 0, 0, float("nan")), lat, lon, alt))
        want = bool(plan.trigger_on[k]) if k < len(plan.trigger_on) else False
        if want != triggering:
            distance = plan.trigger_distance_m if want else 0.0
            # param3 = 1: take the first photo right here, then every `distance` metres.
            items.append((MAV_FRAME.MISSION, MAV_CMD.DO_SET_CAM_TRIGG_DIST, (distance, 0, 1 if want else 0, 0),
                          0.0, 0.0, 0.0))
            triggering = want
    if return_to_launch:
        items.append((MAV_FRAME.MISSION, MAV_CMD.NAV_RETURN_TO_LAUNCH, (0, 0, 0, 0), 0.0, 0.0, 0.0))
    return [MissionItemInt(seq, frame, cmd, 0, 1, *map(float, params), _deg_e7(lat), _deg_e7(lon), float(z),
                           target_system, target_component)
            for seq, (frame, cmd, params, lat, lon, z) in enumerate(items)]
