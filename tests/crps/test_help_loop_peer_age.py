"""A peer's estimate moved to the present (crps/help_loop._peer_now): bounded in time, honest in covariance.

The helper plans its vantage point and aims its camera at where the requester is now: its newest estimate moved
on with its velocity. Estimates come at 10 Hz; when they stop while the peer's heartbeats go on, a held 5 m/s
velocity must not carry the peer on for minutes (300 m a minute).
"""

from __future__ import annotations

import numpy as np
import pytest

from skyfix import geo
from skyfix.crps.help_loop import PEER_MOVE_MAX_S, _peer_now
from skyfix.crps.node import EXTRAPOLATION_ACCEL_MPS2
from skyfix.types import GeoFix

LAT0, LON0, ALT0 = 47.397742, 8.545594, 488.0
VEL = np.array([5.0, 0.0, 0.0])  # east at RTL speed


def _offset_m(fix: GeoFix) -> np.ndarray:
    return geo.LocalFrame(LAT0, LON0, ALT0).to_enu(fix.lat_deg, fix.lon_deg, fix.alt_m)


def _fix(time_s: float) -> GeoFix:
    return GeoFix(LAT0, LON0, ALT0, np.diag([0.25, 0.25, 0.5]), time_s, "skyfix.fusion")


def test_a_fresh_estimate_moves_with_its_velocity():
    now, vel = _peer_now(_fix(100.0), VEL, 100.4)
    np.testing.assert_allclose(_offset_m(now), [2.0, 0.0, 0.0], atol=0.01)  # 5 m/s x 0.4 s
    assert vel is not None and np.allclose(vel, VEL)
    assert now.time_s == 100.4
    # braking at the autopilot's acceleration over 0.4 s: 0.2 m, added in quadrature
    assert now.cov_enu_m2[0, 0] == pytest.approx(0.25 + (0.5 * EXTRAPOLATION_ACCEL_MPS2 * 0.16) ** 2)


def test_a_stale_estimate_is_moved_no_further_than_the_bound_and_gives_no_velocity():
    now, vel = _peer_now(_fix(100.0), VEL, 160.0)  # estimates stopped a minute ago
    np.testing.assert_allclose(_offset_m(now), [5.0 * PEER_MOVE_MAX_S, 0.0, 0.0], atol=0.01)  # 15 m, not 300 m
    assert vel is None
    # where the peer is after a minute unheard: its covariance says "anywhere within kilometres"
    assert np.sqrt(now.cov_enu_m2[0, 0]) > 1000.0


def test_an_estimate_from_the_future_is_not_moved_back():
    now, vel = _peer_now(_fix(100.0), VEL, 99.5)  # clocks 0.5 s apart
    np.testing.assert_allclose(_offset_m(now), [0.0, 0.0, 0.0], atol=0.01)
    assert vel is not None
