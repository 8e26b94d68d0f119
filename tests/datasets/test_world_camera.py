"""The helper camera rendered from the simulator's truth: geometry, gimbal, sensor, what the frame carries.

Vehicles hover where the simulated autopilot flew them (offline stepping, no sockets); every
expected pixel or range is computed here from the simulator's truth with the pinhole model,
independently of the renderer. Tolerances: the detector's stated centroid covariance (3 sigma)
and the gimbal's modelled pointing error (3 sigma), the ranging module's stated sigma.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from skyfix.camera import Camera, CameraPose, world_to_pixel
from skyfix.crps import DroneModel, SilhouetteDetector, observe
from skyfix.datasets.drone_view import TargetPose, render_drones
from skyfix.datasets.sim import Simulator, SimulatorConfig
from skyfix.datasets.sim.world_camera import GimbalConfig, GimbalFault, WorldCamera
from skyfix.errors import InputError
from skyfix.geo import LocalFrame

CAM = Camera.from_fov(1280, 720, 60.0)
HOVER = {0: (0.0, 0.0, 25.0), 1: (20.0, 28.0, 30.0), 2: (-30.0, 60.0, 28.0)}  # world ENU m; 1 is the target


def _fly(sim: Simulator, goals: dict[int, tuple[float, float, float]]) -> None:
    """Take off and hover each vehicle at its goal through the simulated autopilot (GUIDED)."""
    for i, p in goals.items():
        v = sim.vehicle(i)
        v.set_mode("GUIDED")
        v.arm(force=True)
        v.takeoff(p[2])
    sim.run_steps(50)
    for i, p in goals.items():
        sim.vehicle(i).position_target(np.array(p), None)
    sim.run_steps(1500)


@pytest.fixture(scope="module")
def sim():
    s = Simulator(SimulatorConfig(vehicles=3, seed=3))
    _fly(s, HOVER)
    yield s
    s.stop()


def _aim(sim: Simulator, cam: WorldCamera, target: int = 1) -> None:
    """Point the gimbal at the target's true position and let it settle."""
    d = sim.vehicle(target).pos_enu_m - sim.vehicle(cam.index).pos_enu_m
    cam.point(math.degrees(math.atan2(d[0], d[1])), math.degrees(math.atan2(d[2], math.hypot(d[0], d[1]))))
    sim.run_steps(100)


def _truth_enu(sim: Simulator, i: int, frame: LocalFrame) -> np.ndarray:
    t = sim.truth(i)
    return np.array([float(c) for c in frame.to_enu(t["lat_deg"], t["lon_deg"], t["alt_m"])])


def _nearest(dets, uv):
    assert dets, "the detector found nothing"
    return min(dets, key=lambda d: float(np.linalg.norm(d.centroid_uv - uv)))


def test_target_where_the_pinhole_model_puts_it_and_ranged(sim):
    wc = WorldCamera(sim, 0, CAM, seed=1, latency_s=0.0)
    _aim(sim, wc)
    frame = wc()
    assert frame.image.dtype == np.uint8 and frame.image.shape == (720, 1280)
    me = sim.truth(0)
    world = sim.world
    target_enu = _truth_enu(sim, 1, world)[None, :]
    det = _nearest(SilhouetteDetector()(frame.image), world_to_pixel(CAM, wc.last_truth.pose, world, target_enu)[0])
    centroid_sigma = math.sqrt(np.linalg.eigvalsh(det.centroid_cov_px2)[-1])
    # with the TRUE camera pose, the drone is where the pinhole model puts it (detector noise only)
    uv_true = world_to_pixel(CAM, wc.last_truth.pose, world, target_enu)[0]
    assert np.linalg.norm(det.centroid_uv - uv_true) <= 3.0 * centroid_sigma + 0.3
    # with the REPORTED attitude, the gimbal's modelled pointing error adds (3 sigma per axis)
    pose = frame.pose(me["lat_deg"], me["lon_deg"], me["alt_m"])
    uv_rep = world_to_pixel(CAM, pose, world, target_enu)[0]
    allowed_px = 3.0 * math.radians(wc.gimbal_cfg.pointing_sigma_deg) * CAM.fx * math.sqrt(2.0)
    assert np.linalg.norm(det.centroid_uv - uv_rep) <= allowed_px + 3.0 * centroid_sigma
    # the silhouette ranges to the true distance within the ranging module's stated sigma
    obs = observe(CAM, pose, det, wc.model.span_m, attitude_sigma_deg=wc.gimbal_cfg.pointing_sigma_deg)
    sigma_r = math.sqrt(obs.bearing_unit_enu @ obs.cov_enu_m2 @ obs.bearing_unit_enu)
    true_range = float(np.linalg.norm(target_enu[0] - _truth_enu(sim, 0, world)))
    assert sigma_r <= 0.06 * true_range  # a single frame at ~35 m: a few per cent (crps README)
    assert abs(obs.range_m - true_range) <= 3.0 * sigma_r


