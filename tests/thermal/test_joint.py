"""Joint fire estimation over a flight: boresight and camera time offset recovered, GNSS
error shared, stated covariance honest (measurement-level sightings: fast; the rendered
flights are in benchmarks/thermal.py)."""

import numpy as np
import pytest

from skyfix.camera import Camera
from skyfix.datasets.mountain_flight import MountainScene, fly, orbit_log, projected_hotspots
from skyfix.datasets.pose_errors import PoseErrorModel
from skyfix.datasets.terrain import Terrain
from skyfix.datasets.thermal_scene import FireSpec
from skyfix.errors import EstimationError
from skyfix.geo import LocalFrame
from skyfix.thermal.joint import PoseErrorPrior, locate_jointly
from skyfix.thermal.sightings import associate

FRAME = LocalFrame(42.15, 9.05, 800.0)
CAM = Camera.from_fov(640, 512, 50.0)
CHI2_2DOF_95 = (0.0506, 7.378)


@pytest.fixture(scope="module")
def world():
    terrain = Terrain.mountain(FRAME, seed=3, size_m=1200.0)
    rng = np.random.default_rng(3)
    fires = [FireSpec(float(e), float(n), 1.5, 500.0) for e, n in rng.uniform(-60, 60, (4, 2))]
    scene = MountainScene(terrain, fires)
    return scene, terrain.dem_ground(metres_per_px=10.0, sigma_m=1.0)


def errors_en(solution, scene):
    truth = scene.fire_enu()
    out = []
    for f in solution.fires:
        p = np.array(FRAME.to_enu(f.lat_deg, f.lon_deg, f.alt_m), float)
        k = int(np.argmin(np.hypot(*(truth[:, :2] - p[:2]).T)))
        out.append((p[:2] - truth[k, :2], f.cov_en_m2))
    return out


def test_boresight_and_time_offset_recovered_when_only_they_are_wrong(world):
    scene, dem = world
    log = orbit_log(scene, (0.0, 0.0), radius_m=170.0, height_m=90.0, laps=0.6, speed_mps=10.0)
    errors = PoseErrorModel(gnss_h_sigma_m=1e-6, gnss_v_sigma_m=1e-6, gnss_white_m=0.0, attitude_white_deg=0.0,
                            attitude_drift_deg=1e-6, boresight_deg=(0.5, -0.8, 0.4), time_offset_s=0.15)
    flight = fly(scene, CAM, log, errors, seed=1)
    det = projected_hotspots(flight, np.random.default_rng(0), pixel_sigma_px=0.2)
    sightings = associate(CAM, flight.log, det, dem)
    prior = PoseErrorPrior(gnss_h_sigma_m=0.01, gnss_v_sigma_m=0.01, gnss_white_m=0.01, attitude_white_deg=0.005,
                           attitude_drift_deg=0.005, pixel_sigma_px=0.2)
    sol = locate_jointly(CAM, flight.log, sightings, dem, prior=prior)
    assert len(sol.fires) == 4
    # 0.2 px on ~60 frames x 4 fires at 200-250 m: a few millidegrees; the DEM's 10 m
    # cells (fires' heights off by up to ~1 m) leave a few hundredths of a degree.
    np.testing.assert_allclose(sol.boresight_deg, errors.boresight_deg, atol=0.05)
    # An orbit keeps the centre in view whatever the time: the offset is weakly observable
    # (it shows only in off-centre fires); it must agree within its stated sigma.
    assert abs(sol.time_offset_s - 0.15) < 3.0 * sol.time_offset_sigma_s
    assert sol.time_offset_sigma_s < PoseErrorPrior().time_offset_sigma_s
    # The clock error left (tenths of a second along the orbit) moves the fires by
    # decimetres; each stays inside its stated 99.7 % ellipse.
    for err, cov in errors_en(sol, scene):
        assert np.hypot(*err) < 1.0
        assert err @ np.linalg.solve(cov, err) < 11.6


@pytest.mark.slow
def test_stated_covariance_covers_the_truth_with_correlated_gnss(world):
    scene, dem = world
    log = orbit_log(scene, (0.0, 0.0), radius_m=170.0, height_m=90.0, laps=0.8, speed_mps=10.0)
    nees, bore_z = [], []
    for seed in range(4):
        errors = PoseErrorModel.draw(np.random.default_rng(100 + seed))
        flight = fly(scene, CAM, log, errors, seed=seed)
        det = projected_hotspots(flight, np.random.default_rng(seed), pixel_sigma_px=0.3)
        sol = locate_jointly(CAM, flight.log, associate(CAM, flight.log, det, dem), dem)
        nees += [float(e @ np.linalg.solve(c, e)) for e, c in errors_en(sol, scene)]
        d = sol.boresight_deg - np.array(errors.boresight_deg)
        bore_z.append(float(d @ np.linalg.solve(sol.boresight_cov_deg2, d)))
    nees = np.array(nees)
    inside = np.mean((nees > CHI2_2DOF_95[0]) & (nees < CHI2_2DOF_95[1]))
    # 16 fires, but 4 flights: the fires of one flight share its GNSS error, so the
    # fraction is noisy; 95 % for a calibrated covariance, an overconfident one (the
    # independent-frames assumption) puts most fires outside.
    assert inside >= 0.7
    assert np.median(bore_z) < 7.8  # 3-dof chi-square 95 %: boresight sigma honest too


def test_no_fire_seen_often_enough_is_an_error(world):
    scene, dem = world
    log = orbit_log(scene, (0.0, 0.0), radius_m=170.0, height_m=90.0, laps=0.1, speed_mps=10.0)
    flight = fly(scene, CAM, log, PoseErrorModel(), seed=1)
    with pytest.raises(EstimationError):
        associate(CAM, flight.log, [(float(flight.stamps_s[0]), [])], dem)


def test_orbit_flown_both_ways_pins_the_camera_clock(world):
    """One way, a clock offset moves every camera along the circle, still aimed at the
    centre: only off-centre fires show it (stated sigma ~0.2 s on this orbit flown 0.6
    laps one way). Flown back, the same offset moves the cameras the other way while a
    boresight or a fire position does not change sign."""
    scene, dem = world
    errors = PoseErrorModel(time_offset_s=0.15)  # consumer GNSS and attitude errors, boresight 1 deg
    log = orbit_log(scene, (0.0, 0.0), radius_m=170.0, height_m=90.0, laps=0.3, speed_mps=10.0, both_ways=True)
    flight = fly(scene, CAM, log, errors, frame_rate_hz=0.5, seed=4)
    det = projected_hotspots(flight, np.random.default_rng(4), pixel_sigma_px=0.3)
    sol = locate_jointly(CAM, flight.log, associate(CAM, flight.log, det, dem), dem)
    # 33 frames x 4 fires 60 m off-centre, 0.3 px and 0.3 deg white attitude noise per frame
    # against 10 m/s over 170 m: a few hundredths of a second.
    assert sol.time_offset_sigma_s < 0.05
    assert abs(sol.time_offset_s - errors.time_offset_s) < 3.0 * sol.time_offset_sigma_s
