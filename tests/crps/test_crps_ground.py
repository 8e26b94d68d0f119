"""Ground-motion filter: real terrain renders along a helper's flight, with a planted ground object and a drone."""

import glob
import math

import cv2
import numpy as np
import pytest

from skyfix.camera import Camera, CameraPose
from skyfix.crps import (
    DroneModel,
    GroundMotionConfig,
    GroundMotionFilter,
    SilhouetteConfig,
    SilhouetteDetector,
    Tracker,
)
from skyfix.datasets.drone_view import TargetPose, render_drone_view, terrain_background
from skyfix.datasets.render import GroundTexture
from skyfix.errors import InputError
from skyfix.geo import LocalFrame, destination

CAM = Camera.from_fov(1920, 1080, 80.0)
BLUR = 0.7
LAT0, LON0, GROUND = 47.0, 8.0, 400.0
FRAME = LocalFrame(LAT0, LON0, GROUND)
DETECT = SilhouetteDetector(SilhouetteConfig(psf_sigma_px=BLUR))
PHOTOS = sorted(glob.glob("/work/shared/data/seneca-subset/*.jpg"))


def texture_with_rock() -> tuple[GroundTexture, tuple[float, float]]:
    """A real aerial photo (0.15 m/texel) with a dark 1.2 m x 0.8 m object painted on the ground.

    Returns the texture and the object's (east, north) in FRAME.
    """
    if not PHOTOS:
        pytest.skip("shared aerial photos are not available")
    img = cv2.imread(PHOTOS[6], cv2.IMREAD_GRAYSCALE).astype(np.float32) / 255.0
    h, w = img.shape
    row, col = h // 2 + 40, w // 2 - 30
    cv2.ellipse(img, (col, row), (4, 3), 30.0, 0, 360, 0.12, thickness=-1)
    east = (col - (w - 1) / 2.0) * 0.15
    north = ((h - 1) / 2.0 - row) * 0.15
    return GroundTexture(img, 0.15, FRAME), (east, north)


def flight(k: int, rng: np.random.Generator | None = None) -> tuple[CameraPose, CameraPose]:
    """(true pose, pose as the helper knows it) at frame k of a 5 m/s pass 40 m above the ground, 30 Hz."""
    lat, lon = destination(LAT0, LON0, 250.0, 2.0)
    lat, lon = destination(float(lat), float(lon), 70.0, 5.0 * k / 30.0)
    truth = CameraPose(float(lat), float(lon), GROUND + 40.0, yaw_deg=70.0, gimbal_pitch_deg=-80.0)
    if rng is None:
        return truth, truth
    noisy = CameraPose(truth.lat_deg, truth.lon_deg, truth.alt_m + rng.normal(0, 0.2), yaw_deg=70.0 + rng.normal(0, 0.2),
                       gimbal_pitch_deg=-80.0 + rng.normal(0, 0.2), gimbal_roll_deg=rng.normal(0, 0.2))
    return truth, noisy


def rock_pixel(pose: CameraPose, en: tuple[float, float]) -> np.ndarray:
    cam_enu, rot = pose.in_frame(FRAME)
    return CAM.project((np.array([en[0], en[1], 0.0]) - cam_enu) @ rot)[0]


def render(tex, truth, rng, target=None) -> np.ndarray:
    if target is None:
        img = cv2.GaussianBlur(terrain_background(tex, CAM, truth, rng), (0, 0), BLUR)
        return img + rng.standard_normal(img.shape, dtype=np.float32) * np.float32(0.01)
    return render_drone_view(CAM, truth, target, DroneModel.quad(0.5), background=tex, blur_sigma_px=BLUR,
                             noise_sigma=0.01, rng=rng)


def test_ground_object_is_detected_single_frame_and_dropped_by_the_ground_filter():
    tex, rock_en = texture_with_rock()
    rng = np.random.default_rng(3)
    ground = GroundMotionFilter(CAM, GROUND, 0.5, config=GroundMotionConfig(psf_sigma_px=BLUR))
    seen_single = dropped = 0
    for k in range(10):
        truth, known = flight(k, rng)
        image = render(tex, truth, rng)
        uv = rock_pixel(truth, rock_en)
        found = DETECT(image)
        on_rock = [d for d in found if np.linalg.norm(d.centroid_uv - uv) < 6.0]
        seen_single += bool(on_rock)
        kept = ground(image, known, found, k / 30.0)
        assert not any(np.linalg.norm(d.centroid_uv - uv) < 6.0 for d in kept), f"frame {k}: rock kept"
        checks = [c for c in ground.last_checks if np.linalg.norm(c.detection.centroid_uv - uv) < 6.0]
        if k > 0 and checks:
            assert checks[0].verdict == "ground"
            # Registered ground cancels to noise and resampling (measured 0.02-0.1); 0.5 is the decision.
            assert checks[0].residual_fraction < 0.3
            dropped += 1
    # The painted object is a real single-frame false detection, and the filter decided on it.
    assert seen_single >= 8
    assert dropped >= 7


