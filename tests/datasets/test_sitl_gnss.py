"""skyfix.datasets.sitl_gnss: ArduPilot SITL's receiver moved by an ENU error through its glitch
parameters. The conversion is checked against the exact ellipsoidal frame and a hand value; on the
firmware itself, the fix it reports minus its own truth (SIM_STATE) is the error asked for."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from skyfix.datasets import sitl
from skyfix.datasets.sitl_gnss import SitlGnssError
from skyfix.errors import InputError
from skyfix.geo import LocalFrame

HOME = (46.52, 6.63, 372.0, 0.0)


def test_glitch_degrees_move_a_fix_by_the_error_in_metres():
    err = SitlGnssError(None, lambda t: np.zeros(3), lambda: 0.0, HOME[:3])
    x_deg, y_deg, z_m = err.glitch_for(np.array([2.0, -3.0, 1.5]))
    frame = LocalFrame(*HOME[:3])
    e, n, u = frame.to_enu(HOME[0] + x_deg, HOME[1] + y_deg, HOME[2])
    assert (float(e), float(n)) == pytest.approx((2.0, -3.0), abs=1e-6) and z_m == 1.5
    # by hand: WGS84 meridian radius of curvature at 46.52 deg, M = a(1-e2)/(1-e2 sin^2)^1.5 = 6367.2 km,
    # so 3 m south is 3/M rad = 2.6996e-5 deg of latitude; N = a/sqrt(1-e2 sin^2) = 6389.3 km, so 2 m east
    # is 2/(N cos 46.52 deg) rad = 2.4753e-5 deg of longitude
    a, e2, s2 = 6378137.0, 6.69437999014e-3, math.sin(math.radians(HOME[0])) ** 2
    m_m, n_m = a * (1 - e2) / (1 - e2 * s2) ** 1.5, a / math.sqrt(1 - e2 * s2)
    assert x_deg == pytest.approx(-math.degrees(3.0 / m_m), rel=1e-4)
    assert y_deg == pytest.approx(math.degrees(2.0 / (n_m * math.cos(math.radians(HOME[0])))), rel=1e-4)


def test_bad_receiver_is_an_input_error():
    with pytest.raises(InputError, match="receiver"):
        SitlGnssError(None, lambda t: np.zeros(3), lambda: 0.0, HOME[:3], receiver=3)


@pytest.mark.sitl
@pytest.mark.slow
@pytest.mark.skipif(bool(sitl.missing_reason()), reason=sitl.missing_reason() or "-")
def test_sitl_reports_truth_plus_the_error_and_follows_it():
    from skyfix.drivers.vehicle import Vehicle

    with sitl.SitlFleet(1, speedup=5.0, homes=[HOME]) as fleet:
        vehicle = Vehicle.connect(fleet[0].url, timeout_s=30.0)
        truth = sitl.SitlTruth.connect(fleet[0].url_secondary, HOME[2], speedup=5.0)
        try:
            truth.wait(10.0)
            vehicle.wait_until(lambda s: s.gps is not None and s.gps.fix_type >= 3, 60.0, what="GNSS fix")
            t0 = time.monotonic()
            track = [np.array([2.0, -3.0, 1.0])]
            err = SitlGnssError(truth.vehicle, lambda t: track[0], lambda: time.monotonic() - t0, HOME[:3],
                                period_s=0.5, speedup=5.0)
            frame = LocalFrame(*HOME[:3])

            def offset_enu_m() -> np.ndarray:
                time.sleep(1.0)  # the receiver's next fixes (5 Hz, 100 ms lag, 5x speed-up)
                g, t = vehicle.state.gps, truth.truth()  # a parked drone: the truth does not move meanwhile
                fix = np.array(frame.to_enu(g.lat_deg, g.lon_deg, g.alt_ellipsoid_m), dtype=float)
                return fix - np.array(frame.to_enu(t["lat_deg"], t["lon_deg"], t["alt_m"]), dtype=float)

            assert np.abs(offset_enu_m()).max() < 0.05  # perfect before
            err.apply_now()
            # the fix's 1e-7 deg quantisation (1.1 cm) and the height's 1 mm
            assert offset_enu_m() == pytest.approx(track[0], abs=0.03)
            err.start()
            track[0] = np.array([-1.0, 0.5, 0.0])
            time.sleep(0.5)  # one period
            assert offset_enu_m() == pytest.approx(track[0], abs=0.03)
            err.close()
            assert err.updates >= 2 and err.failures == 0
        finally:
            truth.close()
            vehicle.close()
