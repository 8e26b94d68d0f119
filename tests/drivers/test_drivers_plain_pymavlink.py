"""A plain pymavlink client (no skyfix driver code) flies the simulator, as it would an autopilot."""

from __future__ import annotations

import os
import struct
import time

os.environ.setdefault("MAVLINK20", "1")

import pytest
from pymavlink import mavutil

from skyfix.datasets.sim import Simulator, SimulatorConfig


def _wait(master, mtype, cond=lambda m: True, timeout=10.0):
    end = time.time() + timeout
    while time.time() < end:
        m = master.recv_match(type=mtype, blocking=True, timeout=0.2)
        if m is not None and cond(m):
            return m
    raise AssertionError(f"no {mtype} within {timeout} s")


def _ack(master, command):
    return _wait(master, "COMMAND_ACK", lambda m: m.command == command, 3.0).result


@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
def test_plain_pymavlink_flies_the_simulator(flavour, udp_port):
    port = udp_port
    cfg = SimulatorConfig(vehicles=1, flavour=flavour, base_port=port, speed=5.0)
    with Simulator(cfg):
        # like a GCS listening for SITL's output: udpin on the base port
        master = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255)
        try:
            hb = master.wait_heartbeat(timeout=5)
            assert hb is not None and master.target_system == 1
            assert hb.autopilot == (mavutil.mavlink.MAV_AUTOPILOT_PX4 if flavour == "px4"
                                    else mavutil.mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA)
            pos0 = _wait(master, "GLOBAL_POSITION_INT")
            master.mav.command_long_send(1, 1, mavutil.mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 0,
                                         1, 0, 0, 0, 0, 0, 0)
            caps = _wait(master, "AUTOPILOT_VERSION").capabilities
            assert caps & mavutil.mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT
            assert caps & mavutil.mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
            if flavour == "ardupilot":
                master.set_mode("GUIDED")
                assert _ack(master, mavutil.mavlink.MAV_CMD_DO_SET_MODE) == 0
                _wait(master, "HEARTBEAT", lambda m: master.flightmode == "GUIDED")
            master.arducopter_arm()
            assert _ack(master, mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM) == 0
            master.motors_armed_wait()
            alt = 8.0 if flavour == "ardupilot" else pos0.alt / 1000.0 + 8.0  # PX4 takes AMSL
            master.mav.command_long_send(1, 1, mavutil.mavlink.MAV_CMD_NAV_TAKEOFF, 0,
                                         0, 0, 0, 0, 0, 0, alt)
            assert _ack(master, mavutil.mavlink.MAV_CMD_NAV_TAKEOFF) == 0
            _wait(master, "GLOBAL_POSITION_INT", lambda m: m.relative_alt > 7500, 30)
            # upload a one-waypoint mission 20 m north with the MISSION_ITEM_INT protocol
            lat = pos0.lat + int(20.0 / 111_320.0 * 1e7)
            items = [(mavutil.mavlink.MAV_CMD_NAV_WAYPOINT, pos0.lat, pos0.lon, 0.0)] \
                if flavour == "ardupilot" else []  # ArduPilot: item 0 is home
            items += [(mavutil.mavlink.MAV_CMD_NAV_WAYPOINT, lat, pos0.lon, 8.0),
                      (mavutil.mavlink.MAV_CMD_NAV_LAND, 0, 0, 0.0)]
            master.mav.mission_count_send(1, 1, len(items), 0)
            while True:
                m = _wait(master, ["MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"])
                if m.get_type() == "MISSION_ACK":
                    assert m.type == mavutil.mavlink.MAV_MISSION_ACCEPTED
                    break
                cmd, x, y, z = items[m.seq]
                master.mav.mission_item_int_send(1, 1, m.seq, mavutil.mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                                                 cmd, 0, 1, 0, 0, 0, 0, x, y, z, 0)
            master.mav.command_long_send(1, 1, mavutil.mavlink.MAV_CMD_MISSION_START, 0, 0, 0, 0, 0, 0, 0, 0)
            assert _ack(master, mavutil.mavlink.MAV_CMD_MISSION_START) == 0
            _wait(master, "MISSION_ITEM_REACHED", lambda m: m.seq == len(items) - 2, 40)
            near = _wait(master, "GLOBAL_POSITION_INT")
            assert abs(near.lat - lat) / 1e7 * 111_320.0 < 4.0  # 2 m acceptance + GPS bias
            # the land item lands and the autopilot disarms itself
            _wait(master, "HEARTBEAT", lambda m: not m.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED,
                  60)
            landed = _wait(master, "GLOBAL_POSITION_INT")
            assert landed.relative_alt < 200
            # parameters answer like an autopilot's
            master.mav.param_request_read_send(1, 1, b"GPS1_TYPE" if flavour == "ardupilot" else b"EKF2_GPS_CTRL", -1)
            pv = _wait(master, "PARAM_VALUE")
            assert pv.param_type == mavutil.mavlink.MAV_PARAM_TYPE_INT32
            # ArduPilot casts an integer to the float; PX4 copies its bytes (7 -> 9.8e-45)
            raw = struct.unpack("<i", struct.pack("<f", pv.param_value))[0]
            assert (pv.param_value if flavour == "ardupilot" else raw) == (1.0 if flavour == "ardupilot" else 7)
        finally:
            master.close()
