"""External position for the autopilot: GPS_INPUT and VISION_POSITION_ESTIMATE / ODOMETRY.

Autopilots silently ignore injected positions unless configured for them, so
:func:`check_settings` reads the relevant parameters first and raises a
:class:`~skyfix.errors.ConfigurationError` naming the setting to change:

- ArduPilot GPS_INPUT: ``GPS1_TYPE`` (or ``GPS2_TYPE``) = 14 (MAV), EKF source ``EK3_SRC1_POSXY``
  = 3 (GPS). Firmware before 4.6 calls the first one ``GPS_TYPE``: both names are read.
- ArduPilot vision: ``VISO_TYPE`` > 0 and ``EK3_SRC1_POSXY`` = 6 (ExternalNav).
- PX4 GPS_INPUT: ``EKF2_GPS_CTRL`` bit 0 (lon/lat fusion).
- PX4 vision: ``EKF2_EV_CTRL`` bit 0 (horizontal position fusion).

GPS time: GPS_INPUT carries GPS week and milliseconds of week; GPS time runs ahead of
UTC by the leap seconds accumulated since 1980 (18 s since 2017-01-01).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from skyfix import validate
from skyfix.drivers import units
from skyfix.drivers.mav import mavlink
from skyfix.drivers.request import DONE, transact
from skyfix.errors import ConfigurationError, InputError, SkyfixError, SkyfixTimeout
from skyfix.geo import Height, VerticalDatum
from skyfix.rotation import r_ned_from_frd
from skyfix.types import GeoFix

if TYPE_CHECKING:
    from skyfix.drivers.vehicle import Vehicle

log = logging.getLogger(__name__)
M = mavlink

GPS_EPOCH_UNIX_S = 315964800.0  # 1980-01-06T00:00:00Z
GPS_LEAP_SECONDS = 18
_WEEK_S = 7 * 86400

__all__ = ["PositionInjector", "check_settings", "gps_input_message", "gps_week_ms",
           "set_origin", "vision_message"]


def gps_week_ms(unix_s: float) -> tuple[int, int]:
    """(GPS week, milliseconds of week) for a UNIX time."""
    gps_s = unix_s - GPS_EPOCH_UNIX_S + GPS_LEAP_SECONDS
    week = int(gps_s // _WEEK_S)
    return week, int(round((gps_s - week * _WEEK_S) * 1000.0)) % (_WEEK_S * 1000)


def _param(vehicle: Vehicle, name: str) -> float | None:
    try:
        return vehicle.get_param(name, timeout_s=0.5, retries=2)
    except SkyfixTimeout:
        return None


def check_settings(vehicle: Vehicle, kind: str) -> None:
    """Raise ConfigurationError when ``vehicle`` would ignore ``kind`` ("gps" or "vision")."""
    if kind not in ("gps", "vision"):
        raise InputError(f"kind must be 'gps' or 'vision', got {kind!r}")
    sysid = vehicle.system_id
    if vehicle.autopilot == "ardupilot":
        src = _param(vehicle, "EK3_SRC1_POSXY")
        if kind == "gps":
            first = "GPS1_TYPE"
            gps1 = _param(vehicle, first)
            if gps1 is None:  # firmware before 4.6
                first, gps1 = "GPS_TYPE", _param(vehicle, "GPS_TYPE")
            types = {first: gps1, "GPS2_TYPE": _param(vehicle, "GPS2_TYPE")}
            types = {n: (int(v) if v is not None else "unreadable") for n, v in types.items()}
            vehicle.gps_input_id = 0 if types[first] == 14 else 1  # the MAV GPS instance
            if 14 not in types.values():
                raise ConfigurationError(
                    f"vehicle {sysid} (ArduPilot) ignores GPS_INPUT: {first}={types[first]}, "
                    f"GPS2_TYPE={types['GPS2_TYPE']}; set {first}=14 (MAV), or GPS2_TYPE=14 next to the real "
                    "receiver (ARDUPILOT_INJECTED_GPS2_PARAMS), then reboot the autopilot")
            if src is not None and int(src) != 3:
                raise ConfigurationError(
                    f"vehicle {sysid} (ArduPilot) EKF does not use GPS for position: "
                    f"EK3_SRC1_POSXY={int(src)}; set EK3_SRC1_POSXY=3 (GPS) for GPS_INPUT to be fused")
        else:
            viso = _param(vehicle, "VISO_TYPE")
            if not viso:
                raise ConfigurationError(
                    f"vehicle {sysid} (ArduPilot) ignores vision positions: VISO_TYPE="
                    f"{int(viso) if viso is not None else 'unreadable'}; "
                    "set VISO_TYPE=1 (MAVLink) and reboot")
            if src is None or int(src) != 6:
                raise ConfigurationError(
                    f"vehicle {sysid} (ArduPilot) EKF does not use external navigation: "
                    f"EK3_SRC1_POSXY={int(src) if src is not None else 'unreadable'}; "
                    "set EK3_SRC1_POSXY=6 (ExternalNav)")
        return
    if kind == "gps":
        ctrl = _param(vehicle, "EKF2_GPS_CTRL")
        if ctrl is not None and not int(ctrl) & 1:
            raise ConfigurationError(
                f"vehicle {sysid} (PX4) does not fuse GNSS position: EKF2_GPS_CTRL={int(ctrl)}; "
                "set bit 0 (e.g. EKF2_GPS_CTRL=7)")
        return
    ctrl = _param(vehicle, "EKF2_EV_CTRL")
    if ctrl is None:
        aid = _param(vehicle, "EKF2_AID_MASK")  # PX4 before v1.14
        if aid is None or not int(aid) & 8:
            raise ConfigurationError(f"vehicle {sysid} (PX4) does not fuse vision position: set "
                                     "EKF2_EV_CTRL bit 0 (v1.14+) or EKF2_AID_MASK bit 3 (older)")
        return
    if not int(ctrl) & 1:
        raise ConfigurationError(
            f"vehicle {sysid} (PX4) does not fuse vision position: EKF2_EV_CTRL={int(ctrl)}; "
            "set bit 0 (horizontal position), e.g. EKF2_EV_CTRL=15")


def gps_input_message(lat_deg: float, lon_deg: float, alt_amsl_m: float, *, h_acc_m: float,
                      v_acc_m: float | None = None, vel_ned_mps: tuple[float, float, float] | None = None,
                      satellites: int = 12, fix_type: int = 3, time_s: float | None = None,
                      gps_id: int = 0):
    """A GPS_INPUT message; ``time_s`` UNIX time of the fix (now if None); ``gps_id`` the
    autopilot's GPS instance it is for (0: GPS1, 1: GPS2; see :func:`gps_input_instance`)."""
    lat = float(validate.latitude("lat_deg", validate.finite_scalar("lat_deg", lat_deg)))
    lon = float(validate.longitude("lon_deg", validate.finite_scalar("lon_deg", lon_deg)))
    alt = validate.finite_scalar("alt_amsl_m", alt_amsl_m)
    h_acc = validate.positive_scalar("h_acc_m", h_acc_m)
    v_acc = validate.positive_scalar("v_acc_m", v_acc_m) if v_acc_m is not None else 1.5 * h_acc
    if not 0 <= int(fix_type) <= 8:
        raise InputError(f"fix_type must be a GPS_FIX_TYPE 0..8, got {fix_type}")
    t = time.time() if time_s is None else validate.finite_scalar("time_s", time_s)
    week, week_ms = gps_week_ms(t)
    ignore = M.GPS_INPUT_IGNORE_FLAG_SPEED_ACCURACY
    if vel_ned_mps is None:
        vn = ve = vd = 0.0
        ignore |= M.GPS_INPUT_IGNORE_FLAG_VEL_HORIZ | M.GPS_INPUT_IGNORE_FLAG_VEL_VERT
    else:
        vel = validate.finite_array("vel_ned_mps", vel_ned_mps)
        if vel.shape != (3,):
            raise InputError(f"vel_ned_mps must have 3 components, got shape {vel.shape}")
        vn, ve, vd = (float(x) for x in vel)
    return M.MAVLink_gps_input_message(
        int(t * 1e6), int(gps_id), ignore, week_ms, week, int(fix_type), int(round(lat * 1e7)),
        int(round(lon * 1e7)), alt, h_acc / 1.5, v_acc / 1.5, vn, ve, vd, 0.0, h_acc, v_acc,
        int(satellites), 0)


