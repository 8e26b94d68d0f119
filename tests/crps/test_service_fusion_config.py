"""crps.service.fusion_config: a helper whose camera observations reach the node late (inside the
fusion lag) keeps counting as a live, contributing source; with the engine's 2 s defaults the same
stream is called silent between frames and goes on probation."""

import numpy as np
import pytest
from helpnet import ALT0, LAT0, LON0

from skyfix.crps.service import fusion_config
from skyfix.fusion.config import FusionConfig
from skyfix.fusion.engine import FusionEngine
from skyfix.fusion.health import HealthState
from skyfix.geo import LocalFrame
from skyfix.types import RelativeObservation

FRAME = LocalFrame(LAT0, LON0, ALT0)
TARGET = np.array([0.0, 0.0, 50.0])
HELPER = np.array([30.0, 0.0, 45.0])
LATE_S = 2.6     # exposure -> requester's fusion: a loaded camera pipeline at speed 2
FRAME_DT_S = 0.8  # one observation per helper frame
LAG_S = 3.0


def _fly(config: FusionConfig) -> list[tuple[HealthState, bool]]:
    """Target 'a' loses GNSS at 4 s; helper 'h' observes it from then on, each observation LATE_S late.
    Per 0.2 s after 10 s: the relative source's state and whether the estimate rests on it."""
    rng = np.random.default_rng(3)
    eng = FusionEngine((LAT0, LON0, ALT0), lag_s=LAG_S, config=config)
    out, t_obs_next = [], 4.0
    for t in np.arange(0.0, 17.0, 0.2):
        t = round(float(t), 6)
        for d, p in (("a", TARGET), ("h", HELPER)):
            eng.add_velocity(d, t, rng.normal(0, 0.05, 3), 0.1)
            lat, lon, alt = FRAME.to_geodetic(*(p + rng.normal(0, 0.3, 3)))
            eng.add_gnss(d, t, float(lat), float(lon), float(alt), h_sigma_m=0.5, v_sigma_m=0.8,
                         fix_type=0 if d == "a" and t >= 4.0 else 3)
        while t_obs_next + LATE_S <= t + 1e-9:  # delivered now, exposed LATE_S ago
            los = TARGET - HELPER
            r = float(np.linalg.norm(los))
            cov = np.eye(3) * (2e-3 * r) ** 2 + np.outer(los, los) / r**2 * (0.02 * r) ** 2
            lat, lon, alt = FRAME.to_geodetic(*HELPER)
            eng.add_relative(RelativeObservation("h", "a", t_obs_next, los / r, r * (1 + rng.normal(0, 0.02)),
                                                 cov, float(lat), float(lon), float(alt)))
            t_obs_next = round(t_obs_next + FRAME_DT_S, 6)
        eng.update()
        if t >= 10.0:
            state = eng.health("a")["relative:h"].state
            out.append((state, "relative:h" in eng.estimate("a").sources))
    return out


def test_late_observations_inside_the_lag_keep_the_helper_live_and_contributing():
    cfg = fusion_config(("a", "h"), LAG_S)
    base = FusionConfig()
    assert cfg.relative_timeout_s == pytest.approx(LAG_S + base.relative_timeout_s)
    assert cfg.contributing_window_s == pytest.approx(LAG_S + base.contributing_window_s)
    assert cfg.roster == ("a", "h") and fusion_config(None, 1.0).roster == ()
    tuned = _fly(cfg)
    assert all(state is HealthState.OK and used for state, used in tuned)
    # the engine's defaults (2 s) call the same stream silent: not fused while on probation
    default = _fly(FusionConfig(roster=("a", "h")))
    assert sum(state is not HealthState.OK or not used for state, used in default) > len(default) // 2


