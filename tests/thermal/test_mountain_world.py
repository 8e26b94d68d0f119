"""The mountain world of the terrain benchmark: pose log interpolation, Gauss-Markov pose
errors, terrain ray casting, DEMs as users have them, rendered fires where they are."""

import numpy as np
import pytest

from skyfix.camera import Camera, CameraPose
from skyfix.datasets.mountain_flight import MountainScene, fly, lines_log, orbit_log
from skyfix.datasets.pose_errors import PoseErrorModel, gauss_markov
from skyfix.datasets.terrain import TOL_M, Terrain
from skyfix.datasets.thermal_scene import FireSpec
from skyfix.errors import GeometryError, InputError
from skyfix.geo import LocalFrame
from skyfix.thermal import DemGround, detect_hotspots
from skyfix.thermal.poselog import PoseLog

FRAME = LocalFrame(42.15, 9.05, 800.0)
CAM = Camera.from_fov(640, 512, 50.0)


@pytest.fixture(scope="module")
def terrain():
    return Terrain.mountain(FRAME, seed=1, size_m=1200.0)


@pytest.mark.parametrize("stabilized", [True, False])
def test_pose_log_matches_camera_pose(stabilized):
    poses = [CameraPose(42.15 + 0.001 * i, 9.05, 900.0 + i, 3.0 * i, -2.0 + i, 175.0 + 10 * i, -50.0, 5.0, 1.0,
                        stabilized) for i in range(3)]
    log = PoseLog.from_poses([0.0, 1.0, 2.0], poses)
    cam, rot = log.camera_in_frame(FRAME, [0.0, 1.0, 2.0])
    for i, p in enumerate(poses):
        c0, r0 = p.in_frame(FRAME)
        np.testing.assert_allclose(cam[i], c0, atol=1e-6)
        np.testing.assert_allclose(rot[i], r0, atol=1e-12)
    # Yaw 175 -> 185 is interpolated through 180, not back through 0.
    assert log.pose_at(0.5).yaw_deg == pytest.approx(180.0)
    with pytest.raises(InputError, match="outside the pose log"):
        log.camera_in_frame(FRAME, [2.5])


def test_gauss_markov_variance_and_correlation():
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 20000.0, 2.0)
    x = gauss_markov(rng, t, [1.5, 3.0], 60.0)
    # 10000 samples with correlation time 30 samples: ~170 independent ones -> std within ~15 %.
    np.testing.assert_allclose(x.std(axis=0), [1.5, 3.0], rtol=0.2)
    lag = 30  # 60 s
    rho = np.mean(x[:-lag, 0] * x[lag:, 0]) / np.mean(x[:, 0] ** 2)
    assert rho == pytest.approx(np.exp(-1.0), abs=0.12)


def test_terrain_cast_lands_on_the_first_surface(terrain):
    origin = np.array([0.0, -300.0, terrain.max_up_m + 80.0])
    rng = np.random.default_rng(0)
    dirs = rng.normal(size=(300, 3))
    dirs[:, 2] = -np.abs(dirs[:, 2]) - 0.3
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    t = terrain.cast(origin, dirs)
    ok = np.isfinite(t)
    assert ok.mean() > 0.5
    p = origin + t[ok, None] * dirs[ok]
    assert np.max(np.abs(p[:, 2] - terrain.up_at(p[:, 0], p[:, 1]))) < 2 * TOL_M
    # Brute force: the ray stays above the terrain before t (0.5 m steps).
    for k in np.flatnonzero(ok)[:40]:
        s = np.arange(0.0, t[k] - 0.5, 0.5)
        q = origin + s[:, None] * dirs[k]
        assert np.all(q[:, 2] > terrain.up_at(q[:, 0], q[:, 1]))
    with pytest.raises(GeometryError):
        terrain.cast(np.array([0.0, 0.0, -50.0]), dirs)


