"""Issue 15: observer trust, evidence-based re-admission, GNSS drift, Gauss-Markov GNSS honesty."""

import numpy as np
import pytest
from fusion_sim import FRAME, ORIGIN, WHITE_GNSS, Line, fly, relative
from scipy.stats import chi2

from skyfix.errors import InputError
from skyfix.fusion import FusionConfig, FusionEngine, HealthState, SourceMonitor
from skyfix.fusion.drift import GnssDriftTest
from skyfix.types import RelativeObservation

EAST = Line((0.0, 0.0, 80.0), (8.0, 0.0, 0.0))
NORTH = Line((0.0, -60.0, 90.0), (8.0, 0.0, 0.0))


def _forged(t_s: float) -> RelativeObservation:
    """An observation by an id nobody registered, with a made-up observer position 30 m off."""
    lat, lon, alt = (float(c) for c in FRAME.to_geodetic(*(EAST.at(t_s) + [30.0, 0.0, 0.0])))
    return RelativeObservation("X", "A", t_s, np.array([0.0, 1.0, 0.0]), 40.0, np.eye(3) * 0.01,
                               observer_lat_deg=lat, observer_lon_deg=lon, observer_alt_m=alt,
                               observer_cov_enu_m2=np.eye(3) * 0.01)


def test_forged_observer_raises_moves_nothing_and_is_counted():
    rng = np.random.default_rng(11)
    engine = FusionEngine(ORIGIN, config=WHITE_GNSS)
    fly(engine, rng, {"A": EAST, "B": NORTH}, 20.0, observers=("B",), target="A")
    before = engine.estimate("A")
    with pytest.raises(InputError, match="unknown observer 'X'"):
        engine.add_relative(_forged(19.95))
    engine.update()
    after = engine.estimate("A")
    assert np.array_equal(before.enu_m, after.enu_m)          # nothing moved, bit for bit
    assert "X" not in engine.drone_ids and engine.unknown_observations == 1
    assert engine.health("A")["relative:unknown"].state is HealthState.REJECTED
    assert "relative:unknown" not in after.sources and "relative:B" in after.sources


def test_roster_limits_observers_and_targets_and_drone_count():
    rng = np.random.default_rng(12)
    cfg = FusionConfig(roster=("A", "B"), max_drones=3, gnss_gm_h_sigma_m=0.05, gnss_gm_v_sigma_m=0.05)
    engine = FusionEngine(ORIGIN, config=cfg)
    fly(engine, rng, {"A": EAST, "B": NORTH, "C": NORTH}, 10.0, observers=("B",), target="A")
    assert "relative:B" in engine.estimate("A").sources       # B is on the roster
    obs_c = relative(rng, "C", "A", NORTH.at(10.0), EAST.at(10.0), 10.0)
    with pytest.raises(InputError, match="unknown observer 'C'"):  # reports its sensors, but not on the roster
        engine.add_relative(obs_c)
    with pytest.raises(InputError, match="not on the roster"):
        engine.add_relative(relative(rng, "B", "C", NORTH.at(10.0), NORTH.at(10.0) + 50.0, 10.0))
    with pytest.raises(InputError, match="max_drones"):          # a fourth id cannot be created
        engine.add_velocity("D", 10.0, np.zeros(3), 0.1)
    with pytest.raises(InputError, match="roster"):
        FusionConfig(roster="AB")


def test_an_observer_not_yet_localised_is_ignored_not_listed():
    """Its message's own position is never used: the target gets no fix from it."""
    engine = FusionEngine(ORIGIN, config=WHITE_GNSS)
    engine.add_velocity("X", 0.0, np.zeros(3), 0.1)               # X reports (so it may observe) but has no fix
    engine.add_velocity("A", 0.0, np.zeros(3), 0.1)
    obs = _forged(0.05)
    engine.add_relative(RelativeObservation("X", "A", 0.05, obs.bearing_unit_enu, obs.range_m, obs.cov_enu_m2,
                                            obs.observer_lat_deg, obs.observer_lon_deg, obs.observer_alt_m,
                                            obs.observer_cov_enu_m2))
    assert "relative:X" not in engine.health("A")
    with pytest.raises(Exception, match="no absolute position"):
        engine.estimate("A")


def test_one_outlier_does_not_restart_the_readmission_clock():
    m = SourceMonitor(timeout_s=0.7, reject_after=2, readmit_after_s=5.0, now_s=0.0)
    m.judge(0.0, False)
    m.judge(0.2, False)
    assert m.state is HealthState.REJECTED
    times = np.round(np.arange(0.4, 5.61, 0.2), 6)
    fused = [m.judge(float(t), bool(abs(t - 3.0) > 1e-9)) for t in times]  # one failure at 3.0 s
    first = float(times[fused.index(True)])
    assert first == pytest.approx(5.4)                   # 5 s after probation began, >= 80 % consistent
    assert m.state is HealthState.OK


