"""The one place where MAVLink wire units become measurement units.

GPS_RAW_INT (common.xml): ``eph``/``epv`` are HDOP/VDOP x 100, unitless (65535: unknown),
*not* metres; the metre accuracies are the MAVLink 2 extension fields ``h_acc``/``v_acc``
in millimetres (0: unknown). ``alt`` is above mean sea level (mm); ``alt_ellipsoid`` is
above the WGS84 ellipsoid (mm), 0 when the autopilot does not provide it. When it is 0
the ellipsoidal height is AMSL converted through the EGM96 geoid (:class:`skyfix.geo.Height`),
and the record says so (``alt_ellipsoid_source = "egm96"``). GLOBAL_POSITION_INT and
HOME_POSITION carry AMSL altitudes only; their ellipsoidal heights always come from the
geoid model.
"""

from __future__ import annotations

import math
import struct

from skyfix.drivers.mav import mavlink
from skyfix.drivers.state import Battery, EkfStatus, GnssFix, Home, Position, Velocity
from skyfix.geo import Height, VerticalDatum

UINT16_UNKNOWN = 65535


AMSL = VerticalDatum.EGM96
"""The surface of MAVLink's "MSL" altitudes (GPS_RAW_INT.alt, GLOBAL_POSITION_INT.alt,
HOME_POSITION.altitude, GPS_INPUT.alt): EGM96, as ArduPilot, PX4 and most receivers use."""


def ellipsoidal_from_amsl_m(lat_deg: float, lon_deg: float, alt_amsl_m: float) -> float:
    """Height above the WGS84 ellipsoid (m) of a MAVLink AMSL altitude at (lat, lon)."""
    return Height(alt_amsl_m, AMSL).to(VerticalDatum.WGS84, lat_deg, lon_deg).value_m


def _dop(raw: int) -> float:
    return raw / 100.0 if raw != UINT16_UNKNOWN else math.nan


def _acc_m(raw_mm: int) -> float:
    return raw_mm / 1000.0 if raw_mm > 0 else math.nan


def gnss_fix(msg, now_s: float) -> GnssFix:
    """GPS_RAW_INT -> :class:`GnssFix` (metres, degrees; DOPs unitless; NaN = unknown)."""
    lat, lon = msg.lat / 1e7, msg.lon / 1e7
    alt_amsl = msg.alt / 1000.0
    alt_ell_mm = getattr(msg, "alt_ellipsoid", 0)
    has_fix = msg.fix_type >= mavlink.GPS_FIX_TYPE_2D_FIX and (msg.lat or msg.lon)
    if alt_ell_mm:
        alt_ell, source = alt_ell_mm / 1000.0, "autopilot"
    elif has_fix:
        alt_ell, source = ellipsoidal_from_amsl_m(lat, lon, alt_amsl), AMSL.value
    else:
        alt_ell, source = math.nan, "none"
    return GnssFix(
        fix_type=msg.fix_type, satellites=msg.satellites_visible,
        h_acc_m=_acc_m(getattr(msg, "h_acc", 0)), v_acc_m=_acc_m(getattr(msg, "v_acc", 0)),
        hdop=_dop(msg.eph), vdop=_dop(msg.epv), lat_deg=lat, lon_deg=lon, alt_amsl_m=alt_amsl,
        alt_ellipsoid_m=alt_ell, alt_ellipsoid_source=source, time_s=now_s,
        autopilot_time_s=msg.time_usec / 1e6)


def position_velocity(msg, now_s: float) -> tuple[Position, Velocity]:
    """GLOBAL_POSITION_INT -> (:class:`Position`, :class:`Velocity` NED m/s)."""
    stamp_s = msg.time_boot_ms / 1000.0
    lat, lon, alt_amsl = msg.lat / 1e7, msg.lon / 1e7, msg.alt / 1000.0
    pos = Position(lat, lon, alt_amsl, msg.relative_alt / 1000.0, now_s, stamp_s,
                   alt_ellipsoid_m=ellipsoidal_from_amsl_m(lat, lon, alt_amsl))
    vel = Velocity(msg.vx / 100.0, msg.vy / 100.0, msg.vz / 100.0, now_s, stamp_s)
    return pos, vel


def home(msg, now_s: float) -> Home:
    """HOME_POSITION -> :class:`Home` (AMSL altitude and its ellipsoidal height)."""
    lat, lon, alt_amsl = msg.latitude / 1e7, msg.longitude / 1e7, msg.altitude / 1000.0
    return Home(lat, lon, alt_amsl, now_s, msg.time_usec / 1e6,
                alt_ellipsoid_m=ellipsoidal_from_amsl_m(lat, lon, alt_amsl))


def ekf_status(msg, now_s: float) -> EkfStatus:
    """EKF_STATUS_REPORT -> :class:`EkfStatus`."""
    return EkfStatus(int(msg.flags), bool(msg.flags & mavlink.EKF_POS_HORIZ_ABS),
                     bool(msg.flags & mavlink.EKF_CONST_POS_MODE),
                     float(msg.velocity_variance), float(msg.pos_horiz_variance), now_s)


def battery(msg, now_s: float) -> Battery:
    """SYS_STATUS -> :class:`Battery` (V, A, %; NaN when the autopilot does not know)."""
    return Battery(msg.voltage_battery / 1000.0 if msg.voltage_battery != UINT16_UNKNOWN else math.nan,
                   msg.current_battery / 100.0 if msg.current_battery >= 0 else math.nan,
                   float(msg.battery_remaining) if msg.battery_remaining >= 0 else math.nan, now_s)


# ---------------------------------------------------------------- parameters
#: MAV_PARAM_TYPE -> struct code of the integer it holds (REAL32/REAL64 absent: floats).
_PARAM_INT_CODES = {1: "<B", 2: "<b", 3: "<H", 4: "<h", 5: "<I", 6: "<i"}
REAL32 = 9


def param_is_int(param_type: int) -> bool:
    return int(param_type) in _PARAM_INT_CODES


def param_from_wire(value: float, param_type: int, bytewise: bool) -> int | float:
    """PARAM_VALUE's float ``param_value`` -> the parameter's value.

    ArduPilot casts integers to float (C cast); PX4 copies the integer's bytes into the
    float's (byte-wise encoding, MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE)."""
    code = _PARAM_INT_CODES.get(int(param_type))
    if code is None:
        return float(value)
    if not bytewise:
        return int(round(value)) if math.isfinite(value) else 0
    raw = struct.pack("<f", value)
    return struct.unpack(code, raw[:struct.calcsize(code)])[0]


def param_to_wire(value: float, param_type: int, bytewise: bool) -> float:
    """A parameter value -> PARAM_SET's float, in the autopilot's encoding."""
    code = _PARAM_INT_CODES.get(int(param_type))
    if code is None:
        return float(value)
    ivalue = int(round(value))
    if not bytewise:
        return float(ivalue)
    raw = struct.pack(code, ivalue).ljust(4, b"\x00")
    return struct.unpack("<f", raw)[0]
