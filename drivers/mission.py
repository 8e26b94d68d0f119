"""Missions over the MAVLink mission protocol (MISSION_ITEM_INT), with loss recovery.

Upload: the vehicle pulls items one by one (MISSION_REQUEST_INT); skyfix answers
each request with exactly the item asked for, so a lost item is retransmitted alone,
and when the vehicle goes quiet it resends the last packet (COUNT or item). ArduPilot
stores home as item 0 and flies from item 1: skyfix inserts a placeholder on upload
and drops item 0 on download, so callers see the same list on both autopilots.
The item type is the foundation's :class:`skyfix.mission.MissionItem` (re-exported here).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import msgspec

from skyfix.drivers.mav import mavlink
from skyfix.drivers.request import DONE, transact
from skyfix.errors import CommandRejected, InputError, SkyfixTimeout
from skyfix.jsonfile import json_schema
from skyfix.mission import MissionItem

if TYPE_CHECKING:
    from skyfix.drivers.vehicle import Vehicle

M = mavlink
_RESULTS = {v: k for k, v in vars(M).items() if k.startswith("MAV_MISSION_") and isinstance(v, int)
            and k not in ("MAV_MISSION_TYPE_MISSION", "MAV_MISSION_RESULT_ENUM_END")}


class MissionFile(msgspec.Struct, kw_only=True):
    """A mission as ``skyfix vehicle mission download`` writes it and ``upload`` reads it.

    Example:
        >>> from skyfix.jsonfile import convert
        >>> plan = convert({"items": [{"command": 22, "alt_m": 10.0}]}, MissionFile, "plan.json")
        >>> plan.items[0].frame == M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, plan.system_id
        (True, None)
    """

    system_id: int | None = None
    items: list[MissionItem]


def mission_json_schema() -> dict:
    """JSON Schema of the mission file (:class:`MissionFile`), published in docs/schemas/."""
    return json_schema(MissionFile) | {"title": "skyfix mission"}


@dataclass(frozen=True)
class TransferStats:
    """How a mission transfer went: items, wall seconds, packets we had to resend."""

    items: int
    elapsed_s: float
    retransmissions: int


def _wire_items(vehicle: Vehicle, items: Sequence[MissionItem]) -> list[MissionItem]:
    items = list(items)
    for i, it in enumerate(items):
        if not isinstance(it, MissionItem):
            raise InputError(f"mission item {i} must be a MissionItem, got {type(it).__name__}")
    if vehicle.autopilot == "ardupilot" and items:
        home = vehicle.state.home
        placeholder = MissionItem(M.MAV_CMD_NAV_WAYPOINT, home.lat_deg if home else 0.0,
                                  home.lon_deg if home else 0.0, 0.0, frame=M.MAV_FRAME_GLOBAL_INT)
        items.insert(0, placeholder)
    return items


def upload(vehicle: Vehicle, items: Sequence[MissionItem], *, progress: Callable[[int, int], None] | None = None,
           item_timeout_s: float = 0.25, timeout_s: float = 60.0) -> TransferStats:
    """Upload ``items``; ``progress(done, total)`` after each item sent for the first time.

    Raises CommandRejected when the vehicle refuses (MAV_MISSION_* result named) and
    SkyfixTimeout when it stops answering for ``timeout_s``.
    """
    wire = _wire_items(vehicle, items)
    n = len(wire)
    sysid, comp = vehicle.system_id, vehicle.component_id
    count_msg = M.MAVLink_mission_count_message(sysid, comp, n, M.MAV_MISSION_TYPE_MISSION)
    t0 = time.monotonic()
    resent = 0
    highest = -1

    def wanted(m) -> bool:
        return m.get_type() in ("MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK") \
            and getattr(m, "mission_type", 0) == M.MAV_MISSION_TYPE_MISSION

    retries = max(1, int(timeout_s / item_timeout_s))
    resends = [0]

    def count_resend() -> None:
        resends[0] += 1

    with vehicle.subscribe(wanted) as q:
        out, sent = count_msg, False
        progress_t = time.monotonic()  # last time the transfer moved on
        while True:
            if time.monotonic() - progress_t > timeout_s:  # answers, but no progress
                raise SkyfixTimeout(f"vehicle {sysid}: mission upload stuck at item {highest + 1}/{n} "
                                    f"for {timeout_s:.0f} s{vehicle._reasons(t0)}")
            msg = transact(vehicle, out, lambda m: DONE, types=(), replies=q, timeout_s=item_timeout_s,
                           retries=retries, what=f"mission upload at item {highest + 1}/{n}",
                           on_resend=count_resend, first_sent=sent)
            sent = True  # until the vehicle asks for something new, only silence re-sends
            if msg.get_type() == "MISSION_ACK":
                if msg.type == M.MAV_MISSION_ACCEPTED and (n == 0 or out is not count_msg and out.seq == n - 1):
                    return TransferStats(len(items), time.monotonic() - t0, resends[0] + resent)
                if msg.type == M.MAV_MISSION_INVALID_SEQUENCE and out is not count_msg:
                    # ArduPilot already has the item we re-sent: its request for the next one was
                    # lost. It keeps the upload open (and re-asks only after 1 s): send that one now
                    if out.seq + 1 < n:
                        out, sent = wire[out.seq + 1].to_message(out.seq + 1, sysid, comp), False
                        progress_t = time.monotonic()
                    continue
                if msg.type == M.MAV_MISSION_ACCEPTED:
                    continue  # a stale ACK from an earlier transaction: keep listening
                name = _RESULTS.get(msg.type, str(msg.type))
                raise CommandRejected(f"vehicle {sysid} rejected the mission upload ({name}) "
                                      f"at item {highest + 1}/{n}{vehicle._reasons(t0)}",
                                      command="MISSION_COUNT", result=msg.type)
            seq = msg.seq
            if not 0 <= seq < n:
                continue
            out, sent = wire[seq].to_message(seq, sysid, comp), False
            if seq > highest:
                highest, progress_t = seq, time.monotonic()
                if progress is not None:
                    progress(seq + 1, n)
            else:
                resent += 1


def download(vehicle: Vehicle, *, item_timeout_s: float = 0.25, timeout_s: float = 60.0) -> list[MissionItem]:
    """Read the vehicle's mission; lost requests or items are asked for again."""
    sysid, comp = vehicle.system_id, vehicle.component_id

    def wanted(m) -> bool:
        return m.get_type() in ("MISSION_COUNT", "MISSION_ITEM_INT", "MISSION_ITEM")

    retries = max(1, int(timeout_s / item_timeout_s))

    def ask(q, request, match: Callable, what: str):
        return transact(vehicle, request, lambda m: DONE if match(m) else None, types=(), replies=q,
                        timeout_s=item_timeout_s, retries=retries, what=what)

    with vehicle.subscribe(wanted) as q:
        req = M.MAVLink_mission_request_list_message(sysid, comp, M.MAV_MISSION_TYPE_MISSION)
        count = ask(q, req, lambda m: m.get_type() == "MISSION_COUNT", "MISSION_REQUEST_LIST").count
        items = []
        for seq in range(count):
            req = M.MAVLink_mission_request_int_message(sysid, comp, seq, M.MAV_MISSION_TYPE_MISSION)
            msg = ask(q, req, lambda m, s=seq: m.get_type() != "MISSION_COUNT" and m.seq == s,
                      f"MISSION_REQUEST_INT {seq}/{count}")
            items.append(MissionItem.from_message(msg))
        vehicle.send(M.MAVLink_mission_ack_message(sysid, comp, M.MAV_MISSION_ACCEPTED,
                                                   M.MAV_MISSION_TYPE_MISSION))
    return items[1:] if vehicle.autopilot == "ardupilot" and items else items


def clear(vehicle: Vehicle, *, timeout_s: float = 1.0, retries: int = 3) -> None:
    """Delete the vehicle's mission (MISSION_CLEAR_ALL, acknowledged)."""
    sysid, comp = vehicle.system_id, vehicle.component_id
    msg = transact(vehicle, M.MAVLink_mission_clear_all_message(sysid, comp, M.MAV_MISSION_TYPE_MISSION),
                   lambda m: DONE, types=("MISSION_ACK",), timeout_s=timeout_s, retries=retries,
                   what="MISSION_CLEAR_ALL")
    if msg.type != M.MAV_MISSION_ACCEPTED:
        raise CommandRejected(f"vehicle {sysid} refused to clear its mission "
                              f"({_RESULTS.get(msg.type, msg.type)})", command="MISSION_CLEAR_ALL",
                              result=msg.type)
