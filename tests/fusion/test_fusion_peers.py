"""A peer's fused fix rides on its receiver's wandering error: fused as correlated, the drone it
positions (through relative observations) is honest about that error; fused as independent 2 Hz
fixes, the engine averages down a bias it cannot average and is over-confident. Receivers near each
other share most of that error: modelled as their own, two helpers' errors are averaged as if half
of it cancelled (FusionConfig.gnss_common_share)."""

import math

import numpy as np
import pytest
from fusion_sim import FRAME, ORIGIN

from skyfix.fusion import FusionConfig, FusionEngine
from skyfix.types import GeoFix, RelativeObservation

TARGET = np.array([0.0, 0.0, 50.0])     # no GNSS: positioned by the helpers only
HELPERS = {"h": np.array([30.0, 0.0, 45.0]), "g": np.array([-20.0, 25.0, 48.0])}
PEER_SIGMA_M = np.array([1.5, 1.5, 2.5])  # a peer on a consumer receiver states about its wandering error
DURATION_S = 24.0


def _fly(seed: int, correlated: bool, shared_sigma_m: np.ndarray | None = None,
         config: FusionConfig | None = None) -> tuple[float, float, float, float]:
    """Helpers' fixes (2 Hz) carry their receivers' error (nearly constant over a run much shorter than its
    minute of correlation) and their velocities (5 Hz); each sees the target every 0.4 s (2 % range, 0.2 deg).
    ``shared_sigma_m``: the error both receivers share (per axis), the rest of PEER_SIGMA_M's variance their own.
    Returns the target's final horizontal error (m), its 3-D NEES, its stated sigma east (m) and the NEES of its
    error in the swarm's GNSS frame (against the target moved by the shared error; NaN without that model)."""
    rng = np.random.default_rng(seed)
    common = np.zeros(3)
    if shared_sigma_m is None:
        bias = {h: rng.normal(0.0, 1.0, 3) * PEER_SIGMA_M for h in HELPERS}
    else:
        common, own_sigma = rng.normal(0.0, 1.0, 3) * shared_sigma_m, np.sqrt(PEER_SIGMA_M**2 - shared_sigma_m**2)
        bias = {h: common + rng.normal(0.0, 1.0, 3) * own_sigma for h in HELPERS}
    engine = FusionEngine(ORIGIN, lag_s=2.0, config=config)
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
    err, err_frame = est.enu_m - TARGET, est.enu_m - (TARGET + common)
    nees_frame = math.nan if est.cov_frame_enu_m2 is None else err_frame @ np.linalg.solve(est.cov_frame_enu_m2,
                                                                                             err_frame)
    return (float(np.hypot(*err[:2])), float(err @ np.linalg.solve(est.cov_enu_m2, err)),
            float(np.sqrt(est.cov_enu_m2[0, 0])), float(nees_frame))


@pytest.mark.parametrize("correlated", [True, False])
def test_a_peers_wandering_error_is_not_averaged_away(correlated):
    runs = np.array([_fly(seed, correlated)[:2] for seed in range(5 if correlated else 3)])
    err_h, nees = runs[:, 0], runs[:, 1]
    # the target's error is the helpers' receiver errors, ~1.5 m / sqrt(2) per axis: the same either way
    assert np.sqrt(np.mean(err_h**2)) < 3.0
    if correlated:
        # 5 runs of a 3-dof chi-square: mean 3, 99 % of such means fall in 0.9-6.6
        assert 0.9 < np.mean(nees) < 6.6
    else:
        assert np.mean(nees) > 10.0  # what the lost drone's fusion did before: over-confident (seen: 21)


@pytest.mark.parametrize("share", [0.0, 0.9])
def test_an_error_the_helpers_share_is_not_averaged_away(share):
    """Both helpers' receivers share 85 % of their error variance (as receivers tens of metres apart do: the
    same sky; not the 90 % the fusion is told); each helper's fixes fused as correlated. Modelled as each receiver's own, the two helpers'
    errors average as if independent: the target's stated sigma falls to ~1.5 / sqrt(2) m per horizontal axis,
    below the shared error's 1.38 m alone, and its NEES comes out ~1.9x too large. With the shared part in the
    model the NEES is a 3-dof chi-square's. In the swarm's GNSS frame (where home and the helpers' fixes sit) the
    target is placed far better than that: the helpers' own errors and the observations' only."""
    shared = np.sqrt(0.85) * PEER_SIGMA_M
    runs = np.array([_fly(seed, True, shared, FusionConfig(gnss_common_share=share)) for seed in range(20)])
    err_h, nees, sigma_east, nees_frame = runs.T
    assert np.sqrt(np.mean(err_h**2)) < 3.0  # ~1.6 m per axis, both models: weighting alone cannot remove it
    if share:
        assert np.all(sigma_east >= shared[0])
        # 20 runs of a 3-dof chi-square: mean 3, 99 % of such means fall in 1.6-4.6
        assert 1.6 < np.mean(nees) < 4.6
        # the world's own parts (sqrt(0.15) x 1.5 m) averaged over two helpers: ~0.4 m, honest in that frame too
        # (the model's own part, sqrt(0.1) x 1.5 m, is a little smaller than the world's: mean seen 2.9)
        assert 1.6 < np.mean(nees_frame) < 4.6
    else:
        assert np.all(sigma_east < shared[0])
        assert np.mean(nees) > 4.6
        assert np.isnan(nees_frame).all()  # no shared error modelled: no frame of its own



def test_the_shared_error_chain_restarts_after_a_silence():
    """A drone silent for longer than the lag, and a new one whose first fix comes 20 s on, before any update: the
    shared chain starts again there, the silent drone's states carried across the gap (about to be marginalised)
    take its whole error as one chain, and both are estimated again (before: a missing key in the window)."""
    engine = FusionEngine(ORIGIN, lag_s=2.0, config=FusionConfig(gnss_common_share=0.9))
    lat, lon, alt = (float(c) for c in FRAME.to_geodetic(10.0, 0.0, 30.0))

    def report(drone: str, t: float) -> None:
        engine.add_gnss(drone, t, lat, lon, alt, h_sigma_m=1.6, v_sigma_m=2.7)
        engine.add_velocity(drone, t, np.zeros(3), 0.1)

    for i in range(25):
        report("a", 0.2 * i)
    engine.update()
    report("b", 25.0)
    engine.update()
    for i in range(1, 11):
        report("a", 25.0 + 0.2 * i)
        report("b", 25.0 + 0.2 * i)
        engine.update()
    for drone in "ab":
        est = engine.estimate(drone)
        assert np.allclose(est.enu_m, [10.0, 0.0, 30.0], atol=0.1)
        # the stated sigma is the whole receiver error (shared part included): ~1.5 m per horizontal axis
        assert 1.3 < est.sigma_horizontal_m < 1.7
