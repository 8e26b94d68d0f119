"""A helper's camera pipeline on the simulator's rendered frames: it aims, detects, ranges, and fusion
places the target from its observations within the covariance it states.

Two simulated copters hover (flown through the simulator's autopilot API): the target 20 m up, the
helper 36 m away and 5 m lower. The helper knows itself and the target only from their GNSS
receivers (biased, noisy); frames come from the simulator's gimbal camera (WorldCamera: truth
rendered with blur, noise, exposure, a biased gimbal report). Nothing the eye gets is the truth.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from skyfix import geo
from skyfix.camera import Camera
from skyfix.crps.helper_eye import EyeConfig, HelperEye
from skyfix.datasets.sim import Simulator, SimulatorConfig
from skyfix.datasets.sim.world_camera import WorldCamera
from skyfix.fusion.config import FusionConfig
from skyfix.fusion.engine import FusionEngine
from skyfix.types import GeoFix

CHI2_3DOF_999 = 16.27  # 99.9 % quantile of chi-square, 3 degrees of freedom
TARGET_ENU, HELPER_ENU = (0.0, 40.0, 20.0), (25.0, 15.0, 15.0)  # 36 m apart


def _hovering_pair(seed: int) -> Simulator:
    sim = Simulator(SimulatorConfig(vehicles=2, seed=seed))
    for i, goal in enumerate((TARGET_ENU, HELPER_ENU)):
        v = sim.vehicle(i)
        v.set_mode("GUIDED")
        v.arm()
        v.takeoff(goal[2])
    sim.run_steps(300)
    for i, goal in enumerate((TARGET_ENU, HELPER_ENU)):
        sim.vehicle(i).position_target(np.array(goal), None)
    sim.run_steps(1000)
    return sim


def _receiver_fix(sim: Simulator, index: int, sigma_h_m: float) -> GeoFix:
    """What the drone's GNSS receiver says (bias and noise included), with the stated sigma."""
    reading = sim.vehicle(index).last_gps
    lat, lon, alt = (float(c) for c in sim.world.to_geodetic(*reading.pos_enu_m))
    return GeoFix(lat, lon, alt, np.diag([sigma_h_m**2, sigma_h_m**2, (1.5 * sigma_h_m) ** 2]), sim.time_s, "gnss")


