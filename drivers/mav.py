"""pymavlink, pinned to MAVLink 2 and the ardupilotmega dialect (a superset of common).

Import ``mavlink`` and ``mavutil`` from here so every skyfix module speaks the same
protocol version: MAVLink 2 is needed for messages with ids above 255 (ODOMETRY).
"""

from __future__ import annotations

import os

os.environ.setdefault("MAVLINK20", "1")

from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402

#: MAV_AUTOPILOT values skyfix knows how to drive.
AUTOPILOT_ARDUPILOT = mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
AUTOPILOT_PX4 = mavlink.MAV_AUTOPILOT_PX4

RESULT_NAMES = {v: k for k, v in vars(mavlink).items()
                if k.startswith("MAV_RESULT_") and isinstance(v, int) and k != "MAV_RESULT_ENUM_END"}

COMMAND_NAMES = {v: k for k, v in vars(mavlink).items()
                 if k.startswith("MAV_CMD_") and isinstance(v, int) and k != "MAV_CMD_ENUM_END"}


def result_name(result: int) -> str:
    """``MAV_RESULT_DENIED`` for 2, etc.; the number itself when unknown."""
    return RESULT_NAMES.get(int(result), str(result))


def command_name(command: int) -> str:
    """``MAV_CMD_NAV_TAKEOFF`` for 22, etc.; the number itself when unknown."""
    return COMMAND_NAMES.get(int(command), str(command))


__all__ = ["AUTOPILOT_ARDUPILOT", "AUTOPILOT_PX4", "command_name", "mavlink", "mavutil",
           "result_name"]
