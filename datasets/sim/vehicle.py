"""One simulated multirotor: point-mass physics, a toy EKF, flight modes and missions.

Positions are world ENU metres about the simulator's ``LocalFrame`` (origin height above
the WGS84 ellipsoid). Like a real autopilot, the MAVLink face reports altitudes above
mean sea level: AMSL = ellipsoidal height - ``geoid_m`` (the geoid undulation N, one
value for the whole small simulated world), so a client that mixes the two is off by N.
The autopilot flies on its *estimate* (``est_pos_enu_m``), never on the truth, so GPS
faults and injected positions move the real aircraft the way they would move a real one.
No MAVLink here: :mod:`skyfix.datasets.sim.server` maps messages onto this API.
The position estimate and its sources live in :mod:`~skyfix.datasets.sim.estimator`, the
per-behaviour guidance in :mod:`~skyfix.datasets.sim.guidance`; modes, commands, physics here.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from skyfix.datasets.sim.estimator import _NEEDS_POSITION, PositionEstimator, _ExternalFix
from skyfix.datasets.sim.gps import GpsReading, GpsReceiver
from skyfix.datasets.sim.guidance import Guidance
from skyfix.datasets.sim.wind import WindField
from skyfix.drivers.mav import mavlink as M
from skyfix.drivers.modes import ARDUCOPTER_MODES, PX4_MODES
from skyfix.errors import InputError
from skyfix.geo import LocalFrame
from skyfix.mission import MissionItem

G_MPS2 = 9.80665
FORCE_MAGIC = 21196  # param2 of MAV_CMD_COMPONENT_ARM_DISARM that bypasses checks


_BEHAVIOUR = {
    "ardupilot": {"GUIDED": "guided", "AUTO": "mission", "RTL": "rtl", "SMART_RTL": "rtl",
                  "LAND": "land", "LOITER": "hold", "POSHOLD": "hold", "BRAKE": "hold"},
    "px4": {"OFFBOARD": "guided", "AUTO.MISSION": "mission", "AUTO.RTL": "rtl",
            "AUTO.LAND": "land", "AUTO.LOITER": "hold", "POSCTL": "hold", "AUTO.READY": "hold",
            "AUTO.TAKEOFF": "takeoff"},
}

ARDUPILOT_PARAMS: dict[str, float] = {
    "SYSID_THISMAV": 1, "GPS1_TYPE": 1, "GPS2_TYPE": 0, "GPS_AUTO_SWITCH": 1, "GPS_PRIMARY": 0,
    "EK3_SRC1_POSXY": 3, "EK3_SRC1_VELXY": 3, "EK3_SRC1_POSZ": 1, "VISO_TYPE": 0,
    "EK3_SRC2_POSXY": 0, "EK3_SRC2_VELXY": 0, "EK3_SRC2_POSZ": 1, "EK3_SRC2_VELZ": 0, "EK3_SRC2_YAW": 0,
    "WPNAV_SPEED": 500, "WPNAV_SPEED_UP": 250, "WPNAV_SPEED_DN": 150, "WPNAV_RADIUS": 200,
    "RTL_ALT": 1500, "RTL_SPEED": 0, "LAND_SPEED": 50, "DISARM_DELAY": 10, "FS_EKF_ACTION": 1, "MIS_RESTART": 0,
    "BATT_CAPACITY": 5200, "BATT_LOW_MAH": 0, "ARMING_CHECK": 1,
    "SIM_GPS1_ENABLE": 1, "SIM_GPS1_GLTCH_X": 0, "SIM_GPS1_GLTCH_Y": 0, "SIM_GPS1_GLTCH_Z": 0,
    "SIM_WIND_SPD": 0, "SIM_WIND_DIR": 180,
}
#: Integer parameters (the rest are REAL32): ArduPilot sends them as floats (C cast),
#: PX4 copies the INT32's bytes into the float (byte-wise encoding).
INT_PARAMS: frozenset[str] = frozenset({
    "SYSID_THISMAV", "GPS1_TYPE", "GPS_TYPE", "GPS2_TYPE", "GPS_AUTO_SWITCH", "GPS_PRIMARY", "EK3_SRC1_POSXY",
    "EK3_SRC1_VELXY", "EK3_SRC1_POSZ", "VISO_TYPE", "EK3_SRC2_POSXY", "EK3_SRC2_VELXY", "EK3_SRC2_POSZ",
    "EK3_SRC2_VELZ", "EK3_SRC2_YAW", "RTL_ALT", "RTL_SPEED", "FS_EKF_ACTION", "BATT_CAPACITY",
    "ARMING_CHECK", "SIM_GPS1_ENABLE", "SIM_GPS_DISABLE", "DISARM_DELAY", "MIS_RESTART",
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


class SimVehicle(PositionEstimator, Guidance):
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

    def rtl_speed_mps(self) -> float | None:
        """ArduPilot's RTL_SPEED (cm/s; 0: the cruise speed) in m/s, None for the cruise speed (PX4: always)."""
        if self.flavour == "px4" or "RTL_SPEED" not in self.params:
            return None
        cms = self.param("RTL_SPEED")
        return cms / 100.0 if cms > 0 else None

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
            # ArduPilot's AP_Mission::start_or_resume: MIS_RESTART 1 starts the mission over, 0 resumes its current item
            restart = self.flavour == "ardupilot" and self.param("MIS_RESTART") == 1
            if restart or self.mission_seq < self._first_mission_index() or self.mission_seq >= len(self.mission):
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
