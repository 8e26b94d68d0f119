"""One simulated multirotor: point-mass physics, a toy EKF, flight modes and missions.

Positions are world ENU metres about the simulator's ``LocalFrame`` (origin height above
the WGS84 ellipsoid). Like a real autopilot, the MAVLink face reports altitudes above
mean sea level: AMSL = ellipsoidal height - ``geoid_m`` (the geoid undulation N, one
value for the whole small simulated world), so a client that mixes the two is off by N.
The autopilot flies on its *estimate* (``est_pos_enu_m``), never on the truth, so GPS
faults and injected positions move the real aircraft the way they would move a real one.
No MAVLink here: :mod:`skyfix.datasets.sim.server` maps messages onto this API.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from skyfix.datasets.sim.gps import GpsReading, GpsReceiver
from skyfix.datasets.sim.wind import WindField
from skyfix.drivers.mav import mavlink as M
from skyfix.drivers.modes import ARDUCOPTER_MODES, PX4_MODES
from skyfix.errors import InputError
from skyfix.geo import LocalFrame

G_MPS2 = 9.80665
FORCE_MAGIC = 21196  # param2 of MAV_CMD_COMPONENT_ARM_DISARM that bypasses checks


_BEHAVIOUR = {
    "ardupilot": {"GUIDED": "guided", "AUTO": "mission", "RTL": "rtl", "SMART_RTL": "rtl",
                  "LAND": "land", "LOITER": "hold", "POSHOLD": "hold", "BRAKE": "hold"},
    "px4": {"OFFBOARD": "guided", "AUTO.MISSION": "mission", "AUTO.RTL": "rtl",
            "AUTO.LAND": "land", "AUTO.LOITER": "hold", "POSCTL": "hold", "AUTO.READY": "hold",
            "AUTO.TAKEOFF": "takeoff"},
}
_NEEDS_POSITION = {"guided", "mission", "rtl", "hold", "takeoff"}

ARDUPILOT_PARAMS: dict[str, float] = {
    "SYSID_THISMAV": 1, "GPS1_TYPE": 1, "GPS2_TYPE": 0, "GPS_AUTO_SWITCH": 1, "GPS_PRIMARY": 0,
    "EK3_SRC1_POSXY": 3, "EK3_SRC1_VELXY": 3, "EK3_SRC1_POSZ": 1, "VISO_TYPE": 0,
    "EK3_SRC2_POSXY": 0, "EK3_SRC2_VELXY": 0, "EK3_SRC2_POSZ": 1, "EK3_SRC2_VELZ": 0, "EK3_SRC2_YAW": 0,
    "WPNAV_SPEED": 500, "WPNAV_SPEED_UP": 250, "WPNAV_SPEED_DN": 150, "WPNAV_RADIUS": 200,
    "RTL_ALT": 1500, "LAND_SPEED": 50, "DISARM_DELAY": 10, "FS_EKF_ACTION": 1,
    "BATT_CAPACITY": 5200, "BATT_LOW_MAH": 0, "ARMING_CHECK": 1,
    "SIM_GPS1_ENABLE": 1, "SIM_GPS1_GLTCH_X": 0, "SIM_GPS1_GLTCH_Y": 0, "SIM_GPS1_GLTCH_Z": 0,
    "SIM_WIND_SPD": 0, "SIM_WIND_DIR": 180,
}
#: Integer parameters (the rest are REAL32): ArduPilot sends them as floats (C cast),
#: PX4 copies the INT32's bytes into the float (byte-wise encoding).
INT_PARAMS: frozenset[str] = frozenset({
    "SYSID_THISMAV", "GPS1_TYPE", "GPS_TYPE", "GPS2_TYPE", "GPS_AUTO_SWITCH", "GPS_PRIMARY", "EK3_SRC1_POSXY",
    "EK3_SRC1_VELXY", "EK3_SRC1_POSZ", "VISO_TYPE", "EK3_SRC2_POSXY", "EK3_SRC2_VELXY", "EK3_SRC2_POSZ",
    "EK3_SRC2_VELZ", "EK3_SRC2_YAW", "RTL_ALT", "FS_EKF_ACTION", "BATT_CAPACITY",
    "ARMING_CHECK", "SIM_GPS1_ENABLE", "SIM_GPS_DISABLE", "DISARM_DELAY",
    "MAV_SYS_ID", "EKF2_GPS_CTRL", "EKF2_EV_CTRL", "EKF2_HGT_REF", "SIM_GPS_BLOCK"})
#: ArduPilot 4.6+ parameter names -> the names of earlier firmware (``legacy_params``).
#: SIM_GPS_DISABLE is the inverse of SIM_GPS1_ENABLE.
ARDUPILOT_LEGACY_NAMES: dict[str, str] = {
    "GPS1_TYPE": "GPS_TYPE", "SIM_GPS1_ENABLE": "SIM_GPS_DISABLE", "SIM_GPS1_GLTCH_X": "SIM_GPS_GLITCH_X",
    "SIM_GPS1_GLTCH_Y": "SIM_GPS_GLITCH_Y", "SIM_GPS1_GLTCH_Z": "SIM_GPS_GLITCH_Z",
}
PX4_PARAMS: dict[str, float] = {
    "MAV_SYS_ID": 1, "EKF2_GPS_CTRL": 7, "EKF2_EV_CTRL": 0, "EKF2_HGT_REF": 0,
    "MPC_XY_CRUISE": 5.0, "MPC_Z_V_AUTO_UP": 3.0, "MPC_Z_V_AUTO_DN": 1.5, "MPC_LAND_SPEED": 0.7,
    "NAV_ACC_RAD": 2.0, "RTL_RETURN_ALT": 30.0, "MIS_TAKEOFF_ALT": 2.5, "COM_OF_LOSS_T": 1.0,
    "COM_DISARM_PRFLT": 10.0, "BAT1_CAPACITY": 5200, "SIM_GPS_BLOCK": 0,
}


class Refusal(Exception):
    """The simulated autopilot refuses a request; ``result`` is a MAV_RESULT, ``text`` its STATUSTEXT."""

    def __init__(self, result: int, text: str) -> None:
        super().__init__(text)
        self.result = result
        self.text = text


@dataclass
class MissionItem:
    """A stored MISSION_ITEM_INT (x/y in degE7 for global frames, z metres)."""

    seq: int
    frame: int
    command: int
    param1: float = 0.0
    param2: float = 0.0
    param3: float = 0.0
    param4: float = 0.0
    x: int = 0
    y: int = 0
    z: float = 0.0
    autocontinue: int = 1


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


@dataclass
class SimVehicleConfig:
    """Static configuration of one simulated vehicle."""

    flavour: str = "ardupilot"
    system_id: int = 1
    start_enu_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    start_yaw_deg: float = 0.0
    max_speed_xy_mps: float = 15.0
    max_accel_mps2: float = 5.0
    max_tilt_deg: float = 35.0
    drag_per_s: float = 0.3
    hover_current_a: float = 18.0
    seed: int = 0
    params: dict[str, float] = field(default_factory=dict)
    legacy_params: bool = False  # ArduPilot: answer with the parameter names of firmware < 4.6
    geoid_m: float = 0.0  # geoid undulation N, m: AMSL = ellipsoidal height - N


class SimVehicle:
    """Physics + estimator + mode logic of one vehicle. Not thread-safe: one owner thread."""

    def __init__(self, config: SimVehicleConfig, world: LocalFrame, wind: WindField) -> None:
        self.config = config
        self.flavour = config.flavour
        self.world = world
        self.wind = wind
        self.params: dict[str, float] = dict(PX4_PARAMS if self.flavour == "px4" else ARDUPILOT_PARAMS)
        if self.flavour == "ardupilot" and config.legacy_params:
            self.params = {ARDUPILOT_LEGACY_NAMES.get(k, k): v for k, v in self.params.items()}
            self.params["SIM_GPS_DISABLE"] = 0
        self.params["MAV_SYS_ID" if self.flavour == "px4" else "SYSID_THISMAV"] = config.system_id
        unknown = sorted(set(config.params) - set(self.params))
        if unknown:  # a typo would otherwise be kept and never read
            raise InputError(f"unknown {self.flavour} parameter(s) {', '.join(unknown)}; the simulator "
                             f"knows {', '.join(sorted(self.params))}")
        self.params.update(config.params)
        self.ekf_source_set = 1  # ArduPilot EK3_SRCn_* set in use (MAV_CMD_SET_EKF_SOURCE_SET)
        self.t_s = 0.0
        self.pos_enu_m = np.array(config.start_enu_m, dtype=float)
        self.ground_up_m = float(self.pos_enu_m[2])
        self.vel_enu_mps = np.zeros(3)
        self.yaw_deg = float(config.start_yaw_deg)
        self.roll_deg = 0.0
        self.pitch_deg = 0.0
        self._vel_integral = np.zeros(3)
        self.est_err_enu_m = np.zeros(3)
        self.gps = GpsReceiver(seed=config.seed)
        self.last_gps: GpsReading | None = None
        self._gps_next_s = 0.0
        self.mav_gps: _ExternalFix | None = None
        self.vision: _ExternalFix | None = None
        self._last_position_fix_s = 0.0
        self.position_ok = True
        self._rng = np.random.default_rng(config.seed + 1000)
        self._drift_dir = np.zeros(3)
        self.armed = False
        self.landed = True
        self._landed_since_s = 0.0
        self._armed_at_s = 0.0
        self.mode = "STABILIZE" if self.flavour == "ardupilot" else "AUTO.LOITER"
        self.home_enu_m = self.pos_enu_m.copy()
        self.home_set = False
        self.ekf_origin: tuple[float, float, float] | None = None
        self.battery_used_mah = 0.0
        self.battery_current_a = 0.0
        self.target_pos_enu_m: np.ndarray | None = None
        self.target_vel_enu_mps: np.ndarray | None = None
        self._target_vel_time_s = -math.inf
        self._offboard_setpoint_s = -math.inf
        self._takeoff_alt_up_m: float | None = None
        self._hold_enu_m: np.ndarray | None = None
        self._rtl_phase = ""
        self._rtl_up_m: float | None = None
        self._land_xy: np.ndarray | None = None
        self.speed_override_mps: float | None = None
        self.mission: list[MissionItem] = []
        self.mission_seq = 0
        self._mission_item_started = False
        self._loiter_until_s = 0.0
        self.cam_trigger_dist_m = 0.0
        self._cam_dist_acc_m = 0.0
        self.cam_trigger_count = 0
        #: outgoing events for the MAVLink layer: ("statustext", sev, text), ("reached", seq),
        #: ("current", seq), ("camera", n), ("home",), ("origin",), ("mode",)
        self.events: deque[tuple] = deque()
        if self.position_source_ok_now():  # like ArduPilot: home and origin at the first fix
            self._set_origin_from_estimate()
            self.home_set = True

    # ----------------------------------------------------------------- helpers
    @property
    def behaviour(self) -> str:
        return _BEHAVIOUR[self.flavour].get(self.mode, "manual")

    @property
    def est_pos_enu_m(self) -> np.ndarray:
        return self.pos_enu_m + self.est_err_enu_m

    def param(self, name: str) -> float:
        return float(self.params.get(name, 0.0))

    def statustext(self, text: str, severity: int = 6) -> None:
        self.events.append(("statustext", severity, text))

    def altitude_rel_m(self) -> float:
        """Estimated height above home, metres."""
        return float(self.est_pos_enu_m[2] - self.home_enu_m[2])

    def geodetic(self, enu_m: np.ndarray) -> tuple[float, float, float]:
        lat, lon, alt = self.world.to_geodetic(enu_m[0], enu_m[1], enu_m[2])
        return float(lat), float(lon), float(alt)

    def enu(self, lat_deg: float, lon_deg: float, alt_m: float) -> np.ndarray:
        return np.array([float(v) for v in self.world.to_enu(lat_deg, lon_deg, alt_m)])

    @property
    def geoid_m(self) -> float:
        return float(self.config.geoid_m)

    def geodetic_amsl(self, enu_m: np.ndarray) -> tuple[float, float, float]:
        """(lat_deg, lon_deg, alt_amsl_m) of a world ENU point: what MAVLink reports."""
        lat, lon, h = self.geodetic(enu_m)
        return lat, lon, h - self.geoid_m

    def enu_amsl(self, lat_deg: float, lon_deg: float, alt_amsl_m: float) -> np.ndarray:
        """World ENU of a MAVLink (lat, lon, AMSL altitude)."""
        return self.enu(lat_deg, lon_deg, alt_amsl_m + self.geoid_m)

    def global_target_enu(self, frame: int, lat_deg: float, lon_deg: float, z_m: float) -> np.ndarray:
        """World ENU of a global (lat, lon, z) in a MAV_FRAME (AMSL or relative to home)."""
        if frame in (M.MAV_FRAME_GLOBAL, M.MAV_FRAME_GLOBAL_INT):
            alt = z_m + self.geoid_m
        else:
            alt = self.home_enu_m[2] + self.world.alt0_m + z_m
        return self.enu(lat_deg, lon_deg, alt)

    def cruise_speed_mps(self) -> float:
        if self.speed_override_mps:
            return self.speed_override_mps
        if self.flavour == "px4":
            return self.param("MPC_XY_CRUISE")
        return self.param("WPNAV_SPEED") / 100.0

    def climb_speeds_mps(self) -> tuple[float, float]:
        if self.flavour == "px4":
            return self.param("MPC_Z_V_AUTO_UP"), self.param("MPC_Z_V_AUTO_DN")
        return self.param("WPNAV_SPEED_UP") / 100.0, self.param("WPNAV_SPEED_DN") / 100.0

    def land_speed_mps(self) -> float:
        return self.param("MPC_LAND_SPEED") if self.flavour == "px4" else self.param("LAND_SPEED") / 100.0

    def _descent_speed_mps(self) -> float:
        """Landing descent: the auto descent speed high up, the landing speed in the last 10 m."""
        return self.climb_speeds_mps()[1] if self.altitude_rel_m() > 10.0 else self.land_speed_mps()

    def acceptance_radius_m(self) -> float:
        return self.param("NAV_ACC_RAD") if self.flavour == "px4" else self.param("WPNAV_RADIUS") / 100.0

    def battery_capacity_mah(self) -> float:
        return self.param("BAT1_CAPACITY" if self.flavour == "px4" else "BATT_CAPACITY")

    def battery_remaining_pct(self) -> float:
        return max(0.0, 100.0 * (1.0 - self.battery_used_mah / max(self.battery_capacity_mah(), 1.0)))

    def battery_voltage_v(self) -> float:
        soc = self.battery_remaining_pct() / 100.0
        return 4 * (3.5 + 0.7 * soc) - 0.012 * self.battery_current_a

    # --------------------------------------------------------- position sources
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

    # ------------------------------------------------------------- commands
    def arm(self, force: bool = False) -> None:
        if self.armed:
            return
        if not force:
            if self.flavour == "ardupilot" and self.mode in ("AUTO", "RTL", "LAND"):
                raise Refusal(M.MAV_RESULT_FAILED, f"Arm: Mode not armable ({self.mode})")
            if self.behaviour in _NEEDS_POSITION or self.mode == "STABILIZE":
                if not self.position_source_ok_now():
                    raise Refusal(M.MAV_RESULT_FAILED, "PreArm: Need Position Estimate"
                                  if self.flavour == "ardupilot"
                                  else "Preflight Fail: No valid global position")
            if self.battery_remaining_pct() < 10.0:
                raise Refusal(M.MAV_RESULT_FAILED, "PreArm: Battery below minimum arming capacity")
        self.armed = True
        self._armed_at_s = self.t_s
        self.home_enu_m = self.est_pos_enu_m.copy()
        self.home_set = True
        self.events.append(("home",))
        self.statustext("Arming motors" if self.flavour == "ardupilot" else "Armed by external command")

    def disarm(self, force: bool = False) -> None:
        if not self.armed:
            return
        if not self.landed and not force:
            raise Refusal(M.MAV_RESULT_FAILED, "Disarm: vehicle is flying" if self.flavour == "ardupilot"
                          else "Disarming denied: not landed")
        self._disarm()

    def _disarm(self) -> None:
        self.armed = False
        self._takeoff_alt_up_m = None
        self.statustext("Disarming motors" if self.flavour == "ardupilot" else "Disarmed")

    def set_mode(self, name: str) -> None:
        table = PX4_MODES if self.flavour == "px4" else ARDUCOPTER_MODES
        if name not in table:
            raise Refusal(M.MAV_RESULT_DENIED, f"Unknown mode {name}")
        behaviour = _BEHAVIOUR[self.flavour].get(name, "manual")
        if behaviour in _NEEDS_POSITION and not self.position_ok:
            raise Refusal(M.MAV_RESULT_FAILED, f"Flight mode change failed: {name} requires position")
        if behaviour == "mission" and self._first_mission_index() >= len(self.mission):
            raise Refusal(M.MAV_RESULT_FAILED, f"Mode change to {name} failed: no mission")
        if name == "OFFBOARD" and self.t_s - self._offboard_setpoint_s > 0.5:
            raise Refusal(M.MAV_RESULT_DENIED, "Switching to Offboard failed: no offboard setpoints")
        if name == "AUTO.TAKEOFF" and not self.armed:
            raise Refusal(M.MAV_RESULT_DENIED, "Takeoff denied: disarmed")
        self._enter_mode(name)

    def _enter_mode(self, name: str) -> None:
        self.mode = name
        self._hold_enu_m = self.est_pos_enu_m.copy()
        self.target_pos_enu_m = None
        self.target_vel_enu_mps = None
        self._rtl_phase = "climb"
        self._rtl_up_m = None
        self._land_xy = self.est_pos_enu_m[:2].copy()
        if name == "AUTO.TAKEOFF" and self._takeoff_alt_up_m is None:
            self._takeoff_alt_up_m = self.home_enu_m[2] + self.param("MIS_TAKEOFF_ALT")
        if self.behaviour == "mission":
            if self.mission_seq < self._first_mission_index() or self.mission_seq >= len(self.mission):
                self.mission_seq = self._first_mission_index()
            self._mission_item_started = False
            self.events.append(("current", self.mission_seq))
        self.events.append(("mode",))

    def takeoff(self, alt_up_world_m: float) -> None:
        """Climb to a world ENU up-coordinate (the MAVLink layer converts the frames)."""
        if not self.armed:
            raise Refusal(M.MAV_RESULT_FAILED, "Takeoff: vehicle not armed")
        if self.flavour == "ardupilot":
            if self.mode != "GUIDED":
                raise Refusal(M.MAV_RESULT_FAILED, f"Takeoff: not in GUIDED mode ({self.mode})")
            if not self.landed:
                raise Refusal(M.MAV_RESULT_FAILED, "Takeoff: already flying")
            self._takeoff_alt_up_m = alt_up_world_m
            self.target_pos_enu_m = np.array([*self.est_pos_enu_m[:2], alt_up_world_m])
        else:
            self._takeoff_alt_up_m = alt_up_world_m
            self._enter_mode("AUTO.TAKEOFF")
            self._takeoff_alt_up_m = alt_up_world_m

    def position_target(self, pos_enu_m: np.ndarray | None, vel_enu_mps: np.ndarray | None) -> bool:
        """A guided/offboard setpoint; returns False when the current mode ignores it."""
        self._offboard_setpoint_s = self.t_s
        if self.behaviour != "guided" or (self.flavour == "ardupilot" and not self.armed):
            return self.flavour == "px4"  # PX4 buffers setpoints before OFFBOARD
        if pos_enu_m is not None:
            self.target_pos_enu_m = pos_enu_m.copy()
            self.target_vel_enu_mps = None
            self._takeoff_alt_up_m = None
        elif vel_enu_mps is not None:
            self.target_vel_enu_mps = vel_enu_mps.copy()
            self._target_vel_time_s = self.t_s
        return True

    def set_mission(self, items: list[MissionItem]) -> None:
        self.mission = list(items)
        self.mission_seq = self._first_mission_index()
        self._mission_item_started = False

    def set_mission_current(self, seq: int) -> None:
        if 0 <= seq < len(self.mission):
            self.mission_seq = max(seq, self._first_mission_index())
            self._mission_item_started = False
            self.events.append(("current", self.mission_seq))

    def _first_mission_index(self) -> int:
        return 1 if self.flavour == "ardupilot" else 0  # ArduPilot's item 0 is home

    # ------------------------------------------------------------- dynamics
    def step(self, dt_s: float) -> None:
        """Advance the vehicle by ``dt_s`` seconds of simulated time."""
        self.t_s += dt_s
        self._update_estimator(dt_s)
        v_cmd = self._guidance() if self.armed else np.zeros(3)
        self._physics(dt_s, v_cmd)
        self._housekeeping(dt_s)

    def _pos_control(self, target: np.ndarray, speed_mps: float | None = None) -> np.ndarray:
        """Velocity command towards ``target`` (estimated frame), speed-limited with braking."""
        err = target - self.est_pos_enu_m
        speed = min(speed_mps or self.cruise_speed_mps(), self.config.max_speed_xy_mps)
        d_xy = float(np.hypot(err[0], err[1]))
        v = np.zeros(3)
        if d_xy > 1e-6:
            mag = min(speed, math.sqrt(2 * 0.5 * self.config.max_accel_mps2 * d_xy), 1.2 * d_xy)
            v[:2] = err[:2] / d_xy * mag
        up, down = self.climb_speeds_mps()
        v[2] = float(np.clip(1.2 * err[2], -down, up))
        return v

    def _guidance(self) -> np.ndarray:
        b = self.behaviour
        est = self.est_pos_enu_m
        if self.landed and b not in ("takeoff", "mission", "guided") and self._takeoff_alt_up_m is None:
            return np.zeros(3)
        if b == "land" or (b == "rtl" and self._rtl_phase == "land"):
            v = self._pos_control(np.array([*self._land_xy, est[2]]))
            v[2] = -self._descent_speed_mps()
            return v
        if b == "rtl":
            rtl_up = self.home_enu_m[2] + (self.param("RTL_RETURN_ALT") if self.flavour == "px4"
                                           else self.param("RTL_ALT") / 100.0)
            cruise_up = max(rtl_up, est[2])
            if self._rtl_phase == "climb":
                if est[2] >= rtl_up - 0.5:
                    self._rtl_phase = "return"
                    self._rtl_up_m = cruise_up
                return self._pos_control(np.array([*est[:2], rtl_up]))
            target = np.array([*self.home_enu_m[:2], self._rtl_up_m or cruise_up])
            if np.hypot(*(target[:2] - est[:2])) < 1.0:
                self._rtl_phase = "land"
                self._land_xy = self.home_enu_m[:2].copy()
            return self._pos_control(target)
        if b == "takeoff" or (self._takeoff_alt_up_m is not None and b == "guided"):
            goal = self._takeoff_alt_up_m if self._takeoff_alt_up_m is not None else est[2]
            xy = self._hold_enu_m[:2] if self._hold_enu_m is not None else est[:2]
            if est[2] >= goal - 0.3:
                self._takeoff_alt_up_m = None
                if b == "takeoff":
                    self._enter_mode("AUTO.LOITER")
                else:
                    self.target_pos_enu_m = np.array([*est[:2], goal])
            return self._pos_control(np.array([*xy, goal]))
        if b == "guided":
            if self.target_vel_enu_mps is not None:
                timeout = self.param("COM_OF_LOSS_T") if self.flavour == "px4" else 3.0
                if self.t_s - self._target_vel_time_s <= timeout:
                    return self.target_vel_enu_mps.copy()
                self.target_vel_enu_mps = None
                self.target_pos_enu_m = est.copy()
            if self.flavour == "px4" and self.t_s - self._offboard_setpoint_s > self.param("COM_OF_LOSS_T"):
                self.statustext("Failsafe activated: offboard signal lost, holding", 4)
                self._enter_mode("AUTO.LOITER")
                return np.zeros(3)
            if self.target_pos_enu_m is None:
                self.target_pos_enu_m = est.copy()
            return self._pos_control(self.target_pos_enu_m)
        if b == "hold":
            return self._pos_control(self._hold_enu_m if self._hold_enu_m is not None else est)
        if b == "mission":
            return self._mission_guidance()
        return np.array([0.0, 0.0, 0.0])  # manual modes hover in place (sticks centred)

    def _mission_guidance(self) -> np.ndarray:
        est = self.est_pos_enu_m
        while self.mission_seq < len(self.mission):
            item = self.mission[self.mission_seq]
            if item.command == M.MAV_CMD_DO_CHANGE_SPEED:
                self.speed_override_mps = item.param2 if item.param2 > 0 else None
            elif item.command == M.MAV_CMD_DO_SET_CAM_TRIGG_DIST:
                self.cam_trigger_dist_m = max(0.0, item.param1)
                self._cam_dist_acc_m = 0.0
            else:
                break
            self._advance_mission()
        if self.mission_seq >= len(self.mission):
            if self.flavour == "px4":
                self._enter_mode("AUTO.LOITER")
            return self._pos_control(self._hold_enu_m if self._hold_enu_m is not None else est)
        item = self.mission[self.mission_seq]
        if not self._mission_item_started:
            self._mission_item_started = True
            self._hold_enu_m = est.copy()
            self._loiter_until_s = math.inf
            if item.command in (M.MAV_CMD_NAV_RETURN_TO_LAUNCH, M.MAV_CMD_NAV_LAND):
                self._land_xy = est[:2].copy()
                if item.command == M.MAV_CMD_NAV_LAND and (item.x or item.y):
                    self._land_xy = self.global_target_enu(item.frame, item.x / 1e7, item.y / 1e7, 0.0)[:2]
                self._rtl_phase = "climb"
        if item.command == M.MAV_CMD_NAV_TAKEOFF:
            goal = self.home_enu_m[2] + item.z if item.frame != M.MAV_FRAME_GLOBAL_INT else \
                item.z + self.geoid_m - self.world.alt0_m
            if self.landed and not self.armed:
                return np.zeros(3)
            if est[2] >= goal - 0.3:
                self._advance_mission()
            return self._pos_control(np.array([*self._hold_enu_m[:2], goal]))
        if item.command in (M.MAV_CMD_NAV_WAYPOINT, M.MAV_CMD_NAV_LOITER_TIME):
            target = self.global_target_enu(item.frame, item.x / 1e7, item.y / 1e7, item.z) \
                if (item.x or item.y) else np.array([*est[:2], self.home_enu_m[2] + item.z])
            radius = item.param2 if item.command == M.MAV_CMD_NAV_WAYPOINT and item.param2 > 0 \
                else self.acceptance_radius_m()
            hold_s = item.param1
            if math.isinf(self._loiter_until_s):
                if np.hypot(*(target[:2] - est[:2])) < radius and abs(target[2] - est[2]) < 1.0:
                    self._loiter_until_s = self.t_s + max(0.0, hold_s)
            elif self.t_s >= self._loiter_until_s:
                self._advance_mission()
            return self._pos_control(target)
        if item.command == M.MAV_CMD_NAV_LAND:
            v = self._pos_control(np.array([*self._land_xy, est[2]]))
            v[2] = -self._descent_speed_mps()
            return v
        if item.command == M.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            self._enter_mode("AUTO.RTL" if self.flavour == "px4" else "RTL")
            return np.zeros(3)
        self.statustext(f"Mission: skipping unsupported command {item.command}", 4)
        self._advance_mission()
        return np.zeros(3)

    def _advance_mission(self) -> None:
        self.events.append(("reached", self.mission_seq))
        self.mission_seq += 1
        self._mission_item_started = False
        if self.mission_seq < len(self.mission):
            self.events.append(("current", self.mission_seq))
        else:  # mission complete: hold where the last item left the vehicle
            self._hold_enu_m = self.est_pos_enu_m.copy()

    def _physics(self, dt_s: float, v_cmd: np.ndarray) -> None:
        cfg = self.config
        wind = self.wind.at(self.pos_enu_m)
        motors = self.armed and not (self.landed and v_cmd[2] <= 0.0)
        if not motors:
            self.vel_enu_mps[:] = 0.0
            self._vel_integral[:] = 0.0
            self.roll_deg = self.pitch_deg = 0.0
            self.pos_enu_m[2] = self.ground_up_m
            return
        drag = cfg.drag_per_s * (wind - self.vel_enu_mps)
        drag[2] = 0.0
        err = v_cmd - self.vel_enu_mps
        a_ctrl = 4.0 * err + self._vel_integral
        a_xy = float(np.hypot(a_ctrl[0], a_ctrl[1]))
        a_lim = min(cfg.max_accel_mps2, G_MPS2 * math.tan(math.radians(cfg.max_tilt_deg)))
        if a_xy > a_lim:
            a_ctrl[:2] *= a_lim / a_xy
        else:  # integrate only when not saturated (anti-windup)
            self._vel_integral = np.clip(self._vel_integral + 1.5 * err * dt_s, -3.0, 3.0)
        a_ctrl[2] = float(np.clip(a_ctrl[2], -4.0, 4.0))
        self.vel_enu_mps += (a_ctrl + drag) * dt_s
        self.pos_enu_m += self.vel_enu_mps * dt_s
        if self.pos_enu_m[2] <= self.ground_up_m:
            self.pos_enu_m[2] = self.ground_up_m
            self.vel_enu_mps[2] = max(0.0, self.vel_enu_mps[2])
        # attitude: the rotor thrust tilts to produce the horizontal force the controller asks for
        a_body = a_ctrl  # the rotors' horizontal force; drag acts on the airframe separately
        yaw = math.radians(self.yaw_deg)
        fwd = a_body[0] * math.sin(yaw) + a_body[1] * math.cos(yaw)
        right = a_body[0] * math.cos(yaw) - a_body[1] * math.sin(yaw)
        self.pitch_deg = -math.degrees(math.atan2(fwd, G_MPS2))
        self.roll_deg = math.degrees(math.atan2(right, G_MPS2))
        speed_xy = float(np.hypot(v_cmd[0], v_cmd[1]))
        if speed_xy > 1.0:  # nose into the direction of travel, 90 deg/s
            want = math.degrees(math.atan2(v_cmd[0], v_cmd[1]))
            diff = (want - self.yaw_deg + 180.0) % 360.0 - 180.0
            self.yaw_deg = (self.yaw_deg + float(np.clip(diff, -90 * dt_s, 90 * dt_s))) % 360.0

    def _housekeeping(self, dt_s: float) -> None:
        on_ground = self.pos_enu_m[2] <= self.ground_up_m + 0.05 and self.vel_enu_mps[2] <= 0.05
        if on_ground and not self.landed:
            self.landed = True
            self._landed_since_s = self.t_s
            self.statustext("Landed" if self.flavour == "px4" else "Land complete", 6)
        elif not on_ground and self.landed and self.pos_enu_m[2] > self.ground_up_m + 0.2:
            self.landed = False
        if self.landed:
            self.est_err_enu_m[2] = 0.0
        if self.armed:
            speed = float(np.linalg.norm(self.vel_enu_mps))
            self.battery_current_a = 1.0 if self.landed else self.config.hover_current_a + 1.2 * speed
            landing = self.behaviour == "land" or self._rtl_phase == "land" or (
                self.behaviour == "mission" and self.mission_seq < len(self.mission)
                and self.mission[self.mission_seq].command == M.MAV_CMD_NAV_LAND)
            if self.landed and landing and self.t_s - self._landed_since_s > 1.0:
                self._disarm()
                if self.behaviour == "mission":
                    self._advance_mission()
            delay = self.param("COM_DISARM_PRFLT" if self.flavour == "px4" else "DISARM_DELAY")
            if self.landed and delay > 0 and self.t_s - max(self._armed_at_s, self._landed_since_s) > delay \
                    and self._takeoff_alt_up_m is None and self.armed and not landing:
                self.statustext("Disarming: not flown", 6)
                self._disarm()
        else:
            self.battery_current_a = 0.3
        self.battery_used_mah += self.battery_current_a * dt_s / 3.6
        if self.armed and not self.landed and self.battery_remaining_pct() < 10.0 \
                and self.behaviour not in ("rtl", "land"):
            self.statustext("Battery failsafe: returning home", 2)
            self._enter_mode("AUTO.RTL" if self.flavour == "px4" else "RTL")
        if self.cam_trigger_dist_m > 0 and self.armed and not self.landed:
            self._cam_dist_acc_m += float(np.hypot(*self.vel_enu_mps[:2])) * dt_s
            if self._cam_dist_acc_m >= self.cam_trigger_dist_m:
                self._cam_dist_acc_m -= self.cam_trigger_dist_m
                self.cam_trigger_count += 1
                self.events.append(("camera", self.cam_trigger_count))
