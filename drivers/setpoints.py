"""A Vehicle's setpoint stream: the last position or velocity target, re-sent at a steady rate.

Mixed into :class:`skyfix.drivers.vehicle.Vehicle` (which holds ``_setpoint``, its thread and
``setpoint_rate_hz``). PX4 offboard needs a live stream, ArduPilot drops velocity targets after
3 s, and either may lose a packet.
"""

from __future__ import annotations

import threading

from skyfix.drivers.mav import mavlink
from skyfix.errors import InputError, LinkError

M = mavlink
POSITION_ONLY_MASK = 0x0FF8  # SET_POSITION_TARGET type_mask: use x/y/z only
VELOCITY_ONLY_MASK = 0x0FC7  # use vx/vy/vz only


class SetpointStream:
    """Start, replace and stop the re-sent SET_POSITION_TARGET_GLOBAL_INT."""

    def _hold_setpoint(self):
        pos = self._state.position
        if pos is None:
            raise InputError("cannot build a hold setpoint before the first position report")
        return M.MAVLink_set_position_target_global_int_message(
            0, self.system_id, self.component_id, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
            POSITION_ONLY_MASK, int(round(pos.lat_deg * 1e7)), int(round(pos.lon_deg * 1e7)),
            pos.alt_rel_m, 0, 0, 0, 0, 0, 0, 0, 0)

    def _start_setpoints(self, msg) -> None:
        """Send ``msg`` now and keep re-sending it at ``setpoint_rate_hz`` (PX4 offboard needs a
        live stream, ArduPilot drops velocity targets after 3 s, and either may lose a packet)."""
        self._setpoint = msg
        self.send(msg)
        old = self._setpoint_thread
        if old is not None and old.is_alive() and self._setpoint_stop.is_set() \
                and old is not threading.current_thread():
            old.join(timeout=1.0)  # told to stop and not gone yet: it would leave our stream dead
        if self._setpoint_thread is None or not self._setpoint_thread.is_alive():
            self._setpoint_stop.clear()
            self._setpoint_thread = threading.Thread(target=self._setpoint_loop, daemon=True,
                                                     name=f"skyfix-setpoints-{self.system_id}")
            self._setpoint_thread.start()

    def _stop_setpoints(self) -> None:
        self._setpoint = None
        self._setpoint_stop.set()

    def _setpoint_loop(self) -> None:
        period = 1.0 / self.setpoint_rate_hz
        while not self._setpoint_stop.wait(period):
            msg = self._setpoint
            if msg is None or self.link.closed:
                return
            try:
                self.send(msg)
            except LinkError:
                return
