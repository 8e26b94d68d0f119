"""Geolocation: round trips through the foundation camera, hand-computed cases,
covariance against Monte Carlo, datums, gimbal-yaw references, DEM ground, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest

from skyfix.camera import Camera, CameraPose, ground_intersection, world_to_pixel
from skyfix.errors import GeometryError, InputError
from skyfix.geo import LocalFrame, inverse
from skyfix.thermal import (
    DemGround,
    FlatGround,
    Hotspot,
    PoseUncertainty,
    camera_pose,
    geolocate,
    geolocate_many,
    locate_in_frame,
)

CAM = Camera.from_fov(640, 512, 50.0)
FRAME = LocalFrame(45.4592, -73.9191, 30.0)


def pose_at(e: float, n: float, agl: float, **kw) -> CameraPose:
    lat, lon, alt = FRAME.to_geodetic(e, n, agl)
    return CameraPose(float(lat), float(lon), float(alt), **kw)


@pytest.mark.parametrize("kw", [
    {"gimbal_pitch_deg": -90.0},
    {"roll_deg": 12.0, "pitch_deg": -9.0, "yaw_deg": 233.0, "gimbal_pitch_deg": -65.0, "stabilized": False},
    {"roll_deg": -14.0, "pitch_deg": 13.0, "yaw_deg": 47.0, "gimbal_pitch_deg": -75.0,
     "gimbal_yaw_deg": 30.0, "gimbal_roll_deg": 2.0, "stabilized": True},
])
def test_round_trip_ground_point_pixel_ground(kw):
    pose = pose_at(-20.0, 35.0, 120.0, **kw)
    # A ground point on the flat ground at 30 m ellipsoidal height, seen somewhere in the frame.
    truth = ground_intersection(CAM, pose, np.array([[410.3, 133.7]]), 30.0, FRAME)[0]
    uv = world_to_pixel(CAM, pose, FRAME, truth[None, :])[0]
    fix = geolocate(uv, CAM, pose, 30.0)
    lat, lon, alt = FRAME.to_geodetic(*truth)
    assert float(inverse(lat, lon, fix.lat_deg, fix.lon_deg)[1]) < 1e-4  # 0.1 mm
    assert fix.alt_m == pytest.approx(30.0, abs=1e-4)


def test_hand_computed_nadir_case():
    # Nadir camera, heading north, 100 m above flat ground: image right is east, image up is north.
    pose = pose_at(0.0, 0.0, 100.0, gimbal_pitch_deg=-90.0)
    centre = geolocate([CAM.cx, CAM.cy], CAM, pose, 30.0)
    assert float(inverse(pose.lat_deg, pose.lon_deg, centre.lat_deg, centre.lon_deg)[1]) < 1e-3
    du = CAM.fx * math.tan(math.radians(10.0))
    east = geolocate([CAM.cx + du, CAM.cy], CAM, pose, 30.0)
    north = geolocate([CAM.cx, CAM.cy - du], CAM, pose, 30.0)
    expected = 100.0 * math.tan(math.radians(10.0))  # 17.633 m
    e, n, _ = FRAME.to_enu(east.lat_deg, east.lon_deg, east.alt_m)
    assert float(e) == pytest.approx(expected, abs=5e-3) and float(n) == pytest.approx(0.0, abs=5e-3)
    e, n, _ = FRAME.to_enu(north.lat_deg, north.lon_deg, north.alt_m)
    assert float(n) == pytest.approx(expected, abs=5e-3) and float(e) == pytest.approx(0.0, abs=5e-3)


def test_hand_computed_covariance_nadir_position_only():
    # Nadir, centre pixel, only horizontal position error: the ground point inherits it exactly.
    pose = pose_at(0.0, 0.0, 100.0, gimbal_pitch_deg=-90.0)
    unc = PoseUncertainty(position_sigma_m=2.0, altitude_sigma_m=0.0, tilt_sigma_deg=0.0, pixel_sigma_px=0.0)
    fix = geolocate([CAM.cx, CAM.cy], CAM, pose, 30.0, uncertainty=unc)
    np.testing.assert_allclose(fix.cov_enu_m2[:2, :2], 4.0 * np.eye(2), atol=1e-6)
    # Tilt only: 0.5 deg at 100 m height -> 100 * 0.5 deg in radians = 0.873 m per axis.
    unc = PoseUncertainty(position_sigma_m=0.0, altitude_sigma_m=0.0, tilt_sigma_deg=0.5, pixel_sigma_px=0.0)
    fix = geolocate([CAM.cx, CAM.cy], CAM, pose, 30.0, uncertainty=unc)
    sigma = 100.0 * math.radians(0.5)
    np.testing.assert_allclose(np.sqrt(np.diag(fix.cov_enu_m2[:2, :2])), [sigma, sigma], rtol=1e-3)


def test_covariance_matches_monte_carlo():
    rng = np.random.default_rng(7)
    base = dict(roll_deg=8.0, pitch_deg=-6.0, yaw_deg=120.0, gimbal_pitch_deg=-62.0, stabilized=False)
    pose = pose_at(10.0, -40.0, 110.0, **base)
    uv = np.array([[420.0, 150.0]])
    unc = PoseUncertainty(position_sigma_m=1.5, altitude_sigma_m=2.0, tilt_sigma_deg=0.5,
                          yaw_sigma_deg=1.0, pixel_sigma_px=0.7)
    p0, cov = locate_in_frame(CAM, pose, uv, FlatGround(30.0), FRAME, unc)
    e0, n0, u0 = FRAME.to_enu(pose.lat_deg, pose.lon_deg, pose.alt_m)
    samples = []
    for _ in range(3000):
        lat, lon, alt = FRAME.to_geodetic(e0 + rng.normal(0, 1.5), n0 + rng.normal(0, 1.5), u0 + rng.normal(0, 2.0))
        p = CameraPose(float(lat), float(lon), float(alt), base["roll_deg"] + rng.normal(0, 0.5),
                       base["pitch_deg"] + rng.normal(0, 0.5), base["yaw_deg"] + rng.normal(0, 1.0),
                       base["gimbal_pitch_deg"], stabilized=False)
        samples.append(ground_intersection(CAM, p, uv + rng.normal(0, 0.7, 2), 30.0, FRAME)[0, :2])
    mc = np.cov(np.array(samples).T)
    # Whitened sample covariance ~ identity: 3000 samples give ~3 % sampling error per
    # entry; linearisation (and roll/pitch about body vs level axes) adds a few percent.
    w = np.linalg.inv(np.linalg.cholesky(cov[0, :2, :2]))
    np.testing.assert_allclose(w @ mc @ w.T, np.eye(2), atol=0.12)
    assert np.mean(samples, axis=0) == pytest.approx(p0[0, :2], abs=0.15)


def test_gimbal_yaw_reference_and_altitude_datum():
    a = camera_pose(45.0, -73.0, 200.0, altitude_datum="ellipsoid", roll_deg=0.0, pitch_deg=0.0, yaw_deg=30.0,
                    gimbal_pitch_deg=-60.0, gimbal_yaw_deg=20.0, gimbal_yaw_reference="vehicle", stabilized=True)
    b = camera_pose(45.0, -73.0, 200.0, altitude_datum="ellipsoid", roll_deg=0.0, pitch_deg=0.0, yaw_deg=30.0,
                    gimbal_pitch_deg=-60.0, gimbal_yaw_deg=50.0, gimbal_yaw_reference="north", stabilized=True)
    np.testing.assert_allclose(a.r_ned_from_cam(), b.r_ned_from_cam(), atol=1e-12)
    c = camera_pose(45.0, -73.0, 233.0, altitude_datum="amsl", geoid_undulation_m=-33.0, roll_deg=0.0,
                    pitch_deg=0.0, yaw_deg=30.0, gimbal_pitch_deg=-60.0, gimbal_yaw_deg=20.0,
                    gimbal_yaw_reference="vehicle", stabilized=True)
    assert c.alt_m == pytest.approx(200.0)
    with pytest.raises(InputError, match="geoid_undulation_m"):
        camera_pose(45.0, -73.0, 233.0, altitude_datum="amsl", roll_deg=0.0, pitch_deg=0.0, yaw_deg=0.0,
                    gimbal_pitch_deg=-90.0, gimbal_yaw_reference="vehicle", stabilized=True)
    with pytest.raises(InputError, match="AGL"):
        camera_pose(45.0, -73.0, 100.0, altitude_datum="agl", roll_deg=0.0, pitch_deg=0.0, yaw_deg=0.0,
                    gimbal_pitch_deg=-90.0, gimbal_yaw_reference="vehicle", stabilized=True)
    with pytest.raises(InputError, match="gimbal_yaw_reference"):
        camera_pose(45.0, -73.0, 100.0, altitude_datum="ellipsoid", roll_deg=0.0, pitch_deg=0.0, yaw_deg=0.0,
                    gimbal_pitch_deg=-90.0, gimbal_yaw_reference="body", stabilized=True)
    assert FlatGround.from_amsl(63.0, geoid_undulation_m=-33.0).alt_m == pytest.approx(30.0)
    assert FlatGround.from_agl(a, 150.0).alt_m == pytest.approx(50.0)


def test_hotspot_and_batch_inputs():
    pose = pose_at(0.0, 0.0, 80.0, gimbal_pitch_deg=-70.0)
    spot = Hotspot(300.5, 200.25, 20, 400.0, 100.0, (295, 195, 10, 10), "celsius")
    one = geolocate(spot, CAM, pose, 30.0, time_s=12.5, source_id="cam0")
    many = geolocate_many([spot, spot], CAM, pose, 30.0)
    assert one.time_s == 12.5 and one.source_id == "cam0"
    assert many[1].lat_deg == pytest.approx(one.lat_deg, abs=1e-12)
    with pytest.raises(InputError, match="geolocate_many"):
        geolocate([[1.0, 2.0], [3.0, 4.0]], CAM, pose, 30.0)


def make_dem(path, slope: float):
    import rasterio
    from rasterio.transform import from_origin

    # A plane rising `slope` m per m towards the east, on a 0.5 m grid in UTM 18N.
    utm = "EPSG:32618"
    import pyproj
    x0, y0 = pyproj.Transformer.from_crs("EPSG:4326", utm, always_xy=True).transform(FRAME.lon0_deg, FRAME.lat0_deg)
    size = 800
    xs = x0 - 200.0 + 0.5 * (np.arange(size) + 0.5)
    heights = np.tile(30.0 + slope * (xs - x0), (size, 1)).astype(np.float32)
    with rasterio.open(path, "w", driver="GTiff", width=size, height=size, count=1, dtype="float32",
                       crs=utm, transform=from_origin(x0 - 200.0, y0 + 200.0, 0.5, 0.5)) as dst:
        dst.write(heights, 1)
    return path


def test_dem_ground_iterates_to_the_terrain(tmp_path):
    dem = DemGround.from_geotiff(make_dem(tmp_path / "dem.tif", 0.3), datum="ellipsoid", sigma_m=0.5)
    pose = pose_at(-30.0, 0.0, 120.0, yaw_deg=90.0, gimbal_pitch_deg=-55.0)
    uv = np.array([320.0, 300.0])
    fix = geolocate(uv, CAM, pose, dem)
    # The answer lies on the terrain and on the pixel's ray.
    assert fix.alt_m == pytest.approx(float(dem.height_at(fix.lat_deg, fix.lon_deg)), abs=0.02)
    p = FRAME.to_enu(fix.lat_deg, fix.lon_deg, fix.alt_m)
    back = world_to_pixel(CAM, pose, FRAME, np.array([[float(x) for x in p]]))[0]
    assert back == pytest.approx(uv, abs=0.01)
    # Flat ground at 30 m would put it several metres further away (terrain rises to the east).
    flat = geolocate(uv, CAM, pose, 30.0)
    assert float(inverse(fix.lat_deg, fix.lon_deg, flat.lat_deg, flat.lon_deg)[1]) > 3.0
    assert fix.sigma_up_m == pytest.approx(0.5, rel=1e-4)  # axes of the fix vs the frame
    # The same file read as AMSL: every cell raised by the EGM96 undulation there (about
    # -32 m near Montreal), interpolated from a coarse lattice (the geoid is smooth).
    from skyfix.geoid import geoid_undulation_m

    amsl = DemGround.from_geotiff(tmp_path / "dem.tif", datum="amsl")
    lat, lon = fix.lat_deg, fix.lon_deg
    assert float(amsl.height_at(lat, lon) - dem.height_at(lat, lon)) == pytest.approx(
        float(geoid_undulation_m(lat, lon)), abs=0.02)


@pytest.mark.parametrize(("call", "error", "message"), [
    (lambda p: geolocate([np.nan, 3.0], CAM, p, 30.0), InputError, "NaN"),
    (lambda p: geolocate([320.0, 256.0], CAM, p, p.alt_m + 5.0), GeometryError, "not above the ground"),
    (lambda p: geolocate([320.0, 0.0], CAM, pose_at(0, 0, 80.0, gimbal_pitch_deg=0.0), 30.0), GeometryError,
     "horizon"),
    (lambda p: geolocate([320.0, 256.0], "cam", p, 30.0), InputError, "Camera"),
    (lambda p: geolocate([320.0, 256.0], CAM, p, "30"), InputError, "ground_alt_m"),
    (lambda p: geolocate([320.0, 256.0], CAM, p, 30.0, uncertainty=PoseUncertainty(tilt_sigma_deg=-1)),
     InputError, "tilt_sigma_deg"),
    (lambda p: CameraPose(p.lat_deg, p.lon_deg, float("nan")), InputError, "alt_m"),
])
def test_bad_input(call, error, message):
    with pytest.raises(error, match=message):
        call(pose_at(0.0, 0.0, 80.0, gimbal_pitch_deg=-70.0))
