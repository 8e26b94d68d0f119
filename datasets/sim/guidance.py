"""The simulated autopilot's guidance: the velocity command of each flight behaviour (guided
targets, missions, RTL, land, hold) from the vehicle's *estimate*, world ENU m/s.

Mixed into :class:`skyfix.datasets.sim.vehicle.SimVehicle`; ``step`` feeds the command to the
physics.
"""

from __future__ import annotations

import math

import numpy as np

from skyfix.drivers.mav import mavlink as M


class Guidance:
    """Position control, per-behaviour guidance and mission progress."""

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
            return self._pos_control(target, self.rtl_speed_mps())
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
                if item.command == M.MAV_CMD_NAV_LAND and (item.lat_deg or item.lon_deg):
                    self._land_xy = self.global_target_enu(item.frame, item.lat_deg, item.lon_deg, 0.0)[:2]
                self._rtl_phase = "climb"
        if item.command == M.MAV_CMD_NAV_TAKEOFF:
            goal = self.home_enu_m[2] + item.alt_m if item.frame != M.MAV_FRAME_GLOBAL_INT else \
                item.alt_m + self.geoid_m - self.world.alt0_m
            if self.landed and not self.armed:
                return np.zeros(3)
            if est[2] >= goal - 0.3:
                self._advance_mission()
            return self._pos_control(np.array([*self._hold_enu_m[:2], goal]))
        if item.command in (M.MAV_CMD_NAV_WAYPOINT, M.MAV_CMD_NAV_LOITER_TIME):
            target = self.global_target_enu(item.frame, item.lat_deg, item.lon_deg, item.alt_m) \
                if (item.lat_deg or item.lon_deg) else np.array([*est[:2], self.home_enu_m[2] + item.alt_m])
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
