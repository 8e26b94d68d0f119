"""Tracking with a region of interest, the marker path, and the ``skyfix crps range`` command."""

import json
import math

import cv2
import numpy as np
import pytest

from skyfix.camera import Camera, CameraPose
from skyfix.cli import main
from skyfix.crps import DroneModel, MarkerDetector, SilhouetteDetector, Tracker, observe
from skyfix.datasets.drone_view import Plate, TargetPose, render_drone_view
from skyfix.errors import InputError
from skyfix.geo import destination

CAM = Camera.from_fov(1280, 720, 80.0)
HELPER = CameraPose(47.0, 8.0, 400.0, yaw_deg=0.0, gimbal_pitch_deg=10.0)


def frames(n, rng, speed_mps=2.0, dt=0.1):
    """A target 25 m north, 5 m up, crossing east at ``speed_mps``."""
    for k in range(n):
        lat, lon = destination(47.0, 8.0, 0.0, 25.0)
        lat, lon = destination(float(lat), float(lon), 90.0, speed_mps * dt * k + 1.0)
        view = render_drone_view(CAM, HELPER, TargetPose(float(lat), float(lon), 405.0, yaw_deg=20.0),
                                 DroneModel.quad(), blur_sigma_px=0.7, noise_sigma=0.01, rng=rng)
        yield k * dt, view


class CountingDetector:
    """The real silhouette detector, recording which region each call searched."""

    def __init__(self):
        self.inner = SilhouetteDetector()
        self.rois = []

    def __call__(self, image, roi=None):
        self.rois.append(roi)
        return self.inner(image, roi)


def test_tracker_follows_with_roi_and_smooths_size():
    rng = np.random.default_rng(4)
    det = CountingDetector()
    tracker = Tracker(det)
    ranges = []
    for t, view in frames(10, rng):
        d = tracker.update(view.image, t)
        assert d is not None
        assert np.linalg.norm(d.centroid_uv - view.truth.centroid_uv) < 0.5
        ranges.append(observe(CAM, HELPER, d, 0.5).range_m / view.truth.range_m - 1.0)
    assert det.rois[0] is None and all(r is not None for r in det.rois[1:])
    u0, v0, u1, v1 = det.rois[-1]
    assert (u1 - u0) * (v1 - v0) < 0.05 * CAM.width * CAM.height  # searches a small window
    assert abs(np.mean(ranges[-5:])) < 0.03


def test_tracker_drops_a_lost_target_and_rejects_time_going_back():
    rng = np.random.default_rng(5)
    tracker = Tracker(SilhouetteDetector())
    (t0, v0), = list(frames(1, rng))
    first = tracker.update(v0.image, t0)
    assert np.linalg.norm(first.centroid_uv - v0.truth.centroid_uv) < 0.5  # as in the test above
    empty = np.full_like(v0.image, 0.7) + rng.normal(0, 0.01, v0.image.shape).astype(np.float32)
    for k in range(1, 6):
        assert tracker.update(empty, 0.1 * k) is None
    assert not tracker.tracking
    tracker.update(v0.image, 1.0)
    with pytest.raises(InputError, match="increase"):
        tracker.update(v0.image, 0.5)


def marker_view(dist_m, marker_id=7, side_m=0.2):
    tag = cv2.aruco.generateImageMarker(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), marker_id, 60)
    tag = cv2.copyMakeBorder(tag, 10, 10, 10, 10, cv2.BORDER_CONSTANT, value=255)
    plate = Plate(tag, side_m * 80 / 60, center_body_m=(0.0, 0.0, 0.0),
                  r_body_from_plate=np.column_stack(([0, 1.0, 0], [0, 0, 1.0], [1.0, 0, 0])))
    helper = CameraPose(47.0, 8.0, 400.0, gimbal_pitch_deg=0.0)
    lat, lon = destination(47.0, 8.0, 0.0, dist_m)
    return helper, render_drone_view(CAM, helper, TargetPose(float(lat), float(lon), 400.0, yaw_deg=8.0),
                                     None, plate=plate, blur_sigma_px=0.5, noise_sigma=0.005,
                                     rng=np.random.default_rng(1))


@pytest.mark.parametrize("dist_m", [3.0, 6.0])
def test_marker_identity_and_range(dist_m):
    helper, view = marker_view(dist_m)
    dets = MarkerDetector(CAM)(view.image)
    assert [d.marker_id for d in dets] == [7]
    obs = observe(CAM, helper, dets[0], 0.2, attitude_sigma_deg=0.0)
    assert obs.target_id == "marker:7"
    sigma = math.sqrt(obs.bearing_unit_enu @ obs.cov_enu_m2 @ obs.bearing_unit_enu)
    assert abs(obs.range_m - view.truth.range_m) < max(3 * sigma, 0.01 * dist_m)
    assert math.degrees(math.acos(min(1.0, obs.bearing_unit_enu @ view.truth.bearing_unit_enu))) < 0.05
    assert MarkerDetector(CAM, ids={1, 2})(view.image) == []


def test_cli_range_writes_png_and_json(tmp_path):
    rng = np.random.default_rng(2)
    (_, view), = list(frames(1, rng))
    img = tmp_path / "frame.png"
    cv2.imwrite(str(img), np.clip(view.image * 255 + 0.5, 0, 255).astype(np.uint8))
    out = tmp_path / "out" / "r"
    code = main(["-q", "crps", "range", str(img), "--camera", "80", "--size-m", "0.5",
                 "--pose", "47,8,400,0,0,0,10", "-o", str(out)])
    assert code == 0
    report = json.loads(out.with_suffix(".json").read_text())
    assert len(report["detections"]) == 1
    rec = report["detections"][0]
    assert rec["range_m"] == pytest.approx(view.truth.range_m, rel=0.05)
    np.testing.assert_allclose(rec["bearing_enu"], view.truth.bearing_unit_enu, atol=1e-3)
    png = cv2.imread(str(out.with_suffix(".png")))
    assert png.shape == (720, 1280, 3)
    # the same camera as a skyfix camera file made for a 1920x1080 sensor: rescaled, same answer
    from skyfix.camera import Camera
    from skyfix.camera_io import save_camera

    save_camera(tmp_path / "cam.json", Camera.from_fov(1920, 1080, 80.0))
    out2 = tmp_path / "out" / "r2"
    assert main(["-q", "crps", "range", str(img), "--camera", str(tmp_path / "cam.json"), "--size-m", "0.5",
                 "--pose", "47,8,400,0,0,0,10", "-o", str(out2)]) == 0
    rec2 = json.loads(out2.with_suffix(".json").read_text())["detections"][0]
    assert rec2["range_m"] == pytest.approx(rec["range_m"], rel=1e-9)


def test_cli_bad_camera_is_a_clear_error(tmp_path, caplog):
    img = tmp_path / "frame.png"
    cv2.imwrite(str(img), np.full((64, 64), 180, np.uint8))
    assert main(["crps", "range", str(img), "--camera", "wide", "--size-m", "0.5"]) == 2
    assert "--camera" in caplog.text
    assert main(["crps", "range", str(tmp_path / "missing.png"), "--camera", "80", "--size-m", "0.5"]) == 2
