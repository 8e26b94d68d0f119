"""The hand-written pose refinement against scipy: its derivatives against finite
differences, its optimum and covariance against ``least_squares`` on the same residuals.

tags/pose.py keeps Gauss-Newton with written-out rotation derivatives for speed (see its
module docstring); these checks are what lets it stay hand code.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import approx_fprime, least_squares

from skyfix.tags.pose import DOWN_MOUNT, AttitudePrior, _project, _wrap, solve_pose

K = np.array([[554.0, 0.0, 319.5], [0.0, 554.0, 239.5], [0.0, 0.0, 1.0]])
SIGMA_PX = 0.5


def _scene(seed: int):
    """A tilted camera 1.5-3 m above 80 floor points it sees, pixels with 0.5 px noise."""
    rng = np.random.default_rng(seed)
    state = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(1.5, 3.0),
                      rng.uniform(-180, 180), rng.uniform(-12, 12), rng.uniform(-12, 12)])
    ground = np.zeros((80, 3))
    ground[:, :2] = state[:2] + rng.uniform(-1.0, 1.0, (80, 2))
    uv = _project(state, ground, K, DOWN_MOUNT) + rng.normal(0.0, SIGMA_PX, (80, 2))
    prior = AttitudePrior(state[5] + rng.normal(0, 0.5), state[4] + rng.normal(0, 0.5), 1.0)
    return state, ground, uv, prior


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_hand_derivatives_match_finite_differences(seed):
    state, ground, _, _ = _scene(seed)
    _, jac = _project(state, ground, K, DOWN_MOUNT, with_jacobian=True)
    numeric = approx_fprime(state, lambda s: _project(s, ground, K, DOWN_MOUNT).ravel(), 1e-7)
    # forward differences with a 1e-7 step: truncation ~1e-7 x the second derivative (px per
    # m^2 or deg^2, at most ~1e4 here) plus rounding ~1e-16 x 500 px / 1e-7 -> well below 1e-2 px
    np.testing.assert_allclose(jac.reshape(-1, 6), numeric, rtol=0, atol=1e-2)
    assert np.abs(numeric).max() > 100.0  # the comparison is not between near-zero numbers


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_optimum_and_covariance_match_scipy_least_squares(seed):
    state, ground, uv, prior = _scene(seed)
    sol = solve_pose(ground[:, :2], uv, K, prior=prior, sigma_px=SIGMA_PX)

    def residuals(s):
        pix = ((_project(s, ground, K, DOWN_MOUNT) - uv) / SIGMA_PX).ravel()
        return np.append(pix, [_wrap(s[5] - prior.roll_deg), s[4] - prior.pitch_deg])

    ref = least_squares(residuals, state, x_scale=[0.01, 0.01, 0.01, 0.1, 0.1, 0.1], xtol=1e-12, ftol=1e-12)
    # Gauss-Newton stops after a step under 1 cm / 0.3 deg; the next would be microns
    np.testing.assert_allclose(sol.state[:3], ref.x[:3], atol=1e-4)
    assert np.abs((sol.state[3:] - ref.x[3:] + 180.0) % 360.0 - 180.0).max() < 5e-3
    cov_ref = np.linalg.inv(ref.jac.T @ ref.jac) * max(1.0, 2 * ref.cost / (2 * len(uv) - 6))
    if "ambiguous" in sol.flags:  # the mirror pose fits as well: the solver says so, x100 variance
        cov_ref = cov_ref * 100.0
    np.testing.assert_allclose(np.sqrt(np.diag(sol.covariance)), np.sqrt(np.diag(cov_ref)), rtol=0.02)
    # and the truth is inside the stated uncertainty (3 sigma per axis)
    err = np.append(sol.state[:3] - state[:3], (sol.state[3:] - state[3:] + 180.0) % 360.0 - 180.0)
    assert (np.abs(err) < 3.0 * np.sqrt(np.diag(sol.covariance))).all(), err