def _fly_echo(echo_sigma_mps: float | None, seed: int = 5) -> tuple[float, float]:
    """Drone 'a' loses GNSS at 6 s and flies on the injected fix; from 10 s it drifts west at 2 m/s while its
    EKF velocity, echoing the injected fix, still says ~0. Helpers 'h' and 'g' (fixes at 2 Hz, velocities at
    5 Hz, as Service feeds them) see it every 0.8 s, each observation 1.6 s late. Returns the largest
    horizontal error from 15 s on (once observations of the drift have arrived; m) and over the stated sigma."""
    from skyfix.crps.node import Node
    from skyfix.drivers.state import GnssFix, VehicleState, Velocity
    from skyfix.types import GeoFix

    rng = np.random.default_rng(seed)
    helpers = {"h": HELPER, "g": np.array([-30.0, 0.0, 45.0])}
    node = Node("a", (LAT0, LON0, ALT0), lag_s=LAG_S, config=fusion_config(("a", "h", "g"), LAG_S))

    def where(t):
        return TARGET + np.array([-2.0, 0.0, 0.0]) * max(0.0, t - 10.0)

    worst_m = worst_over_sigma = 0.0
    t_obs = 6.0
    for k in range(int(25.0 / 0.2)):
        t = round(0.2 * k, 6)
        lat, lon, alt = FRAME.to_geodetic(*(where(t) + rng.normal(0, 0.3, 3)))
        gps = GnssFix(fix_type=3 if t < 6 else 1, satellites=12, h_acc_m=0.5, v_acc_m=0.8, hdop=0.9, vdop=1.2,
                        lat_deg=float(lat), lon_deg=float(lon), alt_amsl_m=float(alt), alt_ellipsoid_m=float(alt),
                        alt_ellipsoid_source="autopilot", time_s=t)
        v = rng.normal(0, 0.05, 3)
        node.add_telemetry("a", VehicleState(1, velocity=Velocity(v[1], v[0], -v[2], t), gps=gps), lambda m: m.time_s,
                           velocity_sigma_mps=echo_sigma_mps if t >= 6 else None)
        for h, p in helpers.items():
            fix = None
            if k % 5 in (0, 2):
                lat, lon, alt = FRAME.to_geodetic(*(p + rng.normal(0, 0.2, 3)))
                fix = GeoFix(float(lat), float(lon), float(alt), np.eye(3) * 1.5**2, t, f"peer:{h}")
            node.add_peer(h, t, rng.normal(0, 0.05, 3), fix)
        while t_obs + 1.6 <= t + 1e-9:
            for h, p in helpers.items():
                los = where(t_obs) - p
                r = float(np.linalg.norm(los))
                cov = np.eye(3) * (3e-3 * r) ** 2 + np.outer(los, los) / r**2 * (0.02 * r) ** 2
                seen = los + rng.multivariate_normal(np.zeros(3), cov, method="cholesky")
                lat, lon, alt = FRAME.to_geodetic(*p)
                node.add_relative(RelativeObservation(h, "a", t_obs, seen / np.linalg.norm(seen),
                                                      float(np.linalg.norm(seen)), cov, float(lat), float(lon),
                                                      float(alt)))
            t_obs = round(t_obs + 0.8, 6)
        node.update(("a",))
        fix = node.fix("a", t)
        if t >= 15.0:
            e, n, _ = FRAME.to_enu(fix.lat_deg, fix.lon_deg, fix.alt_m)
            err_m = float(np.hypot(e - where(t)[0], n - where(t)[1]))
            worst_m, worst_over_sigma = max(worst_m, err_m), max(worst_over_sigma, err_m / fix.sigma_horizontal_m)
    node.close()
    return worst_m, worst_over_sigma


def test_velocity_of_an_autopilot_flying_on_the_injected_fix_is_a_wandering_echo_the_helpers_measure():
    """While the autopilot flies on skyfix's injected fix its velocity echoes that fix: fused as a fast-walking
    bias, the helpers' observations correct it and the fix stays near the truth, within its stated sigma;
    taken as the EKF's usual velocity, the drift it does not report is believed away.

    Five noise draws, not one: the worst error of one flight depends on its draw (seeds 0-9: 1.35-3.31 m at
    0.47-1.13 sigma; believed away 4.3-5.9 m at 4.3-5.9 sigma), and a single seed's 1.2 m bound failed on
    another CPU, whose LAPACK drew other noise from the same seed (now Cholesky: the same draw everywhere).
    Bound per flight: under the 4.8 m the drone drifts (2 m/s) while an observation is 1.6 s in flight and
    the next is 0.8 s away, i.e. the fix follows the drift rather than waiting for it."""
    from skyfix.crps.node import ECHO_VELOCITY_SIGMA_MPS

    echo = np.array([_fly_echo(ECHO_VELOCITY_SIGMA_MPS, seed) for seed in range(5)])
    naive = np.array([_fly_echo(None, seed) for seed in range(5)])
    assert np.all(echo[:, 0] < 4.0) and np.all(echo[:, 1] < 2.5), echo  # seen 1.60-3.31 m, <= 1.13 sigma
    assert np.median(naive[:, 0]) > 2.0 * np.median(echo[:, 0]), (naive, echo)  # seen 5.40 vs 2.10 m
    assert np.all(naive[:, 1] > 2.5), naive  # seen 4.3-5.9 sigma