def test_drone_over_terrain_is_kept_and_tracked_through_the_ground_filter():
    tex, _ = texture_with_rock()
    rng = np.random.default_rng(4)
    ground = GroundMotionFilter(CAM, GROUND, 0.5, config=GroundMotionConfig(psf_sigma_px=BLUR))
    tracker = Tracker(DETECT, ground=ground)
    truth0, _ = flight(0)
    # A drone 20 m from the helper (about 20 m above the ground) where the detector sees it, drifting 2 m/s.
    cam_enu, rot = truth0.in_frame(FRAME)
    p = cam_enu + rot @ CAM.pixel_to_ray(np.array([[700.0, 400.0]]))[0] * 20.0
    lat, lon, alt = FRAME.to_geodetic(*p)
    hits = 0
    checked = []
    for k in range(12):
        truth, known = flight(k, rng)
        tlat, tlon = destination(float(lat), float(lon), 160.0, 2.0 * k / 30.0)
        view = render(tex, truth, rng, TargetPose(float(tlat), float(tlon), float(alt), yaw_deg=20.0))
        det = tracker.update(view.image, k / 30.0, known)
        if k == 0:
            assert det is None  # no earlier frame: nothing can be decided, nothing is reported
            continue
        if det is not None:
            assert np.linalg.norm(det.centroid_uv - view.truth.centroid_uv) < 3.0
            hits += 1
        checks = [c for c in ground.last_checks
                  if np.linalg.norm(c.detection.centroid_uv - view.truth.centroid_uv) < 5.0]
        if checks:
            # The drone is nearer than the ground and moving: most of its contrast is not explained.
            assert checks[0].verdict == "target" and checks[0].residual_fraction > 0.5
            checked.append(k)
    assert hits >= 9
    # Checked until confirmed in 3 consecutive frames (1-3), then every 10th frame (next: 13).
    assert checked == [1, 2, 3]

def test_sky_detection_is_kept_and_bad_input_is_refused():
    ground = GroundMotionFilter(CAM, GROUND, 0.5)
    helper = CameraPose(LAT0, LON0, GROUND + 30.0, gimbal_pitch_deg=10.0)  # looking above the horizon
    target = TargetPose(*destination(LAT0, LON0, 0.0, 40.0), GROUND + 40.0)
    view = render_drone_view(CAM, helper, target, DroneModel.quad(0.5), blur_sigma_px=BLUR, noise_sigma=0.01,
                             rng=np.random.default_rng(0))
    found = DETECT(view.image)
    assert found
    assert ground(view.image, helper, found, 0.0) == found
    assert [c.verdict for c in ground.last_checks] == ["sky"] * len(found)
    with pytest.raises(InputError, match="time_s"):
        ground(view.image, helper, found, 0.0)
    with pytest.raises(InputError, match="helper_pose"):
        ground(view.image, None, found, 1.0)
    with pytest.raises(InputError, match="image"):
        ground(view.image[:100], helper, found, 1.0)
    with pytest.raises(InputError, match="min_residual_fraction"):
        GroundMotionConfig(min_residual_fraction=0.0)
    with pytest.raises(InputError, match="helper_pose"):
        Tracker(DETECT, ground=ground).update(view.image, 2.0)
    assert math.isfinite(ground.ground_alt_m)


def test_a_track_the_ground_check_finds_on_the_ground_is_dropped():
    # keep_undecided lets the first frame (nothing to compare with) start a track on the
    # painted ground object; the next frame's check finds it on the ground and drops the track.
    tex, rock_en = texture_with_rock()
    rng = np.random.default_rng(6)
    ground = GroundMotionFilter(CAM, GROUND, 0.5, config=GroundMotionConfig(psf_sigma_px=BLUR, keep_undecided=True))
    tracker = Tracker(DETECT, ground=ground)
    for k in range(4):
        truth, known = flight(k, rng)
        image = render(tex, truth, rng)
        det = tracker.update(image, k / 30.0, known)
        uv = rock_pixel(truth, rock_en)
        if k == 0:
            assert det is not None and np.linalg.norm(det.centroid_uv - uv) < 6.0
        else:
            assert det is None or np.linalg.norm(det.centroid_uv - uv) > 20.0, f"frame {k}: still on the rock"
    assert not tracker.tracking or np.linalg.norm(tracker._uv - uv) > 20.0
