"""FusionEngine: accuracy and honesty on straight flights, outages, spoofing, helpers, out-of-order input."""

import dataclasses
import math

import numpy as np
import pytest
from fusion_sim import FRAME, ORIGIN, WHITE_GNSS, Line, fly, gnss_args, velocity_args
from scipy.stats import chi2

from skyfix.errors import InputError, NotAvailableError
from skyfix.fusion import FusionConfig, FusionEngine, HealthState
from skyfix.types import GeoFix

EAST = Line((0.0, 0.0, 80.0), (8.0, 0.0, 0.0))


def test_gnss_and_velocity_track_is_accurate_and_honest():
    rng = np.random.default_rng(1)
    engine = FusionEngine(ORIGIN, config=WHITE_GNSS)
    nees, errs = [], []

    def check(t):
        if t < 10:
            return
        est = engine.estimate("A")
        err = est.enu_m - EAST.at(est.time_s)
        nees.append(err @ np.linalg.solve(est.cov_enu_m2, err))
        errs.append(np.hypot(*err[:2]))

    fly(engine, rng, {"A": EAST}, 60.0, on_tick=check)
    # GNSS sigma 1.5 m at 5 Hz with a 0.1 m/s velocity chain: the fused error is a fraction of GNSS noise
    assert np.sqrt(np.mean(np.square(errs))) < 0.6
    # consistent covariance: 3-dof NEES averages 3; correlated over ~10 s, so +-40 % on 50 s
    assert 1.8 < np.mean(nees) < 4.2
    inside = np.mean((np.array(nees) > chi2.ppf(0.025, 3)) & (np.array(nees) < chi2.ppf(0.975, 3)))
    assert inside > 0.8
    est = engine.estimate("A")
    assert est.sources == ("gnss", "velocity")
    assert np.allclose(est.vel_enu_mps, [8, 0, 0], atol=0.35)
    lat, lon, alt = (float(c) for c in FRAME.to_geodetic(*est.enu_m))
    assert (est.lat_deg, est.lon_deg, est.alt_m) == pytest.approx((lat, lon, alt), abs=1e-9)


def test_velocity_bias_is_estimated_and_dead_reckoning_is_honest():
    """With GNSS gone for 30 s the drone coasts on its velocity minus the bias learnt before."""
    rng = np.random.default_rng(2)
    engine = FusionEngine(ORIGIN, config=WHITE_GNSS)
    bias = {"A": (0.3, -0.2, 0.0)}
    fly(engine, rng, {"A": EAST}, 90.0, bias=bias, gnss_off={"A": lambda t: t >= 60.0})
    est = engine.estimate("A")
    err = est.enu_m - EAST.at(est.time_s)
    # undetected, the bias would put it 0.36 m/s * 30 s = 10.8 m off; learnt to ~0.03 m/s it is ~1 m
    assert np.hypot(*err[:2]) < 3.0
    assert err @ np.linalg.solve(est.cov_enu_m2, err) < chi2.ppf(0.999, 3)
    assert est.health["gnss"].state is HealthState.LOST
    assert "gnss" not in est.sources
    assert est.sigma_horizontal_m > 0.5  # 30 s of coasting is not as good as GNSS


def test_gnss_loss_is_flagged_within_one_second():
    rng = np.random.default_rng(3)
    engine = FusionEngine(ORIGIN, config=WHITE_GNSS)
    seen = {}

    def watch(t):
        if t > 20 and "lost" not in seen and engine.health("A")["gnss"].state is HealthState.LOST:
            seen["lost"] = t

    fly(engine, rng, {"A": EAST}, 25.0, gnss_off={"A": lambda t: t > 20.0}, on_tick=watch)
    # last fix at 20.0 s; the time-out is 0.7 s
    assert 20.0 < seen["lost"] <= 21.0


def test_no_fix_message_marks_gnss_lost_immediately():
    rng = np.random.default_rng(4)
    engine = FusionEngine(ORIGIN, config=WHITE_GNSS)
    fly(engine, rng, {"A": EAST}, 10.0)
    engine.add_gnss("A", 10.05, 0.0, 0.0, 0.0, fix_type=1)
    health = engine.health("A")["gnss"]
    assert health.state is HealthState.LOST and "no fix" in health.reason


