"""Calibration from synthetic board renders recovers the camera that made them."""

from __future__ import annotations

import numpy as np
import pytest

from skyfix.camera import Camera
from skyfix.datasets.calibration_scene import render_calibration_views
from skyfix.distortion import BrownConrady, Fisheye
from skyfix.errors import EstimationError, InputError
from skyfix.mapping.board import BoardSpec
from skyfix.mapping.calibrate import calibrate, detect_board
from skyfix.mapping.lens import projection_difference_px

TRUE_BC = Camera(640, 480, 500.0, 502.0, 322.3, 236.8, BrownConrady(-0.28, 0.09, 0.0005, -0.0003, -0.01))


@pytest.fixture(scope="module")
def chessboard_views():
    return render_calibration_views(TRUE_BC, BoardSpec("chessboard"), 12, seed=1, supersample=2)


def test_rendered_corners_are_detected_where_the_truth_says(chessboard_views):
    spec = BoardSpec("chessboard")
    for view in chessboard_views[:3]:
        found = detect_board(view.image, spec)
        assert found is not None
        pts = found[1]
        err = min(np.linalg.norm(pts - view.corners_px, axis=1).max(),
                  np.linalg.norm(pts[::-1] - view.corners_px, axis=1).max())
        assert err < 0.3  # sub-pixel detector on a clean render (RMS is ~0.04 px)


def test_chessboard_calibration_recovers_distortion(chessboard_views):
    cal = calibrate([v.image for v in chessboard_views], BoardSpec("chessboard"))
    assert cal.rms_px <= 0.1
    assert len(cal.used) >= 9
    # The recovered model puts rays where the true camera does, over the whole image
    # (corner detection noise ~0.04 px, extrapolated into the image corners).
    rms, _ = projection_difference_px(TRUE_BC, cal.camera, n=21)
    assert rms < 0.3
    assert cal.camera.fx == pytest.approx(500.0, rel=0.005)
    assert cal.camera.distortion.k1 == pytest.approx(-0.28, abs=0.01)


def test_charuco_calibration_with_partial_views():
    spec = BoardSpec("charuco")
    views = render_calibration_views(TRUE_BC, spec, 10, seed=2, supersample=2)
    cal = calibrate([v.image for v in views], spec)
    assert cal.rms_px <= 0.1
    assert cal.camera.fx == pytest.approx(500.0, rel=0.01)


def test_fisheye_model():
    cam = Camera(640, 480, 300.0, 300.0, 319.5, 239.5, Fisheye(0.02, -0.005, 0.0, 0.0))
    views = render_calibration_views(cam, BoardSpec("chessboard"), 10, seed=3, supersample=2)
    cal = calibrate([v.image for v in views], BoardSpec("chessboard"), model="fisheye")
    assert isinstance(cal.camera.distortion, Fisheye)
    assert cal.rms_px <= 0.1
    assert cal.camera.fx == pytest.approx(300.0, rel=0.01)


def test_calibration_errors():
    blank = np.full((480, 640), 128, np.uint8)
    with pytest.raises(EstimationError, match="found in 0 of 5"):
        calibrate([blank] * 5, BoardSpec())
    with pytest.raises(InputError):
        calibrate([], BoardSpec())
    with pytest.raises(InputError, match="model"):
        calibrate([blank], BoardSpec(), model="pinhole")
    with pytest.raises(InputError):
        BoardSpec("dots")
