"""Fusing helpers' observations into a fix: exact cases, covariance calibration, errors."""

import math

import numpy as np
import pytest

from skyfix.crps import locate
from skyfix.errors import InputError
from skyfix.geo import LocalFrame
from skyfix.types import RelativeObservation

LAT0, LON0, ALT0 = 47.0, 8.0, 400.0


def observation(frame, helper_enu, target_enu, cov, observer_cov=None, target_id="t", time_s=0.0):
    """The observation a helper at ``helper_enu`` would make of ``target_enu`` (ENU axes at the helper)."""
    lat, lon, alt = (float(x) for x in frame.to_geodetic(*helper_enu))
    r_local_from_frame = frame.enu_rotation_at(lat, lon).T
    offset = r_local_from_frame @ (np.asarray(target_enu) - np.asarray(helper_enu))
    rng_m = float(np.linalg.norm(offset))
    return RelativeObservation("h", target_id, time_s, offset / rng_m, rng_m, cov, lat, lon, alt, observer_cov)


def radial_cov(bearing, sigma_r, sigma_across):
    b = bearing / np.linalg.norm(bearing)
    return sigma_r ** 2 * np.outer(b, b) + sigma_across ** 2 * (np.eye(3) - np.outer(b, b))


def test_single_observation_hand_computed():
    # Helper at the origin sees the target 100 m due north, level.
    obs = RelativeObservation("h", "t", 5.0, np.array([0.0, 1.0, 0.0]), 100.0, np.eye(3) * 0.04,
                              LAT0, LON0, ALT0, np.eye(3) * 0.25)
    fix = locate([obs])
    # 100 m north at height h: latitude grows by 100 / (M + h) rad, M the meridian radius.
    a, e2 = 6378137.0, 6.69437999014e-3
    m = a * (1 - e2) / (1 - e2 * math.sin(math.radians(LAT0)) ** 2) ** 1.5
    assert fix.lat_deg == pytest.approx(LAT0 + math.degrees(100.0 / (m + ALT0)), abs=2e-9)
    assert fix.lon_deg == pytest.approx(LON0, abs=1e-12)
    # The tangent plane at the helper rises above the ellipsoid by d^2 / 2R = 0.8 mm at 100 m.
    assert fix.alt_m == pytest.approx(ALT0 + 100.0 ** 2 / (2 * 6_371_000), abs=2e-4)
    np.testing.assert_allclose(fix.cov_enu_m2, np.eye(3) * 0.29, atol=1e-6)
    assert fix.time_s == 5.0 and fix.source_id == "crps:t"


def test_two_helpers_exact_and_far_apart():
    frame = LocalFrame(LAT0, LON0, ALT0)
    target = np.array([30.0, 2500.0, 40.0])  # 2.5 km away: the ENU axes at each helper differ
    helpers = [np.array([30.0, 0.0, 40.0]), np.array([-2470.0, 2500.0, 40.0])]  # due south, due west
    obs = [observation(frame, h, target, radial_cov(target - h, 1.0, 0.1)) for h in helpers]
    fix = locate(obs, frame)
    got = np.array([float(x) for x in frame.to_enu(fix.lat_deg, fix.lon_deg, fix.alt_m)])
    np.testing.assert_allclose(got, target, atol=1e-3)
    # Two near-orthogonal bearings: each helper's cross-range pins the other's range.
    assert fix.sigma_horizontal_m < 0.11


def test_covariance_is_calibrated_monte_carlo():
    rng = np.random.default_rng(0)
    frame = LocalFrame(LAT0, LON0, ALT0)
    target = np.array([0.0, 0.0, 0.0])
    nees = []
    for _ in range(400):
        obs = []
        for az in (0.0, 75.0):
            d = rng.uniform(40, 70)
            h = -d * np.array([math.sin(math.radians(az)), math.cos(math.radians(az)), -0.2])
            cov = radial_cov(target - h, 0.03 * d, d * math.radians(0.3))
            pos_cov = np.diag([0.25, 0.25, 0.64])
            noisy_target = target + rng.multivariate_normal(np.zeros(3), cov, method="cholesky")
            noisy_helper = h + rng.multivariate_normal(np.zeros(3), pos_cov, method="cholesky")
            # The helper reports its noisy position and what it saw from its true one.
            o = observation(frame, h, noisy_target, cov)
            lat, lon, alt = (float(x) for x in frame.to_geodetic(*noisy_helper))
            obs.append(RelativeObservation("h", "t", 0.0, o.bearing_unit_enu, o.range_m, cov, lat, lon, alt, pos_cov))
        fix = locate(obs, frame)
        err = np.array([float(x) for x in frame.to_enu(fix.lat_deg, fix.lon_deg, fix.alt_m)]) - target
        nees.append(float(err @ np.linalg.solve(fix.cov_enu_m2, err)))
    # chi-square with 3 dof: mean 3, 95 % below 7.81 (400 samples: +-0.25 and +-2.2 % at 2 sigma)
    assert np.mean(nees) == pytest.approx(3.0, abs=0.45)
    assert np.mean(np.array(nees) <= 7.815) == pytest.approx(0.95, abs=0.035)


def test_errors():
    with pytest.raises(InputError, match="at least one"):
        locate([])
    a = RelativeObservation("a", "t1", 0.0, np.array([0, 1.0, 0]), 10.0, np.eye(3), LAT0, LON0, ALT0)
    b = RelativeObservation("b", "t2", 0.0, np.array([1.0, 0, 0]), 10.0, np.eye(3), LAT0, LON0, ALT0)
    with pytest.raises(InputError, match="one target"):
        locate([a, b])
    no_pos = RelativeObservation("c", "t1", 0.0, np.array([0, 1.0, 0]), 10.0, np.eye(3))
    with pytest.raises(InputError, match="observer position"):
        locate([no_pos])
    with pytest.raises(InputError):
        locate(["not an observation"])
