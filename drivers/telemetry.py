"""A Vehicle's reader side: incoming MAVLink telemetry -> typed state records and events.

Mixed into :class:`skyfix.drivers.vehicle.Vehicle`, which owns the state, its lock, the
subscriptions and the event list; the link's reader thread calls ``_on_message`` for every
message and ``_check_heartbeat`` on its clock. Units are converted in :mod:`skyfix.drivers.units`.
"""

from __future__ import annotations

import logging
import math
import time

from skyfix.drivers import params as param_io
from skyfix.drivers import units
from skyfix.drivers.mav import mavlink
from skyfix.drivers.modes import mode_name
from skyfix.drivers.state import Attitude

log = logging.getLogger("skyfix.drivers.vehicle")  # the Vehicle's logger: one name for its whole story
M = mavlink
_LANDED = {0: "UNDEFINED", 1: "ON_GROUND", 2: "IN_AIR", 3: "TAKEOFF", 4: "LANDING"}


class TelemetryHandlers:
    """``_rx_<message type>`` handlers, dispatched by ``_on_message`` (reader thread)."""

    def _on_message(self, msg, t_mono: float) -> None:
        mtype = msg.get_type()
        now = time.time()
        handler = getattr(self, "_rx_" + mtype.lower(), None)
        if handler is not None:
            handler(msg, now, t_mono)
        for sub in list(self._subs):
            try:
                if sub.predicate(msg):
                    sub.queue.put((msg, t_mono))
            except Exception:
                log.exception("subscription predicate failed")

    def _rx_heartbeat(self, msg, now: float, t_mono: float) -> None:
        if msg.get_srcComponent() != self.component_id:
            return
        self._hb_mono = t_mono
        if self.link is not None and not self.link.closed and t_mono - self._position_mono > 2.0 \
                and t_mono - self._streams_mono > 2.0:
            self.request_streams()  # heartbeats but no positions: rates forgotten (reboot)
        old = self._state
        mode = mode_name(self.autopilot, msg.custom_mode)
        armed = bool(msg.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED)
        # events first, then the state change that wakes waiters
        if not old.link_ok:
            log.warning("vehicle %d: heartbeat back", self.system_id)
            self._emit("link_restored", f"heartbeat of vehicle {self.system_id} is back")
        if old.mode and old.mode != mode:
            self._emit("mode", mode, old=old.mode, new=mode)
        if old.armed != armed:
            self._emit("armed" if armed else "disarmed")
        self._update(mode=mode, armed=armed, heartbeat_time_s=now, link_ok=True)
        if not old.link_ok and self.link is not None:
            self.request_streams()  # an autopilot that rebooted forgot our rates
        if old.armed and not armed:
            self._stop_setpoints()

    def _check_heartbeat(self, now_mono: float, timeout_s: float) -> None:
        if self._state.link_ok and now_mono - self._hb_mono > timeout_s:
            log.warning("vehicle %d: no heartbeat for %.1f s", self.system_id, now_mono - self._hb_mono)
            self._emit("link_lost", f"no HEARTBEAT from vehicle {self.system_id} for "
                       f"{now_mono - self._hb_mono:.1f} s")
            self._update(link_ok=False)

    def _rx_global_position_int(self, msg, now: float, t_mono: float) -> None:
        self._position_mono = t_mono
        pos, vel = units.position_velocity(msg, now)
        self._update(position=pos, velocity=vel)
        if self.safety is not None:
            self._check_safety(pos, vel, t_mono)

    def _rx_attitude(self, msg, now: float, t_mono: float) -> None:
        self._update(attitude=Attitude(math.degrees(msg.roll), math.degrees(msg.pitch),
                                       math.degrees(msg.yaw) % 360.0, now))

    def _rx_gps_raw_int(self, msg, now: float, t_mono: float) -> None:
        self._update(gps=units.gnss_fix(msg, now))

    def _rx_ekf_status_report(self, msg, now: float, t_mono: float) -> None:
        self._update(ekf=units.ekf_status(msg, now))

    def _rx_sys_status(self, msg, now: float, t_mono: float) -> None:
        self._update(battery=units.battery(msg, now))

    def _rx_home_position(self, msg, now: float, t_mono: float) -> None:
        self._update(home=units.home(msg, now))

    def _rx_extended_sys_state(self, msg, now: float, t_mono: float) -> None:
        self._update(landed_state=_LANDED.get(msg.landed_state, "UNDEFINED"))

    def _rx_mission_current(self, msg, now: float, t_mono: float) -> None:
        old = self._state.mission_seq
        self._update(mission_seq=msg.seq, mission_count=getattr(msg, "total", 0))
        if old != msg.seq:
            self._emit("mission_current", str(msg.seq), seq=msg.seq)

    def _rx_mission_item_reached(self, msg, now: float, t_mono: float) -> None:
        self._emit("mission_item_reached", str(msg.seq), seq=msg.seq)

    def _rx_camera_feedback(self, msg, now: float, t_mono: float) -> None:
        self._emit("camera_trigger", str(msg.img_idx), index=msg.img_idx, lat_deg=msg.lat / 1e7,
                   lon_deg=msg.lng / 1e7, alt_amsl_m=msg.alt_msl)

    def _rx_camera_trigger(self, msg, now: float, t_mono: float) -> None:
        self._emit("camera_trigger", str(msg.seq), index=msg.seq)

    def _rx_gps_global_origin(self, msg, now: float, t_mono: float) -> None:
        self.ekf_origin = (msg.latitude / 1e7, msg.longitude / 1e7, msg.altitude / 1000.0)
        self._emit("origin", "", lat_deg=self.ekf_origin[0], lon_deg=self.ekf_origin[1],
                   alt_amsl_m=self.ekf_origin[2])

    def _rx_param_value(self, msg, now: float, t_mono: float) -> None:
        name = param_io.param_name(msg)
        self.param_types[name] = int(msg.param_type)
        self.params[name] = param_io.decode(self, msg)

    def _rx_statustext(self, msg, now: float, t_mono: float) -> None:
        text = msg.text if isinstance(msg.text, str) else msg.text.decode(errors="replace")
        text = text.rstrip("\x00")
        if getattr(msg, "id", 0):  # chunked: assemble until a chunk shorter than 50 bytes
            parts = self._chunks.setdefault(msg.id, [])
            parts.append(text)
            if len(text) == 50:
                return
            text = "".join(self._chunks.pop(msg.id))
        self.statustexts.append((t_mono, msg.severity, text))
        log.info("vehicle %d says: %s", self.system_id, text)
        self._emit("statustext", text, severity=msg.severity)