def test_reported_attitude_differs_from_truth_by_the_modelled_error_only(sim):
    small = Camera.from_fov(160, 90, 60.0)
    cfg = GimbalConfig()
    bias_yaw, noise_yaw, noise_pitch = [], [], []
    for seed in range(120):
        wc = WorldCamera(sim, 0, small, seed=seed, latency_s=0.0, gimbal=cfg)
        errs = []
        for _ in range(3):
            f = wc()
            errs.append((((f.yaw_deg - wc.last_truth.pose.yaw_deg) + 180.0) % 360.0 - 180.0,
                         f.pitch_deg - wc.last_truth.pose.gimbal_pitch_deg))
        e = np.array(errs)
        bias_yaw.append(e[:, 0].mean())
        noise_yaw += list(e[:, 0] - e[:, 0].mean())
        noise_pitch += list(e[:, 1] - e[:, 1].mean())
    # sample sigmas of 120 draws (bias) / 240 residual dof (noise): 5 relative standard errors
    expected_bias = math.hypot(cfg.yaw_bias_sigma_deg, cfg.noise_sigma_deg / math.sqrt(3.0))
    assert np.std(bias_yaw) == pytest.approx(expected_bias, rel=5 / math.sqrt(240))
    for res in (noise_yaw, noise_pitch):
        rms = math.sqrt(np.sum(np.square(res)) / 240.0)
        assert rms == pytest.approx(cfg.noise_sigma_deg, rel=5 / math.sqrt(480))


def test_frame_depends_on_the_truth_never_on_the_estimate(sim):
    a, b, c = (WorldCamera(sim, 0, Camera.from_fov(320, 240, 60.0), seed=7, latency_s=0.0) for _ in range(3))
    d = sim.vehicle(1).pos_enu_m - sim.vehicle(0).pos_enu_m
    for cam in (a, b, c):
        cam.point(math.degrees(math.atan2(d[0], d[1])), math.degrees(math.atan2(d[2], math.hypot(d[0], d[1]))))
    sim.run_steps(100)
    a(), b(), c()
    with sim.lock:
        fa = a()
        v = sim.vehicle(0)
        saved = v.est_err_enu_m.copy()
        v.est_err_enu_m += np.array([30.0, -20.0, 5.0])  # the helper's autopilot now believes it is elsewhere
        fb = b()
        v.est_err_enu_m[:] = saved
    np.testing.assert_array_equal(fa.image, fb.image)
    assert (fa.yaw_deg, fa.pitch_deg, fa.t_s) == (fb.yaw_deg, fb.pitch_deg, fb.t_s)
    # control: the same camera seed, pointed the same way, with the TRUE target moved 1 m: another picture
    with sim.lock:
        t = sim.vehicle(1)
        t.pos_enu_m += np.array([1.0, 0.0, 0.0])
        fc = c()
        t.pos_enu_m -= np.array([1.0, 0.0, 0.0])
    assert np.abs(fc.image.astype(int) - fa.image.astype(int)).max() > 15  # a ~4 px drone, same noise draws


