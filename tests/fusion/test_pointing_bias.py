"""A helper camera's heading error is the same in every frame of a flight (its compass reference): fused as if
each frame erred on its own, two helpers' 160 frames shrank the target's stated uncertainty ~10x below its true
error. With FusionConfig.relative_pointing_sigma_deg the observer's pointing error is a state its frames share
(fusion/pointing.py), and the stated covariance covers the error (NEES ~ 3, chi-square with 3 dof: mean 2.35 over these 20 flights, 28 without the states). The world turns
the helpers' rays by exact rotations, not by the fusion's linearised model."""

import numpy as np
import pytest
from fusion_sim import FRAME, ORIGIN

from skyfix.fusion import FusionConfig, FusionEngine
from skyfix.types import GeoFix, RelativeObservation

TARGET = np.array([0.0, 0.0, 15.0])                                   # hovering, its GNSS lost
HELPERS = {"h": np.array([-35.0, 0.0, 10.0]), "g": np.array([0.0, -35.0, 10.0])}
BIAS_DEG = 2.0      # the world's heading and pitch errors per helper and flight (drawn with this 1-sigma)
STATED_DEG = 2.0    # what each observation states across the line of sight
RANGE_REL = 0.02    # ranging 1-sigma, share of the range


def _rotate(v: np.ndarray, yaw_rad: float, pitch_rad: float) -> np.ndarray:
    """``v`` rotated, as a camera mount turns it: by ``yaw_rad`` about the vertical, then by ``pitch_rad`` about its
    own horizontal across axis (exact rotations, not fusion/pointing.py's linearisation)."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    v = np.array([c * v[0] - s * v[1], s * v[0] + c * v[1], v[2]])
    axis = np.array([-v[1], v[0], 0.0]) / np.hypot(v[0], v[1])
    return v * np.cos(pitch_rad) + np.cross(axis, v) * np.sin(pitch_rad)  # Rodrigues: axis is normal to v


def _nees(seed: int, config: FusionConfig) -> float:
    rng = np.random.default_rng(seed)
    eng = FusionEngine(ORIGIN, lag_s=2.0, config=config)
    bias = {h: np.radians(rng.normal(0.0, BIAS_DEG, 2)) for h in HELPERS}
    lat, lon, alt = FRAME.to_geodetic(*(TARGET + rng.normal(0.0, 3.0, 3)))
    eng.add_fix("a", GeoFix(float(lat), float(lon), float(alt), np.eye(3) * 9.0, 0.0, "last good fix"))
    for i in range(int(20.0 / 0.1)):
        t = round(0.1 * i, 6)
        eng.add_velocity("a", t, rng.normal(0.0, 0.05, 3).tolist(), 0.2)
        for h, hp in HELPERS.items():
            eng.add_velocity(h, t, rng.normal(0.0, 0.02, 3).tolist(), 0.05)
            if i % 5 == 0:  # precise receivers: the helpers' own positions are not the question here
                lat, lon, alt = FRAME.to_geodetic(*(hp + rng.normal(0.0, 0.05, 3)))
                eng.add_gnss(h, t, float(lat), float(lon), float(alt), h_sigma_m=0.05, v_sigma_m=0.05)
            if i % 5 in (1, 3):  # 4 frames a second from the two
                los = TARGET - hp
                r = float(np.linalg.norm(los))
                seen = _rotate(los, *(bias[h] + np.radians(rng.normal(0.0, 0.05, 2))))
                seen *= 1.0 + rng.normal(0.0, RANGE_REL)
                u = los / r
                cov = (np.eye(3) - np.outer(u, u)) * (r * np.radians(STATED_DEG)) ** 2 + np.outer(u, u) * (RANGE_REL * r) ** 2
                eng.add_relative(RelativeObservation(h, "a", t, seen / np.linalg.norm(seen), float(np.linalg.norm(seen)),
                                                     cov))
        if i % 4 == 3:
            eng.update()
    est = eng.estimate("a")
    err = est.enu_m - TARGET
    return float(err @ np.linalg.solve(est.cov_enu_m2, err))


def _config(shared_deg: float) -> FusionConfig:
    return FusionConfig(gnss_gm_h_sigma_m=0.05, gnss_gm_v_sigma_m=0.05, gnss_white_min_sigma_m=0.05,
                        relative_pointing_sigma_deg=shared_deg)


@pytest.mark.parametrize("shared_deg, low, high", [(BIAS_DEG, 1.5, 5.0), (0.0, 20.0, np.inf)])
def test_a_shared_pointing_error_is_not_averaged_away(shared_deg, low, high):
    """Mean NEES over 20 flights (3 = honest; 20 of chi-square 3 have a mean within ~3 +- 1.1 at 95 %)."""
    nees = np.array([_nees(seed, _config(shared_deg)) for seed in range(20)])
    assert low < nees.mean() < high, nees.round(1)
