"""Link behaviour: heartbeat loss and recovery, several system ids on one link, PX4 specifics,
refusals carrying the autopilot's own reason."""

from __future__ import annotations

import time

import pytest

from skyfix.datasets.sim import Simulator, SimulatorConfig
from skyfix.drivers.mav import mavlink
from skyfix.drivers.vehicle import Vehicle
from skyfix.errors import CommandRejected, ConfigurationError, LinkError
from skyfix.geo import destination


def test_heartbeat_loss_is_surfaced_and_link_recovers():
    sim = Simulator(SimulatorConfig(vehicles=1, speed=2.0)).start()
    port = sim.addresses[0][1]
    v = Vehicle.connect(sim.url(0), timeout_s=5.0, heartbeat_timeout_s=1.0)
    try:
        v.wait_until(lambda s: s.position is not None, 5.0)
        sim.stop()
        t0 = time.monotonic()
        # heartbeats come every 0.5 s of wall time at 2x; loss declared 1.0 s after the last one,
        # checked every 50 ms (slack for a loaded CI machine)
        with pytest.raises(LinkError, match="lost the heartbeat"):
            v.wait_until(lambda s: False, 5.0, what="never")
        assert time.monotonic() - t0 < 1.0 + 0.5 + 2.5
        assert any(e.kind == "link_lost" for e in v.events)
        # the autopilot comes back on the same port (reboot): state flows again, streams re-requested
        sim2 = Simulator(SimulatorConfig(vehicles=1, speed=2.0, bind_ports=[port])).start()
        try:
            # a wait that starts while the link is down waits for it to come back
            assert v.wait_until(lambda s: s.link_ok, 5.0, what="link back").link_ok
            assert v.wait_link(1.0).link_ok and any(e.kind == "link_restored" for e in v.events)
            t_pos = v.state.position.time_s
            st = v.wait_until(lambda s: s.position is not None and s.position.time_s > t_pos, 3.0)
            assert st.mode == "STABILIZE"
            # the rates we asked for are re-requested from the new autopilot (10 Hz position); the
            # re-request goes out when the link is restored and may land after the first position
            deadline = time.monotonic() + 3.0
            while sim2.servers[0].intervals_s.get("GLOBAL_POSITION_INT") != pytest.approx(0.1) \
                    and time.monotonic() < deadline:
                time.sleep(0.05)
            assert sim2.servers[0].intervals_s["GLOBAL_POSITION_INT"] == pytest.approx(0.1)
        finally:
            sim2.stop()
    finally:
        v.close()


def test_several_system_ids_on_one_link(udp_port):
    cfg = SimulatorConfig(vehicles=3, base_port=udp_port, share_gcs_port=True, speed=5.0)
    with Simulator(cfg) as sim:
        vehicles = Vehicle.connect_all(f"udpin:127.0.0.1:{udp_port}", 3, timeout_s=5.0)
        try:
            assert [v.system_id for v in vehicles] == [1, 2, 3]
            assert len({id(v.link) for v in vehicles}) == 1
            for v in vehicles:
                v.wait_until(lambda s: s.position is not None, 5.0)
            # each vehicle's state is its own: they start 5 m apart along east
            lons = [v.state.position.lon_deg for v in vehicles]
            assert lons[0] < lons[1] < lons[2]
            # commands reach only their target
            vehicles[1].set_mode("GUIDED")
            vehicles[1].arm()
            time.sleep(0.5)
            assert [sim.vehicle(i).armed for i in range(3)] == [False, True, False]
            assert [v.state.armed for v in vehicles] == [False, True, False]
        finally:
            vehicles[0].close()


def test_refusals_carry_the_autopilot_reason(sim, vehicle):
    sim.set_param(0, "SIM_GPS1_ENABLE", 0)
    vehicle.wait_until(lambda s: s.gps is not None and s.gps.fix_type <= 1, 5.0)
    with pytest.raises(CommandRejected, match="PreArm: Need Position Estimate") as err:
        vehicle.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    assert err.value.result == mavlink.MAV_RESULT_FAILED and "MAV_CMD_COMPONENT_ARM_DISARM" in str(err.value)
    sim.set_param(0, "SIM_GPS1_ENABLE", 1)
    with pytest.raises(CommandRejected, match="no mission"):
        vehicle.set_mode("AUTO")