def test_dem_geotiff_round_trip_in_utm_and_geographic(terrain, tmp_path):
    e, n = np.meshgrid(np.linspace(-300, 300, 7), np.linspace(-300, 300, 7))
    up = terrain.up_at(e, n)
    lat, lon, h_true = FRAME.to_geodetic(e, n, up)
    for crs in (None, "EPSG:4326"):
        path = terrain.write_dem(tmp_path / "dem.tif", metres_per_px=10.0, crs=crs, holes=0)
        dem = DemGround.from_geotiff(path, datum="ellipsoid")
        # A 10 m DEM of 0.4 m roughness on 20-40 deg slopes: within ~1.5 m (curvature of
        # the hills over a cell plus the roughness it averages).
        err = dem.height_at(lat, lon) - h_true
        assert np.sqrt(np.mean(err ** 2)) < 1.0 and np.max(np.abs(err)) < 2.5


def test_rendered_fire_is_where_the_true_camera_sees_it(terrain):
    fire = FireSpec(20.0, -10.0, 1.5, 600.0)
    scene = MountainScene(terrain, [fire])
    log = orbit_log(scene, (0.0, 0.0), radius_m=150.0, height_m=80.0, laps=0.1)
    flight = fly(scene, CAM, log, PoseErrorModel(), frame_rate_hz=1.0, seed=2)
    for k, (_, counts) in enumerate(flight.frames(0, 3)):
        cam, r = flight.true_camera(k)
        uv = CAM.project((scene.fire_enu() - cam) @ r)[0]
        spots = detect_hotspots(counts)
        assert len(spots) == 1
        # Centroid of a 1.5 m disc on a slope seen obliquely: perspective and the hotter
        # core shift it by a fraction of a pixel.
        assert np.hypot(*(spots[0].uv - uv)) < 1.0


def test_frames_rendered_ahead_on_threads_equal_the_serial_ones(terrain):
    # frames render on threads while the noise is drawn in frame order: any thread count,
    # the same counts bit for bit (and a consumer stopping early leaves no thread behind)
    scene = MountainScene(terrain, [FireSpec(20.0, -10.0, 1.5, 600.0)])
    flight = fly(scene, CAM, orbit_log(scene, (0.0, 0.0), radius_m=150.0, height_m=80.0, laps=0.1),
                 PoseErrorModel(), frame_rate_hz=1.0, seed=2)
    serial = list(flight.frames(1, 5, threads=1))
    for threads in (2, 3):
        ahead = list(flight.frames(1, 5, threads=threads))
        assert [s for s, _ in ahead] == [s for s, _ in serial]
        assert all(np.array_equal(a, b) for (_, a), (_, b) in zip(ahead, serial, strict=True))
    first = next(iter(flight.frames(threads=2)))
    assert np.array_equal(first[1], next(iter(flight.frames(threads=1)))[1])


def test_lines_and_orbit_logs_refuse_paths_into_the_ground(terrain):
    scene = MountainScene(terrain, [])
    with pytest.raises(GeometryError):
        lines_log(scene, [(-300.0, 0.0), (300.0, 0.0)], up_m=float(terrain.up_at(0.0, 0.0)))
    log = lines_log(scene, [(-300.0, -50.0), (300.0, -50.0), (300.0, 50.0), (-300.0, 50.0)],
                    up_m=terrain.max_up_m + 60.0)
    assert log.time_s[-1] > 2 * 600.0 / 8.0
    with pytest.raises(GeometryError):
        orbit_log(scene, (0.0, 0.0), radius_m=2000.0, height_m=80.0)


