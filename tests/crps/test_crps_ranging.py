"""Range from apparent size: hand-computed values, the reference-image form, error propagation."""

import numpy as np
import pytest

from skyfix.crps import range_from_reference, range_from_size
from skyfix.errors import InputError


def test_range_from_size_hand_computed():
    # 0.5 m spanning 10 px through a 1000 px focal length: 1000 * 0.5 / 10 = 50 m.
    r, s = range_from_size(10.0, 0.5, 1000.0, 0.5)
    assert float(r) == pytest.approx(50.0)
    assert float(s) == pytest.approx(50.0 * 0.5 / 10.0)  # sigma_D = D * sigma_s / s


def test_range_from_size_broadcasts():
    r, s = range_from_size(np.array([[10.0], [20.0]]), 0.5, np.array([1000.0, 2000.0]))
    assert r.shape == (2, 2)
    np.testing.assert_allclose(r, [[50.0, 100.0], [25.0, 50.0]])
    np.testing.assert_array_equal(s, 0.0)


def test_reference_form_is_not_the_papers_inverted_one():
    # Target looks half as big as in the reference at 20 m: it is twice as far (40 m), not 10 m.
    r, s = range_from_reference(20.0, 30.0, 15.0, 0.3)
    assert float(r) == pytest.approx(40.0)
    assert float(s) == pytest.approx(40.0 * 0.3 / 15.0)


def test_reference_form_agrees_with_pinhole():
    f, size = 1144.0, 0.5
    s0 = f * size / 20.0
    d = np.array([10.0, 33.0, 100.0])
    s1 = f * size / d
    np.testing.assert_allclose(range_from_reference(20.0, s0, s1)[0], d)
    np.testing.assert_allclose(range_from_size(s1, size, f)[0], d)


@pytest.mark.parametrize("args", [(0.0, 0.5, 1000.0), (10.0, 0.0, 1000.0), (10.0, 0.5, -1.0),
                                  (np.nan, 0.5, 1000.0), (10.0, 0.5, 1000.0, -0.1)])
def test_bad_inputs_raise(args):
    with pytest.raises(InputError):
        range_from_size(*args)


def test_reference_bad_inputs_raise():
    with pytest.raises(InputError, match="s1_px"):
        range_from_reference(20.0, 30.0, 0.0)
