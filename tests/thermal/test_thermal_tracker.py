"""FireTracker on rendered flights: fusion accuracy and honest sigma, fires that appear,
grow and die, dropped frames."""

from __future__ import annotations

import math

import numpy as np
import pytest

from skyfix.camera import Camera, CameraPose
from skyfix.datasets.thermal_flight import orbit
from skyfix.datasets.thermal_scene import FireSpec, ThermalScene, ThermalSensor
from skyfix.errors import InputError
from skyfix.geo import LocalFrame, inverse
from skyfix.thermal import FireTracker, PoseUncertainty, TrackerSettings

CAM = Camera.from_fov(640, 512, 50.0)
SMALL = Camera.from_fov(320, 256, 50.0)  # same optics, quarter the pixels: faster renders
FRAME = LocalFrame(45.4592, -73.9191, 30.0)
UNC = PoseUncertainty(position_sigma_m=1.5, tilt_sigma_deg=0.5, pixel_sigma_px=0.3)


def noisy(pose: CameraPose, rng: np.random.Generator) -> CameraPose:
    e, n, u = FRAME.to_enu(pose.lat_deg, pose.lon_deg, pose.alt_m)
    lat, lon, alt = FRAME.to_geodetic(e + rng.normal(0, 1.5), n + rng.normal(0, 1.5), u + rng.normal(0, 1.5))
    return CameraPose(float(lat), float(lon), float(alt), pose.roll_deg + rng.normal(0, 0.5),
                      pose.pitch_deg + rng.normal(0, 0.5), pose.yaw_deg + rng.normal(0, 0.5),
                      pose.gimbal_pitch_deg, pose.gimbal_yaw_deg, pose.gimbal_roll_deg, pose.stabilized)


def fly(scene, flight, rng, tracker, sensor, drop: set[int] = frozenset()):
    for k, ff in enumerate(flight):
        if k in drop:
            tracker.update(np.zeros((CAM.height, CAM.width), np.uint16), noisy(ff.pose, rng), ff.time_s)
            continue
        counts = sensor.to_counts(sensor.observe(scene.render(CAM, ff.pose, ff.time_s), rng))
        tracker.update(counts, noisy(ff.pose, rng), ff.time_s)


def truth_of(f: FireSpec) -> tuple[float, float]:
    lat, lon, _ = FRAME.to_geodetic(f.east_m, f.north_m, 0.0)
    return float(lat), float(lon)


def test_fires_appear_grow_and_die():
    growing = FireSpec(0.0, 0.0, radius_m=0.8, growth_mps=0.1, start_s=0.0, peak_c=600.0)
    late = FireSpec(9.0, -6.0, radius_m=1.0, start_s=4.0, peak_c=500.0)
    dying = FireSpec(-8.0, 7.0, radius_m=1.2, end_s=6.0, peak_c=450.0)
    scene = ThermalScene(FRAME, [growing, late, dying], size_m=200.0, seed=4)
    flight = orbit(scene, CAM, (0.0, 0.0), n_frames=24, agl_m=70.0, frame_rate_hz=2.0, gimbal_pitch_deg=-70.0,
                   seed=1)
    rng = np.random.default_rng(9)
    tracker = FireTracker(CAM, FRAME.alt0_m, uncertainty=UNC)
    fly(scene, flight, rng, tracker, ThermalSensor(640, 512, seed=2), drop={10})
    assert tracker.frames_dropped == 1 and tracker.frames_used == 23
    fires = tracker.fires
    assert len(fires) == 3
    by_truth = {}
    for spec in (growing, late, dying):
        lat, lon = truth_of(spec)
        best = min(fires, key=lambda f: float(inverse(lat, lon, f.lat_deg, f.lon_deg)[1]))
        err = float(inverse(lat, lon, best.lat_deg, best.lon_deg)[1])
        # ~20 independent frames at 1.5 m / 0.5 deg: fused sigma well below a metre, error within 3 sigma.
        assert best.sigma_m < 1.0
        assert err < 3.0 * best.sigma_major_m + 0.1
        by_truth[spec] = best
    assert len({f.fire_id for f in by_truth.values()}) == 3
    assert by_truth[late].first_seen_s >= 4.0 and by_truth[late].burning
    assert not by_truth[dying].burning and by_truth[dying].last_seen_s <= 6.0
    assert by_truth[growing].burning
    final_r = growing.radius_at(flight[-1].time_s)
    # Hot area of the growing fire at the end: the disc, within the soft edge and render blur.
    assert by_truth[growing].area_m2 == pytest.approx(math.pi * final_r ** 2, rel=0.3)
    assert by_truth[growing].n_observations >= 20


def test_fused_sigma_shrinks_and_is_honest():
    rng = np.random.default_rng(21)
    inside, sigmas, single = 0, [], []
    n_fires = 6
    for i in range(n_fires):
        spec = FireSpec(float(rng.uniform(-50, 50)), float(rng.uniform(-50, 50)), radius_m=1.0)
        scene = ThermalScene(FRAME, [spec], size_m=300.0, seed=i)
        flight = orbit(scene, SMALL, (spec.east_m, spec.north_m), n_frames=20, agl_m=float(rng.uniform(50, 120)),
                       frame_rate_hz=2.0, gimbal_pitch_deg=-65.0, stabilized=False, wobble_deg=8.0, seed=i)
        tracker = FireTracker(SMALL, FRAME.alt0_m, uncertainty=UNC, settings=TrackerSettings(min_observations=1))
        first = None
        for k, ff in enumerate(flight):
            counts = ThermalSensor(320, 256).to_counts(scene.render(SMALL, ff.pose, ff.time_s))
            tracker.update(counts, noisy(ff.pose, rng), ff.time_s)
            if k == 0:
                first = tracker.fires[0].sigma_m
        (fire,) = tracker.fires
        lat, lon = truth_of(spec)
        err = float(inverse(lat, lon, fire.lat_deg, fire.lon_deg)[1])
        inside += err <= 2.0 * fire.sigma_m
        sigmas.append(fire.sigma_m)
        single.append(first)
        assert fire.n_observations == 20
    # 20 frames: sigma shrinks by ~sqrt(20); 2 * DRMS holds >= 95 % for a correct covariance.
    assert np.all(np.array(sigmas) < np.array(single) / 3.0)
    assert inside >= n_fires - 1


def test_bad_frames_are_dropped_and_bad_arguments_raise():
    tracker = FireTracker(CAM, FRAME.alt0_m)
    pose = CameraPose(45.4592, -73.9191, 130.0)
    assert tracker.update(np.zeros((512, 640), np.int32), pose, 0.0) == []
    assert tracker.update(np.zeros((512, 640), np.uint16), pose, 1.0) == []
    assert tracker.update(np.ones((512, 640), np.uint16), "pose", 2.0) == []
    assert tracker.frames_dropped == 3 and tracker.fires == []
    with pytest.raises(InputError, match="camera"):
        FireTracker("cam", 30.0)
    with pytest.raises(InputError, match="no fire"):
        tracker.track_history(99)
