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
