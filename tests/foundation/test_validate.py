"""skyfix.validate: the shared input checks the whole tree uses instead of local copies."""

from __future__ import annotations

import numpy as np
import pytest

from skyfix import validate
from skyfix.errors import InputError


@pytest.mark.parametrize("check, good, bad", [
    (validate.positive_array, [1e-9, 3.0], [1.0, 0.0]),
    (validate.nonnegative_array, [0.0, 3.0], [1.0, -1e-12]),
    (validate.nonnegative_scalar, 0.0, -1e-12),
    (validate.positive_scalar, 1e-12, 0.0),
])
def test_sign_checks_accept_the_boundary_they_allow_and_name_the_input(check, good, bad):
    np.testing.assert_array_equal(check("x_m", good), np.asarray(good, float))
    with pytest.raises(InputError, match="^x_m must be"):
        check("x_m", bad)
    with pytest.raises(InputError, match="x_m"):
        check("x_m", np.nan)


@pytest.mark.parametrize("value", [True, np.bool_(False), 2.5, "3", None, 13, 1])
def test_integer_in_refuses_bools_fractions_and_out_of_range(value):
    with pytest.raises(InputError, match=r"colors must be an integer in \[2, 12\]"):
        validate.integer_in("colors", value, 2, 12)


def test_integer_in_without_upper_bound():
    assert validate.integer_in("rows", np.int64(10**12), 1) == 10**12
    assert isinstance(validate.integer_in("rows", 4.0, 1), int)
    with pytest.raises(InputError, match="rows must be an integer >= 1, got 0"):
        validate.integer_in("rows", 0, 1)


def _accepted_by_eigenvalues(m: np.ndarray) -> bool:
    """covariance()'s general test, written out: symmetric within tolerance, smallest eigenvalue >= -tol."""
    scale = max(1.0, float(np.abs(m).max()))
    if (np.abs(m - m.T) > 1e-12 * scale + 1e-9 * np.abs(m.T)).any():
        return False
    return bool(np.linalg.eigvalsh(m).min() >= -1e-9 * scale)


def test_covariance_3x3_fast_path_accepts_and_refuses_exactly_as_the_eigenvalue_test():
    rng = np.random.default_rng(7)
    cases = []
    for k in range(4000):
        a = rng.normal(size=(3, 3)) * 10.0 ** rng.uniform(-6, 6)
        m = [a @ a.T, a + a.T, a @ a.T, np.outer(a[0], a[0])][k % 4]
        if k % 4 == 2:  # asymmetric by about the tolerance
            m[0, 1] += rng.normal() * 3e-9 * abs(m[0, 1])
        if k % 4 == 3:  # rank 1: on the boundary
            m = m + np.diag(rng.normal(size=3) * 1e-12)
        cases.append(m)
    cases += [np.zeros((3, 3)), np.diag([1.0, 1.0, -1e-10]), np.diag([1.0, 1.0, -1e-6])]
    for m in cases:
        try:
            validate.covariance("cov_m2", m, 3)
            accepted = True
        except InputError:
            accepted = False
        assert accepted == _accepted_by_eigenvalues(m), m


def test_covariances_accept_a_stack_exactly_when_covariance_accepts_each_and_name_the_first_refused():
    rng = np.random.default_rng(8)
    a = rng.normal(size=(300, 3, 3))
    good = a @ np.swapaxes(a, 1, 2)
    good[::7] = np.einsum("ni,nj->nij", a[::7, 0], a[::7, 0])  # rank 1: the boundary, accepted
    np.testing.assert_array_equal(validate.covariances("cov_m2", good, 3), good)
    for k, m in ((5, np.diag([1.0, 1.0, -1e-6])), (11, good[11] + np.triu(np.full((3, 3), 1e-6), 1))):
        bad = good.copy()
        bad[k] = m
        with pytest.raises(InputError, match=rf"^cov_m2\[{k}\] must be"):
            validate.covariances("cov_m2", bad, 3)
    two = np.array([[[2.0, 0.5], [0.5, 1.0]], [[1.0, 2.0], [2.0, 1.0]]])
    with pytest.raises(InputError, match=r"cov_m2\[1\] must be positive semi-definite"):
        validate.covariances("cov_m2", two, 2)
    with pytest.raises(InputError, match=r"shape \(N, 3, 3\)"):
        validate.covariances("cov_m2", good[0], 3)


@pytest.mark.parametrize("check", [validate.finite_array, validate.latitude, validate.longitude])
@pytest.mark.parametrize("value", [47.0, -90.0, 90.0, 90.0 + 1e-9, -180.0, -180.5, 360.0, 360.5, np.nan, np.inf, -np.inf])
def test_scalar_fast_paths_accept_and_refuse_as_the_array_path(check, value):
    """A Python float (or numpy float64) takes a plain-float path: same 0-d array, same refusals."""
    try:
        expected = check("x_deg", np.array([value]))[0]
    except InputError:
        expected = None
    for scalar in (float(value), np.float64(value)):
        if expected is None:
            with pytest.raises(InputError, match="x_deg"):
                check("x_deg", scalar)
        else:
            got = check("x_deg", scalar)
            assert isinstance(got, np.ndarray) and got.shape == () and got.dtype == np.float64 and got == expected
