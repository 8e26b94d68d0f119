"""skyfix.geo: exactness on the WGS84 ellipsoid, known values, bad input."""

import numpy as np
import pyproj
import pytest

from skyfix.errors import InputError
from skyfix.geo import LocalFrame, destination, ecef_to_enu_rotation, inverse

ORIGINS = [(45.0, 7.0, 200.0), (-33.9, 151.2, 30.0), (0.0, 179.99, 0.0), (78.2, 15.6, 500.0),
           (-89.0, 0.0, 2800.0)]


def _random_points_near(lat0, lon0, rng, n=2000, radius_m=20_000.0):
    az = rng.uniform(0, 360, n)
    dist = rng.uniform(0, radius_m, n)
    lat, lon = destination(np.full(n, lat0), np.full(n, lon0), az, dist)
    alt = rng.uniform(-100.0, 5000.0, n)
    return lat, lon, alt


@pytest.mark.parametrize("origin", ORIGINS)
def test_enu_round_trip_within_20_km_is_sub_millimetre(origin):
    rng = np.random.default_rng(1)
    frame = LocalFrame(*origin)
    lat, lon, alt = _random_points_near(origin[0], origin[1], rng)
    e, n, u = frame.to_enu(lat, lon, alt)
    lat2, lon2, alt2 = frame.to_geodetic(e, n, u)
    e2, n2, u2 = frame.to_enu(lat2, lon2, alt2)
    assert np.max(np.abs(alt2 - alt)) < 1e-3
    assert np.max(np.hypot(e2 - e, n2 - n)) < 1e-3
    # Horizontal geodetic difference expressed in metres.
    _, dist = inverse(lat, lon, lat2, lon2)
    assert np.max(dist) < 1e-3


@pytest.mark.parametrize("origin", ORIGINS)
def test_enu_matches_pyproj_ecef_pipeline(origin):
    rng = np.random.default_rng(2)
    frame = LocalFrame(*origin)
    lat, lon, alt = _random_points_near(origin[0], origin[1], rng)
    to_ecef = pyproj.Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)
    xyz = np.stack(to_ecef.transform(lon, lat, alt), axis=1)
    xyz0 = np.array(to_ecef.transform(origin[1], origin[0], origin[2]))
    expected = (xyz - xyz0) @ ecef_to_enu_rotation(origin[0], origin[1]).T
    got = np.stack(frame.to_enu(lat, lon, alt), axis=1)
    assert np.max(np.linalg.norm(got - expected, axis=1)) < 1e-3


def test_enu_known_value_one_km_north_drops_by_curvature():
    frame = LocalFrame(45.0, 7.0, 0.0)
    lat, lon = destination(45.0, 7.0, 0.0, 1000.0)
    e, n, u = frame.to_enu(lat, lon, 0.0)
    # Meridional radius of curvature at 45 deg: M = a(1-e2)/(1-e2 sin^2)^1.5.
    a, f = 6378137.0, 1 / 298.257223563
    e2 = f * (2 - f)
    m = a * (1 - e2) / (1 - e2 * np.sin(np.radians(45.0)) ** 2) ** 1.5
    assert abs(float(e)) < 1e-6
    assert float(n) == pytest.approx(1000.0 - 1000.0**3 / (6 * m**2), abs=1e-3)
    assert float(u) == pytest.approx(-(1000.0**2) / (2 * m), abs=1e-3)


def test_destination_inverse_agree_with_geod_and_round_trip():
    rng = np.random.default_rng(3)
    geod = pyproj.Geod(ellps="WGS84")
    lat1 = rng.uniform(-80, 80, 500)
    lon1 = rng.uniform(-180, 180, 500)
    az = rng.uniform(0, 360, 500)
    dist = rng.uniform(0, 50_000, 500)
    lat2, lon2 = destination(lat1, lon1, az, dist)
    lon_ref, lat_ref, _ = geod.fwd(lon1, lat1, az, dist)
    _, d_err = inverse(lat2, lon2, lat_ref, lon_ref)
    assert np.max(d_err) < 1e-3
    bearing, distance = inverse(lat1, lon1, lat2, lon2)
    assert np.max(np.abs(distance - dist)) < 1e-3
    bearing_err = (bearing - az + 180.0) % 360.0 - 180.0
    assert np.max(np.abs(bearing_err[dist > 1.0])) < 1e-6


def test_destination_known_value_equator():
    # One degree of longitude along the equator is a * pi / 180 metres.
    lat, lon = destination(0.0, 10.0, 90.0, 6378137.0 * np.pi / 180.0)
    assert float(lat) == pytest.approx(0.0, abs=1e-12)
    assert float(lon) == pytest.approx(11.0, abs=1e-9)
    bearing, dist = inverse(0.0, 10.0, 0.0, 11.0)
    assert float(bearing) == pytest.approx(90.0, abs=1e-9)


def test_enu_rotation_at_origin_is_identity_and_orthonormal():
    frame = LocalFrame(45.0, 7.0, 0.0)
    assert np.allclose(frame.enu_rotation_at(45.0, 7.0), np.eye(3), atol=1e-12)
    r = frame.enu_rotation_at(45.09, 7.1)
    assert np.allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert not np.allclose(r, np.eye(3), atol=1e-4)


@pytest.mark.parametrize("call", [
    lambda: LocalFrame(91.0, 0.0, 0.0),
    lambda: LocalFrame(float("nan"), 0.0, 0.0),
    lambda: LocalFrame(45.0, 7.0, 0.0).to_enu(95.0, 7.0, 0.0),
    lambda: LocalFrame(45.0, 7.0, 0.0).to_geodetic(np.nan, 0.0, 0.0),
    lambda: LocalFrame(45.0, 7.0, 0.0).to_enu_points(np.zeros((4, 2))),
    lambda: destination(45.0, 7.0, 0.0, -5.0),
    lambda: inverse(45.0, 7.0, -91.0, 7.0),
    lambda: destination(45.0, "east", 0.0, 5.0),
])
def test_bad_geodetic_input_raises_input_error(call):
    with pytest.raises(InputError):
        call()