def test_calibration_orbit_flies_the_laps_back_facing_the_centre(terrain):
    scene = MountainScene(terrain, [])
    r_m, v_mps, laps = 150.0, 8.0, 0.5
    log = orbit_log(scene, (0.0, 0.0), radius_m=r_m, height_m=80.0, laps=laps, speed_mps=v_mps, both_ways=True,
                    reverse_s=6.0)
    lap_s = laps * 2 * np.pi * r_m / v_mps
    # Full speed, a 6 s linear ramp through zero, full speed back: 2 * (lap_s + 1.5 s).
    assert log.time_s[-1] == pytest.approx(2 * lap_s + 3.0, abs=0.11)
    enu, _ = log._samples_in(scene.frame)
    np.testing.assert_allclose(np.hypot(enu[:, 0], enu[:, 1]), r_m, atol=1e-6)
    ang = np.unwrap(np.arctan2(enu[:, 0], enu[:, 1]))  # clockwise from north
    turn = int(np.argmax(ang))
    # Half a lap out (to 0.01 rad: the trapezoid sum of the ramp), back to the start.
    assert ang[turn] - ang[0] == pytest.approx(2 * np.pi * laps, abs=0.01)
    assert abs(ang[-1] - ang[0]) < 0.01
    assert log.time_s[turn] == pytest.approx(log.time_s[-1] / 2, abs=0.2)
    speed = np.diff(ang) * r_m / np.diff(log.time_s)
    assert speed[:10] == pytest.approx(v_mps, rel=1e-6) and speed[-10:] == pytest.approx(-v_mps, rel=1e-6)
    # The camera keeps looking at the centre (yaw and gimbal pitch), both ways; the gimbal
    # levels to the vertical at the drone, 150 m / 6371 km = 2.4e-5 rad off the frame's:
    # ~6 mm at the ~230 m range.
    cam, rot = log.camera_in_frame(scene.frame, log.time_s)
    to_centre = np.column_stack((-enu[:, :2], terrain.up_at(0.0, 0.0) - enu[:, 2]))
    np.testing.assert_allclose(np.einsum("nij,nj->ni", np.transpose(rot, (0, 2, 1)), to_centre)[:, :2], 0.0,
                               atol=0.01)


def test_dem_ray_cast_first_hit_holes_and_coverage(terrain, tmp_path):
    from skyfix.errors import DataError
    from skyfix.thermal.ground import intersect

    dem = terrain.dem_ground(metres_per_px=2.0, sigma_m=0.3)
    cam = CAM
    # Camera low on one side looking across the ridge: first hits must match the true terrain's.
    origin = np.array([-350.0, -350.0, terrain.max_up_m + 40.0])
    lat, lon, alt = FRAME.to_geodetic(*origin)
    from skyfix.camera import CameraPose as Pose

    pose = Pose(float(lat), float(lon), float(alt), 0.0, 0.0, 45.0, -35.0, 0.0, 0.0, True)
    uv = np.stack(np.meshgrid(np.linspace(20, 620, 9), np.linspace(250, 500, 6)), -1).reshape(-1, 2)
    pts, heights = intersect(cam, pose, uv, dem, FRAME)
    c, r = pose.in_frame(FRAME)
    d = cam.pixel_to_ray(uv) @ r.T
    t_true = terrain.cast(c, d)
    t_dem = np.linalg.norm(pts - c, axis=1)
    # A 2 m DEM of the 0.4 m-rough terrain: heights within ~0.5 m, so slant ranges within
    # a few metres at 25-40 deg incidence; a skipped ridge would be off by hundreds.
    ok = np.isfinite(t_true)
    assert ok.mean() > 0.9
    assert np.median(np.abs(t_dem[ok] - t_true[ok])) < 1.0 and np.max(np.abs(t_dem[ok] - t_true[ok])) < 8.0
    # Hole: filled from its neighbours by default, refused when not filled.
    path = terrain.write_dem(tmp_path / "holes.tif", metres_per_px=5.0, holes=30, seed=4)
    filled = DemGround.from_geotiff(path, datum="ellipsoid")
    raw = DemGround.from_geotiff(path, datum="ellipsoid", fill_holes=False)
    assert filled.hole_fraction > 0.005 and np.all(np.isfinite(filled.heights_m))
    assert np.isnan(raw.heights_m).any()
    # Coverage: a flight 3 km away is refused with the position named.
    far_lat, far_lon, _ = FRAME.to_geodetic(3000.0, 0.0, 0.0)
    with pytest.raises(DataError, match="does not cover the flight"):
        filled.check_covers([lat, far_lat], [lon, far_lon])


