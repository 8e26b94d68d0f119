"""Drone model geometry and the silhouette shape table."""

import numpy as np
import pytest

from skyfix.crps import DroneModel, shape_table
from skyfix.crps.model import rasterize_convex_parts, silhouette_moments
from skyfix.errors import InputError


def test_rasterize_square_area_and_moments():
    # A 20 x 10 px axis-aligned rectangle: area 200, variances 20^2/12 and 10^2/12.
    rect = np.array([[10.0, 10.0], [30.0, 10.0], [30.0, 20.0], [10.0, 20.0]]) - 0.5
    cover, value = rasterize_convex_parts([rect], [0.3], (40, 50))
    assert cover.sum() == pytest.approx(200, abs=1)
    m0, c, cov = silhouette_moments(cover)
    np.testing.assert_allclose(c, [19.5, 14.5], atol=0.05)
    np.testing.assert_allclose(np.diag(cov), [(20 ** 2 - 1) / 12, (10 ** 2 - 1) / 12], rtol=0.02)
    assert value.max() == pytest.approx(0.3)


def test_parts_span():
    model = DroneModel.quad(0.5)
    pts = np.concatenate([p for _, p in model.parts()])
    radius = np.hypot(pts[:, 0], pts[:, 1]).max()
    assert radius == pytest.approx(0.25, rel=1e-2)  # rotor tips on the span circle (20-gon rotors)


def test_shape_table_symmetry_and_yaw_invariance():
    table = shape_table(DroneModel.quad().scaled_to(1.0))
    np.testing.assert_allclose(table.ratio_mean, table.ratio_mean[::-1])
    # n-fold symmetric airframe: the major-axis RMS barely depends on yaw away from edge-on.
    high = np.abs(table.elevation_deg) >= 30
    assert np.all(table.ratio_std[high] / table.ratio_mean[high] < 0.015)
    # Seen from overhead the silhouette is round; edge-on it is flat.
    assert table.aspect(90.0)[0] > 0.95
    assert table.aspect(0.0)[0] < 0.2
    # A drone is between a ring (ratio 0.354) and a filled disk (0.25) in spread.
    assert 0.2 < float(table.ratio(45.0)[0]) < 0.3


def test_bad_models_raise():
    with pytest.raises(InputError, match="arms"):
        DroneModel(arms=5)
    with pytest.raises(InputError, match="overlap"):
        DroneModel(arms=8, rotor_fraction=0.5)
    with pytest.raises(InputError, match="span_m"):
        DroneModel(span_m=0.0)
