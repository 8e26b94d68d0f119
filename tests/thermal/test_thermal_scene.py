"""Synthetic thermal scenes: fire timing, rendered geometry, sensor model, display, poses."""

from __future__ import annotations

import math

import numpy as np
import pytest

from skyfix.camera import Camera, CameraPose, world_to_pixel
from skyfix.datasets.thermal_flight import pose_seeing
from skyfix.datasets.thermal_scene import (
    FireSpec,
    ThermalScene,
    ThermalSensor,
    random_fires,
    to_display,
)
from skyfix.errors import GeometryError, InputError
from skyfix.geo import LocalFrame
from skyfix.thermal import detect_hotspots

CAM = Camera.from_fov(640, 512, 50.0)
FRAME = LocalFrame(45.4592, -73.9191, 30.0)


def nadir(e: float, n: float, agl: float) -> CameraPose:
    lat, lon, alt = FRAME.to_geodetic(e, n, agl)
    return CameraPose(float(lat), float(lon), float(alt), gimbal_pitch_deg=-90.0)


def test_fire_timing():
    f = FireSpec(0.0, 0.0, radius_m=2.0, growth_mps=-0.5, start_s=10.0, end_s=20.0)
    assert f.radius_at(9.9) == 0.0 and f.radius_at(10.0) == 2.0
    assert f.radius_at(12.0) == pytest.approx(1.0) and f.radius_at(15.0) == 0.0 and f.radius_at(21.0) == 0.0
    assert FireSpec(0.0, 0.0, radius_m=1.0, growth_mps=3.0).radius_at(100.0) == 1.0  # no start: constant
    with pytest.raises(InputError):
        FireSpec(0.0, 0.0, radius_m=-1.0)
    with pytest.raises(InputError):
        FireSpec(0.0, 0.0, start_s=5.0, end_s=1.0)


def test_rendered_fire_has_its_ground_size_and_position():
    scene = ThermalScene(FRAME, [FireSpec(3.0, -2.0, radius_m=2.0, peak_c=600.0)], size_m=200.0)
    pose = nadir(0.0, 0.0, 50.0)
    img = scene.render(CAM, pose)
    (spot,) = detect_hotspots(img)
    metres_per_px = 50.0 / CAM.fx  # nadir ground sample distance at the image centre
    area_m2 = spot.area_px * metres_per_px ** 2
    # Threshold crosses the 0.15 m soft edge ~0.05 m outside the nominal radius: +5 % area.
    assert area_m2 == pytest.approx(math.pi * 2.0 ** 2, rel=0.1)
    uv = world_to_pixel(CAM, pose, FRAME, np.array([[3.0, -2.0, 0.0]]))[0]
    assert spot.uv == pytest.approx(uv, abs=0.05)
    assert scene.render(CAM, pose, 0.0).dtype == np.float32


def test_smoke_attenuates_the_fire():
    clear = ThermalScene(FRAME, [FireSpec(0.0, 0.0, radius_m=1.5)], size_m=200.0)
    smoky = ThermalScene(FRAME, [FireSpec(0.0, 0.0, radius_m=1.5, smoke_opacity=0.8, wind_to_deg=90.0)],
                         size_m=200.0)
    pose = nadir(0.0, 0.0, 60.0)
    a, b = detect_hotspots(clear.render(CAM, pose))[0], detect_hotspots(smoky.render(CAM, pose))[0]
    assert b.peak < a.peak and b.area_px < a.area_px
    # The plume drifts east and hides the fire's eastern half more: centroid moves west (-u).
    assert b.u_px < a.u_px


def test_sensor_dead_pixels_and_counts():
    sensor = ThermalSensor(640, 512, noise_sigma_c=0.0, dead_pixel_fraction=1e-3, seed=1)
    hot, cold = sensor.dead_pixels
    assert len(hot) + len(cold) == round(1e-3 * 640 * 512)
    obs = sensor.observe(np.full((512, 640), 20.0, np.float32), np.random.default_rng(0))
    assert np.all(obs.ravel()[hot] == pytest.approx(sensor.max_c))
    counts = sensor.to_counts(obs)
    assert counts.dtype == np.uint16 and counts.ravel()[hot][0] == 65535 and counts.ravel()[cold][0] == 0
    back = counts.astype(float) * 0.01 - 273.15
    mask = np.ones(obs.size, bool)
    mask[np.concatenate((hot, cold))] = False
    assert np.abs(back.ravel()[mask] - 20.0).max() <= 0.005
    with pytest.raises(InputError):
        sensor.observe(np.zeros((10, 10)), np.random.default_rng(0))


def test_display_frames():
    img = np.linspace(0.0, 150.0, 512 * 640, dtype=np.float32).reshape(512, 640)
    white = to_display(img, span_c=(0.0, 150.0))
    assert white.dtype == np.uint8 and white[0, 0] == 0 and white[-1, -1] == 255
    assert np.array_equal(to_display(img, palette="black-hot", span_c=(0.0, 150.0)), 255 - white)
    assert to_display(img, palette="arctic").shape == (512, 640, 3)
    with pytest.raises(InputError):
        to_display(img, palette="jet")


def test_pose_seeing_puts_the_target_on_the_pixel():
    target = np.array([40.0, -25.0, 0.0])
    for uv in ([100.0, 80.0], [500.0, 400.0]):
        pose = pose_seeing(FRAME, CAM, target, np.array(uv), 120.0, roll_deg=10.0, pitch_deg=-12.0, yaw_deg=300.0,
                           gimbal_pitch_deg=-70.0)
        # Exact up to the ENU axes difference between frame origin and vehicle (~1e-5 rad here).
        assert world_to_pixel(CAM, pose, FRAME, target[None, :])[0] == pytest.approx(uv, abs=0.05)
    with pytest.raises(GeometryError):
        pose_seeing(FRAME, CAM, target, np.array([320.0, 0.0]), 100.0, roll_deg=0.0, pitch_deg=0.0,
                    yaw_deg=0.0, gimbal_pitch_deg=-5.0)


def test_random_fires():
    fires = random_fires(25, np.random.default_rng(1), half_extent_m=30.0, radius_m=(1.0, 2.0))
    assert len(fires) == 25
    assert all(abs(f.east_m) <= 30.0 and abs(f.north_m) <= 30.0 and 1.0 <= f.radius_m <= 2.0 for f in fires)
    assert len({(f.east_m, f.north_m) for f in fires}) == 25
    with pytest.raises(InputError):
        random_fires(-1, np.random.default_rng(1))
