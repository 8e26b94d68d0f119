"""Silhouette detection, moments, observe: against rendered frames with exact truth."""

import math

import numpy as np
import pytest

from skyfix.camera import Camera, CameraPose
from skyfix.crps import (
    BoxDetector,
    Detection,
    DroneModel,
    SilhouetteConfig,
    SilhouetteDetector,
    observe,
    shape_consistent,
)
from skyfix.crps.model import silhouette_moments
from skyfix.datasets.drone_view import TargetPose, render_drone_view, sky_background
from skyfix.errors import GeometryError, InputError
from skyfix.geo import destination

CAM = Camera.from_fov(1920, 1080, 80.0)
BLUR = 0.7


def scene(dist_m, elev_deg, yaw_deg, helper_yaw=20.0, gimbal_pitch=None):
    helper = CameraPose(47.0, 8.0, 400.0, yaw_deg=helper_yaw,
                        gimbal_pitch_deg=elev_deg + 3.0 if gimbal_pitch is None else gimbal_pitch)
    lat, lon = destination(47.0, 8.0, helper_yaw + 10.0, dist_m * math.cos(math.radians(elev_deg)))
    target = TargetPose(float(lat), float(lon), 400.0 + dist_m * math.sin(math.radians(elev_deg)), yaw_deg=yaw_deg)
    return helper, target


def test_moments_recover_blurred_silhouette_exactly_without_noise():
    # Blur adds its variance to the second moments; subtracting it recovers the silhouette's.
    helper, target = scene(25.0, 20.0, 17.0)
    view = render_drone_view(CAM, helper, target, DroneModel.quad(), blur_sigma_px=BLUR,
                             rng=np.random.default_rng(0))
    dets = SilhouetteDetector(SilhouetteConfig(psf_sigma_px=BLUR))(view.image)
    assert len(dets) == 1
    _, c, cov = silhouette_moments(view.truth.coverage)
    truth_cov = cov - np.eye(2) / 12.0  # the coverage is already box-filtered by the pixel
    # Cloud shading is curved where the background fit is a plane: a few hundredths of a pixel.
    np.testing.assert_allclose(dets[0].centroid_uv, c + view.truth.bbox_px[:2], atol=0.05)
    np.testing.assert_allclose(np.linalg.eigvalsh(dets[0].moments_px2), np.linalg.eigvalsh(truth_cov), rtol=0.02)


@pytest.mark.parametrize("dist_m", [12.0, 40.0])
def test_observe_range_and_bearing(dist_m):
    rng = np.random.default_rng(int(dist_m))
    helper, target = scene(dist_m, 20.0, 33.0)
    view = render_drone_view(CAM, helper, target, DroneModel.quad(), blur_sigma_px=BLUR, noise_sigma=0.01, rng=rng)
    dets = SilhouetteDetector()(view.image, time_s=12.5)
    assert len(dets) == 1
    assert shape_consistent(CAM, helper, dets[0])
    obs = observe(CAM, helper, dets[0], 0.5, observer_id="h1", target_id="t", attitude_sigma_deg=0.0)
    sigma_r = math.sqrt(obs.bearing_unit_enu @ obs.cov_enu_m2 @ obs.bearing_unit_enu)
    # At 20 deg elevation the model's yaw spread is ~1.2 %; noise adds a little at 40 m.
    assert abs(obs.range_m - view.truth.range_m) <= max(3.0 * sigma_r, 0.01 * dist_m)
    assert sigma_r / obs.range_m < 0.04
    bearing_err_deg = math.degrees(math.acos(min(1.0, float(obs.bearing_unit_enu @ view.truth.bearing_unit_enu))))
    # Centroid noise is ~0.05 px; the airframe is not symmetric top to bottom (rotors sit ~1 cm
    # above the arms), which moves the silhouette centroid by up to ~0.05 deg at 12 m.
    assert bearing_err_deg < 0.06
    assert obs.time_s == 12.5 and obs.observer_id == "h1"
    assert obs.observer_lat_deg == helper.lat_deg and obs.has_observer_position
    assert np.linalg.eigvalsh(obs.cov_enu_m2).min() > 0


def test_attitude_sigma_widens_the_cross_range_covariance():
    helper, target = scene(30.0, 15.0, 0.0)
    view = render_drone_view(CAM, helper, target, DroneModel.quad(), blur_sigma_px=BLUR,
                             rng=np.random.default_rng(3))
    det = SilhouetteDetector()(view.image)[0]
    tight = observe(CAM, helper, det, 0.5, attitude_sigma_deg=0.0)
    loose = observe(CAM, helper, det, 0.5, attitude_sigma_deg=1.0)
    across = np.linalg.eigvalsh(loose.cov_enu_m2 - tight.cov_enu_m2)
    # Two cross-range axes gain (range * 1 deg)^2, the range axis gains nothing.
    np.testing.assert_allclose(np.sort(across)[1:], (tight.range_m * math.radians(1.0)) ** 2, rtol=1e-3)
    assert abs(np.sort(across)[0]) < 1e-6