def test_spoofed_jump_is_rejected_and_readmitted_when_honest_again():
    rng = np.random.default_rng(5)
    engine = FusionEngine(ORIGIN, config=WHITE_GNSS)
    states, worst = {}, [0.0]

    def watch(t):
        state = engine.health("A")["gnss"].state
        states.setdefault(state, t)
        if t >= 30.0:
            est = engine.estimate("A")
            worst[0] = max(worst[0], float(np.hypot(*(est.enu_m - EAST.at(est.time_s))[:2])))

    fly(engine, rng, {"A": EAST}, 70.0, spoof={"A": lambda t: (50.0, 0.0, 0.0) if 30.0 <= t < 45.0 else (0.0, 0, 0)},
        on_tick=watch)
    assert 30.0 <= states[HealthState.REJECTED] <= 32.0   # two gate failures at 5 Hz: 0.2 s
    assert worst[0] < 2.0                                   # the fused track did not follow the 50 m jump
    health = engine.health("A")["gnss"]
    assert health.state is HealthState.OK                   # honest again from 45 s: re-admitted once
    assert 48.8 <= health.since_s <= 50.2                   # >= 80 % of the last 5 s consistent: ~4 s


@pytest.mark.parametrize("fraction", [0.5, 1.0])
def test_readmit_fraction_of_the_config_sets_when_gnss_is_fused_again(fraction):
    """Honest again from 45 s; the last 5 s of probation hold the spoof's failures until 50 s,
    so the share ``fraction`` of passes is reached at 45 + 5 x fraction s (fixes every 0.2 s)."""
    config = dataclasses.replace(WHITE_GNSS, readmit_fraction=fraction)
    engine = FusionEngine(ORIGIN, config=config)
    fly(engine, np.random.default_rng(5), {"A": EAST}, 60.0,
        spoof={"A": lambda t: (50.0, 0.0, 0.0) if 30.0 <= t < 45.0 else (0.0, 0, 0)})
    health = engine.health("A")["gnss"]
    assert health.state is HealthState.OK
    assert health.since_s == pytest.approx(45.0 + 5.0 * fraction, abs=0.3)


def test_helpers_localise_a_drone_without_gnss():
    rng = np.random.default_rng(6)
    lines = {"A": EAST, "B": Line((-30.0, -40.0, 90.0), (8.0, 0.0, 0.0)), "C": Line((-30.0, 40.0, 70.0), (8.0, 0, 0))}
    engine = FusionEngine(ORIGIN, config=WHITE_GNSS)
    errs, nees = [], []

    def check(t):
        if t > 30:
            est = engine.estimate("A")
            err = est.enu_m - EAST.at(est.time_s)
            errs.append(np.hypot(*err[:2]))
            nees.append(err @ np.linalg.solve(est.cov_enu_m2, err))

    fly(engine, rng, lines, 90.0, bias={"A": (0.2, 0.2, 0.0)}, gnss_off={"A": lambda t: t >= 20.0},
        observers=("B", "C"), target="A", on_tick=check)
    est = engine.estimate("A")
    assert est.health["gnss"].state is HealthState.LOST
    assert {"relative:B", "relative:C"} <= set(est.sources)
    # two helpers 50 m away, 3 % range and 0.2 deg: about 0.2-0.5 m; dead reckoning alone would be ~10 m
    assert np.sqrt(np.mean(np.square(errs))) < 1.0
    assert 1.5 < np.mean(nees) < 5.0


def test_relative_observation_anchors_a_drone_that_never_had_gnss():
    rng = np.random.default_rng(7)
    lines = {"B": Line((-30.0, -40.0, 90.0), (8.0, 0.0, 0.0)), "A": EAST}
    engine = FusionEngine(ORIGIN, config=WHITE_GNSS)
    fly(engine, rng, lines, 30.0, gnss_off={"A": lambda t: True}, observers=("B",), target="A")
    est = engine.estimate("A")
    assert np.linalg.norm((est.enu_m - EAST.at(est.time_s))[:2]) < 2.0
    assert engine.health("A")["relative:B"].state is HealthState.OK