def test_fix_moved_on_a_held_velocity_states_what_braking_could_change():
    """Node.fix moves the newest estimate to the present with its velocity. A drone flying east at 5 m/s whose
    inputs stop (a MAVLink drop) and that brakes to a stop at ArduPilot's 2.5 m/s^2 is 5 m short of the held
    velocity's answer 2 s later: the fix's sigma must say so (the acceleration term, 0.5 a t^2 = 5 m)."""
    from skyfix.crps.node import EXTRAPOLATION_ACCEL_MPS2, Node
    from skyfix.drivers.state import GnssFix, VehicleState, Velocity

    rng = np.random.default_rng(9)
    node = Node("a", (LAT0, LON0, ALT0), lag_s=LAG_S, config=fusion_config(("a",), LAG_S))
    vel = np.array([5.0, 0.0, 0.0])
    for k in range(50):  # 10 s of GNSS and velocity at 5 Hz
        t = round(0.2 * k, 6)
        lat, lon, alt = FRAME.to_geodetic(*(TARGET + vel * t + rng.normal(0, 0.3, 3)))
        gps = GnssFix(fix_type=3, satellites=12, h_acc_m=0.5, v_acc_m=0.8, hdop=0.9, vdop=1.2, lat_deg=float(lat),
                      lon_deg=float(lon), alt_amsl_m=float(alt), alt_ellipsoid_m=float(alt),
                      alt_ellipsoid_source="autopilot", time_s=t)
        node.add_telemetry("a", VehicleState(1, velocity=Velocity(vel[1], vel[0], -vel[2], t), gps=gps),
                           lambda m: m.time_s)
        node.update(("a",))
    t_last = node.latest["a"].time_s
    now = t_last + 2.0
    fix = node.fix("a", now)
    e, n, _ = FRAME.to_enu(fix.lat_deg, fix.lon_deg, fix.alt_m)
    held_e_m = TARGET[0] + vel[0] * now
    assert float(e) == pytest.approx(held_e_m, abs=1.5)  # moved on with the fused velocity
    braked_e_m = TARGET[0] + vel[0] * t_last + 0.5 * vel[0] ** 2 / EXTRAPOLATION_ACCEL_MPS2  # stopped in 2 s
    assert abs(float(e) - braked_e_m) == pytest.approx(5.0, abs=1.5)
    assert fix.sigma_horizontal_m >= 0.5 * EXTRAPOLATION_ACCEL_MPS2 * 2.0**2  # that 5 m is within 1 sigma
    # at the estimate's own time: the estimate's own covariance, nothing added
    assert np.allclose(node.fix("a", t_last).cov_enu_m2, node.latest["a"].cov_enu_m2)
    assert fix.sigma_horizontal_m > node.latest["a"].sigma_horizontal_m + 3.0
    # in the swarm's GNSS frame (the node fuses the receivers' shared error): the same growth on a covariance
    # without that error, which a lone drone's own receiver cannot tell from its position
    est = node.latest["a"]
    assert est.cov_frame_enu_m2 is not None and est.sigma_frame_horizontal_m < est.sigma_horizontal_m
    assert np.allclose(node.fix("a", t_last, frame=True).cov_enu_m2, est.cov_frame_enu_m2)
    assert np.allclose(node.fix("a", now, frame=True).cov_enu_m2 - est.cov_frame_enu_m2,
                       fix.cov_enu_m2 - est.cov_enu_m2)
    node.close()
