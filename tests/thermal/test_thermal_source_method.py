"""The source thesis's method (benchmark baseline) is right where its assumptions hold
and wrong by the expected amount where they do not."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from skyfix.camera import Camera, CameraPose
from skyfix.datasets.thermal_scene import FireSpec, ThermalScene, to_display
from skyfix.errors import InputError
from skyfix.geo import LocalFrame, inverse
from skyfix.thermal import RelativeTemperatureWarning, detect_hotspots, geolocate
from skyfix.thermal.source_method import source_method_locate

CAM = Camera.from_fov(640, 512, 50.0)
FRAME = LocalFrame(45.4592, -73.9191, 30.0)


def run(fire_en: tuple[float, float], *, roll_deg: float = 0.0, yaw_deg: float = 0.0,
        gimbal_pitch_deg: float = -90.0) -> tuple[float, float]:
    """(source-method error, skyfix error) in metres on one rendered 8-bit frame."""
    scene = ThermalScene(FRAME, [FireSpec(*fire_en, radius_m=1.0)], size_m=400.0)
    lat, lon, alt = FRAME.to_geodetic(0.0, 0.0, 100.0)
    pose = CameraPose(float(lat), float(lon), float(alt), roll_deg=roll_deg, yaw_deg=yaw_deg,
                      gimbal_pitch_deg=gimbal_pitch_deg, stabilized=False)
    u8 = to_display(scene.render(CAM, pose), span_c=(0.0, 150.0))
    est = source_method_locate(u8, threshold_level=200, hfov_deg=CAM.hfov_deg, vfov_deg=CAM.vfov_deg,
                               lat_deg=pose.lat_deg, lon_deg=pose.lon_deg, height_m=100.0, heading_deg=yaw_deg,
                               pitch_deg=0.0, camera_depression_deg=-gimbal_pitch_deg)
    truth = FRAME.to_geodetic(*fire_en, 0.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RelativeTemperatureWarning)
        fix = geolocate(detect_hotspots(u8)[0], CAM, pose, FRAME.alt0_m)
    return (float(inverse(truth[0], truth[1], est[0], est[1])[1]),
            float(inverse(truth[0], truth[1], fix.lat_deg, fix.lon_deg)[1]))


def test_exact_enough_when_its_assumptions_hold():
    # Nadir, level, fire at the centre: only the W/2 vs (W-1)/2 half-pixel (0.07 m at 100 m).
    assert run((0.0, 0.0))[0] < 0.15
    # Straight ahead along the heading (40 deg): linear FOV/pixel vs pinhole angle errs
    # by a few percent of the 15 m offset.
    b = math.radians(40.0)
    assert run((15.0 * math.sin(b), 15.0 * math.cos(b)), yaw_deg=40.0)[0] < 1.0


def test_sideways_offsets_and_roll_are_where_it_fails():
    # Ground distance comes from the vertical image offset only: at nadir a fire 15 m to
    # the side is put (almost) under the drone.
    source, ours = run((15.0, 0.0))
    assert source == pytest.approx(15.0, abs=1.5) and ours < 0.05
    # Roll ignored: a camera at -60 deg rolled 8 deg, fire on the optical axis of the
    # level camera (57.7 m ahead): metres of error; skyfix on the same frame: centimetres.
    source, ours = run((0.0, 100.0 / math.tan(math.radians(60.0))), roll_deg=8.0, gimbal_pitch_deg=-60.0)
    assert source > 3.0 and ours < 0.05


def test_no_hot_pixel_and_bad_input():
    frame = np.zeros((512, 640), np.uint8)
    kw = dict(threshold_level=200, hfov_deg=50.0, vfov_deg=40.0, lat_deg=45.0, lon_deg=-73.0, height_m=100.0,
              heading_deg=0.0, pitch_deg=0.0, camera_depression_deg=90.0)
    assert source_method_locate(frame, **kw) is None
    with pytest.raises(InputError):
        source_method_locate(frame.astype(np.uint16), **kw)