def test_tag_fix_is_fused():
    rng = np.random.default_rng(8)
    engine = FusionEngine(ORIGIN, config=WHITE_GNSS)
    fly(engine, rng, {"A": EAST}, 20.0, gnss_off={"A": lambda t: t > 5.0})
    before = engine.estimate("A").sigma_horizontal_m
    p = EAST.at(20.05)
    lat, lon, alt = (float(c) for c in FRAME.to_geodetic(*p))
    engine.add_fix("A", GeoFix(lat, lon, alt, np.eye(3) * 0.05**2, time_s=20.05, source_id="tags"))
    engine.add_velocity("A", 20.1, **velocity_args(rng, EAST))
    est = engine.estimate("A")
    assert est.sigma_horizontal_m < 0.2 < before
    assert "fix:tags" in est.sources
    assert np.linalg.norm(est.enu_m - EAST.at(est.time_s)) < 0.3


def test_out_of_order_measurements_inside_the_lag_give_the_same_answer():
    """GNSS delivered 0.5 s late lands on the same states as when delivered on time."""
    # no robust re-weighting and no gate: the problem is exactly linear and every input is used
    cfg = FusionConfig(robust_k=1e6, gate_probability=1 - 1e-12, gnss_gm_h_sigma_m=0.05, gnss_gm_v_sigma_m=0.05)
    results = []
    for delay_s in (0.0, 0.5):
        rng = np.random.default_rng(9)
        engine = FusionEngine(ORIGIN, lag_s=2.0, config=cfg)
        late = []
        for i in range(301):
            t = i / 10.0
            engine.add_velocity("A", t, **velocity_args(rng, EAST))
            if i % 2 == 0:
                args = gnss_args(rng, EAST, t)
                if 50 < i < 250 and i % 10 == 0 and delay_s:
                    late.append((t + delay_s, t, args))
                else:
                    engine.add_gnss("A", t, **args)
            for due, t_meas, args in [x for x in late if x[0] <= t + 1e-9]:
                engine.add_gnss("A", t_meas, **args)
                late.remove((due, t_meas, args))
            if i % 5 == 4:
                engine.update()
        results.append((engine.estimate("A", time_s=29.0).enu_m, engine.estimate("A").enu_m))
    # equal to the round-off of solves whose information spans 1e-4 m (velocity) to 3 m (weak walk) sigmas
    assert np.allclose(results[0][0], results[1][0], atol=1e-4)
    assert np.allclose(results[0][1], results[1][1], atol=1e-4)


def test_inputs_older_than_the_lag_are_refused_and_the_engine_goes_on():
    rng = np.random.default_rng(10)
    engine = FusionEngine(ORIGIN, lag_s=2.0, config=WHITE_GNSS)
    fly(engine, rng, {"A": EAST}, 10.0)
    with pytest.raises(InputError, match="older than the fusion lag"):
        engine.add_gnss("A", 5.0, **gnss_args(rng, EAST, 5.0))
    with pytest.raises(InputError, match="ahead of the engine time"):
        engine.add_gnss("A", 1e6, **gnss_args(rng, EAST, 10.0))
    fly(engine, rng, {"A": EAST}, 2.0, t0_s=10.1)
    assert np.linalg.norm(engine.estimate("A").enu_m - EAST.at(12.1)) < 1.5


@pytest.mark.parametrize("call, match", [
    (lambda e: e.add_gnss("A", float("nan"), 47.0, 8.0, 400.0), "time_s must be finite"),
    (lambda e: e.add_gnss("A", 10.2, float("nan"), 8.0, 400.0), "lat_deg"),
    (lambda e: e.add_gnss("A", 10.2, 47.0, 8.0, 400.0, fix_type=9), "fix_type"),
    (lambda e: e.add_gnss("A", 10.2, 47.0, 8.0, 400.0, h_sigma_m=0.0), "h_sigma_m"),
    (lambda e: e.add_velocity("A", 10.2, [1.0, 2.0], 0.1), "shape"),
    (lambda e: e.add_velocity("A", 10.2, [1.0, 2.0, float("inf")], 0.1), "vel_enu_mps"),
    (lambda e: e.add_altitude("A", 10.2, 480.0, -1.0), "sigma_m"),
    (lambda e: e.add_fix("A", GeoFix(47.0, 8.0, 480.0, np.zeros((3, 3)), time_s=10.2)), "positive definite"),
    (lambda e: e.add_fix("A", "here"), "GeoFix"),
    (lambda e: e.add_relative("A"), "RelativeObservation"),
    (lambda e: e.add_gnss("", 10.2, 47.0, 8.0, 400.0), "drone id"),
    (lambda e: e.estimate("Z"), "unknown drone id"),
    (lambda e: e.estimate("A", time_s=1.0), "before drone 'A'"),
])
def test_bad_input_raises_and_the_engine_keeps_running(call, match):
    rng = np.random.default_rng(11)
    engine = FusionEngine(ORIGIN, config=WHITE_GNSS)
    fly(engine, rng, {"A": EAST}, 10.0)
    with pytest.raises(InputError, match=match):
        call(engine)
    fly(engine, rng, {"A": EAST}, 2.0, t0_s=10.1)
    assert np.linalg.norm(engine.estimate("A").enu_m - EAST.at(engine.estimate("A").time_s)) < 1.5