def vision_message(north_m: float, east_m: float, down_m: float, *, sigma_m: float,
                   roll_deg: float = 0.0, pitch_deg: float = 0.0, yaw_deg: float = 0.0,
                   time_s: float | None = None, odometry: bool = False):
    """VISION_POSITION_ESTIMATE (or ODOMETRY, MAV_FRAME_LOCAL_NED) in metres about the EKF origin."""
    n, e, d = (validate.finite_scalar(k, v) for k, v in (("north_m", north_m), ("east_m", east_m),
                                                         ("down_m", down_m)))
    sigma = validate.positive_scalar("sigma_m", sigma_m)
    r, p, y = (validate.finite_scalar(k, v) for k, v in (("roll_deg", roll_deg), ("pitch_deg", pitch_deg),
                                                         ("yaw_deg", yaw_deg)))
    t_us = int((time.time() if time_s is None else validate.finite_scalar("time_s", time_s)) * 1e6)
    var = sigma * sigma
    ang_var = math.radians(5.0) ** 2
    if not odometry:
        # upper-right triangle of the 6x6 pose covariance (x, y, z, roll, pitch, yaw), row-major
        cov = []
        for i in range(6):
            for j in range(i, 6):
                cov.append((var if i < 3 else ang_var) if i == j else 0.0)
        return M.MAVLink_vision_position_estimate_message(t_us, n, e, d, math.radians(r), math.radians(p),
                                                          math.radians(y), cov, 0)
    rot = r_ned_from_frd(y, p, r)
    w = math.sqrt(max(1e-12, 1.0 + rot[0, 0] + rot[1, 1] + rot[2, 2])) / 2.0
    q = [w, (rot[2, 1] - rot[1, 2]) / (4 * w), (rot[0, 2] - rot[2, 0]) / (4 * w),
         (rot[1, 0] - rot[0, 1]) / (4 * w)]
    pose_cov = [math.nan] * 21
    pose_cov[0], pose_cov[6], pose_cov[11] = var, var, var
    return M.MAVLink_odometry_message(t_us, M.MAV_FRAME_LOCAL_NED, M.MAV_FRAME_BODY_FRD, n, e, d, q,
                                      math.nan, math.nan, math.nan, math.nan, math.nan, math.nan,
                                      pose_cov, [math.nan] * 21, 0, M.MAV_ESTIMATOR_TYPE_VISION, 100)


