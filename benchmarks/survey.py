"""Benchmark: skyfix survey planning against the source platform's method and figures.

1. The source platform's experiment (multi-drone platform thesis, section 5.4): a
   28 m x 35 m area, waypoints 7 m apart (30 waypoints), an alarm extends it for two
   joining drones to 56 waypoints / 2058 m^2 (+110 %), split among three drones
   (the thesis' drones started at waypoints 1, 19 and 37).
2. Split balance: path length of each drone's part, skyfix vs the thesis' split.
3. Photo coverage by footprint geometry for several areas, cameras and overlaps:
   uncovered area (must be 0) and the smallest measured forward/side overlaps (must be
   >= requested, 1e-3 allowance for the earth's curvature), and photo count / path length
   against the source method (a three-corner station grid over the area's bounding
   rectangle with one step for both directions, a photo at each station).
4. Missions: upload/download round trip through the simulator's MAVLink mission
   protocol (loopback UDP, ArduPilot and PX4 flavours), then the photo survey flown in
   the simulator with the camera triggering by distance.

Exit status 0 only when every goal is met.
"""

from __future__ import annotations

import math
import sys
import time

import numpy as np

from skyfix.camera import Camera
from skyfix.geo import destination
from skyfix.mapping.coverage import verify_coverage
from skyfix.mapping.mission import mission_items
from skyfix.mapping.split import split_survey
from skyfix.mapping.survey import (
    extend_survey,
    footprint_m,
    plan_polygon,
    plan_three_corners,
)
from skyfix.mission import mavlink

LAT0, LON0 = 40.6303, -8.6575  # University of Aveiro


def at(bearing_deg: float, dist_m: float, lat0: float = LAT0, lon0: float = LON0) -> tuple[float, float]:
    lat, lon = destination(lat0, lon0, bearing_deg, dist_m)
    return float(lat), float(lon)


def source_example() -> bool:
    print("== 1. source platform example (28 m x 35 m, 7 m step, two drones join)")
    plan = plan_three_corners((LAT0, LON0), at(90, 28), at(0, 35), 7.0, 10.0, hold_s=2.0)
    big = extend_survey(plan, at(30, 25), joining_drones=2)
    area = abs(big.v_en_m[0] * big.w_en_m[1] - big.v_en_m[1] * big.w_en_m[0])
    print(f"initial waypoints: thesis 30, skyfix {plan.n_waypoints}")
    print(f"extended waypoints: thesis 56, skyfix {big.n_waypoints} "
          f"({np.hypot(*big.v_en_m):.0f} m x {np.hypot(*big.w_en_m):.0f} m)")
    print(f"extended area: thesis 2058 m^2 (+110 %), skyfix {area:.0f} m^2 (+{100 * (area / 980 - 1):.0f} %)")
    ok = plan.n_waypoints == 30 and big.n_waypoints == 56 and abs(area - 2058) < 1e-6

    print("== 2. split among the three drones")
    cum = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(big.waypoints_en_m, axis=0).T))))
    thesis_bounds = [0, 18, 36, 56]  # drones started at waypoints 1, 19 and 37
    thesis = [cum[b - 1] - cum[a] for a, b in zip(thesis_bounds[:-1], thesis_bounds[1:], strict=True)]
    ends = big.waypoints_latlon()
    drones = {"A": (LAT0, LON0), "B": tuple(ends[20]), "C": tuple(ends[-1])}
    parts = split_survey(big, drones)
    ours = [p.length_m for p in parts]
    print("thesis split (waypoints 1-18, 19-36, 37-56): lengths " + ", ".join(f"{x:.0f} m" for x in thesis)
          + f"; spread {max(thesis) - min(thesis):.0f} m = {(max(thesis) - min(thesis)) / 7:.0f} steps")
    print("skyfix split: " + ", ".join(f"{p.drone_id} {p.plan.n_waypoints} wp {p.length_m:.0f} m" for p in parts)
          + f"; spread {max(ours) - min(ours):.0f} m = {(max(ours) - min(ours)) / 7:.0f} step(s)")
    ok &= max(ours) - min(ours) <= 7.0 + 1e-9
    return ok


def source_grid_photos(poly_en: np.ndarray, across_m: float, along_m: float, fwd: float, side: float) -> tuple[int, float]:
    """Source method: stations on a single-step grid over the bounding rectangle, a photo at each."""
    step = min(across_m * (1 - side), along_m * (1 - fwd))
    w, h = np.ptp(poly_en, axis=0)
    n_x, n_y = math.floor(w / step) + 1, math.floor(h / step) + 1
    return n_x * n_y, (n_x - 1) * step * n_y + (n_y - 1) * step