def test_drone_without_a_position_source_is_not_available():
    engine = FusionEngine(ORIGIN, config=WHITE_GNSS)
    engine.add_velocity("A", 0.0, [1.0, 0.0, 0.0], 0.1)
    engine.add_altitude("A", 0.0, 480.0, 0.5)
    with pytest.raises(NotAvailableError, match="no absolute position"):
        engine.estimate("A")


def test_window_stays_bounded():
    rng = np.random.default_rng(12)
    engine = FusionEngine(ORIGIN, lag_s=2.0, config=WHITE_GNSS)
    sizes = []
    fly(engine, rng, {"A": EAST, "B": Line((0.0, 50.0, 80.0), (0.0, 5.0, 0.0))}, 60.0,
        on_tick=lambda t: sizes.append(engine._window.n_factors))
    # 2 s of two drones at 10 Hz: a few hundred factors, the same at 20 s as at 60 s
    assert max(sizes[200:]) <= 1.1 * max(sizes[150:200])
    assert max(sizes) < 400


def test_constructor_checks():
    with pytest.raises(InputError, match="origin"):
        FusionEngine((47.0, 8.0))
    with pytest.raises(InputError, match="lag_s"):
        FusionEngine(ORIGIN, lag_s=0.1)
    with pytest.raises(InputError, match="max_speed_mps"):
        FusionConfig(max_speed_mps=-1.0)
    assert math.isinf(FusionEngine(ORIGIN).now_s)


def test_altitude_is_used_for_a_drone_placed_only_by_helpers():
    rng = np.random.default_rng(13)
    lines = {"B": Line((-30.0, -40.0, 90.0), (8.0, 0.0, 0.0)), "A": EAST}
    engine = FusionEngine(ORIGIN, config=WHITE_GNSS)

    def baro(t):
        alt = float(FRAME.to_geodetic(*EAST.at(t))[2])
        engine.add_altitude("A", t, alt + rng.normal(0.0, 0.3), 0.3)

    fly(engine, rng, lines, 30.0, gnss_off={"A": lambda t: True}, observers=("B",), target="A", on_tick=baro)
    est = engine.estimate("A")
    assert "altitude" in est.sources
    # one helper at 50 m: the barometer, not the 1.5 m range noise, sets the height (0.3 m per sample)
    assert math.sqrt(est.cov_enu_m2[2, 2]) < 0.15
    assert abs(est.enu_m[2] - EAST.at(est.time_s)[2]) < 0.45


def test_a_message_delivered_twice_is_fused_once():
    """The same GNSS fix arriving over two links must not count double (it would halve the variance)."""
    results = []
    for copies in (1, 2):
        rng = np.random.default_rng(14)
        engine = FusionEngine(ORIGIN, config=WHITE_GNSS)
        for i in range(101):
            t = i / 10.0
            engine.add_velocity("A", t, **velocity_args(rng, EAST))
            if i % 2 == 0:
                args = gnss_args(rng, EAST, t)
                for _ in range(copies):
                    engine.add_gnss("A", t, **args)
            engine.update()
        results.append(engine.estimate("A"))
    assert np.array_equal(results[0].enu_m, results[1].enu_m)
    assert np.array_equal(results[0].cov_enu_m2, results[1].cov_enu_m2)
