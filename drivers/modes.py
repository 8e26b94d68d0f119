"""Flight-mode names <-> HEARTBEAT (base_mode, custom_mode) for ArduPilot Copter and PX4.

ArduPilot puts the mode number in ``custom_mode``. PX4 packs a main mode in bits 16-23
and an AUTO sub-mode in bits 24-31 of ``custom_mode``. PX4 modes are named as in
QGroundControl's internal names (``OFFBOARD``, ``POSCTL``, ``AUTO.MISSION``...), so no
PX4 mode ever reads as UNKNOWN.
"""

from __future__ import annotations

from skyfix.drivers.mav import AUTOPILOT_PX4
from skyfix.errors import InputError

#: ArduCopter mode numbers (ArduCopter/mode.h).
ARDUCOPTER_MODES: dict[str, int] = {
    "STABILIZE": 0, "ACRO": 1, "ALT_HOLD": 2, "AUTO": 3, "GUIDED": 4, "LOITER": 5, "RTL": 6,
    "CIRCLE": 7, "LAND": 9, "DRIFT": 11, "SPORT": 13, "FLIP": 14, "AUTOTUNE": 15,
    "POSHOLD": 16, "BRAKE": 17, "THROW": 18, "AVOID_ADSB": 19, "GUIDED_NOGPS": 20,
    "SMART_RTL": 21, "FLOWHOLD": 22, "FOLLOW": 23, "ZIGZAG": 24, "SYSTEMID": 25,
    "AUTOROTATE": 26, "AUTO_RTL": 27,
}
_ARDU_BY_NUMBER = {v: k for k, v in ARDUCOPTER_MODES.items()}

#: PX4 (main_mode, sub_mode) per name (px4_custom_mode.h).
PX4_MODES: dict[str, tuple[int, int]] = {
    "MANUAL": (1, 0), "ALTCTL": (2, 0), "POSCTL": (3, 0), "ACRO": (5, 0), "OFFBOARD": (6, 0),
    "STABILIZED": (7, 0), "RATTITUDE": (8, 0),
    "AUTO.READY": (4, 1), "AUTO.TAKEOFF": (4, 2), "AUTO.LOITER": (4, 3), "AUTO.MISSION": (4, 4),
    "AUTO.RTL": (4, 5), "AUTO.LAND": (4, 6), "AUTO.RTGS": (4, 7), "AUTO.FOLLOW_TARGET": (4, 8),
    "AUTO.PRECLAND": (4, 9),
}
_PX4_BY_PAIR = {v: k for k, v in PX4_MODES.items()}

#: skyfix's flavour-neutral roles -> each autopilot's mode name.
ROLE_MODES: dict[str, dict[str, str]] = {
    "guided": {"ardupilot": "GUIDED", "px4": "OFFBOARD"},
    "hold": {"ardupilot": "LOITER", "px4": "AUTO.LOITER"},
    "mission": {"ardupilot": "AUTO", "px4": "AUTO.MISSION"},
    "rtl": {"ardupilot": "RTL", "px4": "AUTO.RTL"},
    "land": {"ardupilot": "LAND", "px4": "AUTO.LAND"},
    "takeoff": {"ardupilot": "GUIDED", "px4": "AUTO.TAKEOFF"},
}


def flavour_of(autopilot: int) -> str:
    """``"px4"`` for MAV_AUTOPILOT_PX4, otherwise ``"ardupilot"``."""
    return "px4" if int(autopilot) == AUTOPILOT_PX4 else "ardupilot"


def mode_name(flavour: str, custom_mode: int) -> str:
    """Name of the mode in a HEARTBEAT's ``custom_mode`` (``"MODE(n)"`` if not in the table)."""
    custom_mode = int(custom_mode)
    if flavour == "px4":
        main, sub = (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF
        name = _PX4_BY_PAIR.get((main, sub)) or _PX4_BY_PAIR.get((main, 0))
        return name or f"MODE({main}.{sub})"
    return _ARDU_BY_NUMBER.get(custom_mode, f"MODE({custom_mode})")


def custom_mode_of(flavour: str, name: str) -> int:
    """``custom_mode`` number for a mode name (case-insensitive); InputError if unknown."""
    key = str(name).upper()
    if flavour == "px4":
        if key not in PX4_MODES:
            raise InputError(f"mode must be one of the PX4 modes {sorted(PX4_MODES)}, got {name!r}")
        main, sub = PX4_MODES[key]
        return (main << 16) | (sub << 24)
    if key not in ARDUCOPTER_MODES:
        raise InputError(f"mode must be one of the ArduCopter modes {sorted(ARDUCOPTER_MODES)}, "
                         f"got {name!r}")
    return ARDUCOPTER_MODES[key]


def role_mode(flavour: str, role: str) -> str:
    """The mode a flavour uses for a role such as ``"rtl"`` or ``"hold"``."""
    try:
        return ROLE_MODES[role][flavour]
    except KeyError:
        raise InputError(f"role must be one of {sorted(ROLE_MODES)}, got {role!r}") from None
