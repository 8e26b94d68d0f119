"""ArrivalLag: the fusion lag follows how late observations arrive, within its bounds."""

import pytest

from skyfix.crps.arrival_lag import HEADROOM, SHRINK_AFTER_S, WINDOW_S, ArrivalLag
from skyfix.errors import InputError


def feed(lag: ArrivalLag, t0_s: float, seconds: float, delay_s: float) -> list[tuple[float, float]]:
    """Observations at 4/s, each ``delay_s`` late; the lags proposed (clock s, lag s)."""
    out = []
    for i in range(int(seconds * 4)):
        t = t0_s + i / 4.0
        lag.arrived(t, delay_s)
        new = lag.propose(t)
        if new is not None:
            out.append((t, new))
    return out


def test_the_lag_grows_with_late_observations_and_is_capped():
    lag = ArrivalLag(2.0, 8.0)
    assert feed(lag, 0.0, 5.0, 0.5) == []  # idle: the configured lag covers them
    grown = feed(lag, 5.0, 5.0, 4.0)
    # at the second late one (> 5 % of the window): the 95th percentile (interpolated) with headroom, at most
    # HEADROOM x the delay; later changes under MIN_CHANGE_S are not made
    assert grown[0][0] <= 5.5 and HEADROOM * 4.0 - 0.5 < lag.lag_s <= HEADROOM * 4.0
    feed(lag, 10.0, 40.0, 20.0)
    assert lag.lag_s == 8.0 and lag.largest_s == 8.0  # never beyond the cap


def test_the_lag_shrinks_back_slowly_once_the_load_is_gone():
    lag = ArrivalLag(2.0, 8.0)
    feed(lag, 0.0, 10.0, 4.0)
    assert lag.lag_s == pytest.approx(HEADROOM * 4.0)
    shrunk = feed(lag, 10.0, WINDOW_S + SHRINK_AFTER_S, 0.4)
    assert shrunk and shrunk[-1][1] == 2.0  # back to the configured lag, never below
    assert all(b[0] - a[0] >= SHRINK_AFTER_S for a, b in zip(shrunk, shrunk[1:], strict=False))


def test_bad_bounds_and_bad_delays():
    with pytest.raises(InputError):
        ArrivalLag(2.0, 1.0)
    lag = ArrivalLag(2.0, 8.0)
    for t in range(10):
        lag.arrived(float(t), float("nan"))
        lag.arrived(float(t), -3.0)  # an observation stamped ahead of the engine: no delay to learn from
    assert lag.propose(10.0) is None
