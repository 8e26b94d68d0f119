"""Unit checks with known values: modes, GPS time, fences, mission items, simulator physics."""

from __future__ import annotations

import math

import numpy as np
import pytest

from skyfix.datasets.sim import GpsFault, GpsReceiver, SimVehicle, SimVehicleConfig, WindField
from skyfix.drivers.injection import gps_input_message, gps_week_ms, vision_message
from skyfix.drivers.mav import mavlink
from skyfix.drivers.mission import MissionItem
from skyfix.drivers.modes import ARDUCOPTER_MODES, PX4_MODES, custom_mode_of, mode_name, role_mode
from skyfix.drivers.safety import Geofence, SafetyGate
from skyfix.errors import InputError, SafetyViolation
from skyfix.geo import LocalFrame, destination


def test_mode_round_trips_and_known_values():
    for name in ARDUCOPTER_MODES:
        assert mode_name("ardupilot", custom_mode_of("ardupilot", name)) == name
    for name in PX4_MODES:
        assert mode_name("px4", custom_mode_of("px4", name)) == name
    assert custom_mode_of("ardupilot", "guided") == 4
    assert custom_mode_of("px4", "OFFBOARD") == 6 << 16
    assert custom_mode_of("px4", "AUTO.MISSION") == (4 << 16) | (4 << 24)  # 0x04040000
    assert mode_name("px4", 3 << 16) == "POSCTL"
    assert mode_name("ardupilot", 99) == "MODE(99)"
    assert role_mode("px4", "rtl") == "AUTO.RTL"
    with pytest.raises(InputError):
        custom_mode_of("px4", "GUIDED")


def test_gps_week_known_values():
    # 2017-01-01T00:00:00Z = GPS week 1930, 0 s + 18 leap seconds into Sunday
    assert gps_week_ms(1483228800.0) == (1930, 18_000)
    # the GPS epoch itself (leap seconds then: 0, but the constant offset is what GPS_INPUT needs now)
    week, ms = gps_week_ms(315964800.0 - 18)
    assert (week, ms) == (0, 0)
    msg = gps_input_message(47.0, 8.0, 500.0, h_acc_m=1.5, time_s=1483228800.5)
    assert (msg.time_week, msg.time_week_ms, msg.lat, msg.horiz_accuracy) == (1930, 18_500, 470000000, 1.5)
    assert msg.ignore_flags & mavlink.GPS_INPUT_IGNORE_FLAG_VEL_HORIZ


def test_vision_and_odometry_messages():
    msg = vision_message(1.0, 2.0, -3.0, sigma_m=0.2, yaw_deg=90.0, time_s=10.0)
    assert (msg.x, msg.y, msg.z, msg.usec) == (1.0, 2.0, -3.0, 10_000_000)
    assert msg.covariance[0] == pytest.approx(0.04) and msg.covariance[6] == pytest.approx(0.04)
    assert msg.yaw == pytest.approx(math.pi / 2)
    odo = vision_message(1.0, 2.0, -3.0, sigma_m=0.2, yaw_deg=90.0, odometry=True)
    # yaw 90 deg about down: q = (cos 45, 0, 0, sin 45)
    assert odo.q == pytest.approx([math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5)], abs=1e-6)


def test_geofence_known_points():
    lat0, lon0 = 47.3977, 8.5456
    fence = Geofence.circle(lat0, lon0, 100.0, max_alt_rel_m=50.0, min_alt_rel_m=-1.0)
    for bearing in (0.0, 77.0, 200.0):
        la_in, lo_in = destination(lat0, lon0, bearing, 95.0)
        la_out, lo_out = destination(lat0, lon0, bearing, 105.0)
        assert fence.contains(float(la_in), float(lo_in), 10.0)
        assert "outside" in fence.violation(float(la_out), float(lo_out), 10.0)
    assert "above the fence maximum" in fence.violation(lat0, lon0, 51.0)
    assert "below the fence minimum" in fence.violation(lat0, lon0, -2.0)
    # a concave L-shaped polygon: the notch is outside
    f = LocalFrame(lat0, lon0, 0.0)
    en = np.array([[0, 0], [100, 0], [100, 40], [40, 40], [40, 100], [0, 100]], dtype=float)
    ll = f.to_geodetic_points(np.column_stack([en, np.zeros(6)]))[:, :2]
    lfence = Geofence([ll])
    la, lo, _ = f.to_geodetic(70.0, 70.0, 0.0)
    assert not lfence.contains(float(la), float(lo), 0.0)
    la, lo, _ = f.to_geodetic(20.0, 70.0, 0.0)
    assert lfence.contains(float(la), float(lo), 0.0)
    gate = SafetyGate(lfence, max_speed_mps=5.0, max_alt_rel_m=30.0)
    with pytest.raises(SafetyViolation):
        gate.check_velocity_setpoint(3.0, 4.0, 0.1)  # 5.001 m/s
    gate.check_velocity_setpoint(3.0, 4.0, 0.0)
    assert "speed" in gate.violation(float(la), float(lo), 1.0, speed_mps=5.5)


def test_mission_item_wire_round_trip():
    item = MissionItem.waypoint(-35.1234567, 149.7654321, 12.5, hold_s=2.0, acceptance_m=3.0)
    back = MissionItem.from_message(item.to_message(7, 1, 1))
    assert back == item
    trig = MissionItem.camera_trigger_distance(15.0)
    assert trig.command == mavlink.MAV_CMD_DO_SET_CAM_TRIGG_DIST and trig.param1 == 15.0


def _vehicle(**kw) -> SimVehicle:
    world = LocalFrame(-35.363261, 149.165230, 584.0)
    return SimVehicle(SimVehicleConfig(**kw), world, kw.pop("wind", None) or WindField())


