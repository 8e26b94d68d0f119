"""Mission upload as one file over MAVLink FTP (ArduPilot 4.1+), verified by reading it back.

The item protocol (:mod:`skyfix.drivers.mission`) moves one item per round trip, and
ArduPilot answers each on its next scheduler ticks: ~5.8 ms per item at 400 Hz, 2.9 s for
500 items however fast the client is. ArduPilot also exposes its mission as the virtual
file ``@MISSION/mission.dat`` (``libraries/AP_Filesystem/AP_Filesystem_Mission.cpp``): a
10-byte header (magic 0x763d, mission type, options, first index, item count; little-endian
uint16) followed by each item as the MISSION_ITEM_INT payload in wire order (38 bytes,
home as item 0). Written with MAVLink FTP (several 239-byte writes in flight), it is
replaced on close. MAVProxy's ``wp ftpload`` uses the same path.

The FTP protocol itself is pymavlink's :class:`pymavlink.mavftp.MAVFTP`, fed through a
small adapter from skyfix's link (its reader thread owns the socket). Opening the client
resets the autopilot's FTP sessions, which would abort another client's transfer in flight.
"""

from __future__ import annotations

import io
import logging
import queue
import struct
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING

from skyfix.drivers.mav import mavlink
from skyfix.drivers.mission import MissionItem, TransferStats, _wire_items
from skyfix.errors import CommandRejected, SkyfixTimeout

if TYPE_CHECKING:
    from skyfix.drivers.vehicle import Vehicle

log = logging.getLogger(__name__)
M = mavlink
MISSION_FILE = "@MISSION/mission.dat"
_MAGIC = 0x763D
_HEADER = struct.Struct("<HHHHH")  # magic, mission type, options, start index, item count


class _LinkAdapter:
    """What MAVFTP needs of a pymavlink connection, on top of a skyfix Vehicle: ``mav``
    with ``file_transfer_protocol_send``, ``recv_match`` and the source ids."""

    def __init__(self, vehicle: Vehicle, replies: queue.Queue) -> None:
        self._vehicle, self._replies = vehicle, replies
        self.source_system = vehicle.link.source_system
        self.source_component = vehicle.link.source_component
        self.mav = self

    def file_transfer_protocol_send(self, network: int, target_system: int, target_component: int,
                                    payload) -> None:
        self._vehicle.send(M.MAVLink_file_transfer_protocol_message(network, target_system,
                                                                    target_component, bytes(payload)))

    def recv_match(self, type=None, timeout: float | None = None, blocking: bool = True):  # noqa: A002
        try:
            return self._replies.get(timeout=timeout if blocking else 0.0)[0]
        except queue.Empty:
            return None


def mission_file(vehicle: Vehicle, items: Sequence[MissionItem]) -> bytes:
    """The bytes of ``@MISSION/mission.dat`` for ``items`` (ArduPilot's home item 0 added)."""
    wire = _wire_items(vehicle, items)
    out = bytearray(_HEADER.pack(_MAGIC, M.MAV_MISSION_TYPE_MISSION, 0, 0, len(wire)))
    for seq, item in enumerate(wire):
        msg = item.to_message(seq, vehicle.system_id, vehicle.component_id)
        out += msg.unpacker.pack(*(getattr(msg, f) for f in msg.ordered_fieldnames))
    return bytes(out)


def _ftp(vehicle: Vehicle, replies: queue.Queue):
    from pymavlink import mavftp

    settings = mavftp.MAVFTPSettings([
        ("debug", int, 0), ("pkt_loss_tx", int, 0), ("pkt_loss_rx", int, 0), ("max_backlog", int, 5),
        ("burst_read_size", int, 239), ("write_size", int, 239),  # full FTP payloads
        ("write_qsize", int, 5), ("idle_detection_time", float, 1.2), ("read_retry_time", float, 0.5),
        ("retry_time", float, 0.5)])
    return mavftp.MAVFTP(_LinkAdapter(vehicle, replies), vehicle.system_id, vehicle.component_id,
                         settings=settings)


