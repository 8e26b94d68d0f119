"""The drone-view renderer: exact truth, occlusion, plates, errors."""

import math

import cv2
import numpy as np
import pytest

from skyfix.camera import Camera, CameraPose, world_to_pixel
from skyfix.crps import DroneModel
from skyfix.crps.model import silhouette_moments
from skyfix.datasets.drone_view import Plate, TargetPose, render_drone_view
from skyfix.errors import GeometryError, InputError
from skyfix.geo import LocalFrame, destination

CAM = Camera.from_fov(640, 480, 80.0)
HELPER = CameraPose(47.0, 8.0, 400.0, yaw_deg=30.0, gimbal_pitch_deg=5.0)


def target_at(bearing_deg, dist_m, dz_m=0.0, **att):
    lat, lon = destination(47.0, 8.0, bearing_deg, dist_m)
    return TargetPose(float(lat), float(lon), 400.0 + dz_m, **att)


def test_truth_matches_projection_and_geodesy():
    t = target_at(35.0, 20.0, 1.5, yaw_deg=10.0)
    view = render_drone_view(CAM, HELPER, t, DroneModel.quad(), rng=np.random.default_rng(0))
    frame = LocalFrame(HELPER.lat_deg, HELPER.lon_deg, HELPER.alt_m)
    enu = np.array([float(x) for x in frame.to_enu(t.lat_deg, t.lon_deg, t.alt_m)])
    np.testing.assert_allclose(view.truth.target_enu_m, enu, atol=1e-6)
    assert view.truth.range_m == pytest.approx(math.hypot(20.0, 1.5), abs=0.01)
    np.testing.assert_allclose(view.truth.centroid_uv, world_to_pixel(CAM, HELPER, frame, enu)[0], atol=1e-6)
    assert view.truth.elevation_deg == pytest.approx(-math.degrees(math.atan2(1.5, 20.0)), abs=0.05)
    # The silhouette's centroid is the projected airframe centre (symmetric airframe, 20 m).
    _, c, _ = silhouette_moments(view.truth.coverage)
    np.testing.assert_allclose(c + view.truth.bbox_px[:2], view.truth.centroid_uv, atol=0.15)


def test_apparent_size_scales_inverse_with_range():
    areas = []
    for d in (10.0, 20.0):
        view = render_drone_view(CAM, CameraPose(47.0, 8.0, 400.0, gimbal_pitch_deg=-90.0),
                                 TargetPose(47.0, 8.0, 400.0 - d), DroneModel.quad(), supersample=8,
                                 rng=np.random.default_rng(0))
        areas.append(view.truth.coverage.sum())
    assert areas[0] / areas[1] == pytest.approx(4.0, rel=0.02)  # area ~ 1 / range^2


def test_occlusion_hides_the_requested_fraction():
    t = target_at(30.0, 10.0)
    view = render_drone_view(CAM, HELPER, t, DroneModel.quad(), occlusion_fraction=0.3,
                             rng=np.random.default_rng(1))
    assert view.truth.visible_fraction == pytest.approx(0.7, abs=0.02)


def test_plate_with_marker_decodes():
    tag = cv2.aruco.generateImageMarker(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), 3, 60)
    tag = cv2.copyMakeBorder(tag, 10, 10, 10, 10, cv2.BORDER_CONSTANT, value=255)
    # Plate on the drone's tail, facing backwards (plate x = body right, y = down, z = forward).
    plate = Plate(tag, 0.2 * 80 / 60, center_body_m=(-0.1, 0.0, 0.0),
                  r_body_from_plate=np.column_stack(([0, 1.0, 0], [0, 0, 1.0], [1.0, 0, 0])))
    helper = CameraPose(47.0, 8.0, 400.0, yaw_deg=0.0, gimbal_pitch_deg=0.0)
    view = render_drone_view(CAM, helper, target_at(0.0, 3.0), DroneModel.quad(), plate=plate,
                             rng=np.random.default_rng(0))
    corners, ids, _ = cv2.aruco.ArucoDetector(
        cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)).detectMarkers(
        np.clip(view.image * 255, 0, 255).astype(np.uint8))
    assert ids is not None and ids.ravel().tolist() == [3]


def test_errors():
    with pytest.raises(GeometryError, match="behind"):
        render_drone_view(CAM, HELPER, target_at(210.0, 10.0), DroneModel.quad())
    with pytest.raises(InputError):
        render_drone_view(CAM, HELPER, target_at(30.0, 10.0), None)
    with pytest.raises(InputError, match="occlusion_fraction"):
        render_drone_view(CAM, HELPER, target_at(30.0, 10.0), DroneModel.quad(), occlusion_fraction=1.0)
    with pytest.raises(InputError):
        TargetPose(float("nan"), 8.0, 400.0)