@pytest.mark.parametrize("seed", [2])
def test_helper_eye_observes_the_target_and_fusion_places_it(seed):
    sim = _hovering_pair(seed)
    cam = WorldCamera(sim, 1, Camera.from_fov(960, 720, 50.0), seed=seed)
    eye = HelperEye(cam, "h", lambda _t: _receiver_fix(sim, 1, 0.8), lambda: sim.time_s,
                    EyeConfig(target_span_m=cam.model.span_m, attitude_sigma_deg=cam.gimbal_cfg.pointing_sigma_deg),
                    run=False)
    prior = _receiver_fix(sim, 0, 2.0)  # the help request's last fix
    observations, ranges, in_view = [], [], 0
    for _ in range(14):
        own = _receiver_fix(sim, 1, 0.8)
        az_deg, dist_m = geo.inverse(own.lat_deg, own.lon_deg, prior.lat_deg, prior.lon_deg)
        eye.point(float(az_deg), math.degrees(math.atan2(prior.alt_m - own.alt_m, float(dist_m))))
        sim.run_steps(10)  # 0.2 s: the gimbal slews (from level, facing north), the next frame exposes
        frame = cam()
        obs = eye.observe_frame(frame, "t", prior)
        in_view += cam.last_truth.in_view(0)  # scoring only
        if obs is not None:
            observations.append(obs)
            ranges.append(obs.range_m / float(np.linalg.norm(sim.vehicle(0).pos_enu_m - sim.vehicle(1).pos_enu_m)))
    assert in_view >= 10, f"the gimbal did not bring the target into view ({in_view} of 14 frames)"
    assert len(observations) >= in_view - 1, f"target detected in {len(observations)} of {in_view} frames in view"
    # each observation, from where the helper believes it is, puts the target where it is within its covariance
    target = sim.truth(0)
    nis = []
    for obs in observations:
        at_helper = geo.LocalFrame(obs.observer_lat_deg, obs.observer_lon_deg, obs.observer_alt_m)
        true_offset = np.array([float(c) for c in at_helper.to_enu(target["lat_deg"], target["lon_deg"], target["alt_m"])])
        err = obs.bearing_unit_enu * obs.range_m - true_offset
        nis.append(float(err @ np.linalg.solve(obs.cov_enu_m2 + obs.observer_cov_enu_m2, err)))
    assert np.mean(np.array(nis) < CHI2_3DOF_999) >= 0.9, f"normalised errors {np.round(nis, 1)}"
    # where its own eye saw the target (the gimbal follows it): fresh, within its covariance of the truth
    seen = eye.sighting("t", observations[-1].time_s + 1.0)
    true_enu = np.array([target["east_m"], target["north_m"], target["up_m"]])
    off = np.array([float(c) for c in sim.world.to_enu(seen.lat_deg, seen.lon_deg, seen.alt_m)]) - true_enu
    assert float(off @ np.linalg.solve(seen.cov_enu_m2, off)) < CHI2_3DOF_999, off
    assert eye.sighting("t", observations[-1].time_s + 2.5) is None  # older than sighting_fresh_s: not followed
    assert eye.sighting("other", observations[-1].time_s) is None
    # aimed at its own sighting, the target centred in view, a requester's fix 20 m off (2 m sigma) still
    # refuses it: the search window is the requester's fix, not where the camera points
    frame_enu = np.array([float(c) for c in sim.world.to_enu(prior.lat_deg, prior.lon_deg, prior.alt_m)])
    lat, lon, alt = (float(c) for c in sim.world.to_geodetic(*(frame_enu + np.array([20.0, 0.0, 0.0]))))
    wrong = GeoFix(lat, lon, alt, prior.cov_enu_m2, prior.time_s, "peer:t")
    own = _receiver_fix(sim, 1, 0.8)
    az_deg, dist_m = geo.inverse(own.lat_deg, own.lon_deg, seen.lat_deg, seen.lon_deg)
    eye.point(float(az_deg), math.degrees(math.atan2(seen.alt_m - own.alt_m, float(dist_m))))
    sim.run_steps(10)
    frame = cam()
    assert cam.last_truth.in_view(0)
    assert eye.observe_frame(frame, "t", wrong) is None
    found = eye.observe_frame(frame, "t", prior)  # the same frame, searched around the right fix
    true_range_m = float(np.linalg.norm(sim.vehicle(0).pos_enu_m - sim.vehicle(1).pos_enu_m))
    range_sigma_m = math.sqrt(found.bearing_unit_enu @ found.cov_enu_m2 @ found.bearing_unit_enu)
    assert abs(found.range_m - true_range_m) <= 3.0 * range_sigma_m, (found.range_m, true_range_m, range_sigma_m)
    # ranging: a 0.5 m quad at ~36 m, ~14 px across: a few per cent
    assert abs(np.median(ranges) - 1.0) < 0.05, f"range / true range {np.round(ranges, 3)}"
    # the requester's fusion (its velocity, the helper's fix, the observations) places it within 3 sigma
    engine = FusionEngine((sim.world.lat0_deg, sim.world.lon0_deg, sim.world.alt0_m), config=FusionConfig(roster=("h", "t")))
    for obs in observations:
        engine.add_fix("h", GeoFix(obs.observer_lat_deg, obs.observer_lon_deg, obs.observer_alt_m,
                                   obs.observer_cov_enu_m2, obs.time_s, "peer:h"))
        engine.add_velocity("t", obs.time_s, np.zeros(3), 0.2)
        engine.add_relative(obs)
    est = engine.estimate("t")
    err = est.enu_m - true_enu
    assert "relative:h" in est.sources
    assert float(err @ np.linalg.solve(est.cov_enu_m2, err)) < CHI2_3DOF_999, (err, np.sqrt(np.diag(est.cov_enu_m2)))
    assert math.hypot(err[0], err[1]) < 2.0
