"""The simulated autopilot's telemetry: one MAVLink message built from the vehicle's state
per ``_msg_<name>`` method, in the units and frames ArduPilot and PX4 send (altitudes AMSL,
``geoid_m`` below the ellipsoid; accuracies in mm; DOPs x 100).

Mixed into :class:`skyfix.datasets.sim.server.VehicleServer` (``self.vehicle`` is the
:class:`~skyfix.datasets.sim.vehicle.SimVehicle`); the server streams them by name.
"""

from __future__ import annotations

import logging
import math
import time

import numpy as np

from skyfix.drivers.mav import mavlink
from skyfix.drivers.modes import custom_mode_of

log = logging.getLogger("skyfix.datasets.sim.server")  # the server's logger: one name for its story
M = mavlink


def _dop_x100(dop: float) -> int:
    """A DOP as GPS_RAW_INT carries it: x 100, 65535 when unknown."""
    return min(int(round(dop * 100)), 65534) if math.isfinite(dop) else 65535


class TelemetryMessages:
    """``_msg_<message name>()`` -> the message now (reads ``self.vehicle``)."""

    def _base_mode(self) -> int:
        base = M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | M.MAV_MODE_FLAG_STABILIZE_ENABLED
        if self.vehicle.behaviour in ("guided", "mission", "rtl", "land", "hold", "takeoff"):
            base |= M.MAV_MODE_FLAG_GUIDED_ENABLED
        if self.vehicle.armed:
            base |= M.MAV_MODE_FLAG_SAFETY_ARMED
        return base

    def _msg_heartbeat(self):
        v = self.vehicle
        autopilot = M.MAV_AUTOPILOT_PX4 if v.flavour == "px4" else M.MAV_AUTOPILOT_ARDUPILOTMEGA
        status = M.MAV_STATE_ACTIVE if v.armed else M.MAV_STATE_STANDBY
        return M.MAVLink_heartbeat_message(M.MAV_TYPE_QUADROTOR, autopilot, self._base_mode(),
                                           custom_mode_of(v.flavour, v.mode), status, 3)

    def _boot_ms(self) -> int:
        return int(self.vehicle.t_s * 1000) & 0xFFFFFFFF

    def _msg_global_position_int(self):
        v = self.vehicle
        est = v.est_pos_enu_m
        lat, lon, alt = v.geodetic_amsl(est)
        rel = v.altitude_rel_m()
        vel = v.vel_enu_mps
        self.log.append((time.monotonic(), "position", (lat, lon, rel)))
        return M.MAVLink_global_position_int_message(
            self._boot_ms(), int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000)),
            int(round(rel * 1000)), int(round(vel[1] * 100)), int(round(vel[0] * 100)),
            int(round(-vel[2] * 100)), int(round(v.yaw_deg * 100)) % 36000)

    def _msg_local_position_ned(self):
        v = self.vehicle
        ned = v.enu_to_local_ned(v.est_pos_enu_m)
        vel = v.vel_enu_mps
        return M.MAVLink_local_position_ned_message(self._boot_ms(), *ned, vel[1], vel[0], -vel[2])

    def _msg_attitude(self):
        v = self.vehicle
        yaw = math.radians(((v.yaw_deg + 180.0) % 360.0) - 180.0)
        return M.MAVLink_attitude_message(self._boot_ms(), math.radians(v.roll_deg),
                                          math.radians(v.pitch_deg), yaw, 0.0, 0.0, 0.0)

    def _msg_gps_raw_int(self):
        v = self.vehicle
        r = v.gps_report()
        if r is None or r.fix_type < M.GPS_FIX_TYPE_2D_FIX or not np.all(np.isfinite(r.pos_enu_m)):
            return M.MAVLink_gps_raw_int_message(int(v.t_s * 1e6), 1 if r else 0, 0, 0, 0, 65535,
                                                 65535, 65535, 65535, 0, 0, 0, 0, 0, 0, 0)
        lat, lon, alt_ell = v.geodetic(r.pos_enu_m)
        speed = float(np.hypot(*r.vel_enu_mps[:2]))
        cog = (math.degrees(math.atan2(r.vel_enu_mps[0], r.vel_enu_mps[1])) + 360.0) % 360.0
        # as autopilots encode it: alt AMSL, eph/epv = DOP x 100 (unitless), h_acc/v_acc in mm,
        # alt_ellipsoid above WGS84 (mm)
        return M.MAVLink_gps_raw_int_message(
            int(v.t_s * 1e6), r.fix_type, int(round(lat * 1e7)), int(round(lon * 1e7)),
            int(round((alt_ell - v.geoid_m) * 1000)), _dop_x100(r.hdop), _dop_x100(r.vdop), int(speed * 100), int(cog * 100), r.satellites,
            int(round(alt_ell * 1000)), int(round(r.eph_m * 1000)), int(round(r.epv_m * 1000)), 100, 0, 0)

    def _msg_ekf_status_report(self):
        """ArduPilot's EKF verdict as Copter 4.7 SITL reports it: 831 (attitude, velocities,
        relative and absolute position, predicted positions) when healthy; 37 (attitude,
        vertical velocity, absolute height) once it has lost its horizontal position source,
        with no position innovations left to test (ratio 0)."""
        v = self.vehicle
        if v.flavour != "ardupilot":
            return None
        ok = v.position_ok
        ratio = 0.05 if ok else 0.0
        return M.MAVLink_ekf_status_report_message(831 if ok else 37, ratio, ratio, 0.01, 0.05, 0.0, 0.0)

    def _msg_sys_status(self):
        v = self.vehicle
        sensors = (M.MAV_SYS_STATUS_SENSOR_3D_GYRO | M.MAV_SYS_STATUS_SENSOR_3D_ACCEL
                   | M.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE | M.MAV_SYS_STATUS_SENSOR_GPS)
        health = sensors if v.position_ok else sensors & ~M.MAV_SYS_STATUS_SENSOR_GPS
        return M.MAVLink_sys_status_message(
            sensors, sensors, health, 200, int(v.battery_voltage_v() * 1000),
            int(v.battery_current_a * 100), int(v.battery_remaining_pct()), 0, 0, 0, 0, 0, 0, 0, 0, 0)

    def _msg_battery_status(self):
        v = self.vehicle
        cells = [int(v.battery_voltage_v() * 1000)] + [65535] * 9
        return M.MAVLink_battery_status_message(
            0, M.MAV_BATTERY_FUNCTION_ALL, M.MAV_BATTERY_TYPE_LIPO, 2500, cells,
            int(v.battery_current_a * 100), int(v.battery_used_mah), -1,
            int(v.battery_remaining_pct()), 0, 0, [0, 0, 0, 0], 0, 0)

    def _msg_vfr_hud(self):
        v = self.vehicle
        speed = float(np.hypot(*v.vel_enu_mps[:2]))
        lat, lon, alt = v.geodetic_amsl(v.est_pos_enu_m)
        return M.MAVLink_vfr_hud_message(speed, speed, int(v.yaw_deg) % 360,
                                         50 if v.armed and not v.landed else 0, alt, v.vel_enu_mps[2])

    def _msg_extended_sys_state(self):
        v = self.vehicle
        if v.landed:
            state = M.MAV_LANDED_STATE_ON_GROUND
        elif v.vel_enu_mps[2] < -0.3 and v.behaviour == "land":
            state = M.MAV_LANDED_STATE_LANDING
        else:
            state = M.MAV_LANDED_STATE_IN_AIR
        return M.MAVLink_extended_sys_state_message(M.MAV_VTOL_STATE_MC, state)

    def _msg_mission_current(self):
        v = self.vehicle
        total = len(v.mission)
        state = M.MISSION_STATE_NO_MISSION if not total else (
            M.MISSION_STATE_ACTIVE if v.behaviour == "mission" and v.mission_seq < total
            else M.MISSION_STATE_COMPLETE if v.mission_seq >= total else M.MISSION_STATE_NOT_STARTED)
        return M.MAVLink_mission_current_message(min(v.mission_seq, 65535), total, state,
                                                 1 if v.behaviour == "mission" else 0)

    def _msg_home_position(self):
        v = self.vehicle
        if not v.home_set:
            return None
        lat, lon, alt = v.geodetic_amsl(v.home_enu_m)
        ned = v.enu_to_local_ned(v.home_enu_m)
        return M.MAVLink_home_position_message(int(round(lat * 1e7)), int(round(lon * 1e7)),
                                               int(round(alt * 1000)), *ned, [1.0, 0.0, 0.0, 0.0],
                                               0.0, 0.0, 0.0, int(v.t_s * 1e6))

    def _msg_autopilot_version(self):
        caps = (M.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT | M.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
                | M.MAV_PROTOCOL_CAPABILITY_MISSION_INT | M.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                | M.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
                | M.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED | M.MAV_PROTOCOL_CAPABILITY_MAVLINK2)
        # version word: major.minor.patch.type, type 255 = official release; skyfix-sim 0.1.0
        return M.MAVLink_autopilot_version_message(caps, (0 << 24) | (1 << 16) | (0 << 8) | 255, 0, 0, 0,
                                                   [0] * 8, [0] * 8, [0] * 8, 0, 0,
                                                   self.system_id, [0] * 18)

    def _msg_gps_global_origin(self):
        o = self.vehicle.ekf_origin
        if o is None:
            return None
        return M.MAVLink_gps_global_origin_message(int(round(o[0] * 1e7)), int(round(o[1] * 1e7)),
                                                   int(round((o[2] - self.vehicle.geoid_m) * 1000)),
                                                   int(self.vehicle.t_s * 1e6))
