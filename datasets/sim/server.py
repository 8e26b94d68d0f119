"""The MAVLink face of one simulated vehicle: parses what ground stations send, answers
like ArduPilot Copter or PX4, and emits telemetry streams at the requested rates.

Telemetry intervals and mission-protocol timings run on simulated time, as SITL's do,
so a simulator running at ``speed`` x real time also streams ``speed`` x faster. Every
COMMAND_LONG/COMMAND_INT gets exactly one COMMAND_ACK (FAILED when handling it raised).
Each sender has its own parser, so a truncated datagram cannot swallow another's.
Telemetry messages are built in :mod:`~skyfix.datasets.sim.server_telemetry`, the parameter
and mission protocols answered in :mod:`~skyfix.datasets.sim.server_params` and
:mod:`~skyfix.datasets.sim.server_missions`; I/O, streams and commands are here.
"""

from __future__ import annotations

import logging
import math
import socket
import time
from collections import deque
from collections.abc import Callable

import numpy as np

from skyfix.datasets.sim.server_missions import MissionProtocol
from skyfix.datasets.sim.server_params import ParamProtocol
from skyfix.datasets.sim.server_telemetry import TelemetryMessages
from skyfix.datasets.sim.vehicle import (
    FORCE_MAGIC,
    Refusal,
    SimVehicle,
)
from skyfix.drivers.mav import mavlink
from skyfix.drivers.modes import mode_name

log = logging.getLogger(__name__)

M = mavlink
ACCEPTED, UNSUPPORTED = M.MAV_RESULT_ACCEPTED, M.MAV_RESULT_UNSUPPORTED

#: Streams sent without being asked (interval in simulated seconds), as a stock autopilot does.
DEFAULT_INTERVALS_S: dict[str, float] = {
    "HEARTBEAT": 1.0, "SYS_STATUS": 1.0, "GLOBAL_POSITION_INT": 0.25, "ATTITUDE": 0.25,
    "GPS_RAW_INT": 0.5, "VFR_HUD": 0.5, "BATTERY_STATUS": 1.0, "EXTENDED_SYS_STATE": 1.0,
    "EKF_STATUS_REPORT": 1.0,
    "MISSION_CURRENT": 1.0, "HOME_POSITION": 5.0, "LOCAL_POSITION_NED": 0.0,
}
#: REQUEST_DATA_STREAM groups (ArduPilot's SRx_ mapping) -> message names.
DATA_STREAMS: dict[int, tuple[str, ...]] = {
    M.MAV_DATA_STREAM_EXTENDED_STATUS: ("SYS_STATUS", "GPS_RAW_INT", "MISSION_CURRENT",
                                        "BATTERY_STATUS", "EXTENDED_SYS_STATE"),
    M.MAV_DATA_STREAM_POSITION: ("GLOBAL_POSITION_INT", "LOCAL_POSITION_NED"),
    M.MAV_DATA_STREAM_EXTRA1: ("ATTITUDE",),
    M.MAV_DATA_STREAM_EXTRA2: ("VFR_HUD",),
}
_MSG_NAME_BY_ID = {cls.id: cls.msgname for cls in M.mavlink_map.values()}
_MAX_PEERS = 64


