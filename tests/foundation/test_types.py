"""skyfix.types: GeoFix.many builds the same fixes as the constructor, with the same refusals."""

from __future__ import annotations

import numpy as np
import pytest

from skyfix.errors import InputError
from skyfix.types import GeoFix


def _inputs(n: int = 6):
    rng = np.random.default_rng(3)
    a = rng.normal(size=(n, 3, 3))
    return 45.0 + rng.random(n), -73.0 + rng.random(n), 30.0 + rng.random(n), a @ np.swapaxes(a, 1, 2)


def test_many_equals_one_by_one():
    lat, lon, alt, cov = _inputs()
    many = GeoFix.many(lat, lon, alt, cov, 12.5, "thermal")
    assert len(many) == lat.size
    for k, fix in enumerate(many):
        one = GeoFix(lat[k], lon[k], alt[k], cov[k], 12.5, "thermal")
        assert (fix.lat_deg, fix.lon_deg, fix.alt_m, fix.time_s, fix.source_id) == \
            (one.lat_deg, one.lon_deg, one.alt_m, one.time_s, one.source_id)
        assert type(fix.lat_deg) is float and type(fix.alt_m) is float
        np.testing.assert_array_equal(fix.cov_enu_m2, one.cov_enu_m2)
        assert not fix.cov_enu_m2.flags.writeable
        assert fix.sigma_horizontal_m == one.sigma_horizontal_m
    cov[0, 0, 0] = 1e6  # the caller's array is copied
    assert many[0].cov_enu_m2[0, 0] != 1e6
    assert GeoFix.many([], [], [], np.zeros((0, 3, 3))) == []


@pytest.mark.parametrize("field, index, value, message", [
    ("lat", 2, 90.5, r"GeoFix.lat_deg must be within \[-90, 90\]"),
    ("lon", 0, 400.0, "GeoFix.lon_deg must be within"),
    ("alt", 4, np.nan, "GeoFix.alt_m contains 1 NaN"),
    ("cov", 3, -np.eye(3), r"GeoFix.cov_enu_m2\[3\] must be positive semi-definite"),
])
def test_many_refuses_what_the_constructor_refuses(field, index, value, message):
    lat, lon, alt, cov = _inputs()
    arrays = {"lat": lat, "lon": lon, "alt": alt, "cov": cov}
    arrays[field][index] = value
    with pytest.raises(InputError, match=message):
        GeoFix.many(arrays["lat"], arrays["lon"], arrays["alt"], arrays["cov"])


def test_many_refuses_mismatched_lengths_and_a_bad_time():
    lat, lon, alt, cov = _inputs()
    with pytest.raises(InputError, match="shape"):
        GeoFix.many(lat[:2], lon, alt, cov)
    with pytest.raises(InputError, match="time_s"):
        GeoFix.many(lat, lon, alt, cov, time_s=np.inf)