#: ArduPilot parameters for a companion that injects GPS_INPUT as a second GPS next to the
#: real receiver, set before flight: GPS1 stays the only GPS the EKF uses (GPS_AUTO_SWITCH 0,
#: GPS_PRIMARY 0) until :func:`use_injected_gps` switches; EKF source set 2 takes GPS
#: positions without GPS velocity (GPS_INPUT from a position-only fusion carries none, and
#: EK3 fusing the MAV GPS's stale zero velocity throws "GPS Glitch" and an EKF failsafe).
#: GPS2_TYPE stays 0 until then: with 14 from boot, arming is refused ("GPS 2: Bad fix")
#: unless the companion injects before take-off. Measured on Copter 4.7 SITL.
ARDUPILOT_INJECTED_GPS2_PARAMS: dict[str, float] = {
    "GPS_AUTO_SWITCH": 0, "GPS_PRIMARY": 0,
    "EK3_SRC2_POSXY": 3, "EK3_SRC2_VELXY": 0, "EK3_SRC2_POSZ": 1, "EK3_SRC2_VELZ": 0, "EK3_SRC2_YAW": 1,
}


def use_injected_gps(vehicle: Vehicle, on: bool) -> None:
    """ArduPilot: make the injected (MAV) GPS the one the EKF uses (``on``), or the real
    receiver again. On: GPS2_TYPE 14 when no GPS is of type MAV yet (ArduPilot starts the MAV
    driver without a reboot), GPS_PRIMARY to that instance, EKF source set 2 (positions
    only). Off: GPS_PRIMARY 0, source set 1, GPS2_TYPE back to 0 if this set it. Needs
    GPS_AUTO_SWITCH 0 (:data:`ARDUPILOT_INJECTED_GPS2_PARAMS`), else ConfigurationError."""
    if vehicle.autopilot != "ardupilot":
        raise ConfigurationError(f"vehicle {vehicle.system_id}: switching the GPS instance is ArduPilot's "
                                 f"(GPS_PRIMARY); {vehicle.autopilot} fuses every enabled GNSS source")
    if int(vehicle.get_param("GPS_AUTO_SWITCH")) != 0:
        raise ConfigurationError(f"vehicle {vehicle.system_id}: GPS_AUTO_SWITCH must be 0 for GPS_PRIMARY "
                                 "to pick the GPS instance (see ARDUPILOT_INJECTED_GPS2_PARAMS)")
    if on:
        first = "GPS1_TYPE" if _param(vehicle, "GPS1_TYPE") is not None else "GPS_TYPE"
        if int(vehicle.get_param(first)) != 14 and int(vehicle.get_param("GPS2_TYPE")) == 0:
            vehicle.set_param("GPS2_TYPE", 14)
            vehicle.gps2_type_set_by_skyfix = True
        check_settings(vehicle, "gps")
    vehicle.set_param("GPS_PRIMARY", vehicle.gps_input_id if on else 0)
    vehicle.command(M.MAV_CMD_SET_EKF_SOURCE_SET, 2 if on else 1)
    if not on and getattr(vehicle, "gps2_type_set_by_skyfix", False):
        vehicle.set_param("GPS2_TYPE", 0)
        vehicle.gps2_type_set_by_skyfix = False