class VehicleServer(TelemetryMessages, ParamProtocol, MissionProtocol):
    """MAVLink endpoint of one :class:`SimVehicle` over one UDP socket.

    ``gcs_address``: where telemetry goes before anybody talks (SITL's ``--out``);
    every address that sends a valid packet is answered too. ``loss_rate`` drops that
    fraction of datagrams in each direction (packet-loss injection for tests).
    """

    def __init__(self, vehicle: SimVehicle, sock: socket.socket, *,
                 gcs_address: tuple[str, int] | None, loss_rate: float = 0.0,
                 rng: np.random.Generator | None = None) -> None:
        self.vehicle = vehicle
        self.sock = sock
        self.gcs_address = gcs_address
        self.loss_rate = float(loss_rate)
        self._rng = rng or np.random.default_rng(vehicle.config.seed + 7)
        self.mav = M.MAVLink(None, srcSystem=vehicle.config.system_id, srcComponent=1)  # encoder
        self._parsers: dict[tuple[str, int], M.MAVLink] = {}  # one per sender: no shared buffer
        self.peers: dict[tuple[str, int], float] = {}
        self.intervals_s = dict(DEFAULT_INTERVALS_S)
        self._next_due_s: dict[str, float] = {}
        self._upload: dict | None = None
        self._last_upload_count = -1
        #: (monotonic time, kind, payload) of sent positions and received mode requests
        self.log: deque[tuple[float, str, tuple]] = deque(maxlen=50000)
        self.bad_packets = 0
        self.packets_in = 0
        self.gps_input_ignored = 0
        self._handlers: dict[str, Callable] = {
            "HEARTBEAT": lambda m, a: None,
            "COMMAND_LONG": self._on_command, "COMMAND_INT": self._on_command,
            "SET_MODE": self._on_set_mode, "REQUEST_DATA_STREAM": self._on_request_data_stream,
            "PARAM_REQUEST_LIST": self._on_param_list, "PARAM_REQUEST_READ": self._on_param_read,
            "PARAM_SET": self._on_param_set,
            "SET_POSITION_TARGET_GLOBAL_INT": self._on_target_global,
            "SET_POSITION_TARGET_LOCAL_NED": self._on_target_local,
            "GPS_INPUT": self._on_gps_input, "VISION_POSITION_ESTIMATE": self._on_vision,
            "ODOMETRY": self._on_odometry, "SET_GPS_GLOBAL_ORIGIN": self._on_set_origin,
            "MISSION_COUNT": self._on_mission_count, "MISSION_ITEM_INT": self._on_mission_item,
            "MISSION_ITEM": self._on_mission_item, "MISSION_REQUEST_LIST": self._on_mission_list,
            "MISSION_REQUEST_INT": self._on_mission_request, "MISSION_REQUEST": self._on_mission_request,
            "MISSION_CLEAR_ALL": self._on_mission_clear, "MISSION_SET_CURRENT": self._on_mission_set_current,
            "MISSION_ACK": lambda m, a: None,
        }

    @property
    def system_id(self) -> int:
        return self.vehicle.config.system_id

    # ------------------------------------------------------------------ I/O
    def send(self, msg, to: tuple[str, int] | None = None) -> None:
        """Pack and send to one address, or to the GCS address and every live peer."""
        buf = msg.pack(self.mav)
        if to is not None:
            targets = [to]
        else:
            # the configured GCS address always gets telemetry, as ArduPilot's udpclient output
            # (SITL --serialN udpclient:HOST:PORT) does, however long that GCS stays silent;
            # other senders are answered while they were heard in the last 10 s
            now = time.monotonic()
            targets = [a for a, seen in self.peers.items() if now - seen < 10.0 and a != self.gcs_address]
            if self.gcs_address:
                targets.append(self.gcs_address)
        for addr in targets:
            if self.loss_rate and self._rng.random() < self.loss_rate:
                continue
            try:
                self.sock.sendto(buf, addr)
            except OSError:  # nobody listening (ICMP port unreachable): keep going
                pass

    def handle_datagram(self, data: bytes, addr: tuple[str, int]) -> None:
        """Parse one datagram and act on every message addressed to this vehicle."""
        if self.loss_rate and self._rng.random() < self.loss_rate:
            return
        parser = self._parsers.get(addr)
        if parser is None:
            if len(self._parsers) >= _MAX_PEERS:  # forget the oldest sender
                self._parsers.pop(next(iter(self._parsers)))
            parser = self._parsers[addr] = M.MAVLink(None)
            parser.robust_parsing = True
        try:
            msgs = parser.parse_buffer(data) or []
        except Exception as exc:  # malformed input must never stop the autopilot
            self.bad_packets += 1
            log.debug("sim %d: unparsable datagram from %s: %s", self.system_id, addr, exc)
            return
        for msg in msgs:
            if msg.get_type() == "BAD_DATA":
                self.bad_packets += 1
                continue
            target = getattr(msg, "target_system", 0)
            if target not in (0, self.system_id):
                continue
            self.packets_in += 1
            self.peers[addr] = time.monotonic()
            handler = self._handlers.get(msg.get_type())
            if handler is None:
                continue
            try:
                handler(msg, addr)
            except Exception:
                self.bad_packets += 1
                log.exception("sim %d: failed to handle %s", self.system_id, msg.get_type())

    # ------------------------------------------------------------- periodic
    def after_step(self) -> None:
        """Send due telemetry and queued events; called after each physics step."""
        v = self.vehicle
        while v.events:
            self._send_event(v.events.popleft())
        t = v.t_s
        for name, interval in self.intervals_s.items():
            if interval <= 0:
                continue
            due = self._next_due_s.get(name, 0.0)
            if t + 1e-9 >= due:
                self._next_due_s[name] = due + interval if t - due < interval else t + interval
                self.send_message_named(name)
        self.service_upload()

    def send_message_named(self, name: str, to: tuple[str, int] | None = None) -> bool:
        builder = getattr(self, "_msg_" + name.lower(), None)
        if builder is None:
            return False
        msg = builder()
        if msg is not None:
            self.send(msg, to)
        return True

    def _send_event(self, ev: tuple) -> None:
        v = self.vehicle
        kind = ev[0]
        if kind == "statustext":
            self.statustext(ev[2], ev[1])
        elif kind == "reached":
            self.send(M.MAVLink_mission_item_reached_message(ev[1]))
        elif kind == "current":
            self.send(self._msg_mission_current())
        elif kind == "home":
            self.send(self._msg_home_position())
        elif kind == "origin":
            self.send(self._msg_gps_global_origin())
        elif kind == "mode":
            self.send(self._msg_heartbeat())
        elif kind == "camera":
            lat, lon, alt = v.geodetic_amsl(v.pos_enu_m)
            if v.flavour == "ardupilot":
                self.send(M.MAVLink_camera_feedback_message(
                    int(v.t_s * 1e6), 0, 0, ev[1], int(lat * 1e7), int(lon * 1e7), alt,
                    v.altitude_rel_m(), v.roll_deg, v.pitch_deg, v.yaw_deg, 0.0, 0, ev[1]))
            else:
                self.send(M.MAVLink_camera_trigger_message(int(v.t_s * 1e6), ev[1]))

    def statustext(self, text: str, severity: int = M.MAV_SEVERITY_INFO) -> None:
        """STATUSTEXT, split into 50-byte chunks with a shared id when longer."""
        raw = text.encode("ascii", "replace")
        chunks = [raw[i:i + 50] for i in range(0, len(raw), 50)] or [b""]
        msg_id = (hash(text) & 0x7FFF) + 1 if len(chunks) > 1 else 0
        for i, chunk in enumerate(chunks):
            self.send(M.MAVLink_statustext_message(severity, chunk, msg_id, i))

    # ------------------------------------------------------------- commands
    def _ack(self, msg, command: int, result: int, addr) -> None:
        self.send(M.MAVLink_command_ack_message(command, result, 0, 0, msg.get_srcSystem(),
                                                msg.get_srcComponent()), addr)

    def _on_command(self, msg, addr) -> None:
        v = self.vehicle
        cmd = msg.command
        p = [msg.param1, msg.param2, msg.param3, msg.param4]
        if msg.get_type() == "COMMAND_INT":
            p += [msg.x / 1e7, msg.y / 1e7, msg.z]
        else:
            p += [msg.param5, msg.param6, msg.param7]
        try:
            result = self._execute(cmd, p, msg, addr)
        except Refusal as refusal:
            self.statustext(refusal.text, M.MAV_SEVERITY_WARNING)
            result = refusal.result
        except Exception as exc:  # a bug or a value it cannot use: FAILED, never silence
            log.exception("sim %d: %s failed", self.system_id, cmd)
            self.statustext(f"Command {cmd} failed: {exc}"[:100], M.MAV_SEVERITY_ERROR)
            result = M.MAV_RESULT_FAILED
        if result is not None:
            self._ack(msg, cmd, result, addr)
        while v.events:  # mode changes etc. go out right behind the ACK
            self._send_event(v.events.popleft())

    def _execute(self, cmd: int, p: list[float], msg, addr) -> int | None:
        v = self.vehicle
        if cmd == M.MAV_CMD_COMPONENT_ARM_DISARM:
            force = math.isfinite(p[1]) and int(round(p[1])) == FORCE_MAGIC  # MAVSDK sends NaN
            v.arm(force) if p[0] >= 0.5 else v.disarm(force)
            return ACCEPTED
        if cmd == M.MAV_CMD_DO_SET_MODE:
            if v.flavour == "px4":
                name = mode_name("px4", (int(p[1]) << 16) | (int(p[2]) << 24))
            else:
                name = mode_name("ardupilot", int(p[1]))
            self.log.append((time.monotonic(), "mode_request", (name,)))
            v.set_mode(name)
            return ACCEPTED
        if cmd == M.MAV_CMD_NAV_TAKEOFF:
            v.takeoff(self._takeoff_up_m(p))
            return ACCEPTED
        if cmd in (M.MAV_CMD_NAV_LAND, M.MAV_CMD_NAV_RETURN_TO_LAUNCH):
            name = ("AUTO.LAND" if v.flavour == "px4" else "LAND") if cmd == M.MAV_CMD_NAV_LAND \
                else ("AUTO.RTL" if v.flavour == "px4" else "RTL")
            self.log.append((time.monotonic(), "mode_request", (name,)))
            v.set_mode(name)
            return ACCEPTED
        if cmd == M.MAV_CMD_MISSION_START:
            if p[0] > 0:
                v.set_mission_current(int(p[0]))
            v.set_mode("AUTO.MISSION" if v.flavour == "px4" else "AUTO")
            return ACCEPTED
        if cmd == M.MAV_CMD_SET_MESSAGE_INTERVAL:
            name = _MSG_NAME_BY_ID.get(int(p[0]))
            if name is None or not hasattr(self, "_msg_" + name.lower()):
                return UNSUPPORTED
            interval_us = p[1]
            self.intervals_s[name] = (DEFAULT_INTERVALS_S.get(name, 0.0) if interval_us == 0
                                      else 0.0 if interval_us < 0 else interval_us / 1e6)
            self._next_due_s[name] = v.t_s
            return ACCEPTED
        if cmd in (M.MAV_CMD_REQUEST_MESSAGE, M.MAV_CMD_GET_HOME_POSITION,
                   M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES):
            return self._request_message(cmd, p, msg, addr)
        if cmd == M.MAV_CMD_DO_REPOSITION:
            return self._reposition(p, msg)
        if cmd == M.MAV_CMD_SET_EKF_SOURCE_SET and v.flavour == "ardupilot":
            if int(p[0]) not in (1, 2, 3):
                raise Refusal(M.MAV_RESULT_DENIED, f"EKF source set {p[0]:g} not in 1..3")
            v.ekf_source_set = int(p[0])  # the point-mass estimator uses positions only
            return ACCEPTED
        if cmd == M.MAV_CMD_DO_SET_CAM_TRIGG_DIST:
            v.cam_trigger_dist_m = max(0.0, p[0])
            v._cam_dist_acc_m = 0.0
            return ACCEPTED
        if cmd == M.MAV_CMD_DO_CHANGE_SPEED:
            v.speed_override_mps = p[1] if p[1] > 0 else None
            return ACCEPTED
        if cmd == M.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN:
            if v.armed:
                raise Refusal(M.MAV_RESULT_DENIED, "Reboot: disarm first")
            self.statustext("Reboot requested: simulated settings apply immediately")
            return ACCEPTED
        if cmd == M.MAV_CMD_DO_SET_HOME:
            v.home_enu_m = v.est_pos_enu_m.copy() if p[0] >= 0.5 else v.enu_amsl(p[4], p[5], p[6])
            v.home_set = True
            v.events.append(("home",))
            return ACCEPTED
        return UNSUPPORTED

    def _takeoff_up_m(self, p: list[float]) -> float:
        """MAV_CMD_NAV_TAKEOFF's target height, m up in the world frame (param7: PX4 AMSL,
        NaN = MIS_TAKEOFF_ALT above home; ArduPilot metres above home, > 0)."""
        v = self.vehicle
        if v.flavour == "px4":
            alt_ell = p[6] + v.geoid_m if math.isfinite(p[6]) else \
                v.home_enu_m[2] + v.world.alt0_m + v.param("MIS_TAKEOFF_ALT")
            return alt_ell - v.world.alt0_m
        if not math.isfinite(p[6]) or p[6] <= 0:
            raise Refusal(M.MAV_RESULT_DENIED, "Takeoff: altitude must be > 0")
        return v.home_enu_m[2] + p[6] if v.home_set else v.est_pos_enu_m[2] + p[6]

    def _request_message(self, cmd: int, p: list[float], msg, addr) -> int | None:
        """REQUEST_MESSAGE and its older forms: ack first, then send the message once."""
        msg_id = {M.MAV_CMD_GET_HOME_POSITION: M.MAVLINK_MSG_ID_HOME_POSITION,
                  M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: M.MAVLINK_MSG_ID_AUTOPILOT_VERSION
                  }.get(cmd, int(p[0]))
        name = _MSG_NAME_BY_ID.get(msg_id, "")
        if not hasattr(self, "_msg_" + name.lower()):
            return UNSUPPORTED  # once, before anything else
        if name == "HOME_POSITION" and not self.vehicle.home_set:
            raise Refusal(M.MAV_RESULT_FAILED, "Home position not set")
        self._ack(msg, cmd, ACCEPTED, addr)
        self.send_message_named(name, addr)
        return None

    def _reposition(self, p: list[float], msg) -> int:
        """MAV_CMD_DO_REPOSITION (MAVSDK's goto_location): fly to (lat, lon, alt) and hold there.
        NaN or 0 lat/lon and NaN alt keep the current value; param2 bit 0 allows the mode change
        (PX4 holds in AUTO.LOITER, ArduPilot flies it in GUIDED)."""
        v = self.vehicle
        if not v.armed or v.landed:
            raise Refusal(M.MAV_RESULT_DENIED, "Reposition: not flying")
        frame = msg.frame if msg.get_type() == "COMMAND_INT" else M.MAV_FRAME_GLOBAL
        lat, lon, alt_amsl = v.geodetic_amsl(v.est_pos_enu_m)
        if math.isfinite(p[4]) and math.isfinite(p[5]) and (p[4] or p[5]):
            lat, lon = p[4], p[5]
        if math.isfinite(p[6]):
            target = v.global_target_enu(frame, lat, lon, p[6])
        else:
            target = v.enu_amsl(lat, lon, alt_amsl)
        if math.isfinite(p[0]) and p[0] > 0:
            v.speed_override_mps = p[0]
        change_mode = math.isfinite(p[1]) and int(p[1]) & 1
        if v.flavour == "px4":
            v.set_mode("AUTO.LOITER")
            v._hold_enu_m = target
            return ACCEPTED
        if v.mode != "GUIDED":
            if not change_mode:
                raise Refusal(M.MAV_RESULT_DENIED, "Reposition: not in GUIDED")
            v.set_mode("GUIDED")
        v.position_target(target, None)
        return ACCEPTED

    def _on_set_mode(self, msg, addr) -> None:
        v = self.vehicle
        name = mode_name(v.flavour, msg.custom_mode)
        self.log.append((time.monotonic(), "mode_request", (name,)))
        try:
            v.set_mode(name)
            result = ACCEPTED
        except Refusal as refusal:
            self.statustext(refusal.text, M.MAV_SEVERITY_WARNING)
            result = refusal.result
        self._ack(msg, M.MAVLINK_MSG_ID_SET_MODE, result, addr)
        while v.events:
            self._send_event(v.events.popleft())

    def _on_request_data_stream(self, msg, addr) -> None:
        ids = list(DATA_STREAMS) if msg.req_stream_id == M.MAV_DATA_STREAM_ALL else [msg.req_stream_id]
        for sid in ids:
            for name in DATA_STREAMS.get(sid, ()):
                on = msg.start_stop and msg.req_message_rate > 0
                self.intervals_s[name] = 1.0 / msg.req_message_rate if on else 0.0
                self._next_due_s[name] = self.vehicle.t_s

    # ------------------------------------------------------------- setpoints
    def _on_target_global(self, msg, addr) -> None:
        v = self.vehicle
        mask = msg.type_mask
        values = [msg.lat_int, msg.lon_int, msg.alt, msg.vx, msg.vy, msg.vz]
        if not all(math.isfinite(x) for x in values):
            self.statustext("Guided: ignored a non-finite setpoint", M.MAV_SEVERITY_WARNING)
            return
        if not mask & 0x7:
            frame = msg.coordinate_frame
            target = v.global_target_enu(frame, msg.lat_int / 1e7, msg.lon_int / 1e7, msg.alt)
            v.position_target(target, None)
        elif not mask & 0x38:
            v.position_target(None, np.array([msg.vy, msg.vx, -msg.vz]))

    def _on_target_local(self, msg, addr) -> None:
        v = self.vehicle
        if not all(math.isfinite(x) for x in (msg.x, msg.y, msg.z, msg.vx, msg.vy, msg.vz)):
            self.statustext("Guided: ignored a non-finite setpoint", M.MAV_SEVERITY_WARNING)
            return
        if not msg.type_mask & 0x7 and msg.coordinate_frame == M.MAV_FRAME_LOCAL_NED:
            v.position_target(v.local_ned_to_enu(msg.x, msg.y, msg.z), None)
        elif not msg.type_mask & 0x38:
            v.position_target(None, np.array([msg.vy, msg.vx, -msg.vz]))

    # ------------------------------------------------------------- external position
    def _on_gps_input(self, msg, addr) -> None:
        """GPS_INPUT as ArduPilot's MAV GPS driver reads it: ``alt`` AMSL, accuracies in metres
        unless their ignore flags are set (then HDOP/VDOP x 1.5 m stand in), DOPs unitless."""
        ign = msg.ignore_flags
        if not all(math.isfinite(x) for x in (msg.alt, msg.horiz_accuracy, msg.hdop, msg.vdop)):
            return
        instances = self.vehicle._gps_instances()
        if self.vehicle.flavour == "ardupilot" and "mav" in instances and msg.gps_id != instances.index("mav"):
            # ArduPilot hands GPS_INPUT to the instance gps_id names (Copter 4.7 SITL: GPS2_TYPE
            # 14 stays "Bad fix" on gps_id 0)
            self.gps_input_ignored += 1
            return
        hdop = msg.hdop if not ign & M.GPS_INPUT_IGNORE_FLAG_HDOP and msg.hdop > 0 else math.nan
        vdop = msg.vdop if not ign & M.GPS_INPUT_IGNORE_FLAG_VDOP and msg.vdop > 0 else math.nan
        use_h = msg.horiz_accuracy > 0 and not ign & M.GPS_INPUT_IGNORE_FLAG_HORIZONTAL_ACCURACY
        use_v = msg.vert_accuracy > 0 and not ign & M.GPS_INPUT_IGNORE_FLAG_VERTICAL_ACCURACY
        eph = msg.horiz_accuracy if use_h else 1.5 * (hdop if hdop >= 0.5 else 1.0)
        epv = msg.vert_accuracy if use_v else 1.5 * (vdop if vdop >= 0.5 else 1.5)
        if not self.vehicle.gps_input(msg.lat / 1e7, msg.lon / 1e7, msg.alt, msg.fix_type,
                                      msg.satellites_visible, eph, epv, hdop, vdop):
            self.gps_input_ignored += 1  # silently, as the real autopilot does

    def _on_vision(self, msg, addr) -> None:
        cov0 = msg.covariance[0] if msg.covariance and math.isfinite(msg.covariance[0]) else 0.01
        if all(math.isfinite(x) for x in (msg.x, msg.y, msg.z)):
            self.vehicle.vision_position(msg.x, msg.y, msg.z, math.sqrt(max(cov0, 1e-6)))

    def _on_odometry(self, msg, addr) -> None:
        cov0 = msg.pose_covariance[0] if math.isfinite(msg.pose_covariance[0]) else 0.01
        if msg.frame_id in (M.MAV_FRAME_LOCAL_NED, M.MAV_FRAME_LOCAL_FRD) and \
                all(math.isfinite(x) for x in (msg.x, msg.y, msg.z)):
            self.vehicle.vision_position(msg.x, msg.y, msg.z, math.sqrt(max(cov0, 1e-6)))

    def _on_set_origin(self, msg, addr) -> None:
        self.vehicle.set_origin(msg.latitude / 1e7, msg.longitude / 1e7, msg.altitude / 1000.0)
        self.send(self._msg_gps_global_origin())
