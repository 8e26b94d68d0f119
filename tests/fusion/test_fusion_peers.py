"""A peer's fused fix rides on its receiver's wandering error: fused as correlated, the drone it
positions (through relative observations) is honest about that error; fused as independent 2 Hz
fixes, the engine averages down a bias it cannot average and is over-confident."""

import numpy as np
import pytest
from fusion_sim import FRAME, ORIGIN

from skyfix.fusion import FusionEngine
from skyfix.types import GeoFix, RelativeObservation

TARGET = np.array([0.0, 0.0, 50.0])     # no GNSS: positioned by the helpers only
HELPERS = {"h": np.array([30.0, 0.0, 45.0]), "g": np.array([-20.0, 25.0, 48.0])}
PEER_SIGMA_M = np.array([1.5, 1.5, 2.5])  # a peer on a consumer receiver states about its wandering error
DURATION_S = 24.0


def _fly(seed: int, correlated: bool) -> tuple[float, float]:
    """Helpers' fixes (2 Hz) carry their receivers' error (nearly constant over a run much shorter than its
    minute of correlation) and their velocities (5 Hz); each sees the target every 0.4 s (2 % range, 0.2 deg).
    Returns the target's final horizontal error (m) and its 3-D NEES."""
    rng = np.random.default_rng(seed)
    bias = {h: rng.normal(0.0, 1.0, 3) * PEER_SIGMA_M for h in HELPERS}
    engine = FusionEngine(ORIGIN, lag_s=2.0)
    for i in range(int(DURATION_S / 0.2) + 1):
        t = round(0.2 * i, 6)
        engine.add_velocity("a", t, rng.normal(0.0, 0.1, 3), 0.2)
        for h, p in HELPERS.items():
            engine.add_velocity(h, t, rng.normal(0.0, 0.1, 3), 0.2)
            if i % 5 in (0, 2):  # 2 Hz-ish, uneven like the service's rate limit
                lat, lon, alt = FRAME.to_geodetic(*(p + bias[h] + rng.normal(0.0, 0.1, 3)))
                fix = GeoFix(float(lat), float(lon), float(alt), np.diag(PEER_SIGMA_M**2 + 0.3**2), t, f"peer:{h}")
                engine.add_fix(h, fix, correlated=correlated)
            if i % 2 == 1:
                los = TARGET - p
                r = float(np.linalg.norm(los))
                cov = np.eye(3) * (3.5e-3 * r) ** 2 + np.outer(los, los) / r**2 * (0.02 * r) ** 2
                seen = los + rng.multivariate_normal(np.zeros(3), cov, method="cholesky")
                lat, lon, alt = FRAME.to_geodetic(*(p + bias[h]))  # the helper's own belief; never used
                engine.add_relative(RelativeObservation(h, "a", t, seen / np.linalg.norm(seen),
                                                        float(np.linalg.norm(seen)), cov, float(lat), float(lon),
                                                        float(alt)))
        if i % 5 == 4:
            engine.update()
    est = engine.estimate("a")
    err = est.enu_m - TARGET
    return float(np.hypot(*err[:2])), float(err @ np.linalg.solve(est.cov_enu_m2, err))


@pytest.mark.parametrize("correlated", [True, False])
def test_a_peers_wandering_error_is_not_averaged_away(correlated):
    runs = np.array([_fly(seed, correlated) for seed in range(5 if correlated else 3)])
    err_h, nees = runs[:, 0], runs[:, 1]
    # the target's error is the helpers' receiver errors, ~1.5 m / sqrt(2) per axis: the same either way
    assert np.sqrt(np.mean(err_h**2)) < 3.0
    if correlated:
        # 5 runs of a 3-dof chi-square: mean 3, 99 % of such means fall in 0.9-6.6
        assert 0.9 < np.mean(nees) < 6.6
    else:
        assert np.mean(nees) > 10.0  # what the lost drone's fusion did before: over-confident (seen: 21)
