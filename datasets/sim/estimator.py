"""The simulated autopilot's position estimate: which source it flies on (its receivers, an
injected GPS_INPUT, vision), a toy EKF that follows it, and the external-position inputs.

Mixed into :class:`skyfix.datasets.sim.vehicle.SimVehicle` (world ENU metres; the receivers
are created there). Like ArduPilot's EKF source sets and PX4's EKF2 controls, the parameters
pick the source.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from skyfix.datasets.sim.gps import GpsReading
from skyfix.drivers.mav import mavlink as M
from skyfix.geo import LocalFrame

_NEEDS_POSITION = {"guided", "mission", "rtl", "hold", "takeoff"}


@dataclass
class _ExternalFix:
    """A position from GPS_INPUT or vision, as an estimator residual (fix - truth), ENU m."""

    residual_enu_m: np.ndarray
    time_s: float
    fix_type: int = 3
    satellites: int = 0
    eph_m: float = 1.0
    epv_m: float = 1.5
    lat_deg: float = 0.0
    lon_deg: float = 0.0
    alt_m: float = 0.0
    consumed: bool = False
    hdop: float = math.nan
    vdop: float = math.nan


class PositionEstimator:
    """Source selection, the estimate's update and GPS_INPUT / vision / origin inputs."""

    def _gps_instances(self) -> list[str]:
        """Receiver types in priority order: ``"real"`` or ``"mav"`` (GPS_INPUT)."""
        if self.flavour == "px4":
            return ["real", "mav"] if int(self.param("EKF2_GPS_CTRL")) & 1 else []
        out = []
        for name in ("GPS1_TYPE" if "GPS1_TYPE" in self.params else "GPS_TYPE", "GPS2_TYPE"):
            kind = int(self.param(name))
            if kind == 14:
                out.append("mav")
            elif kind != 0:
                out.append("real")
        return out

    def _fix_instances(self) -> list[str]:
        """The receivers the estimator may use, in priority order. ArduPilot with
        GPS_AUTO_SWITCH 0 uses only the GPS_PRIMARY instance (0: GPS1, 1: GPS2), so a
        companion can pin its GPS_INPUT while the real receiver is back but distrusted."""
        instances = self._gps_instances()
        if self.flavour == "ardupilot" and int(self.param("GPS_AUTO_SWITCH")) == 0 and instances:
            primary = int(self.param("GPS_PRIMARY"))
            return instances[primary:primary + 1]
        return instances

    def uses_vision(self) -> bool:
        if self.flavour == "px4":
            return bool(int(self.param("EKF2_EV_CTRL")) & 1)
        return self.param("VISO_TYPE") > 0 and int(self.param("EK3_SRC1_POSXY")) == 6

    def gps_report(self) -> GpsReading | None:
        """What GPS_RAW_INT shows: the first configured receiver, real or MAV."""
        instances = self._gps_instances()
        if not instances:
            return None
        if instances[0] == "mav":
            return self._mav_reading()
        return self.last_gps

    def _mav_reading(self) -> GpsReading | None:
        fix = self.mav_gps
        if fix is None or self.t_s - fix.time_s > 1.0:
            return GpsReading(np.full(3, np.nan), np.full(3, np.nan), 1, 0, math.inf, math.inf)
        return GpsReading(self.pos_enu_m + fix.residual_enu_m, self.vel_enu_mps.copy(), fix.fix_type,
                          fix.satellites, fix.eph_m, fix.epv_m, fix.hdop, fix.vdop)

    def _select_fix(self) -> tuple[np.ndarray, float] | None:
        """(residual, eph) of a fresh usable position measurement, or None."""
        if self.uses_vision():
            v = self.vision
            if v is not None and not v.consumed and self.t_s - v.time_s < 0.5:
                v.consumed = True
                return v.residual_enu_m, v.eph_m
            if self.flavour == "ardupilot":
                return None
        # the first healthy instance in priority order is the only one used (ArduPilot's
        # primary GPS), never a blend of both: between its 5 Hz fixes nothing else is fused
        for inst in self._fix_instances():
            if inst == "real":
                r = self.last_gps
                if r is not None and r.fix_type >= M.GPS_FIX_TYPE_3D_FIX and r.satellites >= 6:
                    if not self._gps_fresh:
                        return np.full(3, np.nan), 0.0  # good source, no new sample this step
                    self._gps_fresh = False
                    return r.pos_enu_m - self.pos_enu_m, r.eph_m
            else:
                m = self.mav_gps
                if m is not None and m.fix_type >= M.GPS_FIX_TYPE_3D_FIX and self.t_s - m.time_s < 1.0:
                    if m.consumed:
                        return np.full(3, np.nan), 0.0  # good source, no new sample this step
                    m.consumed = True
                    return m.residual_enu_m, m.eph_m
        return None

    def position_source_ok_now(self) -> bool:
        """True when a position source currently delivers (used by arming and mode checks)."""
        if self.uses_vision() and self.vision is not None and self.t_s - self.vision.time_s < 0.5:
            return True
        for inst in self._fix_instances():
            if inst == "real":
                r = self.gps.read(self.t_s, self.pos_enu_m, self.vel_enu_mps)
                if r.fix_type >= M.GPS_FIX_TYPE_3D_FIX and r.satellites >= 6:
                    return True
            elif self.mav_gps is not None and self.mav_gps.fix_type >= M.GPS_FIX_TYPE_3D_FIX \
                    and self.t_s - self.mav_gps.time_s < 1.0:
                return True
        return False

    def _update_estimator(self, dt_s: float) -> None:
        if self.flavour == "px4":
            self.gps.disabled = bool(self.param("SIM_GPS_BLOCK"))
        elif "SIM_GPS1_ENABLE" in self.params:
            self.gps.disabled = not self.param("SIM_GPS1_ENABLE")
        else:
            self.gps.disabled = bool(self.param("SIM_GPS_DISABLE"))
        lat0 = math.radians(self.world.lat0_deg)
        glitch = "SIM_GPS1_GLTCH_" if "SIM_GPS1_GLTCH_X" in self.params else "SIM_GPS_GLITCH_"
        self.gps.glitch_enu_m = np.array([
            self.param(glitch + "Y") * math.pi / 180 * 6378137.0 * math.cos(lat0),
            self.param(glitch + "X") * math.pi / 180 * 6378137.0,
            self.param(glitch + "Z")])
        self.gps.step(dt_s)
        self._gps_fresh = False
        if self.t_s >= self._gps_next_s:  # receivers report at 5 Hz
            self._gps_next_s = self.t_s + 0.2
            self.last_gps = self.gps.read(self.t_s, self.pos_enu_m, self.vel_enu_mps)
            self._gps_fresh = True
        sel = self._select_fix()
        if sel is not None:
            residual, eph = sel
            self._last_position_fix_s = self.t_s
            if np.all(np.isfinite(residual)):
                tau_s = 0.3 + 0.1 * min(eph, 20.0)  # less accurate fixes are trusted more slowly
                gain = min(1.0, 0.2 / tau_s) if eph > 0 else 1.0
                self.est_err_enu_m[:2] += gain * (residual[:2] - self.est_err_enu_m[:2])
            if not self.position_ok:
                self.position_ok = True
                self.statustext("EKF3 IMU0 is using GPS" if self.flavour == "ardupilot"
                                else "Global position regained", 6)
                if self.ekf_origin is None:
                    self._set_origin_from_estimate()
            return
        # dead reckoning: the horizontal estimate drifts (IMU integration, no aiding)
        if not np.any(self._drift_dir):
            ang = self._rng.uniform(0, 2 * math.pi)
            self._drift_dir = np.array([math.cos(ang), math.sin(ang), 0.0])
        self.est_err_enu_m += 0.6 * self._drift_dir * dt_s
        if self.position_ok and self.t_s - self._last_position_fix_s > 3.0:
            self.position_ok = False
            self._drift_dir = np.zeros(3)
            self.statustext("EKF3 lost position aiding" if self.flavour == "ardupilot"
                            else "Global position lost", 4)
            if self.armed and not self.landed and self.behaviour in _NEEDS_POSITION:
                if self.flavour == "ardupilot":
                    self.statustext("EKF Failsafe: changed to LAND Mode", 2)
                    self._enter_mode("LAND")
                else:
                    self.statustext("Failsafe activated: no global position, landing", 2)
                    self._enter_mode("AUTO.LAND")

    def _set_origin_from_estimate(self) -> None:
        self.ekf_origin = self.geodetic(self.est_pos_enu_m)
        self.events.append(("origin",))

    # -------------------------------------------------------------- inputs
    def gps_input(self, lat_deg: float, lon_deg: float, alt_amsl_m: float, fix_type: int,
                  satellites: int, eph_m: float, epv_m: float, hdop: float = math.nan,
                  vdop: float = math.nan) -> bool:
        """A GPS_INPUT sample; returns False when the autopilot's settings ignore it."""
        if "mav" not in self._gps_instances():
            return False
        pos = self.enu_amsl(lat_deg, lon_deg, alt_amsl_m)
        self.mav_gps = _ExternalFix(pos - self.pos_enu_m, self.t_s, fix_type, satellites,
                                    max(eph_m, 0.01), max(epv_m, 0.01), lat_deg, lon_deg, alt_amsl_m,
                                    hdop=hdop, vdop=vdop)
        return True

    def vision_position(self, north_m: float, east_m: float, down_m: float, sigma_m: float) -> bool:
        """A vision position in local NED about the EKF origin; False when ignored."""
        if not self.uses_vision() or self.ekf_origin is None:
            return False
        origin = LocalFrame(*self.ekf_origin)
        lat, lon, alt = origin.to_geodetic(east_m, north_m, -down_m)
        pos = self.enu(float(lat), float(lon), float(alt))
        self.vision = _ExternalFix(pos - self.pos_enu_m, self.t_s, 3, 0, max(sigma_m, 0.01),
                                   max(sigma_m, 0.01))
        return True

    def set_origin(self, lat_deg: float, lon_deg: float, alt_amsl_m: float) -> None:
        self.ekf_origin = (lat_deg, lon_deg, alt_amsl_m + self.geoid_m)  # kept ellipsoidal
        self.events.append(("origin",))

    def local_ned_to_enu(self, north_m: float, east_m: float, down_m: float) -> np.ndarray:
        """Local NED about the EKF origin -> world ENU (exact, through geodetic)."""
        origin = LocalFrame(*(self.ekf_origin or self.geodetic(self.home_enu_m)))
        lat, lon, alt = origin.to_geodetic(east_m, north_m, -down_m)
        return self.enu(float(lat), float(lon), float(alt))

    def enu_to_local_ned(self, enu_m: np.ndarray) -> np.ndarray:
        origin = LocalFrame(*(self.ekf_origin or self.geodetic(self.home_enu_m)))
        lat, lon, alt = self.geodetic(enu_m)
        e, n, u = origin.to_enu(lat, lon, alt)
        return np.array([float(n), float(e), -float(u)])