def set_origin(vehicle: Vehicle, lat_deg: float, lon_deg: float, alt_amsl_m: float, *,
               timeout_s: float = 1.0, retries: int = 3) -> None:
    """SET_GPS_GLOBAL_ORIGIN, then wait for a GPS_GLOBAL_ORIGIN matching it (1e-7 deg, 1 cm)."""
    lat_e7 = int(round(float(validate.latitude("lat_deg", validate.finite_scalar("lat_deg", lat_deg))) * 1e7))
    lon_e7 = int(round(float(validate.longitude("lon_deg", validate.finite_scalar("lon_deg", lon_deg))) * 1e7))
    alt_mm = int(round(validate.finite_scalar("alt_amsl_m", alt_amsl_m) * 1000))

    def confirms(m) -> bool:
        return m.get_type() == "GPS_GLOBAL_ORIGIN" and abs(m.latitude - lat_e7) <= 1 \
            and abs(m.longitude - lon_e7) <= 1 and abs(m.altitude - alt_mm) <= 10

    try:
        transact(vehicle, lambda attempt: M.MAVLink_set_gps_global_origin_message(
            vehicle.system_id, lat_e7, lon_e7, alt_mm, int(time.time() * 1e6)),
            lambda m: DONE if confirms(m) else None, types=("GPS_GLOBAL_ORIGIN",), timeout_s=timeout_s,
            retries=retries, what="SET_GPS_GLOBAL_ORIGIN")
    except SkyfixTimeout as exc:
        raise SkyfixTimeout(f"vehicle {vehicle.system_id} did not confirm the EKF origin "
                            f"{lat_deg:.7f},{lon_deg:.7f},{alt_amsl_m:.2f} with GPS_GLOBAL_ORIGIN: {exc}") from None


class PositionInjector:
    """Sends GPS_INPUT from ``source()`` (a :class:`GeoFix` or None) at a steady rate.

    GeoFix heights are ellipsoidal; GPS_INPUT wants AMSL: the height converted to
    ``units.AMSL`` (EGM96) at the fix (:class:`skyfix.geo.Height`), or h - ``geoid_height_m`` when given
    (an autopilot whose AMSL uses another geoid model). The fix's ``time_s``
    (UNIX) becomes the message time stamp; its covariance becomes the accuracies.
    A failing source is logged and skipped; the loop keeps its schedule.
    """

    def __init__(self, vehicle: Vehicle, source: Callable[[], GeoFix | None], *, rate_hz: float = 5.0,
                 geoid_height_m: float | None = None) -> None:
        self.vehicle = vehicle
        self.source = source
        self.period_s = 1.0 / validate.positive_scalar("rate_hz", rate_hz)
        self.geoid_height_m = None if geoid_height_m is None else \
            validate.finite_scalar("geoid_height_m", geoid_height_m)
        self.sent = 0
        self.skipped = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True,
                                        name=f"skyfix-gps-inject-{vehicle.system_id}")

    def start(self) -> PositionInjector:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)

    def _amsl_m(self, fix: GeoFix) -> float:
        """The fix's ellipsoidal height as the autopilot's AMSL altitude, metres."""
        if self.geoid_height_m is not None:
            return fix.alt_m - self.geoid_height_m
        return Height(fix.alt_m, VerticalDatum.WGS84).to(units.AMSL, fix.lat_deg, fix.lon_deg).value_m

    def _run(self) -> None:
        next_t = time.monotonic()
        while not self._stop.is_set():
            try:
                fix = self.source()
                if fix is None:
                    self.skipped += 1
                else:
                    h_acc = max(fix.sigma_horizontal_m, 0.05)
                    self.vehicle.send(gps_input_message(
                        fix.lat_deg, fix.lon_deg, self._amsl_m(fix), h_acc_m=h_acc,
                        v_acc_m=max(fix.sigma_up_m, 0.05), time_s=fix.time_s or None,
                        gps_id=self.vehicle.gps_input_id))
                    self.sent += 1
            except SkyfixError as exc:
                self.skipped += 1
                log.warning("GPS injection for vehicle %d skipped a fix: %s", self.vehicle.system_id, exc)
            next_t += self.period_s
            delay = next_t - time.monotonic()
            if delay < -self.period_s:  # fell behind: restart the schedule, no burst
                next_t = time.monotonic()
                delay = 0.0
            self._stop.wait(max(0.0, delay))


