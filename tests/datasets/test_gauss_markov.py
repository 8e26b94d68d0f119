"""The one Gauss-Markov implementation: stationary sigma, exp(-lag/tau) correlation, exactness.

Statistics are taken over N independent axes (an ensemble), so the tolerances are sampling
errors: the sample std's relative standard error is 1/sqrt(2N), a correlation's is
(1 - r^2)/sqrt(N) < 1/sqrt(N); the checks allow 5 of them.
"""

from __future__ import annotations

import numpy as np
import pytest

from skyfix.datasets.gauss_markov import gauss_markov, gauss_markov_step, transition
from skyfix.errors import InputError

N_AXES = 4000
SIGMA = 1.5
TAU_S = 60.0


def _check_stationary(first: np.ndarray, lagged: np.ndarray, lag_over_tau: float) -> None:
    n = first.size
    assert abs(first.std() / SIGMA - 1.0) < 5.0 / np.sqrt(2 * n)
    assert abs(lagged.std() / SIGMA - 1.0) < 5.0 / np.sqrt(2 * n)
    assert abs(np.corrcoef(first, lagged)[0, 1] - np.exp(-lag_over_tau)) < 5.0 / np.sqrt(n)


def test_series_is_stationary_with_lag_tau_correlation_exp_minus_one():
    rng = np.random.default_rng(0)
    t = np.sort(rng.uniform(0.0, TAU_S, 200))  # irregular spacing: the discretisation is exact for any dt
    t = np.concatenate([[0.0], t, [TAU_S]])
    x = gauss_markov(rng, t, np.full(N_AXES, SIGMA), TAU_S)
    _check_stationary(x[0], x[-1], 1.0)


def test_series_stays_stationary_across_blocks_and_gaps():
    # 1500 tau long (five internal blocks) with a 400 tau gap: the end still has sigma and
    # the correlation over the last tau is exp(-1)
    rng = np.random.default_rng(1)
    t = np.concatenate([np.linspace(0.0, 700.0 * TAU_S, 150), np.linspace(1100.0 * TAU_S, 1500.0 * TAU_S, 150)])
    t = np.append(t, t[-1] + TAU_S)
    x = gauss_markov(rng, t, np.full(N_AXES, SIGMA), TAU_S)
    _check_stationary(x[-2], x[-1], 1.0)


def test_series_equals_the_step_by_step_recursion():
    t = np.cumsum(np.random.default_rng(2).uniform(0.0, 4.0, 3000))  # ~200 tau of 60 s -> several blocks at tau 7
    x = gauss_markov(np.random.default_rng(3), t, [1.0, 0.0, 2.0], 7.0)
    w = np.random.default_rng(3).standard_normal((t.size, 3)) * [1.0, 0.0, 2.0]
    phi, gain = transition(np.diff(t), 7.0)
    y = np.empty_like(w)
    y[0] = w[0]
    for k in range(1, t.size):
        y[k] = phi[k - 1] * y[k - 1] + gain[k - 1] * w[k]
    np.testing.assert_allclose(x, y, rtol=0, atol=1e-10)
    assert (x[:, 1] == 0).all()


def test_running_state_is_stationary_with_lag_tau_correlation():
    rng = np.random.default_rng(4)
    x0 = SIGMA * rng.standard_normal(N_AXES)  # start in the stationary distribution
    x = x0
    for _ in range(60):
        x = gauss_markov_step(rng, x, TAU_S / 60.0, SIGMA, TAU_S)
    _check_stationary(x0, x, 1.0)


def test_bad_input_raises():
    rng = np.random.default_rng(0)
    with pytest.raises(InputError, match="non-decreasing"):
        gauss_markov(rng, [0.0, 2.0, 1.0], 1.0, 10.0)
    with pytest.raises(InputError, match="sigma"):
        gauss_markov(rng, [0.0, 1.0], [-1.0], 10.0)
    with pytest.raises(InputError, match="tau_s"):
        gauss_markov(rng, [0.0, 1.0], 1.0, 0.0)
    assert gauss_markov(rng, [], [1.0, 2.0], 10.0).shape == (0, 2)
