"""One MAVLink mission item, the type every layer shares (mapping plans it, drivers fly
it, the simulator stores it).

Commands and frames are pymavlink's dialect constants (``MAV_CMD_*``, ``MAV_FRAME_*``),
never numbers typed by hand. Positions are WGS84 degrees here and degE7 integers only
on the wire (:meth:`MissionItem.to_message` / :meth:`MissionItem.from_message`).

Example:
    >>> item = MissionItem.waypoint(47.3976667, 8.5455941, 20.0, hold_s=2.0)
    >>> item.command == mavlink.MAV_CMD_NAV_WAYPOINT, item.frame == mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
    (True, True)
    >>> msg = item.to_message(seq=1, target_system=1, target_component=1)
    >>> msg.x, msg.y, msg.z, msg.param1
    (473976667, 85455941, 20.0, 2.0)
    >>> MissionItem.from_message(msg) == item
    True
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from msgspec import Meta
from pymavlink.dialects.v20 import ardupilotmega as mavlink  # the dialect skyfix.drivers speaks

from skyfix import validate

__all__ = ["MissionItem", "mavlink"]

M = mavlink


@dataclass(frozen=True)
class MissionItem:
    """One mission item: ``lat_deg``/``lon_deg`` WGS84 (0, 0 = here, for commands without a
    position), ``alt_m`` metres in ``frame`` (default MAV_FRAME_GLOBAL_RELATIVE_ALT_INT: above
    home; MAV_FRAME_GLOBAL_INT: AMSL); param1..4 as the MAV_CMD ``command`` defines them
    (NaN: MAVLink's "default / unchanged"; the constructors refuse it where a value is needed).

    The fields of MAVLink ``MISSION_ITEM_INT`` without its addressing (sequence, target).
    """

    command: Annotated[int, Meta(ge=0, le=65535, description="MAV_CMD")]
    lat_deg: Annotated[float, Meta(ge=-90, le=90)] = 0.0
    lon_deg: Annotated[float, Meta(ge=-180, le=180)] = 0.0
    alt_m: float = 0.0
    param1: float = 0.0
    param2: float = 0.0
    param3: float = 0.0
    param4: float = 0.0
    frame: int = M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
    autocontinue: bool = True

    def __post_init__(self) -> None:
        validate.latitude("MissionItem.lat_deg", validate.finite_scalar("MissionItem.lat_deg", self.lat_deg))
        validate.longitude("MissionItem.lon_deg", validate.finite_scalar("MissionItem.lon_deg", self.lon_deg))
        # NaN is MAVLink's "default / unchanged"; GCSs send it (MAVSDK: z and hold of DO items)
        for name in ("alt_m", "param1", "param2", "param3", "param4"):
            validate.finite_or_nan_scalar(f"MissionItem.{name}", getattr(self, name))

    @classmethod
    def waypoint(cls, lat_deg: float, lon_deg: float, alt_m: float, *, hold_s: float = 0.0,
                 acceptance_m: float = 0.0, frame: int = M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                 yaw_deg: float = 0.0) -> MissionItem:
        """Fly to a point (``alt_m`` above home by default); hold ``hold_s``; reached within
        ``acceptance_m``; ``yaw_deg`` NaN leaves the heading to the autopilot."""
        alt_m = validate.finite_scalar("alt_m", alt_m)
        return cls(M.MAV_CMD_NAV_WAYPOINT, lat_deg, lon_deg, alt_m, hold_s, acceptance_m, 0.0, yaw_deg, frame)

    @classmethod
    def takeoff(cls, alt_m: float, lat_deg: float = 0.0, lon_deg: float = 0.0, *,
                yaw_deg: float = 0.0) -> MissionItem:
        """Climb to ``alt_m`` above home (here, or over ``lat_deg``/``lon_deg``)."""
        return cls(M.MAV_CMD_NAV_TAKEOFF, lat_deg, lon_deg, validate.positive_scalar("alt_m", alt_m),
                   param4=yaw_deg)

    @classmethod
    def land(cls, lat_deg: float = 0.0, lon_deg: float = 0.0) -> MissionItem:
        """Land here (0, 0) or at the given point."""
        return cls(M.MAV_CMD_NAV_LAND, lat_deg, lon_deg, 0.0)

    @classmethod
    def rtl(cls) -> MissionItem:
        """Return to launch."""
        return cls(M.MAV_CMD_NAV_RETURN_TO_LAUNCH, frame=M.MAV_FRAME_MISSION)

    @classmethod
    def camera_trigger_distance(cls, distance_m: float, *, trigger_now: bool = True) -> MissionItem:
        """Trigger the camera every ``distance_m`` metres from here on (0 stops); with
        ``trigger_now`` the first photo is taken at once (param3 = 1)."""
        validate.nonnegative_scalar("distance_m", distance_m)
        return cls(M.MAV_CMD_DO_SET_CAM_TRIGG_DIST, param1=float(distance_m), param3=1.0 if trigger_now else 0.0,
                   frame=M.MAV_FRAME_MISSION)

    @classmethod
    def change_speed(cls, speed_mps: float) -> MissionItem:
        """Set the ground speed (param1 = 1) to ``speed_mps``, throttle unchanged (-1)."""
        return cls(M.MAV_CMD_DO_CHANGE_SPEED, param1=1.0,
                   param2=validate.positive_scalar("speed_mps", speed_mps), param3=-1.0,
                   frame=M.MAV_FRAME_MISSION)

    def to_message(self, seq: int, target_system: int, target_component: int, *,
                   current: bool = False) -> mavlink.MAVLink_mission_item_int_message:
        """This item as a ``MISSION_ITEM_INT`` message with sequence number ``seq``."""
        return M.MAVLink_mission_item_int_message(
            target_system, target_component, seq, self.frame, self.command, int(current), int(self.autocontinue),
            self.param1, self.param2, self.param3, self.param4, int(round(self.lat_deg * 1e7)),
            int(round(self.lon_deg * 1e7)), float(self.alt_m), M.MAV_MISSION_TYPE_MISSION)

    @classmethod
    def from_message(cls, msg: mavlink.MAVLink_message) -> MissionItem:
        """The item of a received ``MISSION_ITEM_INT`` (degE7) or ``MISSION_ITEM`` (degrees)."""
        scale = 1e7 if msg.get_type() == "MISSION_ITEM_INT" else 1.0
        return cls(msg.command, msg.x / scale, msg.y / scale, msg.z, msg.param1, msg.param2, msg.param3,
                   msg.param4, msg.frame, bool(msg.autocontinue))
