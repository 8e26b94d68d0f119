"""Bad input gets clear errors; the reader and the simulator survive malformed packets."""

from __future__ import annotations

import math
import socket
import time

import numpy as np
import pytest

from skyfix.drivers.mav import mavlink
from skyfix.drivers.mission import MissionItem
from skyfix.drivers.safety import Geofence, SafetyGate
from skyfix.drivers.vehicle import Vehicle
from skyfix.errors import InputError, LinkError, SafetyViolation


def test_unreachable_url_gives_link_error(udp_port):
    t0 = time.monotonic()
    with pytest.raises(LinkError, match="no HEARTBEAT") as err:
        Vehicle.connect(f"udpout:127.0.0.1:{udp_port}", timeout_s=0.5)
    assert "udpout:127.0.0.1" in str(err.value) and time.monotonic() - t0 < 5.0  # 0.5 s asked; slack for load
    with pytest.raises(LinkError, match="cannot open"):
        Vehicle.connect(f"tcp:127.0.0.1:{udp_port}", timeout_s=0.5)  # nobody listens: refused
    with pytest.raises(LinkError, match="cannot open"):
        Vehicle.connect("/dev/ttyNOPE0:57600", timeout_s=0.5)


@pytest.mark.parametrize("url", ["", "127.0.0.1:14550", "udp:localhost", "http://x:1", None])
def test_malformed_url_gives_input_error(url):
    with pytest.raises(InputError, match="MAVLink url must look like"):
        Vehicle.connect(url, timeout_s=0.5)


def _frames_and_garbage(rng: np.random.Generator) -> list[bytes]:
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    good = mavlink.MAVLink_statustext_message(6, b"hello", 0, 0).pack(mav)
    bad_crc = bytearray(good)
    bad_crc[-1] ^= 0xFF
    return [rng.integers(0, 256, 300, dtype=np.uint8).tobytes(),  # noise
            bytes(bad_crc),  # corrupted checksum
            good[:7],  # truncated frame
            b"\xfd\xff" + bytes(20),  # header claiming 255 bytes of payload
            b"\xfe\x09\x00\x01\x01\x00" + bytes(11)]  # MAVLink 1 heartbeat with a wrong CRC


def test_reader_survives_garbage(sim, vehicle):
    port = vehicle.link._conn.port.getsockname()[1]
    rng = np.random.default_rng(1)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for _ in range(50):
            for blob in _frames_and_garbage(rng):
                s.sendto(blob, ("127.0.0.1", port))
        # garbage into the simulator too: the autopilot keeps flying and answering
        for blob in _frames_and_garbage(rng):
            s.sendto(blob, sim.addresses[0])
    time.sleep(0.3)
    t_pos = vehicle.state.position.time_s
    st = vehicle.wait_until(lambda st: st.position.time_s > t_pos, 2.0, what="fresh telemetry")
    assert st.link_ok
    assert vehicle.link.bad_packets > 0
    vehicle.set_mode("GUIDED")  # the command path still works
    assert sim.servers[0].bad_packets > 0


def test_bad_setpoints_are_refused(vehicle):
    home = vehicle.state.home
    vehicle.set_safety(SafetyGate(Geofence.circle(home.lat_deg, home.lon_deg, 50.0, max_alt_rel_m=30.0),
                                  max_speed_mps=8.0))
    with pytest.raises(InputError, match="lat_deg must be finite"):
        vehicle.goto(math.nan, home.lon_deg, 10.0)
    with pytest.raises(InputError, match="alt_m must be finite"):
        vehicle.goto(home.lat_deg, home.lon_deg, math.inf)
    with pytest.raises(InputError, match="within \\[-90, 90\\]"):
        vehicle.goto(91.0, home.lon_deg, 10.0)
    with pytest.raises(InputError, match="east_mps must be finite"):
        vehicle.velocity(0.0, math.nan, 0.0)
    with pytest.raises(SafetyViolation, match="exceeds max_speed_mps"):
        vehicle.velocity(10.0, 0.0, 0.0)
    with pytest.raises(SafetyViolation, match="exceeds max_alt_rel_m|above the fence maximum"):
        vehicle.goto(home.lat_deg, home.lon_deg, 45.0)
    with pytest.raises(SafetyViolation, match="outside the geofence"):
        vehicle.goto(home.lat_deg + 0.001, home.lon_deg, 10.0)  # 111 m north
    with pytest.raises(InputError, match="alt_m must be > 0"):
        vehicle.takeoff(-1.0)
    with pytest.raises(InputError, match="mode must be one of the ArduCopter modes"):
        vehicle.set_mode("OFFBOARD")
    with pytest.raises(InputError, match="MissionItem.lat_deg"):
        MissionItem.waypoint(math.nan, 0.0, 10.0)
    with pytest.raises(InputError, match="mission item 0 must be a MissionItem"):
        vehicle.upload_mission([("not", "an", "item")])
    with pytest.raises(InputError, match="h_acc_m must be > 0"):
        vehicle.inject_gps(home.lat_deg, home.lon_deg, 0.0, h_acc_m=0.0)
    assert vehicle.state.mode == "STABILIZE"  # nothing was sent that changed the vehicle


def test_geofence_and_gate_validation():
    with pytest.raises(InputError, match="at least 3 vertices"):
        Geofence([np.array([[0.0, 0.0], [0.0, 1e-4]])])
    with pytest.raises(InputError, match="min_alt_rel_m < max_alt_rel_m"):
        Geofence(min_alt_rel_m=10.0, max_alt_rel_m=5.0)
    with pytest.raises(InputError, match="action must be one of"):
        SafetyGate(action="explode")
    with pytest.raises(InputError, match="max_speed_mps must be > 0"):
        SafetyGate(max_speed_mps=math.nan)