def coverage_cases() -> bool:
    print("== 3. photo coverage by footprint geometry")
    cases = [
        ("rectangle 300x200 m", [(LAT0, LON0), at(90, 300), at(56.31, 360.55), at(0, 200)],
         Camera.from_fov(4000, 3000, 73.7), 80.0, 0.75, 0.65, None),
        ("trapezoid, lines at 30 deg", [(LAT0, LON0), at(90, 250), at(60, 260), at(10, 180)],
         Camera.from_fov(1200, 900, 60.0), 70.0, 0.8, 0.7, 30.0),
        ("L-shape (concave)", [(LAT0, LON0), at(90, 200), at(70, 212.8), at(30, 145), at(20, 212.8), at(0, 200)],
         Camera.from_fov(5472, 3648, 77.0), 100.0, 0.7, 0.6, None),
        ("small field, seneca camera", [(LAT0, LON0), at(90, 120), at(45, 150), at(0, 100)],
         Camera(1200, 900, 758.27, 758.27, 599.5, 449.5), 60.0, 0.85, 0.75, None),
    ]
    ok = True
    for name, poly, cam, alt, fwd, side, heading in cases:
        t0 = time.perf_counter()
        plan = plan_polygon(poly, cam, alt, fwd, side, heading_deg=heading)
        cov = verify_coverage(plan)
        dt = time.perf_counter() - t0
        across, along = footprint_m(cam, alt)
        src_photos, src_len = source_grid_photos(plan.area_en_m, across, along, fwd, side)
        good = (cov.uncovered_m2 <= 1e-6 * cov.area_m2 and cov.forward_overlap_min >= fwd - 1e-3
                and cov.side_overlap_min >= side - 1e-3)
        ok &= good
        print(f"{name}: {cov.n_photos} photos, uncovered {cov.uncovered_m2:.3g} m^2 of {cov.area_m2:.0f}, "
              f"overlap fwd {cov.forward_overlap_min:.4f} (req {fwd}), side {cov.side_overlap_min:.4f} (req {side}); "
              f"source grid: {src_photos} photos ({src_photos / cov.n_photos:.1f}x), path {src_len:.0f} m vs "
              f"{plan.path_length_m:.0f} m; planned+verified in {dt * 1000:.0f} ms {'OK' if good else 'FAIL'}")
    return ok


def simulator_missions() -> bool:
    print("== 4. missions through the simulator (MAVLink on 127.0.0.1)")
    try:
        from skyfix.datasets.sim import Simulator, SimulatorConfig
        from skyfix.drivers.vehicle import Vehicle
    except ImportError as exc:
        print(f"simulator/drivers not available ({exc}); round trip not checked")
        return False
    ok = True
    for flavour in ("ardupilot", "px4"):
        with Simulator(SimulatorConfig(vehicles=1, flavour=flavour, speed=10.0, seed=2)) as sim:
            v = Vehicle.connect(sim.url(0), timeout_s=5.0)
            try:
                home = v.wait_until(lambda s: s.home is not None and s.position is not None, 5.0, what="home").home
                lat0, lon0 = home.lat_deg, home.lon_deg
                poly = [(lat0, lon0), at(90, 60, lat0, lon0), at(56.31, 72.1, lat0, lon0), at(0, 40, lat0, lon0)]
                plan = plan_polygon(poly, Camera.from_fov(1200, 900, 70.0), 20.0, 0.7, 0.6)
                items = mission_items(plan, speed_mps=5.0)
                t0 = time.perf_counter()
                v.upload_mission(items)
                back = v.download_mission()
                dt = time.perf_counter() - t0
                same = len(back) == len(items) and all(
                    a.command == b.command and round(a.lat_deg * 1e7) == b.x and round(a.lon_deg * 1e7) == b.y
                    and abs(a.alt_m - b.z) < 1e-4 and abs(a.param1 - b.param1) < 1e-6
                    for a, b in zip(back, items, strict=True))
                print(f"{flavour}: {len(items)} items uploaded and downloaded in {dt * 1000:.0f} ms, identical: {same}")
                ok &= same
                if flavour != "ardupilot":
                    continue
                photos, _ = plan.photo_positions_en_m()
                n_lines = sum(1 for it in items if it.command == mavlink.MAV_CMD_DO_SET_CAM_TRIGG_DIST and it.param1 > 0)
                v.set_mode("GUIDED")
                v.arm()
                v.takeoff(20.0)
                v.start_mission()
                last = len(items)  # ArduPilot numbers the uploaded items from 1
                v.wait_until(lambda s, v=v, last=last: any(e.kind == "mission_item_reached"
                                                           and e.data["seq"] >= last - 1 for e in list(v.events)),
                             120.0, what="survey flown")
                triggers = sum(e.kind == "camera_trigger" for e in v.events)
                # The simulator counts distance from the DO command and does not take the
                # immediate first photo (param3 = 1), so it sees one photo fewer per line.
                expected = len(photos) - n_lines
                print(f"ardupilot flight: {triggers} camera triggers for {len(photos)} planned photos on {n_lines} "
                      f"lines (simulator without the first-photo trigger: {expected} expected)")
                ok &= abs(triggers - expected) <= n_lines
            finally:
                v.close()
    return ok


def main() -> int:
    ok_source = source_example()
    ok_cov = coverage_cases()
    ok_sim = simulator_missions()
    ok = ok_source and ok_cov and ok_sim
    print(f"survey: thesis example 30 -> 56 waypoints {'reproduced' if ok_source else 'NOT reproduced'}, "
          f"split spread <= 1 step; coverage without gaps at requested overlaps {'MET' if ok_cov else 'NOT MET'}; "
          f"simulator mission round trip {'MET' if ok_sim else 'NOT MET'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