def test_no_detection_in_empty_sky():
    rng = np.random.default_rng(5)
    det = SilhouetteDetector()
    for k in range(5):
        helper = CameraPose(47.0, 8.0, 400.0, yaw_deg=70.0 * k, gimbal_pitch_deg=10.0 * k)
        img = sky_background(CAM, helper, rng, clouds=0.12) + rng.normal(0, 0.01, (1080, 1920)).astype(np.float32)
        assert det(img) == []


def test_roi_and_dtypes_give_the_same_detection():
    helper, target = scene(20.0, 10.0, 50.0)
    view = render_drone_view(CAM, helper, target, DroneModel.quad(), blur_sigma_px=BLUR, noise_sigma=0.005,
                             rng=np.random.default_rng(2))
    det = SilhouetteDetector()
    full = det(view.image)[0]
    u, v = (int(x) for x in view.truth.centroid_uv)
    roi = det(view.image, roi=(u - 80, v - 60, u + 80, v + 60))[0]
    # Same measurement; only the sensor-noise estimate (from the searched pixels) differs.
    np.testing.assert_allclose(roi.centroid_uv, full.centroid_uv, atol=0.05)
    as_u8 = np.clip(view.image * 255 + 0.5, 0, 255).astype(np.uint8)
    bgr = np.repeat(as_u8[..., None], 3, axis=2)
    np.testing.assert_allclose(det(bgr)[0].centroid_uv, full.centroid_uv, atol=0.05)


def test_box_detector_adapter_with_refinement():
    helper, target = scene(20.0, 10.0, 50.0)
    view = render_drone_view(CAM, helper, target, DroneModel.quad(), blur_sigma_px=BLUR,
                             rng=np.random.default_rng(3))

    def threshold_model(image):  # a user's own detector: dark pixels' bounding box
        vv, uu = np.nonzero(image < 0.5)
        return np.array([[uu.min(), vv.min(), uu.max() + 1, vv.max() + 1]]), np.array([0.9])

    boxes = BoxDetector(threshold_model)(view.image)
    assert len(boxes) == 1 and boxes[0].kind == "box"
    obs_box = observe(CAM, helper, boxes[0], 0.5)
    assert obs_box.range_m == pytest.approx(view.truth.range_m, rel=0.3)  # a box width is a crude size
    refined = BoxDetector(threshold_model, refine=SilhouetteDetector())(view.image)
    assert refined[0].kind == "silhouette" and refined[0].score == pytest.approx(0.9)
    assert observe(CAM, helper, refined[0], 0.5).range_m == pytest.approx(view.truth.range_m, rel=0.06)


def test_bad_inputs():
    helper, target = scene(20.0, 10.0, 50.0)
    view = render_drone_view(CAM, helper, target, DroneModel.quad(), blur_sigma_px=BLUR,
                             rng=np.random.default_rng(3))
    det = SilhouetteDetector()(view.image)[0]
    with pytest.raises(InputError, match="target_size_m"):
        observe(CAM, helper, det, 0.0)
    with pytest.raises(InputError, match="alt_m"):
        CameraPose(47.0, 8.0, float("nan"))
    outside = Detection(np.array([5000.0, 10.0]), np.eye(2), (0, 0, 1, 1), 1.0, "box", size_px=3.0)
    with pytest.raises(GeometryError, match="outside"):
        observe(CAM, helper, outside, 0.5)
    bad = view.image.copy()
    bad[0, 0] = np.nan
    with pytest.raises(InputError, match="NaN"):
        SilhouetteDetector()(bad)
    with pytest.raises(InputError, match="roi"):
        SilhouetteDetector()(view.image, roi=(10, 10, 12, 12))
    with pytest.raises(InputError, match="polarity"):
        SilhouetteConfig(polarity="up")
    with pytest.raises(InputError, match="moments_px2"):
        Detection(np.zeros(2), np.eye(2), (0, 0, 1, 1), 1.0, "silhouette")


def test_hexacopter_uses_its_own_shape_table():
    helper, target = scene(20.0, 25.0, 12.0)
    hexa = DroneModel.hex(0.8)
    view = render_drone_view(CAM, helper, target, hexa, blur_sigma_px=BLUR, noise_sigma=0.005,
                             rng=np.random.default_rng(6))
    det = SilhouetteDetector()(view.image)[0]
    right = observe(CAM, helper, det, 0.8, model=hexa, attitude_sigma_deg=0.0)
    wrong = observe(CAM, helper, det, 0.8, model=DroneModel.quad(), attitude_sigma_deg=0.0)
    assert right.range_m == pytest.approx(view.truth.range_m, rel=0.02)
    # The hex silhouette spreads ~4 % more per unit span than the quad's at 25 deg.
    assert abs(wrong.range_m / view.truth.range_m - 1.0) > abs(right.range_m / view.truth.range_m - 1.0)
