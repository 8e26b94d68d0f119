"""More link behaviour: TCP reconnect, retries under loss, stream rates, safety actions,
PX4 vision (ODOMETRY)."""

from __future__ import annotations

import socket
import threading
import time

import pytest

from skyfix.datasets.sim import Simulator, SimulatorConfig
from skyfix.drivers.mav import mavlink
from skyfix.drivers.mission import MissionItem
from skyfix.drivers.modes import custom_mode_of
from skyfix.drivers.safety import SafetyGate
from skyfix.drivers.vehicle import Vehicle
from skyfix.geo import destination


def _heartbeat_server(listener: socket.socket, modes: list[str], stop: threading.Event) -> None:
    """A TCP peer that sends ArduPilot heartbeats, one connection per mode, closing in between."""
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    for mode in modes:
        conn, _ = listener.accept()
        end = time.monotonic() + 0.6
        while time.monotonic() < end and not stop.is_set():
            hb = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                                   mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                                                   custom_mode_of("ardupilot", mode), 3, 3)
            conn.sendall(hb.pack(mav))
            time.sleep(0.05)
        conn.close()


def test_tcp_link_reconnects_after_the_peer_closes():
    listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    listener.bind(("127.0.0.1", 0))
    listener.listen(2)
    stop = threading.Event()
    server = threading.Thread(target=_heartbeat_server, args=(listener, ["LOITER", "BRAKE"], stop), daemon=True)
    server.start()
    v = Vehicle.connect(f"tcp:127.0.0.1:{listener.getsockname()[1]}", timeout_s=3.0)
    try:
        assert v.wait_until(lambda s: s.mode == "LOITER", 2.0).mode == "LOITER"
        # the server drops the connection after 0.6 s and accepts again: the link reopens itself
        v.wait_until(lambda s: s.mode == "BRAKE", 5.0, what="heartbeats on the new TCP connection")
        assert v.link.reconnects >= 1
    finally:
        stop.set()
        v.close()
        listener.close()


def test_commands_retry_through_packet_loss():
    with Simulator(SimulatorConfig(vehicles=1, speed=2.0, loss_rate=0.3, seed=9)) as sim:
        v = Vehicle.connect(sim.url(0), timeout_s=5.0)
        try:
            # 30 % loss each way: a single attempt fails about half the time; 6 attempts
            # all fail with probability 0.51**6 ~ 2 %, per command
            for _ in range(10):
                v.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_ATTITUDE, 100_000,
                          timeout_s=0.1, retries=8)
            v.set_param("WPNAV_SPEED", 800.0, timeout_s=0.2, retries=10)  # 0.51**11 ~ 6e-4 to fail
            assert sim.vehicle(0).params["WPNAV_SPEED"] == 800.0
        finally:
            v.close()


def test_streams_arrive_at_requested_rates(sim):
    v = Vehicle.connect(sim.url(0), timeout_s=5.0,
                        stream_rates_hz={"GLOBAL_POSITION_INT": 20.0, "ATTITUDE": 2.0})
    try:
        v.wait_until(lambda s: s.position is not None, 3.0)
        counts = {"GLOBAL_POSITION_INT": 0, "ATTITUDE": 0}
        with v.subscribe(lambda m: m.get_type() in counts) as q:
            t0 = sim.time_s
            time.sleep(1.0)
            t1 = sim.time_s
            while not q.empty():
                counts[q.get()[0].get_type()] += 1
        sim_s = t1 - t0
        # rates run on simulated time; the window's edges are read from the simulator's clock
        # while messages are still in flight (at 5x, 0.1 s of wall is 0.5 s of sim): +-2
        # messages for those, +-20 % for timing jitter on a loaded machine. The default 10 Hz
        # ATTITUDE (~50 here) stays far outside the 2 Hz band (~6-14).
        assert abs(counts["GLOBAL_POSITION_INT"] - 20.0 * sim_s) <= 2 + 0.2 * 20 * sim_s
        assert abs(counts["ATTITUDE"] - 2.0 * sim_s) <= 2.5 + 0.2 * 2 * sim_s
    finally:
        v.close()


def test_speed_violation_in_telemetry_triggers_land(sim, vehicle):
    v = vehicle
    home = v.state.home
    v.set_mode("GUIDED")
    v.arm()
    v.takeoff(10.0)
    v.set_safety(SafetyGate(max_speed_mps=6.0, action="land"))
    lat, lon = (float(x) for x in destination(home.lat_deg, home.lon_deg, 0.0, 150.0))
    # the mission asks for 9 m/s: the gate cannot vet mission legs, telemetry shows the excess
    v.upload_mission([MissionItem.change_speed(9.0), MissionItem.waypoint(lat, lon, 10.0)])
    v.start_mission()
    st = v.wait_until(lambda s: s.mode == "LAND", 30.0, what="LAND after the speed violation")
    latency_s, reason = v.safety_log[-1]
    assert "speed" in reason and latency_s < 0.05
    assert st.velocity.speed_mps > 6.0
    v.wait_until(lambda s: not s.armed, 60.0, what="landed")


def test_px4_vision_odometry_moves_the_estimate():
    with Simulator(SimulatorConfig(vehicles=1, flavour="px4", speed=2.0)) as sim:
        v = Vehicle.connect(sim.url(0), timeout_s=5.0)
        try:
            home = v.wait_until(lambda s: s.home is not None, 5.0).home
            with pytest.raises(Exception, match="EKF2_EV_CTRL"):
                v.inject_vision(0.0, 0.0, 0.0, sigma_m=0.1, odometry=True)
            v.set_param("EKF2_EV_CTRL", 15)
            v.set_param("EKF2_GPS_CTRL", 0)  # vision only, so the estimate must follow it
            v.set_origin(home.lat_deg, home.lon_deg, home.alt_amsl_m)
            e0, n0, u0 = (float(x) for x in sim.world.to_enu(home.lat_deg, home.lon_deg, home.alt_ellipsoid_m))
            for _ in range(30):
                t = sim.truth(0)
                v.inject_vision(t["north_m"] - n0 - 2.0, t["east_m"] - e0, -(t["up_m"] - u0), sigma_m=0.1,
                                odometry=True)
                time.sleep(0.05)
            # the estimate follows the vision fixes, 2 m south of the truth (0.1 m sigma)
            assert 1.5 < sim.truth(0)["est_error_m"] < 2.5
        finally:
            v.close()