class InjectionCommands:
    """A Vehicle's external-position commands (mixed into :class:`~skyfix.drivers.vehicle.Vehicle`,
    which holds ``injector``, ``gps_input_id`` and the settings already checked)."""

    def check_injection(self, kind: str) -> None:
        """Raise ConfigurationError naming the setting that makes the autopilot ignore
        ``kind`` (``"gps"`` for GPS_INPUT, ``"vision"`` for VISION_POSITION_ESTIMATE)."""
        check_settings(self, kind)
        self._injection_checked.add(kind)

    def inject_gps(self, lat_deg: float, lon_deg: float, alt_amsl_m: float, *, h_acc_m: float,
                   v_acc_m: float | None = None, vel_ned_mps: tuple[float, float, float] | None = None,
                   satellites: int = 12, fix_type: int = 3, time_s: float | None = None) -> None:
        """Send one GPS_INPUT (checks the autopilot's GPS settings on first use)."""
        msg = gps_input_message(lat_deg, lon_deg, alt_amsl_m, h_acc_m=h_acc_m,
                                          v_acc_m=v_acc_m, vel_ned_mps=vel_ned_mps,
                                          satellites=satellites, fix_type=fix_type, time_s=time_s)
        if "gps" not in self._injection_checked:
            self.check_injection("gps")
        msg.gps_id = self.gps_input_id
        self.send(msg)

    def use_injected_gps(self, on: bool) -> None:
        """ArduPilot: fly on the injected GPS (GPS_INPUT) instead of the receiver, or back;
        see :func:`use_injected_gps` and ``ARDUPILOT_INJECTED_GPS2_PARAMS``."""
        use_injected_gps(self, on)

    def inject_vision(self, north_m: float, east_m: float, down_m: float, *, sigma_m: float,
                      roll_deg: float = 0.0, pitch_deg: float = 0.0, yaw_deg: float = 0.0,
                      time_s: float | None = None, odometry: bool = False) -> None:
        """Send one VISION_POSITION_ESTIMATE (or ODOMETRY) in local NED about the EKF origin."""
        msg = vision_message(north_m, east_m, down_m, sigma_m=sigma_m, roll_deg=roll_deg,
                                       pitch_deg=pitch_deg, yaw_deg=yaw_deg, time_s=time_s,
                                       odometry=odometry)
        if "vision" not in self._injection_checked:
            self.check_injection("vision")
        self.send(msg)

    def start_gps_injection(self, source: Callable[[], GeoFix | None], *,
                            rate_hz: float = 5.0,
                            geoid_height_m: float | None = None) -> PositionInjector:
        """Inject ``source()`` fixes (ellipsoidal heights) as GPS_INPUT at a steady ``rate_hz``
        on a thread; AMSL through EGM96 unless ``geoid_height_m`` is given."""
        self.check_injection("gps")
        if self.injector is not None:
            self.injector.stop()
        self.injector = PositionInjector(self, source, rate_hz=rate_hz,
                                                   geoid_height_m=geoid_height_m)
        return self.injector.start()

    def set_origin(self, lat_deg: float, lon_deg: float, alt_amsl_m: float, *,
                   timeout_s: float = 1.0, retries: int = 3) -> None:
        """Set the EKF origin (SET_GPS_GLOBAL_ORIGIN) and wait for GPS_GLOBAL_ORIGIN to confirm."""
        set_origin(self, lat_deg, lon_deg, alt_amsl_m, timeout_s=timeout_s, retries=retries)
