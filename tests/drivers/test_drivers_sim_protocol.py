"""skyfix's simulator answers like the firmware where clients rely on it, checked with
plain pymavlink clients on real UDP sockets: one COMMAND_ACK per command (FAILED when it
cannot be handled, UNSUPPORTED once), NaN for unused params, one parser per sender, and
the mission protocol's re-request and give-up timings (ArduPilot: 1 s and 8 s)."""

from __future__ import annotations

import itertools
import math
import os
import socket
import statistics
import time

os.environ.setdefault("MAVLINK20", "1")

import pytest
from pymavlink import mavutil

from skyfix.datasets.sim import Simulator, SimulatorConfig

M = mavutil.mavlink


def _client(sim, source_system: int = 255):
    master = mavutil.mavlink_connection(sim.url(0), source_system=source_system)
    master.mav.heartbeat_send(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    assert master.wait_heartbeat(timeout=5) is not None
    return master


def _collect(master, mtype: str, seconds: float, cond=lambda m: True) -> list:
    out, end = [], time.monotonic() + seconds
    while time.monotonic() < end:
        m = master.recv_match(type=mtype, blocking=True, timeout=0.05)
        if m is not None and cond(m):
            out.append(m)
    return out


@pytest.fixture
def sim():
    with Simulator(SimulatorConfig(vehicles=1, speed=5.0, seed=9)) as s:
        yield s


def test_every_command_gets_exactly_one_ack(sim):
    master = _client(sim)
    try:
        def acks_for(command: int, *params: float) -> list[int]:
            p = list(params) + [0.0] * (7 - len(params))
            master.mav.command_long_send(1, 1, command, 0, *p)
            return [a.result for a in _collect(master, "COMMAND_ACK", 0.6, lambda a: a.command == command)]

        # a message the simulator does not produce: UNSUPPORTED, once (no ACCEPTED first)
        assert acks_for(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_WIND_COV) == [M.MAV_RESULT_UNSUPPORTED]
        assert acks_for(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_AUTOPILOT_VERSION) == [M.MAV_RESULT_ACCEPTED]
        # a value the handler cannot use (NaN mode number) is FAILED, not silence
        assert acks_for(M.MAV_CMD_DO_SET_MODE, 1, math.nan) == [M.MAV_RESULT_FAILED]
        assert sim.servers[0].vehicle.mode == "STABILIZE"
        # NaN in an unused param (MAVSDK's habit) is accepted
        assert acks_for(M.MAV_CMD_COMPONENT_ARM_DISARM, 0, math.nan, math.nan) == [M.MAV_RESULT_ACCEPTED]
        assert acks_for(M.MAV_CMD_DO_FLIGHTTERMINATION + 5000) == [M.MAV_RESULT_UNSUPPORTED]
    finally:
        master.close()


def test_a_truncated_frame_from_one_sender_does_not_swallow_anothers(sim):
    good = _client(sim, source_system=250)
    try:
        frame = M.MAVLink_param_request_read_message(1, 1, b"GPS1_TYPE", -1).pack(M.MAVLink(None, 251, 190))
        noisy = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        noisy.sendto(frame[: len(frame) // 2], sim.addresses[0])  # half a frame from another sender
        noisy.close()
        good.mav.param_request_read_send(1, 1, b"GPS1_TYPE", -1)
        got = _collect(good, "PARAM_VALUE", 1.0, lambda m: m.param_id == "GPS1_TYPE")
        assert len(got) == 1 and got[0].param_value == 1.0
    finally:
        good.close()


def test_mission_upload_timings_follow_the_firmware(sim):
    master = _client(sim)
    try:
        master.mav.mission_count_send(1, 1, 3, M.MAV_MISSION_TYPE_MISSION)
        t_req: list[float] = []
        ack = None
        end = time.monotonic() + 5.0
        while time.monotonic() < end and ack is None:
            m = master.recv_match(type=["MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"],
                                  blocking=True, timeout=0.05)
            if m is None:
                continue
            if m.get_type() == "MISSION_ACK":
                ack = (m, sim.time_s)
            else:
                assert m.seq == 0
                t_req.append(sim.time_s)
        assert ack is not None and ack[0].type == M.MAV_MISSION_OPERATION_CANCELLED
        gaps = [b - a for a, b in itertools.pairwise(t_req)]
        # re-requested every 1 s of autopilot time; the simulated clock is read when this client
        # gets the packet, so a loaded machine adds its scheduling delay (up to ~0.3 s seen)
        assert gaps and all(0.9 <= g <= 1.5 for g in gaps) and abs(statistics.median(gaps) - 1.0) < 0.15, gaps
        assert 7.6 <= ack[1] - t_req[0] <= 8.8  # abandoned after 8 s of silence
    finally:
        master.close()


def test_a_duplicate_item_is_refused_but_the_upload_goes_on(sim):
    """ArduPilot's MissionItemProtocol: an item that is not the one requested gets MISSION_ACK
    INVALID_SEQUENCE and the upload stays open (skyfix's uploader must not give up on it)."""
    master = _client(sim)
    try:
        lat, lon = sim.truth(0)["lat_deg"], sim.truth(0)["lon_deg"]

        def item(seq: int):
            return M.MAVLink_mission_item_int_message(1, 1, seq, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                                                      M.MAV_CMD_NAV_WAYPOINT, 0, 1, 0, 0, 0, 0,
                                                      int(lat * 1e7), int(lon * 1e7), 10.0, 0)

        master.mav.mission_count_send(1, 1, 2, M.MAV_MISSION_TYPE_MISSION)
        assert _collect(master, "MISSION_REQUEST_INT", 0.5, lambda m: m.seq == 0)
        master.mav.send(item(0))
        assert _collect(master, "MISSION_REQUEST_INT", 0.5, lambda m: m.seq == 1)
        master.mav.send(item(0))  # a re-send of an item it already has
        acks = _collect(master, "MISSION_ACK", 0.3)
        assert [a.type for a in acks] == [M.MAV_MISSION_INVALID_SEQUENCE]
        master.mav.send(item(1))
        acks = _collect(master, "MISSION_ACK", 0.5)
        assert [a.type for a in acks] == [M.MAV_MISSION_ACCEPTED]
        assert len(sim.vehicle(0).mission) == 2
    finally:
        master.close()


def test_gps_primary_pinned_with_auto_switch_off():
    """ArduPilot's GPS_AUTO_SWITCH 0 + GPS_PRIMARY 1: the EKF follows the second (GPS_INPUT)
    instance even while the real receiver is healthy; with auto switch on it follows GPS1."""
    from skyfix.drivers.vehicle import Vehicle

    with Simulator(SimulatorConfig(vehicles=1, speed=5.0, params={"GPS2_TYPE": 14})) as sim:
        v = Vehicle.connect(sim.url(0), timeout_s=5.0)
        try:
            v.wait_until(lambda s: s.position is not None and s.home is not None, 10.0)
            t = sim.truth(0)
            north_m = 25.0  # the injected position is 25 m north of the truth

            def inject_for(wall_s: float) -> None:
                end = time.monotonic() + wall_s
                while time.monotonic() < end:
                    v.inject_gps(t["lat_deg"] + north_m / 111_320.0, t["lon_deg"], t["alt_amsl_m"], h_acc_m=0.5)
                    time.sleep(0.02)

            inject_for(1.0)
            assert sim.truth(0)["est_error_m"] < 2.0  # auto switch: the healthy GPS1 wins
            v.set_param("GPS_AUTO_SWITCH", 0)
            v.use_injected_gps(True)  # GPS_PRIMARY 1 (the MAV GPS) + EKF source set 2
            assert v.get_param("GPS_PRIMARY") == 1 and sim.vehicle(0).ekf_source_set == 2
            inject_for(2.0)
            assert math.isclose(sim.truth(0)["est_error_m"], north_m, abs_tol=2.0)
            v.use_injected_gps(False)  # back to the real receiver
            assert sim.vehicle(0).ekf_source_set == 1
            inject_for(2.0)
            assert sim.truth(0)["est_error_m"] < 2.0
        finally:
            v.close()
