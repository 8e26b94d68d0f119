"""skyfix.geo.Height: a height that names its datum, converted through PROJ's geoid grids."""

from __future__ import annotations

import pytest

from skyfix.errors import InputError, NotAvailableError
from skyfix.geo import Height, VerticalDatum
from skyfix.geoid import find_geoid_grid, geoid_undulation_m

WGS84, EGM96, EGM2008 = VerticalDatum.WGS84, VerticalDatum.EGM96, VerticalDatum.EGM2008


def test_amsl_to_ellipsoidal_matches_nga_check_value():
    # NGA's EGM96 check point (38.6281550, -90.2208450): N = -31.628 m (the grid's bilinear
    # value is within 0.1 m of the full synthesis; the ~100 m cache cell adds < 1 cm).
    h = Height(150.0, EGM96).to(WGS84, 38.6281550, -90.2208450)
    assert h.datum is WGS84 and h.value_m == pytest.approx(150.0 - 31.628, abs=0.1)


def test_round_trip_is_exact_and_same_datum_is_identity():
    amsl = Height(372.0, "egm96")
    there = (46.52, 6.63)
    ell = amsl.to("wgs84", *there)
    assert ell.value_m - amsl.value_m == pytest.approx(float(geoid_undulation_m(*there)), abs=0.01)
    assert ell.to(EGM96, *there) == amsl  # the same N both ways: bit-exact back
    assert amsl.to(EGM96, 0.0, 0.0) is amsl  # no position needed to stay on one datum


def test_egm2008_converts_where_its_grid_is_installed_and_says_how_to_get_it_otherwise():
    try:
        find_geoid_grid("egm2008")
    except NotAvailableError as exc:
        assert "us_nga_egm08_25.tif" in str(exc) and "projsync" in str(exc)
        with pytest.raises(NotAvailableError, match="EGM2008"):
            Height(10.0, EGM96).to(EGM2008, 46.52, 6.63)
        return
    # EGM96 and EGM2008 differ by < 1 m over Europe (and < 2 m nearly everywhere).
    h08 = Height(10.0, EGM96).to(EGM2008, 46.52, 6.63)
    assert h08.datum is EGM2008 and abs(h08.value_m - 10.0) < 1.0


def test_bad_heights_and_datums_are_refused():
    with pytest.raises(InputError, match="Height.datum.*egm96"):
        Height(1.0, "amsl")
    with pytest.raises(InputError, match="Height.value_m"):
        Height(float("nan"), WGS84)
    with pytest.raises(InputError, match="lat_deg"):
        Height(1.0, EGM96).to(WGS84, 95.0, 0.0)
    with pytest.raises(InputError, match="unknown geoid model"):
        find_geoid_grid("egm84")