def test_injection_refused_when_autopilot_would_ignore_it(sim, vehicle):
    with pytest.raises(ConfigurationError, match="GPS1_TYPE=14"):
        vehicle.inject_gps(-35.0, 149.0, 600.0, h_acc_m=1.0)
    with pytest.raises(ConfigurationError, match="VISO_TYPE"):
        vehicle.inject_vision(1.0, 2.0, -3.0, sigma_m=0.1)
    # GPS_INPUT while GPS1_TYPE=1 would have been dropped silently by the autopilot
    assert sim.servers[0].gps_input_ignored == 0


def test_gps_loss_without_injection_triggers_ekf_failsafe(sim, vehicle):
    vehicle.set_mode("GUIDED")
    vehicle.arm()
    vehicle.takeoff(8.0)
    assert vehicle.wait_until(lambda s: s.ekf is not None, 5.0).ekf.pos_horiz_abs
    sim.set_param(0, "SIM_GPS1_ENABLE", 0)
    # the EKF's own verdict first (3 s without a fix), then ArduPilot's failsafe lands
    ekf = vehicle.wait_until(lambda s: not s.ekf.pos_horiz_abs, 10.0, what="EKF loses position").ekf
    assert ekf.flags == 37  # what ArduPilot 4.7 SITL reports in the same case (test_drivers_sitl)
    st = vehicle.wait_until(lambda s: s.mode == "LAND", 20.0, what="EKF failsafe")
    assert st.mode == "LAND"
    assert any("EKF Failsafe" in e.text for e in vehicle.events if e.kind == "statustext")


def test_vision_injection_and_origin(sim, vehicle):
    vehicle.set_param("VISO_TYPE", 1)
    vehicle.set_param("EK3_SRC1_POSXY", 6)
    home = vehicle.state.home
    vehicle.set_origin(home.lat_deg, home.lon_deg, home.alt_amsl_m)
    assert vehicle.ekf_origin == pytest.approx((home.lat_deg, home.lon_deg, home.alt_amsl_m), abs=1e-6)
    # a vision fix 3 m north of the truth: the estimate follows it within a second
    for _ in range(40):
        t = sim.truth(0)
        e, n, u = sim.world.to_enu(home.lat_deg, home.lon_deg, home.alt_ellipsoid_m)
        vehicle.inject_vision(t["north_m"] - float(n) + 3.0, t["east_m"] - float(e), -(t["up_m"] - float(u)),
                              sigma_m=0.1)
        time.sleep(0.05)
    assert 2.0 < sim.truth(0)["est_error_m"] < 4.0


def test_px4_offboard_takeoff_goto_land():
    with Simulator(SimulatorConfig(vehicles=1, flavour="px4", speed=5.0)) as sim:
        v = Vehicle.connect(sim.url(0), timeout_s=5.0)
        try:
            st = v.wait_until(lambda s: s.position is not None and s.home is not None, 5.0)
            assert st.autopilot == "px4" and st.mode == "AUTO.LOITER"
            # OFFBOARD without a setpoint stream is refused with PX4's reason
            with pytest.raises(CommandRejected, match="Offboard"):
                v.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 6, 0)
            v.arm()
            v.takeoff(6.0)
            assert v.state.mode in ("AUTO.TAKEOFF", "AUTO.LOITER")
            lat, lon = (float(x) for x in destination(st.home.lat_deg, st.home.lon_deg, 180.0, 15.0))
            v.goto(lat, lon, 6.0, wait=True)  # streams setpoints, then switches to OFFBOARD
            assert v.state.mode == "OFFBOARD"
            modes = [e.data.get("new") for e in v.events if e.kind == "mode"]
            assert "OFFBOARD" in modes and not any(m and m.startswith("MODE(") for m in modes)
            v.land(wait=True, timeout_s=60.0)
            assert sim.truth(0)["alt_rel_m"] < 0.1
        finally:
            v.close()