def test_drift_window_test_flags_a_slow_drift_not_noise():
    """Residual changes against an odometer: honest fixes pass, a 0.5 m/s drift fails within 12 s."""
    rng = np.random.default_rng(5)
    test = GnssDriftTest(window_s=10.0, gm_sigma_m=1.5, gm_tau_s=60.0, bias_walk_mps_per_sqrt_s=0.01,
                         max_gap_s=1.0)
    gate = chi2.ppf(0.99999, 2)
    nis, t_flag = [], None
    gm = np.zeros(2)
    for k in range(1, 1000):
        t = 0.1 * k
        test.velocity(t, np.array([8.0, 0.0, 0.0]))
        if k % 2:
            continue
        gm = np.exp(-0.2 / 60) * gm + 1.5 * np.sqrt(1 - np.exp(-0.4 / 60)) * rng.normal(0, 1, 2)
        drift = 0.5 * max(0.0, t - 60.0) * np.array([0.6, 0.8])
        z = np.array([8.0 * t, 0.0]) + gm + rng.normal(0, 0.3, 2) + drift
        test.record(t, test.residual(t, z), 0.09)
        test.bias(t, np.zeros(3), np.eye(3) * 0.03**2)
        v = test.window_nis(t)
        if v is not None and t < 60.0:
            nis.append(v)
        if v is not None and t >= 60.0 and v > gate and t_flag is None:
            t_flag = t
    assert np.percentile(nis, 99) < gate                      # honest: chi-square(2) like, far below the gate
    assert 0.5 < np.mean(nis) < 4.0
    assert t_flag is not None and t_flag - 60.0 <= 12.0


@pytest.mark.slow
def test_drift_is_flagged_then_gnss_readmitted_and_estimate_pulled_back():
    """0.5 m/s drift 30-70 s: rejected within 20 s at < 10 m error; honest again after 70 s,
    re-admitted and back under 3 m within 15 s."""
    rng = np.random.default_rng(21)
    engine = FusionEngine(ORIGIN, config=WHITE_GNSS)
    trace = []

    def watch(t):
        if t > 5.0:
            est = engine.estimate("A")
            trace.append((t, est.health["gnss"].state, np.hypot(*(est.enu_m - EAST.at(est.time_s))[:2])))

    drift = {"A": lambda t: (0.3 * (t - 30.0), 0.4 * (t - 30.0), 0.0) if 30.0 <= t < 70.0 else (0.0, 0.0, 0.0)}
    fly(engine, rng, {"A": EAST}, 90.0, spoof=drift, on_tick=watch)
    t, state, err = (np.array(x) for x in zip(*trace, strict=True))
    flagged = t[(t >= 30.0) & (state == HealthState.REJECTED)]
    assert flagged.size and flagged[0] - 30.0 <= 20.0
    assert err[t == flagged[0]][0] <= 10.0
    back = t[(t >= 70.0) & (state == HealthState.OK)]
    assert back.size and back[0] - 70.0 <= 15.0
    assert err[(t >= 85.0)].max() < 3.0


def _ticks(scenario, engine: FusionEngine, n_ticks: int, drop_late: bool = False):
    """Feed ``scenario``'s events by arrival and update ``engine`` every 0.1 s, as benchmarks/fusion.py does; yields
    (tick s, the events fed at it). ``drop_late``: an input the engine refuses as older than its lag is dropped."""
    from skyfix.datasets.fusion_scenario import feed

    evs = scenario.events()
    pending = next(evs)
    for tick in np.round(np.arange(1, n_ticks) * 0.1, 6):
        fed = []
        while pending is not None and pending.arrival_s <= tick + 1e-9:
            try:
                feed(engine, pending)
            except InputError:
                if not drop_late:
                    raise
            fed.append(pending)
            pending = next(evs, None)
        engine.update()
        yield tick, fed


@pytest.mark.slow
def test_gauss_markov_gnss_stated_covariance_covers_the_truth():
    """Correlated GNSS (1.5 m, tau 60 s): consecutive fixes are not independent evidence, and
    the default engine's 3-dof NEES stays in the 95 % band most of the time."""
    from skyfix.datasets.fusion_scenario import correlated_scenario

    s = correlated_scenario(100.0, seed=7, faults=False)
    engine = FusionEngine(s.origin)
    nees = []
    for tick, _ in _ticks(s, engine, 1000):
        if tick > 20.0 and round(tick * 10) % 5 == 0:
            for d in s.drone_ids:
                est = engine.estimate(d)
                e = est.enu_m - s.truth_enu(d, est.time_s)[0]
                nees.append(e @ np.linalg.solve(est.cov_enu_m2, e))
    nees = np.array(nees)
    inside = np.mean((nees >= chi2.ppf(0.025, 3)) & (nees <= chi2.ppf(0.975, 3)))
    # correlated over ~a minute, so 80 s is only a few independent samples: wide bounds
    assert 1.2 < nees.mean() < 6.0 and inside > 0.75