def test_gimbal_rate_limit_lag_and_motion_blur(sim):
    cfg = GimbalConfig(max_rate_dps=100.0, tau_s=0.1)
    wc = WorldCamera(sim, 0, Camera.from_fov(320, 240, 60.0), seed=2, latency_s=0.0, gimbal=cfg)
    wc.point(0.0, 0.0)
    sim.run_steps(100)
    wc()
    wc.point(90.0, 0.0)
    sim.run_steps(10)  # 0.2 s: rate limited, 20 deg at most
    f = wc()
    yaw = wc.last_truth.pose.yaw_deg
    assert 15.0 <= yaw <= 20.0 + 1e-6
    assert wc.last_truth.rate_dps[0] == pytest.approx(100.0)
    expected_blur = math.radians(100.0) * wc.camera.fx * wc.last_truth.exposure_s
    assert wc.last_truth.blur_px == pytest.approx(expected_blur, rel=1e-6)
    assert abs(f.yaw_deg - yaw) < 2.0
    sim.run_steps(150)  # 3 s: settled (lag 0.1 s)
    wc()
    assert wc.last_truth.pose.yaw_deg == pytest.approx(90.0, abs=0.01)
    assert wc.last_truth.blur_px < 0.01
    wc.point(0.0, -120.0)  # beyond the stop
    sim.run_steps(150)
    wc()
    assert wc.last_truth.pose.gimbal_pitch_deg == pytest.approx(cfg.pitch_min_deg, abs=0.01)


def test_gimbal_fault_takes_the_target_out_of_view_and_back(sim):
    t0 = sim.time_s
    wc = WorldCamera(sim, 0, Camera.from_fov(640, 360, 60.0), seed=4, latency_s=0.0,
                     gimbal_fault=GimbalFault(t0 + 3.0, 2.0, 90.0))
    _aim(sim, wc)  # 2 s
    wc()
    assert wc.last_truth.in_view(1)
    sim.run_steps(100)  # t0 + 4 s: the gimbal looks 90 deg away
    f = wc()
    assert not wc.last_truth.in_view(1)
    assert abs(((f.yaw_deg - wc.last_truth.pose.yaw_deg) + 180) % 360 - 180) < 2.0  # it reports where it looks
    sim.run_steps(100)  # t0 + 6 s: fault over, back on the command
    wc()
    assert wc.last_truth.in_view(1)
    assert [keys for _, keys in wc.in_view_log] == [(1,), (), (1,)]
    wc.set_gimbal_fault(GimbalFault(sim.time_s, 5.0, -60.0))  # scheduled in flight
    sim.run_steps(50)
    wc()
    assert not wc.last_truth.in_view(1)
    wc.set_gimbal_fault(None)
    sim.run_steps(50)
    wc()
    assert wc.last_truth.in_view(1)


def test_extra_targets_are_drawn_like_simulated_vehicles(sim):
    # a vehicle the simulator does not fly (e.g. SITL's SIM_STATE truth), 30 m north-east of the helper, 3 m up
    me = sim.vehicle(0).pos_enu_m
    lat, lon, alt = sim.world.to_geodetic(me[0] + 21.2, me[1] + 21.2, me[2] + 3.0)
    extra = TargetPose(float(lat), float(lon), float(alt), yaw_deg=20.0)
    wc = WorldCamera(sim, 0, Camera.from_fov(640, 360, 60.0), seed=6, latency_s=0.0, extra_targets=lambda: [extra])
    wc.point(45.0, math.degrees(math.atan2(3.0, 30.0)))
    sim.run_steps(100)
    frame = wc()
    assert wc.last_truth.in_view("extra:0")
    uv = wc.last_truth.vehicles["extra:0"].centroid_uv
    assert np.linalg.norm(uv - np.array([319.5, 179.5])) < 15.0  # aimed at: near the centre
    assert min(np.linalg.norm(d.centroid_uv - uv) for d in SilhouetteDetector()(frame.image)) < 1.0


