"""A real client, MAVSDK (the native C++ library through its Python binding), flies
skyfix's simulator in its PX4 flavour: connect, arm, takeoff, goto_location (which is
MAV_CMD_DO_REPOSITION), a mission upload/download and run, RTL and landing.

Every step is checked against the simulator's ground truth, not against what MAVSDK says.
"""

from __future__ import annotations

import math
import time

import pytest

from skyfix.datasets.sim import Simulator, SimulatorConfig
from skyfix.geo import inverse

mavsdk = pytest.importorskip("mavsdk", minversion="4.0", reason="MAVSDK (native binding, v4+) not installed")
from mavsdk.plugins.action import Action  # noqa: E402
from mavsdk.plugins.mission import Mission, MissionItem, MissionPlan  # noqa: E402
from mavsdk.plugins.telemetry import Telemetry  # noqa: E402

pytestmark = pytest.mark.slow


def _until(predicate, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"{what} not reached within {timeout_s} s")
        time.sleep(0.05)


def _waypoint(lat: float, lon: float, rel_alt_m: float) -> MissionItem:
    nan = math.nan
    return MissionItem(lat, lon, rel_alt_m, 5.0, True, nan, nan, MissionItem.CameraAction.NONE, nan, nan,
                       1.0, nan, nan, MissionItem.VehicleAction.NONE)


def test_mavsdk_flies_the_px4_flavour(udp_port):
    port = udp_port
    with Simulator(SimulatorConfig(vehicles=1, flavour="px4", speed=5.0, base_port=port, seed=8)) as sim:
        config = mavsdk.Configuration.create_with_component_type(mavsdk.ComponentType.GROUND_STATION)
        with mavsdk.Mavsdk(config) as client:
            assert client.add_any_connection(f"udpin://127.0.0.1:{port}") == mavsdk.ConnectionResult.SUCCESS
            system = client.first_autopilot(10.0)
            assert system is not None and system.get_system_id() == 1
            action, mission, telemetry = Action(system), Mission(system), Telemetry(system)
            home = sim.truth(0)
            _until(lambda: telemetry.home().latitude_deg == pytest.approx(home["lat_deg"], abs=1e-5), 10.0,
                   "MAVSDK's home")
            # PX4 reports AMSL; the simulator's world carries the EGM96 separation (+47.3 m in Zurich)
            assert telemetry.home().absolute_altitude_m == pytest.approx(home["alt_amsl_m"], abs=1.0)

            action.arm()
            _until(lambda: sim.vehicle(0).armed, 5.0, "armed")
            action.set_takeoff_altitude(10.0)
            action.takeoff()
            _until(lambda: sim.truth(0)["alt_rel_m"] > 9.0, 20.0, "takeoff to 10 m")

            lat, lon = home["lat_deg"] + 2.0e-4, home["lon_deg"] + 1.0e-4   # ~25 m away
            action.goto_location(lat, lon, home["alt_amsl_m"] + 12.0, 0.0)
            _until(lambda: float(inverse(sim.truth(0)["lat_deg"], sim.truth(0)["lon_deg"], lat, lon)[1]) < 1.5
                   and abs(sim.truth(0)["alt_rel_m"] - 12.0) < 1.0, 30.0, "goto_location target")

            wps = [(home["lat_deg"] + 1.0e-4 * i, home["lon_deg"] - 1.5e-4, 8.0 + i) for i in range(3)]
            mission.upload_mission(MissionPlan([_waypoint(*w) for w in wps]))
            back = mission.download_mission()
            assert [(round(b.latitude_deg, 6), round(b.longitude_deg, 6), round(b.relative_altitude_m, 2))
                    for b in back.mission_items] == [(round(a, 6), round(o, 6), float(h)) for a, o, h in wps]
            mission.start_mission()
            _until(mission.is_mission_finished, 40.0, "mission finished")
            last = sim.truth(0)
            assert float(inverse(last["lat_deg"], last["lon_deg"], wps[-1][0], wps[-1][1])[1]) < 2.0

            action.return_to_launch()
            _until(lambda: sim.vehicle(0).landed, 60.0, "landed at home")
            end = sim.truth(0)
            assert float(inverse(end["lat_deg"], end["lon_deg"], home["lat_deg"], home["lon_deg"])[1]) < 2.0