@pytest.mark.slow
def test_velocity_scale_and_heading_states_keep_dead_reckoning_on_a_circle():
    """A velocity 4 % too large and turned by 3 deg (the errors an additive bias cannot hold in
    turns): with the scale/heading states, 30 s without GNSS on a 60 m circle ends within 2 m
    and the states find 4 % and 3 deg; without them the bias model is tens of metres off."""
    import dataclasses

    radius_m, speed_mps, psi, scale = 60.0, 8.0, np.radians(3.0), 0.04
    rot = np.array([[np.cos(psi), -np.sin(psi), 0.0], [np.sin(psi), np.cos(psi), 0.0], [0.0, 0.0, 1.0]])

    def truth(t):
        a = speed_mps / radius_m * t
        return (np.array([radius_m * np.sin(a), -radius_m * np.cos(a), 80.0]),
                np.array([speed_mps * np.cos(a), speed_mps * np.sin(a), 0.0]))

    def fly_circle(on: bool):
        rng = np.random.default_rng(3)
        engine = FusionEngine(ORIGIN, config=dataclasses.replace(WHITE_GNSS, velocity_scale_heading=on))
        for i in range(1101):
            t = i / 10.0
            p, v = truth(t)
            engine.add_velocity("A", t, (1 + scale) * rot @ v + rng.normal(0, 0.05, 3), 0.05)
            if i % 2 == 0 and t < 80.0:
                lat, lon, alt = (float(c) for c in FRAME.to_geodetic(*(p + rng.normal(0, 1, 3) * [1.5, 1.5, 2.5])))
                engine.add_gnss("A", t, lat, lon, alt, h_sigma_m=1.5, v_sigma_m=2.5)
            engine.update()
        est = engine.estimate("A")
        err = np.hypot(*(est.enu_m - truth(est.time_s)[0])[:2])
        drone = engine._drones["A"]
        q = engine._window.value(drone.index, 3, drone.last_k) if on else None
        return err, q

    err_on, q = fly_circle(True)
    err_off, _ = fly_circle(False)
    assert err_on < 2.0 and err_off > 10.0
    assert abs(q[0] - scale) < 0.01 and abs(q[1] - psi) < np.radians(1.0)


@pytest.mark.slow
def test_healthy_gnss_on_a_fast_drone_passes_the_gate_and_is_never_rejected():
    """The correlated scenario's drones fly at 6.5-8 m/s with healthy receivers (2 % multipath outliers of 5-20 m)
    and updates every 0.1 s. A fix is gated against the prediction from the last solved step moved by the velocity:
    from a step newer than the last solve (its initial guess, its predecessor's value) the prediction lagged ~0.25 s
    (2 m along track at 8 m/s), 22 % of fixes failed the 0.999 gate and GNSS was rejected 37 times in 160 s.
    Now the fixes that fail are about the outliers (2 %) and two in a row (a rejection) are rare."""
    from skyfix.datasets.fusion_scenario import correlated_scenario

    s = correlated_scenario(60.0, seed=0, faults=False)
    engine = FusionEngine(s.origin)
    degraded = rejected = fixes = 0
    last = {d: HealthState.OK for d in s.drone_ids}
    for _, fed in _ticks(s, engine, 600):
        fixes += sum(e.kind == "gnss" for e in fed)
        for d in s.drone_ids:
            health = engine.health(d).get("gnss") if d in engine.drone_ids else None
            if health is None:
                continue
            state = health.state
            degraded += state is HealthState.DEGRADED and last[d] is not HealthState.DEGRADED
            rejected += state is HealthState.REJECTED and last[d] is not HealthState.REJECTED
            last[d] = state
    # 2 % outliers plus the gate's own 0.1 %: ~2 % of fixes fail it (a failure is one DEGRADED spell)
    assert degraded <= 0.05 * fixes
    assert rejected <= 1


@pytest.mark.slow
def test_correlated_outage_stays_within_a_metre_in_the_benchmark_scenario():
    """benchmarks/fusion.py's correlated scenario, seed 0 (A's GNSS silent 150-240 s, positioned by B and C's
    cameras and its velocity): A's horizontal outage RMSE was 0.79-0.86 m from 2026-11-25 and 1.95 m from 017c1a8
    (2026-11-29) until the gates stopped predicting from unsolved states: that commit changed which of the lag's
    spurious GNSS rejections happened, and the ones before this outage left A 3.3 m off at its start. The benchmark's
    pooled goal (<= 0.9x the joint EKF) failed for a day without a test noticing. 0.76 m now."""
    from skyfix.datasets.fusion_scenario import correlated_scenario

    s = correlated_scenario(600.0, seed=0)  # the benchmark's run: its draws depend on the length
    engine = FusionEngine(s.origin)
    err = []
    for tick, _ in _ticks(s, engine, 2400, drop_late=True):  # a message later than the lag: dropped, as there
        if 150.0 <= tick < 240.0:
            est = engine.estimate("A")
            err.append(np.linalg.norm((est.enu_m - s.truth_enu("A", est.time_s)[0])[:2]))
    rmse_m = float(np.sqrt(np.mean(np.square(err))))
    assert rmse_m < 1.2, f"outage RMSE {rmse_m:.2f} m"
