"""Help-request prior gate: the last known position projected into the helper's image."""

import numpy as np
import pytest

from skyfix.camera import Camera, CameraPose
from skyfix.crps import Detection, prior_gate, prior_window
from skyfix.errors import GeometryError, InputError
from skyfix.geo import destination
from skyfix.types import GeoFix

CAM = Camera.from_fov(1920, 1080, 80.0)
HELPER = CameraPose(47.0, 8.0, 400.0, yaw_deg=0.0, gimbal_pitch_deg=0.0)


def det_at(uv, rms_px=2.0):
    return Detection(np.asarray(uv, float), np.eye(2) * 0.01, (0, 0, 1, 1), 50.0,
                     moments_px2=np.diag([rms_px ** 2, 0.25 * rms_px ** 2]))


def test_prior_projects_to_the_right_pixel_with_the_expected_spread():
    lat, lon = destination(47.0, 8.0, 0.0, 50.0)  # 50 m straight ahead, level: image centre
    prior = GeoFix(float(lat), float(lon), 400.0, np.diag([4.0, 4.0, 4.0]))
    win = prior_window(CAM, HELPER, prior, attitude_sigma_deg=0.0)
    np.testing.assert_allclose(win.uv_px, [CAM.cx, CAM.cy], atol=0.5)
    # 2 m 1-sigma across the line of sight at 50 m: fx * 2 / 50 px; along it: nothing.
    np.testing.assert_allclose(np.sqrt(np.diag(win.cov_px2)), [CAM.fx * 2.0 / 50.0] * 2, rtol=0.02)
    inside, outside = det_at(win.uv_px + [100.0, 0.0]), det_at(win.uv_px + [400.0, 0.0])
    assert prior_gate(win, [inside, outside]) == [inside]
    u0, v0, u1, v1 = win.roi(CAM.width, CAM.height)
    assert u0 < win.uv_px[0] < u1 and v0 < win.uv_px[1] < v1


def test_prior_bad_input():
    lat, lon = destination(47.0, 8.0, 180.0, 50.0)
    behind = GeoFix(float(lat), float(lon), 400.0, np.eye(3))
    with pytest.raises(GeometryError, match="behind"):
        prior_window(CAM, HELPER, behind)
    with pytest.raises(InputError, match="GeoFix"):
        prior_window(CAM, HELPER, (47.0, 8.0, 400.0))
