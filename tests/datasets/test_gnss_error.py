"""The simulated GNSS world: receivers of one area share most of their error (skyfix.datasets.gnss_error).

Statistics over many independent areas (seeds), so every sample of the slow common part is
independent: with n samples a standard deviation is known to ~1/sqrt(2n) relative, a
correlation coefficient r to ~(1 - r^2)/sqrt(n); tolerances are 4 such sigmas.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from skyfix.datasets.gnss_error import INDEPENDENT, REALISTIC, CommonGnssError, GnssErrorModel
from skyfix.datasets.sim.gps import GpsReceiver
from skyfix.errors import InputError

AREAS = 400


def _receiver(model: GnssErrorModel, seed: int, common: CommonGnssError | None) -> GpsReceiver:
    rx = GpsReceiver(seed, bias_sigma_m=model.own_sigma_m, bias_tau_s=model.own_tau_s,
                     noise_sigma_m=model.white_sigma_m, common=common)
    rx.step(20.0 * model.own_tau_s)  # its own error from the steady state
    return rx


def _pair_errors(model: GnssErrorModel, t_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Errors (AREAS, 3) of two receivers per area, read at ``t_s`` (truth at the origin)."""
    zero = np.zeros(3)
    a, b = [], []
    for area in range(AREAS):
        common = CommonGnssError(area, model.common_sigma_m, model.common_tau_s) if model.common_sigma_m else None
        a.append(_receiver(model, 2 * area + 10_000, common).read(t_s, zero, zero).pos_enu_m)
        b.append(_receiver(model, 2 * area + 10_001, common).read(t_s, zero, zero).pos_enu_m)
    return np.array(a), np.array(b)


def test_two_receivers_share_most_of_their_error():
    a, b = _pair_errors(REALISTIC, 37.0)
    n = a.size  # per-axis samples
    rel = 4.0 / math.sqrt(2 * n)
    # one receiver alone: issue 15's consumer figure, 1.5 m per axis
    assert REALISTIC.total_sigma_m == pytest.approx(1.5, abs=0.01)
    assert a.std() == pytest.approx(REALISTIC.total_sigma_m, rel=rel)
    # two of them: their difference is only the own parts, 0.76 m per axis
    assert (a - b).std() == pytest.approx(REALISTIC.difference_sigma_m, rel=rel)
    assert REALISTIC.difference_sigma_m < 0.55 * REALISTIC.total_sigma_m
    r = np.corrcoef(a.ravel(), b.ravel())[0, 1]
    r_expected = REALISTIC.common_sigma_m**2 / REALISTIC.total_sigma_m**2
    assert r == pytest.approx(r_expected, abs=4.0 * (1.0 - r_expected**2) / math.sqrt(n))


def test_independent_receivers_share_nothing():
    a, b = _pair_errors(INDEPENDENT, 37.0)
    n = a.size
    assert (a - b).std() == pytest.approx(math.sqrt(2.0) * INDEPENDENT.total_sigma_m, rel=4.0 / math.sqrt(2 * n))
    assert abs(np.corrcoef(a.ravel(), b.ravel())[0, 1]) < 4.0 / math.sqrt(n)


def test_common_track_is_gauss_markov_in_time():
    lag_s, step_s = 900.0, 60.0  # half the 1800 s correlation time: r = exp(-0.5)
    x0, x1 = [], []
    for seed in range(600):
        track = CommonGnssError(seed, REALISTIC.common_sigma_m, REALISTIC.common_tau_s, step_s=step_s)
        x0.append(track.at(120.0))
        x1.append(track.at(120.0 + lag_s))
    x0, x1 = np.array(x0).ravel(), np.array(x1).ravel()
    n = x0.size
    assert x0.std() == pytest.approx(REALISTIC.common_sigma_m, rel=4.0 / math.sqrt(2 * n))
    r = math.exp(-lag_s / REALISTIC.common_tau_s)
    assert np.corrcoef(x0, x1)[0, 1] == pytest.approx(r, abs=4.0 * (1.0 - r**2) / math.sqrt(n))


def test_common_track_does_not_depend_on_who_asks_first():
    late_first = CommonGnssError(3, 1.4, 1800.0)
    in_order = CommonGnssError(3, 1.4, 1800.0)
    late = late_first.at(250.7)
    early = late_first.at(12.25)
    assert np.array_equal(early, in_order.at(12.25))
    assert np.array_equal(late, in_order.at(250.7))
    # between grid points: on the straight line between its neighbours
    assert np.allclose(in_order.at(12.25), 0.75 * in_order.at(12.0) + 0.25 * in_order.at(13.0))


def test_bad_inputs_are_refused():
    with pytest.raises(InputError, match="t_s"):
        CommonGnssError(0, 1.4, 1800.0).at(-1.0)
    with pytest.raises(InputError, match="common_tau_s"):
        GnssErrorModel(common_tau_s=0.0)
    with pytest.raises(InputError, match="own_sigma_m"):
        GnssErrorModel(own_sigma_m=-0.1)