def _previous_geolocate_many(camera, pose, uv, ground, frame, unc):
    """The per-fire implementation geolocate_many had until 2026-11-25 (every DEM hit
    through pyproj in the DEM's own frame, then back; covariance and its rotation to
    each fix's ENU axes one fire at a time, scalar arithmetic): the oracle of the
    vectorised path."""
    import math

    from skyfix.geo import ecef_to_enu_rotation

    local = ground.local()
    cam_l, r_l = pose.in_frame(local.frame)
    d_l = camera.pixel_to_ray(uv) @ r_l.T
    p = cam_l + local.cast(cam_l, d_l)[:, None] * d_l
    pts = np.stack(frame.to_enu(*local.frame.to_geodetic(p[:, 0], p[:, 1], p[:, 2])), axis=1)
    cam_enu, r_f = pose.in_frame(frame)
    n = uv.shape[0]
    rays = (camera.pixel_to_ray(np.concatenate((uv, uv + [1.0, 0.0], uv + [0.0, 1.0]))) @ r_f.T).tolist()
    tilt, yaw, px = math.radians(unc.tilt_sigma_deg) ** 2, math.radians(unc.heading_deg) ** 2, unc.pixel_sigma_px ** 2
    pos, gv = unc.position_sigma_m ** 2, ground.sigma_m ** 2
    vert = unc.vertical_m ** 2 + gv
    lat, lon, alt = frame.to_geodetic(pts[:, 0], pts[:, 1], pts[:, 2])
    out = []
    for i in range(n):
        dx, dy, dz = rays[i]
        sx, sy, k = dx / dz, dy / dz, (cam_enu[2] - pts[i, 2]) / -dz
        moves = ((0.0, -dz, dy, tilt), (dz, 0.0, -dx, tilt), (-dy, dx, 0.0, yaw),
                 (*(a - b for a, b in zip(rays[n + i], rays[i], strict=True)), px),
                 (*(a - b for a, b in zip(rays[2 * n + i], rays[i], strict=True)), px))
        cee = cen = cnn = 0.0
        for mx, my, mz, var in moves:
            ge, gn = k * (mx - sx * mz), k * (my - sy * mz)
            cee, cen, cnn = cee + var * ge * ge, cen + var * ge * gn, cnn + var * gn * gn
        cov = np.array([[cee + pos + vert * sx * sx, cen + vert * sx * sy, gv * sx],
                        [cen + vert * sx * sy, cnn + pos + vert * sy * sy, gv * sy], [gv * sx, gv * sy, gv]])
        r = ecef_to_enu_rotation(frame.lat0_deg, frame.lon0_deg) @ ecef_to_enu_rotation(lat[i], lon[i]).T
        out.append((lat[i], lon[i], alt[i], r.T @ cov @ r))
    return out


def test_dem_geolocation_matches_the_previous_per_fire_implementation(terrain):
    """The vectorised DEM path (rigid frame-to-frame motion instead of pyproj round trips,
    rays shared by the hit and the pixel Jacobian, the fixes' covariance rotations all at
    once) gives the previous results: positions to 1e-6 m (pyproj round trips: ~1e-8 m),
    covariances to 1e-7 relative."""
    from skyfix.geo import inverse
    from skyfix.thermal import PoseUncertainty, geolocate_many
    from skyfix.thermal.ground import frame_near

    dem = terrain.dem_ground(metres_per_px=2.0, sigma_m=0.7)
    unc = PoseUncertainty(position_sigma_m=1.5, altitude_sigma_m=2.5, tilt_sigma_deg=0.5, yaw_sigma_deg=0.8,
                          pixel_sigma_px=0.4)
    uv = np.array([[100.5, 300.2], [320.0, 256.0], [600.1, 480.9], [33.3, 400.0], [500.0, 290.0]])
    for e, n, yaw, g_pitch in ((-200.0, 150.0, 120.0, -55.0), (180.0, -90.0, 300.0, -80.0), (0.0, 320.0, 190.0, -40.0)):
        lat, lon, alt = FRAME.to_geodetic(e, n, terrain.max_up_m + 120.0)
        pose = CameraPose(float(lat), float(lon), float(alt), 3.0, -4.0, yaw, g_pitch, 0.0, 0.0, False)
        fixes = geolocate_many(uv, CAM, pose, dem, uncertainty=unc)
        frame = frame_near(pose.lat_deg, pose.lon_deg, dem.alt_m)
        for fix, (la, lo, al, cov) in zip(fixes, _previous_geolocate_many(CAM, pose, uv, dem, frame, unc), strict=True):
            assert float(inverse(fix.lat_deg, fix.lon_deg, la, lo)[1]) < 1e-6 and abs(fix.alt_m - al) < 1e-6
            np.testing.assert_allclose(fix.cov_enu_m2, cov, rtol=1e-7, atol=1e-7 * np.abs(cov).max())
