"""``Vehicle``: one autopilot (ArduPilot or PX4) reached over a :class:`MavlinkLink`.

Telemetry is kept as typed, timestamped records (:mod:`skyfix.drivers.state`) updated by
the link's reader thread. Commands block until the autopilot acknowledges them, retry a
bounded number of times on silence, and raise :mod:`skyfix.errors` exceptions whose
messages carry the autopilot's own STATUSTEXT explanation.

Altitude conventions: ``alt_m`` arguments of :meth:`takeoff` and :meth:`goto` are metres
above home; ``alt_amsl_m`` values are above mean sea level.

The class is assembled from one module per job: the reader side
(:mod:`~skyfix.drivers.telemetry`), the setpoint stream (:mod:`~skyfix.drivers.setpoints`),
the safety monitor (:mod:`~skyfix.drivers.safety_monitor`) and the external-position
commands (:class:`~skyfix.drivers.injection.InjectionCommands`); connecting, commands,
modes and flight are here.
"""

from __future__ import annotations

import contextlib
import logging
import math
import queue
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import replace
from typing import Any

from skyfix import validate
from skyfix.drivers import injection, mission
from skyfix.drivers import params as param_io
from skyfix.drivers.injection import InjectionCommands
from skyfix.drivers.link import MavlinkLink
from skyfix.drivers.mav import command_name, mavlink, result_name
from skyfix.drivers.modes import custom_mode_of, flavour_of, role_mode
from skyfix.drivers.request import AGAIN, DONE, WAIT, transact
from skyfix.drivers.safety import SafetyGate
from skyfix.drivers.safety_monitor import CONFIRMING_TYPES, SafetyMonitor
from skyfix.drivers.setpoints import POSITION_ONLY_MASK, VELOCITY_ONLY_MASK, SetpointStream
from skyfix.drivers.state import VehicleEvent, VehicleState
from skyfix.drivers.telemetry import TelemetryHandlers
from skyfix.errors import CommandRejected, InputError, LinkError, SafetyViolation, SkyfixTimeout

log = logging.getLogger(__name__)
M = mavlink

#: Message -> rate (Hz) requested at connect with MAV_CMD_SET_MESSAGE_INTERVAL.
DEFAULT_STREAM_RATES_HZ: dict[str, float] = {
    "GLOBAL_POSITION_INT": 10.0, "ATTITUDE": 10.0, "GPS_RAW_INT": 5.0, "SYS_STATUS": 2.0,
    "BATTERY_STATUS": 1.0, "EXTENDED_SYS_STATE": 2.0, "MISSION_CURRENT": 2.0, "HOME_POSITION": 0.5,
    "EKF_STATUS_REPORT": 2.0,  # ArduPilot only (PX4 answers UNSUPPORTED)
}


class _Subscription:
    def __init__(self, predicate: Callable) -> None:
        self.predicate = predicate
        self.queue: queue.Queue = queue.Queue()