def upload_ftp(vehicle: Vehicle, items: Sequence[MissionItem], *, timeout_s: float = 10.0,
               verify: bool = True) -> TransferStats:
    """Upload ``items`` as ``@MISSION/mission.dat`` (ArduPilot only); with ``verify`` the file
    is read back (FTP burst read) and compared byte for byte, so a mission the autopilot did
    not take (it rejects a bad file on close) is an error, not a silent loss.

    Raises CommandRejected when the autopilot refuses (no FTP, not ArduPilot, file rejected)
    and SkyfixTimeout when the transfer does not finish within ``timeout_s``.
    """
    if vehicle.autopilot != "ardupilot":
        raise CommandRejected(f"vehicle {vehicle.system_id}: mission upload over FTP needs ArduPilot "
                              f"({vehicle.autopilot} has no {MISSION_FILE}); use the item protocol",
                              command="FTP")
    data = mission_file(vehicle, items)
    t0 = time.monotonic()
    with vehicle.subscribe(lambda m: m.get_type() == "FILE_TRANSFER_PROTOCOL") as replies:
        ftp = _ftp(vehicle, replies)
        ftp.cmd_put(["mission", MISSION_FILE], fh=io.BytesIO(data))
        result = ftp.process_ftp_reply("put", timeout=timeout_s)
        if result.error_code != 0:
            _raise(vehicle, t0, "write", result)
        if verify:
            back = ftp.read(MISSION_FILE, len(data))
            differs = "nothing" if back is None else _difference(data, bytes(back))
            if differs:
                raise CommandRejected(f"vehicle {vehicle.system_id} did not keep the uploaded mission: "
                                      f"{MISSION_FILE} read back: {differs}{vehicle._reasons(t0)}",
                                      command="FTP")
    return TransferStats(len(items), time.monotonic() - t0, 0)


#: ArduPilot stores positions as integers and reports frames without the _INT suffix
_FRAME_BASE = {M.MAV_FRAME_GLOBAL_INT: M.MAV_FRAME_GLOBAL,
               M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT: M.MAV_FRAME_GLOBAL_RELATIVE_ALT,
               M.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT: M.MAV_FRAME_GLOBAL_TERRAIN_ALT}


_KEPT = (4, 5, 6, 7, 8, 11)  # x, y, z, seq, command, frame in MISSION_ITEM_INT's wire order


def _items_of(blob: bytes) -> list[tuple]:
    """The mission items in a mission file as (seq, command, frame, lat degE7, lon degE7,
    alt cm): home item 0 is left out (the autopilot keeps its own home there), and so are
    the params, which ArduPilot stores in narrower types (a 2.5 s hold comes back as 2)."""
    unpack = M.MAVLink_mission_item_int_message.unpacker.unpack
    size = M.MAVLink_mission_item_int_message.unpacker.size
    out = []
    for ofs in range(_HEADER.size + size, len(blob) - size + 1, size):
        x, y, z, seq, cmd, frame = (v for i, v in enumerate(unpack(blob[ofs:ofs + size])) if i in _KEPT)
        frame = _FRAME_BASE.get(frame, frame)
        positional = frame in _FRAME_BASE.values()  # DO_ commands keep their own fields
        out.append((seq, cmd, frame, x, y, round(z * 100.0)) if positional else (seq, cmd))
    return out


def _difference(sent: bytes, back: bytes) -> str:
    """'' when ``back`` holds the items of ``sent``, else what differs (for the error)."""
    if len(back) != len(sent) or _HEADER.unpack(back[:_HEADER.size]) != _HEADER.unpack(sent[:_HEADER.size]):
        return f"{len(back)} bytes, not the {len(sent)}-byte mission sent"
    for a, b in zip(_items_of(sent), _items_of(back), strict=True):
        if a != b:
            return f"item {a[0]} is {b[1:]}, sent {a[1:]}"
    return ""


def _raise(vehicle: Vehicle, t0: float, what: str, result) -> None:
    from pymavlink.mavftp import FtpError

    text = f"{FtpError(result.error_code).name} (FTP {result.operation_name})"
    if result.error_code == FtpError.RemoteReplyTimeout:
        raise SkyfixTimeout(f"vehicle {vehicle.system_id}: mission {what} over FTP not answered: "
                            f"{text}{vehicle._reasons(t0)}")
    raise CommandRejected(f"vehicle {vehicle.system_id} refused the mission {what} over FTP: "
                          f"{text}{vehicle._reasons(t0)}", command="FTP", result=result.error_code)