def test_latency_stamps_the_exposure_time(sim):
    wc = WorldCamera(sim, 0, Camera.from_fov(160, 90, 60.0), seed=0, latency_s=0.1)
    assert wc() is None  # nothing exposed 0.1 s before the camera existed
    sim.run_steps(10)
    f = wc()
    assert f.t_s == pytest.approx(sim.time_s - 0.1)
    assert wc.last_truth.t_s == f.t_s


def test_auto_exposure_follows_the_scene(sim):
    wc = WorldCamera(sim, 0, Camera.from_fov(320, 180, 60.0), seed=5, latency_s=0.0)
    wc.point(0.0, 20.0)  # sky
    sim.run_steps(200)
    wc()
    sky_exposure = wc.last_truth.exposure_s
    wc.point(0.0, -60.0)  # darker ground: longer exposure, after the loop's lag
    sim.run_steps(10)
    first = wc()
    for _ in range(20):
        sim.run_steps(10)
        last = wc()
    assert wc.last_truth.exposure_s > 1.5 * sky_exposure
    level = wc.sensor.ae_target * 255
    assert abs(float(last.image.mean()) - level) < abs(float(first.image.mean()) - level)
    assert float(last.image.mean()) == pytest.approx(level, rel=0.2)  # vignetting and metering weights


def test_render_drones_culls_and_occludes():
    cam = Camera.from_fov(320, 240, 60.0)
    pose = CameraPose(47.0, 8.0, 400.0, yaw_deg=0.0, gimbal_pitch_deg=-20.0)
    frame = LocalFrame(47.0, 8.0, 400.0)

    def at(e, n, u):
        lat, lon, alt = frame.to_geodetic(e, n, u)
        return TargetPose(float(lat), float(lon), float(alt), yaw_deg=10.0)

    near, far = at(0.0, 8.0, -8.0 * math.tan(math.radians(20.0))), at(0.2, 16.0, -16.0 * math.tan(math.radians(20.0)))
    behind, aside = at(0.0, -10.0, 0.0), at(50.0, 5.0, 0.0)
    both = np.full((240, 320), 0.8, np.float32)
    truths = render_drones(both, cam, pose, [far, behind, near, aside], DroneModel.quad(), drone_gray=0.1)
    assert truths[1] is None and truths[3] is None
    assert truths[0].range_m == pytest.approx(math.hypot(0.2, 16.0 / math.cos(math.radians(20.0))), abs=1e-3)
    near_only = np.full((240, 320), 0.8, np.float32)
    (t_near,) = render_drones(near_only, cam, pose, [near], DroneModel.quad(), drone_gray=0.1)
    far_only = np.full((240, 320), 0.8, np.float32)
    (t_far,) = render_drones(far_only, cam, pose, [far], DroneModel.quad(), drone_gray=0.1)
    # the far drone is behind the near one: where the near one fully covers a pixel, only it shows
    full = np.zeros((240, 320), bool)
    u0, v0, u1, v1 = t_near.bbox_px
    full[v0:v1, u0:u1] = t_near.coverage >= 1.0
    overlap = full & (far_only < 0.79)
    assert overlap.sum() >= 5
    np.testing.assert_array_equal(both[full], near_only[full])
    assert np.any((both < 0.79) & ~(near_only < 0.79))  # and it still shows around the near one


def test_errors(sim):
    with pytest.raises(InputError, match="index"):
        WorldCamera(sim, 3, CAM, seed=0)
    with pytest.raises(InputError, match="camera"):
        WorldCamera(sim, 0, "cam", seed=0)
    with pytest.raises(InputError, match="latency_s"):
        WorldCamera(sim, 0, CAM, seed=0, latency_s=-0.1)
    with pytest.raises(InputError, match="yaw_deg"):
        WorldCamera(sim, 0, CAM, seed=0).point(float("nan"), 0.0)
