"""Lens models: ImageMagick barrel semantics, conversions to and from OpenCV's model."""

from __future__ import annotations

import numpy as np
import pytest

from skyfix.camera import Camera
from skyfix.distortion import Barrel, BrownConrady
from skyfix.errors import GeometryError, InputError
from skyfix.mapping.correct import Undistortion
from skyfix.mapping.lens import (
    BarrelModel,
    barrel_camera,
    barrel_to_opencv,
    opencv_to_barrel,
    parse_barrel,
    projection_difference_px,
)


def test_barrel_model_is_the_foundation_model_with_default_d():
    b = BarrelModel(0.1, -0.32, 0.0)
    assert isinstance(b, Barrel)
    assert b.d == pytest.approx(1.22)


def test_parse_barrel_accepts_three_or_four_numbers():
    assert parse_barrel("0.1 -0.32 0") == Barrel(0.1, -0.32, 0.0)
    assert parse_barrel("0.1,-0.32,0,1.3").d == pytest.approx(1.3)
    for bad in ("0.1 -0.32", "a b c", "1 2 3 4 5", "nan 0 0"):
        with pytest.raises(InputError):
            parse_barrel(bad)


def test_correction_table_matches_imagemagick_formula_by_hand():
    # 1200x900: centre (599.5, 449.5) in OpenCV pixels, radius unit 450 px.
    u = Undistortion.for_barrel(parse_barrel("0.1 -0.32 0"), 1200, 900)
    col, row = 1000, 100
    dx, dy = col - 599.5, row - 449.5
    r = np.hypot(dx, dy) / 450.0
    factor = 0.1 * r**3 - 0.32 * r**2 + 0.0 * r + 1.22
    assert u.map_x[row, col] == pytest.approx(599.5 + dx * factor, abs=1e-3)
    assert u.map_y[row, col] == pytest.approx(449.5 + dy * factor, abs=1e-3)
    assert u.focal_scale == pytest.approx(1 / 1.22)


def test_barrel_camera_focal_is_raw_focal_over_d():
    cam = barrel_camera(Barrel(0.1, -0.32, 0.0), 1200, 900, raw_focal_px=925.0)
    assert cam.fx == pytest.approx(925.0 / 1.22)
    # Paraxial rays land where a pinhole with the raw focal puts them.
    ray = np.array([[1e-4, 0.0, 1.0]])
    assert cam.project(ray)[0, 0] - cam.cx == pytest.approx(925.0 * 1e-4, rel=1e-6)
    with pytest.raises(GeometryError):
        barrel_camera(Barrel(0.5, 0.5, 0.5), 1200, 900)  # d = -0.5


def test_barrel_to_opencv_to_barrel_round_trip():
    barrel = Barrel(0.02, -0.08, 0.0)
    fit = barrel_to_opencv(barrel, 1200, 900, raw_focal_px=900.0)
    # Even-power series vs a cubic with odd terms: sub-pixel over the whole image.
    assert fit.rms_px < 0.5
    assert isinstance(fit.camera.distortion, BrownConrady)
    back = opencv_to_barrel(barrel_camera(barrel, 1200, 900, 900.0))
    d = back.camera.distortion
    assert (d.a, d.b, d.c) == pytest.approx((0.02, -0.08, 0.0), abs=1e-6)
    assert back.rms_px < 1e-3


def test_opencv_to_barrel_reports_residual_of_an_off_centre_camera():
    cam = Camera(640, 480, 500, 500, 330, 240, BrownConrady(-0.2, 0.05))
    fit = opencv_to_barrel(cam)
    centred = opencv_to_barrel(Camera(640, 480, 500, 500, 319.5, 239.5, BrownConrady(-0.2, 0.05)))
    assert fit.rms_px > centred.rms_px
    rms, worst = projection_difference_px(cam, fit.camera)
    assert rms == pytest.approx(fit.rms_px)