def _fly_to(v: SimVehicle, target, seconds: float, wind: WindField | None = None):
    speeds = []
    for _ in range(int(seconds / 0.02)):
        if wind is not None:
            wind.step(0.02)
        v.step(0.02)
        speeds.append(float(np.hypot(*v.vel_enu_mps[:2])))
    return speeds


def test_sim_vehicle_respects_speed_limit_and_arrives():
    v = _vehicle()
    v.set_mode("GUIDED")
    v.arm()
    v.takeoff(10.0)
    _fly_to(v, None, 8.0)
    assert v.pos_enu_m[2] == pytest.approx(10.0, abs=0.5)
    v.position_target(np.array([100.0, 0.0, 10.0]), None)
    speeds = _fly_to(v, None, 35.0)
    # WPNAV_SPEED 500 cm/s: the velocity loop may overshoot the command by a few percent only
    assert max(speeds) < 5.0 * 1.05
    assert abs(v.est_pos_enu_m[0] - 100.0) < 0.3 and abs(v.pos_enu_m[0] - 100.0) < 2.0  # GPS bias
    assert v.battery_used_mah > 0


def test_sim_vehicle_holds_against_wind_with_tilt():
    wind = WindField((8.0, 0.0, 0.0))  # 8 m/s towards east
    v = SimVehicle(SimVehicleConfig(), LocalFrame(-35.36, 149.16, 584.0), wind)
    v.set_mode("GUIDED")
    v.arm()
    v.takeoff(10.0)
    _fly_to(v, None, 30.0, wind)
    # the integrator cancels the drag: it holds within a metre, leaning into the wind (west)
    assert abs(v.est_pos_enu_m[0]) < 1.0 and abs(v.vel_enu_mps[0]) < 0.2
    tilt = math.degrees(math.atan(0.3 * 8.0 / 9.80665))  # drag 0.3/s x 8 m/s, balanced by tilt
    assert math.hypot(v.roll_deg, v.pitch_deg) == pytest.approx(tilt, abs=1.5)


def test_gps_faults():
    rx = GpsReceiver(seed=1)
    truth = np.array([10.0, 20.0, 30.0])
    rx.faults.append(GpsFault("jump", start_s=5.0, duration_s=5.0, offset_enu_m=(30.0, 0.0, 0.0)))
    rx.faults.append(GpsFault("loss", start_s=20.0, duration_s=2.0))
    rx.faults.append(GpsFault("spoof", start_s=30.0, offset_enu_m=(0.0, 40.0, 0.0), drift_mps=2.0))
    rx.faults.append(GpsFault("degraded", start_s=100.0, eph_m=12.0))
    assert np.linalg.norm(rx.read(1.0, truth, np.zeros(3)).pos_enu_m - truth) < 1.0
    assert rx.read(6.0, truth, np.zeros(3)).pos_enu_m[0] == pytest.approx(40.0, abs=1.0)
    lost = rx.read(21.0, truth, np.zeros(3))
    assert lost.fix_type == 1 and lost.satellites == 0
    assert rx.read(35.0, truth, np.zeros(3)).pos_enu_m[1] == pytest.approx(30.0, abs=1.0)  # 2 m/s x 5 s
    assert rx.read(60.0, truth, np.zeros(3)).pos_enu_m[1] == pytest.approx(60.0, abs=1.0)  # capped at 40
    deg = rx.read(101.0, truth, np.zeros(3))
    assert deg.eph_m == 12.0 and deg.satellites == 5
    with pytest.raises(InputError):
        GpsFault("meteor", 0.0)


def test_wind_gusts_statistics():
    w = WindField((1.0, 2.0, 0.0), gust_sigma_mps=1.5, gust_tau_s=2.0, seed=4)
    samples = []
    for _ in range(20000):
        w.step(0.05)
        samples.append(w.at(np.zeros(3)))
    s = np.array(samples)
    # stationary Gauss-Markov: mean = constant part, std = sigma (1000 s = 500 correlation times)
    assert s[:, 0].mean() == pytest.approx(1.0, abs=0.25) and s[:, 0].std() == pytest.approx(1.5, rel=0.15)
    assert s[:, 2].std() == pytest.approx(0.3 * 1.5, rel=0.15)  # vertical: 0.3 of the horizontal sigma
    lag = 40  # 2 s = tau: autocorrelation exp(-1); ~500 correlation times -> standard error ~0.05
    z = s[:, 2] - s[:, 2].mean()
    assert np.mean(z[:-lag] * z[lag:]) / np.mean(z * z) == pytest.approx(np.exp(-1.0), abs=0.15)
    grid = (np.array([0.0, 100.0]), np.array([0.0, 100.0]), np.array([[[0, 0], [4, 0]], [[0, 4], [4, 4]]], float))
    wg = WindField(grid=grid)
    assert wg.at(np.array([50.0, 50.0, 0.0]))[:2] == pytest.approx([2.0, 2.0])
    assert wg.at(np.array([500.0, 0.0, 0.0]))[:2] == pytest.approx([4.0, 0.0])  # clamped at the edge


def test_simulator_runs_faster_than_real_time_and_offline():
    import time

    from skyfix.datasets.sim import Simulator, SimulatorConfig

    with Simulator(SimulatorConfig(vehicles=2, speed=8.0)) as sim:
        t0_wall, t0_sim = time.monotonic(), sim.time_s
        time.sleep(1.0)
        ratio = (sim.time_s - t0_sim) / (time.monotonic() - t0_wall)
    # 8x asked; a starved loop slows down rather than skipping physics, hence only a lower bound
    assert 4.0 < ratio < 8.5
    offline = Simulator(SimulatorConfig(vehicles=1, dt_s=0.02))
    offline.run_steps(500)
    assert offline.time_s == pytest.approx(10.0)
    offline.stop()
