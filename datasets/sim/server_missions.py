"""The simulated autopilot's mission protocol (MISSION_COUNT / REQUEST_INT / ITEM_INT / ACK,
list, clear, set current) on simulated time, with the firmware's re-request and give-up timings.

Mixed into :class:`skyfix.datasets.sim.server.VehicleServer` (``_upload`` holds the upload in
progress; ``service_upload`` runs after each simulation step).
"""

from __future__ import annotations

import dataclasses

from skyfix.drivers.mav import mavlink
from skyfix.errors import InputError
from skyfix.mission import MissionItem

M = mavlink
#: Mission upload timings, simulated seconds, as the firmware's: (re-request a missing item
#: after, abandon the upload after no item for). ArduPilot MissionItemProtocol: 1 s / 8 s;
#: PX4 MavlinkMissionManager: 0.25 s / 5 s.
MISSION_TIMINGS_S = {"ardupilot": (1.0, 8.0), "px4": (0.25, 5.0)}


class MissionProtocol:
    """MISSION_* handlers and the upload state machine."""

    def _mission_ack(self, addr, result: int, msg=None) -> None:
        sys_id, comp = (msg.get_srcSystem(), msg.get_srcComponent()) if msg else (255, 0)
        self.send(M.MAVLink_mission_ack_message(sys_id, comp, result, 0), addr)

    def _request_item(self) -> None:
        up = self._upload
        up["last_tx"] = self.vehicle.t_s
        self.send(M.MAVLink_mission_request_int_message(up["sys"], up["comp"], up["next"], 0), up["addr"])

    def _on_mission_count(self, msg, addr) -> None:
        if getattr(msg, "mission_type", M.MAV_MISSION_TYPE_MISSION) != M.MAV_MISSION_TYPE_MISSION:
            self._mission_ack(addr, M.MAV_MISSION_UNSUPPORTED, msg)
            return
        if msg.count == 0:
            self.vehicle.set_mission([])
            self._upload = None
            self._mission_ack(addr, M.MAV_MISSION_ACCEPTED, msg)
            return
        self._upload = {"count": msg.count, "items": [None] * msg.count, "next": 0, "addr": addr,
                        "sys": msg.get_srcSystem(), "comp": msg.get_srcComponent(),
                        "last_rx": self.vehicle.t_s}
        self._request_item()

    def _on_mission_item(self, msg, addr) -> None:
        up = self._upload
        if up is None:
            # the GCS missed our final ACK and resends its last item: acknowledge again
            if msg.seq == self._last_upload_count - 1:
                self._mission_ack(addr, M.MAV_MISSION_ACCEPTED, msg)
            return
        if msg.seq != up["next"]:
            if self.vehicle.flavour == "ardupilot":  # MissionItemProtocol: says so, keeps the upload,
                self._mission_ack(addr, M.MAV_MISSION_INVALID_SEQUENCE, msg)  # re-asks after 1 s
            else:
                self._request_item()  # duplicate or out of order: ask again for what we need
            return
        try:
            up["items"][msg.seq] = MissionItem.from_message(msg)
        except InputError as exc:  # NaN or out-of-range position/params: refuse the upload, as firmware does
            self._upload = None
            self._mission_ack(addr, M.MAV_MISSION_INVALID, msg)
            self.statustext(f"Mission: item {msg.seq} refused: {exc}", M.MAV_SEVERITY_WARNING)
            return
        up["next"] += 1
        up["last_rx"] = self.vehicle.t_s
        if up["next"] == up["count"]:
            self.vehicle.set_mission(up["items"])
            self._last_upload_count = up["count"]
            self._upload = None
            self._mission_ack(addr, M.MAV_MISSION_ACCEPTED, msg)
            self.statustext(f"Mission: {up['count']} items received")
        else:
            self._request_item()

    @property
    def upload_active(self) -> bool:
        return self._upload is not None

    def service_upload(self) -> None:
        """Re-request the missing mission item after silence, abandon the upload after a longer
        one (the firmware's timings, on the autopilot's simulated clock); called every step."""
        up = self._upload
        retry_s, give_up_s = MISSION_TIMINGS_S[self.vehicle.flavour]
        t = self.vehicle.t_s
        if up is None or t - up["last_tx"] < retry_s:
            return
        if t - up["last_rx"] > give_up_s:
            self._upload = None
            self._mission_ack(up["addr"], M.MAV_MISSION_OPERATION_CANCELLED)
            self.statustext("Mission upload timed out", M.MAV_SEVERITY_WARNING)
            return
        self._request_item()

    def _on_mission_list(self, msg, addr) -> None:
        if getattr(msg, "mission_type", M.MAV_MISSION_TYPE_MISSION) != M.MAV_MISSION_TYPE_MISSION:
            self.send(M.MAVLink_mission_count_message(msg.get_srcSystem(), msg.get_srcComponent(), 0,
                                                      msg.mission_type), addr)
            return
        self.send(M.MAVLink_mission_count_message(msg.get_srcSystem(), msg.get_srcComponent(),
                                                  len(self.vehicle.mission), 0), addr)

    def _on_mission_request(self, msg, addr) -> None:
        v = self.vehicle
        if not 0 <= msg.seq < len(v.mission):
            self._mission_ack(addr, M.MAV_MISSION_INVALID_SEQUENCE, msg)
            return
        it = v.mission[msg.seq]
        if v.flavour == "ardupilot" and msg.seq == 0:  # item 0 is the current home
            lat, lon, alt = v.geodetic_amsl(v.home_enu_m)
            it = dataclasses.replace(it, lat_deg=lat, lon_deg=lon, alt_m=alt, frame=M.MAV_FRAME_GLOBAL_INT)
        self.send(it.to_message(msg.seq, msg.get_srcSystem(), msg.get_srcComponent(),
                                current=msg.seq == v.mission_seq), addr)

    def _on_mission_clear(self, msg, addr) -> None:
        self.vehicle.set_mission([])
        self._mission_ack(addr, M.MAV_MISSION_ACCEPTED, msg)

    def _on_mission_set_current(self, msg, addr) -> None:
        self.vehicle.set_mission_current(msg.seq)
        self.send(self._msg_mission_current())