class Vehicle(TelemetryHandlers, SetpointStream, SafetyMonitor, InjectionCommands):
    """One autopilot on a link. Create with :meth:`connect` (or :meth:`connect_all`)."""

    def __init__(self, link: MavlinkLink, system_id: int, component_id: int, autopilot: int) -> None:
        self.link = link
        self.system_id = int(system_id)
        self.component_id = int(component_id)
        self.autopilot = flavour_of(autopilot)
        self.stream_rates_hz: dict[str, float] = dict(DEFAULT_STREAM_RATES_HZ)
        self._lock = threading.Condition()
        self._state = VehicleState(system_id=self.system_id, autopilot=self.autopilot, link_ok=True)
        self._hb_mono = time.monotonic()
        self._position_mono = -math.inf  # last GLOBAL_POSITION_INT received
        self._streams_mono = -math.inf  # last time the streams were requested
        # the reader thread re-requests streams on the first heartbeat while connect() asks for
        # the caller's rates: serialised, the last request sent always carries the latest rates
        self._streams_lock = threading.Lock()
        self._subs: list[_Subscription] = []
        self.statustexts: deque[tuple[float, int, str]] = deque(maxlen=200)
        self._chunks: dict[int, list[str]] = {}
        self.events: deque[VehicleEvent] = deque(maxlen=1000)
        self._listeners: list[Callable[[VehicleEvent], None]] = []
        self.params: dict[str, int | float] = {}
        self.param_types: dict[str, int] = {}  # MAV_PARAM_TYPE per name, as last reported
        self._command_lock = threading.Lock()  # one command in flight per vehicle
        self._command_seq = 0  # commands given so far: a newer one supersedes the safety action
        self.ekf_origin: tuple[float, float, float] | None = None
        self.safety: SafetyGate | None = None
        self._safety_latched = False
        #: (detection latency s from telemetry receipt to action sent, reason) per violation
        self.safety_log: deque[tuple[float, str]] = deque(maxlen=1000)
        self._setpoint: mavlink.MAVLink_message | None = None
        self._setpoint_thread: threading.Thread | None = None
        self._setpoint_stop = threading.Event()
        self.setpoint_rate_hz = 10.0
        self.injector: injection.PositionInjector | None = None
        self._injection_checked: set[str] = set()
        #: GPS_INPUT's gps_id: the autopilot's MAV GPS instance (0: GPS1_TYPE=14, 1: GPS2_TYPE=14),
        #: set by check_injection("gps")
        self.gps_input_id = 0

    # ------------------------------------------------------------------ connecting
    @classmethod
    def connect(cls, url: str, *, timeout_s: float = 10.0, system_id: int | None = None,
                heartbeat_timeout_s: float = 3.0, stream_rates_hz: dict[str, float] | None = None,
                source_system: int = 255) -> Vehicle:
        """Open ``url`` (udpin/udpout/tcp/serial), wait for the autopilot's HEARTBEAT and
        request telemetry streams. ``system_id`` picks one vehicle on a shared link."""
        validate.positive_scalar("timeout_s", timeout_s)
        link = MavlinkLink(url, source_system=source_system, heartbeat_timeout_s=heartbeat_timeout_s)
        link.vehicle_factory = cls
        try:
            vehicle = link.wait_vehicle(system_id, timeout_s)
        except LinkError:
            link.close()
            raise
        if stream_rates_hz:
            vehicle.stream_rates_hz.update(stream_rates_hz)
        vehicle.request_streams()
        return vehicle

    @classmethod
    def connect_all(cls, url: str, count: int, *, timeout_s: float = 10.0,
                    heartbeat_timeout_s: float = 3.0) -> list[Vehicle]:
        """Every vehicle on one shared link (one :class:`Vehicle` per system id)."""
        link = MavlinkLink(url, heartbeat_timeout_s=heartbeat_timeout_s)
        link.vehicle_factory = cls
        try:
            vehicles = link.wait_vehicles(int(count), timeout_s)
        except LinkError:
            link.close()
            raise
        for v in vehicles:
            v.request_streams()
        return vehicles

    def close(self) -> None:
        """Stop streams and injection, and close the link (shared links close for all)."""
        self._stop_setpoints()
        if self.injector is not None:
            self.injector.stop()
        self.link.close()

    def __enter__(self) -> Vehicle:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def request_streams(self) -> None:
        """Ask for each telemetry message at ``stream_rates_hz`` (fire and forget; asked again
        when positions stop while heartbeats go on, e.g. after the autopilot rebooted)."""
        with self._streams_lock:
            self._streams_mono = time.monotonic()
            for name, rate in list(self.stream_rates_hz.items()):
                msg_id = getattr(M, f"MAVLINK_MSG_ID_{name}", None)
                if msg_id is None:
                    continue
                interval_us = 1e6 / rate if rate > 0 else -1
                self._send_command_long(M.MAV_CMD_SET_MESSAGE_INTERVAL, [msg_id, interval_us], 0)
            self._send_command_long(M.MAV_CMD_REQUEST_MESSAGE, [M.MAVLINK_MSG_ID_HOME_POSITION], 0)

    # ------------------------------------------------------------------ state
    @property
    def state(self) -> VehicleState:
        """The latest consistent snapshot."""
        with self._lock:
            return self._state

    def on_event(self, callback: Callable[[VehicleEvent], None]) -> None:
        """Call ``callback(event)`` for every event (from the reader thread: keep it short)."""
        self._listeners.append(callback)

    def _emit(self, kind: str, text: str = "", **data) -> None:
        with self._lock:  # ordered with state updates: waiters woken by a state change see it
            ev = VehicleEvent(kind, time.time(), text, data)
            self.events.append(ev)
        for cb in list(self._listeners):
            try:
                cb(ev)
            except Exception:
                log.exception("event listener failed on %s", kind)

    def wait_until(self, predicate: Callable[[VehicleState], bool], timeout_s: float, *,
                   what: str = "condition") -> VehicleState:
        """Block until ``predicate(state)`` is true; SkyfixTimeout after ``timeout_s``.
        LinkError as soon as the heartbeat is lost during the wait; a wait that starts while
        the link is down (e.g. for ``s.link_ok``) waits for it to come back."""
        validate.positive_scalar("timeout_s", timeout_s)
        deadline = time.monotonic() + timeout_s
        with self._lock:
            link_was_ok = self._state.link_ok
            while True:
                st = self._state
                if predicate(st):
                    return st
                if link_was_ok and not st.link_ok:
                    raise LinkError(f"lost the heartbeat of vehicle {self.system_id} while waiting "
                                    f"for {what}; last state: {st.summary()}")
                left = deadline - time.monotonic()
                if left <= 0:
                    raise SkyfixTimeout(f"vehicle {self.system_id}: {what} not reached within "
                                        f"{timeout_s:.1f} s; state: {st.summary()}{self._reasons(deadline - timeout_s)}")
                self._lock.wait(min(left, 0.1))

    def wait_link(self, timeout_s: float) -> VehicleState:
        """Wait until the autopilot's heartbeat is heard again (after a reboot, a cable
        pulled, a radio out of range); SkyfixTimeout after ``timeout_s``."""
        return self.wait_until(lambda s: s.link_ok, timeout_s, what="the link back")

    def _update(self, **fields) -> None:
        with self._lock:
            self._state = replace(self._state, **fields)
            self._lock.notify_all()

    def _reasons(self, since_mono: float, limit: int = 3) -> str:
        """The autopilot's recent warnings (severity NOTICE or worse) since ``since_mono``, for
        error messages; its INFO chatter ("EKF3 IMU0 origin set") explains nothing."""
        lines = [t for (tm, sev, t) in self.statustexts if tm >= since_mono and sev <= 5]
        return ("; autopilot says: " + " | ".join(lines[-limit:])) if lines else ""

    @contextlib.contextmanager
    def subscribe(self, predicate: Callable) -> Iterator[queue.Queue]:
        """Queue of ``(msg, t_mono)`` for incoming messages matching ``predicate`` while open."""
        sub = self._open_subscription(predicate)
        try:
            yield sub.queue
        finally:
            self._close_subscription(sub)

    def _open_subscription(self, predicate: Callable) -> _Subscription:
        """A subscription that outlives one call (the safety gate opens it on the reader
        thread before its first send and its confirming thread closes it)."""
        sub = _Subscription(predicate)
        self._subs.append(sub)
        return sub

    def _close_subscription(self, sub: _Subscription) -> None:
        with contextlib.suppress(ValueError):
            self._subs.remove(sub)

    def send(self, msg) -> None:
        self.link.send(msg)

    # ------------------------------------------------------------------ commands
    def _command_long(self, command: int, params: list[float], confirmation: int):
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        return M.MAVLink_command_long_message(self.system_id, self.component_id, command, confirmation, *p)

    def _send_command_long(self, command: int, params: list[float], confirmation: int) -> None:
        """Fire and forget (stream rates): no ACK awaited, so no command lock either."""
        self.send(self._command_long(command, params, confirmation))

    def command(self, command: int, *params: float, timeout_s: float = 1.0, retries: int = 3,
                confirmed_by: Callable[[Any], bool] | None = None) -> int:
        """Send COMMAND_LONG and wait for its COMMAND_ACK, resending up to ``retries`` times.

        Commands to one vehicle go out one at a time (the safety gate's included), so an ACK
        is never taken for another request's. ``confirmed_by(msg)``: a HEARTBEAT or
        EXTENDED_SYS_STATE that proves the command took effect also ends the wait (on a lossy
        link every ACK may be lost while the command got through). Returns the MAV_RESULT
        (ACCEPTED). Raises CommandRejected (with the autopilot's STATUSTEXT reason),
        SkyfixTimeout, or LinkError when the heartbeat is lost.
        """
        if len(params) > 7:
            raise InputError(f"a COMMAND_LONG takes at most 7 params, got {len(params)}")
        for i, p in enumerate(params):
            if isinstance(p, float) and math.isinf(p):
                raise InputError(f"param{i + 1} of {command_name(command)} must be finite or NaN, got {p}")
        with self._command_lock:
            self._command_seq += 1
            return self._command_locked(command, list(params), timeout_s, retries, confirmed_by=confirmed_by)

    def _ack_verdict(self, command: int) -> Callable[[Any], str | None]:
        src = (self.link.source_system, self.link.source_component) if self.link else (0, 0)

        def verdict(ack) -> str | None:
            if ack.command != command or getattr(ack, "target_system", 0) not in (0, src[0]) \
                    or getattr(ack, "target_component", 0) not in (0, src[1]):
                return None
            if ack.result == M.MAV_RESULT_IN_PROGRESS:
                return WAIT
            return AGAIN if ack.result == M.MAV_RESULT_TEMPORARILY_REJECTED else DONE

        return verdict

    def _command_locked(self, command: int, params: list[float], timeout_s: float, retries: int, *,
                        first_sent: bool = False, replies: queue.Queue | None = None,
                        confirmed_by: Callable[[Any], bool] | None = None) -> int:
        """One command transaction; the caller holds ``_command_lock``.

        ``replies``: a subscription queue opened before attempt 0 was sent (``first_sent``), so
        a fast ACK is not missed. ``confirmed_by(msg)``: another message that proves the command
        took effect (the heartbeat showing the new mode) when every ACK is lost.
        """
        name = command_name(command)
        t0 = time.monotonic()
        ack_verdict = self._ack_verdict(command)
        verdict = ack_verdict
        if confirmed_by is not None:
            def verdict(msg) -> str | None:
                if msg.get_type() == "COMMAND_ACK":
                    return ack_verdict(msg)
                return DONE if confirmed_by(msg) else None
        ack = transact(self, lambda attempt: self._command_long(command, params, attempt), verdict,
                       types=("COMMAND_ACK",) if confirmed_by is None else CONFIRMING_TYPES, timeout_s=timeout_s,
                       retries=retries,
                       what=f"{name} (COMMAND_ACK)", first_sent=first_sent, replies=replies)
        if ack.get_type() != "COMMAND_ACK" or ack.result == M.MAV_RESULT_ACCEPTED:
            return M.MAV_RESULT_ACCEPTED
        time.sleep(0.02)  # a STATUSTEXT explaining the refusal may trail the ACK
        reason = self._reasons(t0 - 0.5)
        raise CommandRejected(f"vehicle {self.system_id} rejected {name} ({result_name(ack.result)}){reason}",
                              command=name, result=ack.result, reason=reason.removeprefix("; autopilot says: "))

    def arm(self, *, force: bool = False, timeout_s: float = 3.0) -> None:
        """Arm the motors and wait until the heartbeat shows it."""
        self.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1, 21196 if force else 0,
                     confirmed_by=lambda msg: self._heartbeat_armed(msg, True))
        self.wait_until(lambda s: s.armed, timeout_s, what="armed")

    def disarm(self, *, force: bool = False, timeout_s: float = 3.0) -> None:
        """Disarm (the autopilot refuses in flight unless ``force``) and wait for it."""
        self.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 21196 if force else 0,
                     confirmed_by=lambda msg: self._heartbeat_armed(msg, False))
        self.wait_until(lambda s: not s.armed, timeout_s, what="disarmed")

    def set_mode(self, name: str, *, timeout_s: float = 3.0) -> None:
        """Switch flight mode by name (``GUIDED``, ``AUTO.MISSION``, ``OFFBOARD``...) and wait
        for the heartbeat to report it. PX4 OFFBOARD gets a setpoint stream first."""
        name = str(name).upper()
        custom_mode_of(self.autopilot, name)  # InputError for an unknown mode
        if self.autopilot == "px4" and name == "OFFBOARD":
            if self._setpoint is None:
                self._start_setpoints(self._hold_setpoint())
            time.sleep(max(0.0, 3.0 / self.setpoint_rate_hz))  # PX4 wants a live stream
        mode_params = self._mode_params(name)
        if name not in ("OFFBOARD", "GUIDED"):
            self._stop_setpoints()
        if name == "OFFBOARD" and self._setpoint is not None:
            # a fresh setpoint right before the switch: the stream thread may have been delayed
            # (PX4 refuses OFFBOARD unless a setpoint arrived within COM_OF_LOSS_T)
            self.send(self._setpoint)
        self.command(M.MAV_CMD_DO_SET_MODE, *mode_params, confirmed_by=lambda msg: self._heartbeat_in_mode(msg, name))
        self.wait_until(lambda s: s.mode == name, timeout_s, what=f"mode {name}")

    def _ensure_guided(self) -> None:
        mode = role_mode(self.autopilot, "guided")
        if self._state.mode != mode:
            self.set_mode(mode)

    def takeoff(self, alt_m: float, *, wait: bool = True, timeout_s: float | None = None) -> None:
        """Take off to ``alt_m`` metres above home (ArduPilot: in GUIDED; PX4: AUTO.TAKEOFF).
        The vehicle must be armed. With ``wait`` block until within 0.5 m of the altitude."""
        alt_m = validate.positive_scalar("alt_m", alt_m)
        if self.safety is not None:
            pos = self._state.position
            if pos is not None:
                self.safety.check_position_setpoint(pos.lat_deg, pos.lon_deg, alt_m)
        if self.autopilot == "px4":
            home = self._state.home or self.wait_until(lambda s: s.home is not None, 3.0, what="home").home
            params = [0, 0, 0, math.nan, math.nan, math.nan, home.alt_amsl_m + alt_m]
        else:
            if self._state.mode != "GUIDED":
                self.set_mode("GUIDED")
            params = [0, 0, 0, 0, 0, 0, alt_m]
        t0 = time.monotonic()
        try:
            self.command(M.MAV_CMD_NAV_TAKEOFF, *params, confirmed_by=self._reports_airborne)
        except CommandRejected:
            # a re-sent takeoff whose first copy was accepted (its ACK lost) is refused as
            # "already flying": not an error when the vehicle did leave the ground just now
            with contextlib.suppress(SkyfixTimeout):
                self.wait_until(lambda s: s.landed_state in ("IN_AIR", "TAKEOFF") and s.position
                                is not None and s.position.time_s > time.time() - 0.5, 1.5,
                                what="lift-off")
            if self._state.landed_state not in ("IN_AIR", "TAKEOFF") or time.monotonic() - t0 > 10.0:
                raise
        if wait:
            self.wait_until(lambda s: s.position is not None and s.position.alt_rel_m >= alt_m - 0.5,
                            timeout_s or alt_m / 0.5 + 10.0, what=f"takeoff to {alt_m:.1f} m")

    def goto(self, lat_deg: float, lon_deg: float, alt_m: float, *, wait: bool = False,
             tolerance_m: float = 1.5, timeout_s: float | None = None) -> None:
        """Fly to (lat, lon) at ``alt_m`` above home with SET_POSITION_TARGET_GLOBAL_INT,
        switching to GUIDED/OFFBOARD if needed. The safety gate checks the target first."""
        lat = float(validate.latitude("lat_deg", validate.finite_scalar("lat_deg", lat_deg)))
        lon = float(validate.longitude("lon_deg", validate.finite_scalar("lon_deg", lon_deg)))
        alt = validate.finite_scalar("alt_m", alt_m)
        if self.safety is not None:
            self.safety.check_position_setpoint(lat, lon, alt)
        msg = M.MAVLink_set_position_target_global_int_message(
            0, self.system_id, self.component_id, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
            POSITION_ONLY_MASK, int(round(lat * 1e7)), int(round(lon * 1e7)), alt, 0, 0, 0, 0, 0, 0, 0, 0)
        self._start_setpoints(msg)
        self._ensure_guided()
        if self._setpoint is not msg:  # the gate stopped the stream while we switched: ours is newer
            self._start_setpoints(msg)
        if wait:
            from skyfix.geo import inverse
            pos = self._state.position
            dist = float(inverse(pos.lat_deg, pos.lon_deg, lat, lon)[1]) if pos else 100.0

            def arrived(s: VehicleState) -> bool:
                if s.position is None:
                    return False
                d = float(inverse(s.position.lat_deg, s.position.lon_deg, lat, lon)[1])
                return d <= tolerance_m and abs(s.position.alt_rel_m - alt) <= max(tolerance_m, 1.0)

            self.wait_until(arrived, timeout_s or dist / 1.0 + 15.0,
                            what=f"arrival at {lat:.7f},{lon:.7f} {alt:.1f} m")

    def velocity(self, north_mps: float, east_mps: float, down_mps: float) -> None:
        """Fly at a NED velocity (m/s); the command is streamed until another setpoint,
        mode change or :meth:`hold` replaces it."""
        vn, ve, vd = (validate.finite_scalar(n, v) for n, v in
                      (("north_mps", north_mps), ("east_mps", east_mps), ("down_mps", down_mps)))
        if self.safety is not None:
            self.safety.check_velocity_setpoint(vn, ve, vd)
            if self._safety_latched:
                raise SafetyViolation(f"vehicle {self.system_id} is outside the safety envelope; "
                                      "velocity setpoints are refused until it is back inside "
                                      "(use goto() to a point inside, hold() or rtl())")
        msg = M.MAVLink_set_position_target_global_int_message(
            0, self.system_id, self.component_id, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
            VELOCITY_ONLY_MASK, 0, 0, 0, vn, ve, vd, 0, 0, 0, 0, 0)
        self._start_setpoints(msg)
        self._ensure_guided()
        if self._setpoint is not msg:  # the gate acted while we switched modes: it wins over a velocity
            raise SafetyViolation(f"vehicle {self.system_id} left the safety envelope while the velocity "
                                  "setpoint was being started; it was stopped")

    def hold(self) -> None:
        """Stop and hold position (LOITER / AUTO.LOITER)."""
        self.set_mode(role_mode(self.autopilot, "hold"))

    def land(self, *, wait: bool = False, timeout_s: float = 120.0) -> None:
        """Land where the vehicle is; with ``wait`` block until it has disarmed."""
        self.set_mode(role_mode(self.autopilot, "land"))
        if wait:
            self.wait_until(lambda s: not s.armed, timeout_s, what="landed and disarmed")

    def rtl(self, *, wait: bool = False, timeout_s: float = 300.0) -> None:
        """Return to launch; with ``wait`` block until landed and disarmed."""
        self.set_mode(role_mode(self.autopilot, "rtl"))
        if wait:
            self.wait_until(lambda s: not s.armed, timeout_s, what="return home and disarm")

    # ------------------------------------------------------------------ parameters
    def get_param(self, name: str, *, timeout_s: float = 1.0, retries: int = 3) -> int | float:
        """Read one autopilot parameter: int for integer parameters, float otherwise."""
        return param_io.get_param(self, name, timeout_s=timeout_s, retries=retries)

    def set_param(self, name: str, value: float, *, timeout_s: float = 1.0, retries: int = 3) -> int | float:
        """Write one parameter (in the type the autopilot reports for it) and wait for the echo."""
        return param_io.set_param(self, name, value, timeout_s=timeout_s, retries=retries)

    # ------------------------------------------------------------------ missions
    def upload_mission(self, items: list[mission.MissionItem], *,
                       progress: Callable[[int, int], None] | None = None,
                       item_timeout_s: float = 0.25, timeout_s: float = 60.0,
                       ftp: bool = False) -> mission.TransferStats:
        """Upload a mission: the MISSION_ITEM_INT protocol (:func:`mission.upload`), or with
        ``ftp`` (ArduPilot only) one file over MAVLink FTP, read back and compared
        (:func:`mission_ftp.upload_ftp`: ~4x faster for long missions on ArduPilot SITL)."""
        if ftp:
            from skyfix.drivers import mission_ftp

            return mission_ftp.upload_ftp(self, items, timeout_s=min(timeout_s, 30.0))
        return mission.upload(self, items, progress=progress, item_timeout_s=item_timeout_s,
                              timeout_s=timeout_s)

    def download_mission(self, *, item_timeout_s: float = 0.25,
                         timeout_s: float = 60.0) -> list[mission.MissionItem]:
        """The mission stored on the vehicle (ArduPilot's home item 0 removed)."""
        return mission.download(self, item_timeout_s=item_timeout_s, timeout_s=timeout_s)

    def clear_mission(self, *, timeout_s: float = 1.0) -> None:
        mission.clear(self, timeout_s=timeout_s)

    def start_mission(self) -> None:
        """Switch to the mission mode (AUTO / AUTO.MISSION); the vehicle must be armed."""
        self.set_mode(role_mode(self.autopilot, "mission"))

    def set_camera_trigger_distance(self, distance_m: float) -> None:
        """Trigger the camera every ``distance_m`` metres travelled (0 stops)."""
        d = validate.nonnegative_scalar("distance_m", distance_m)
        self.command(M.MAV_CMD_DO_SET_CAM_TRIGG_DIST, d, 0, 1)
