"""The three-drone fusion scenario: truth geometry, noise statistics, faults, delivery.

Tolerances come from sample sizes: a sample standard deviation of N normal draws has a
relative standard error of 1/sqrt(2N); checks allow 5 standard errors.
"""

from __future__ import annotations

import inspect
import time

import numpy as np
import pytest

from skyfix.datasets.fusion_scenario import (
    DRONE_IDS,
    FusionEvent,
    feed,
    survey_scenario,
)
from skyfix.errors import InputError
from skyfix.types import RelativeObservation


@pytest.fixture(scope="module")
def scen():
    return survey_scenario(600.0, seed=3)


def _std_ok(sample: np.ndarray, sigma: float) -> bool:
    n = sample.size
    return abs(sample.std() / sigma - 1.0) < 5.0 / np.sqrt(2 * n) and abs(sample.mean()) < 5 * sigma / np.sqrt(n)


def _local_rot(scen, drone_id: str, t_s: np.ndarray) -> np.ndarray:
    """Rotations frame-ENU -> ENU at the drone, one per time (N, 3, 3)."""
    lla = scen.truth_geodetic(drone_id, t_s)
    return np.stack([scen.frame.enu_rotation_at(la, lo).T for la, lo, _ in lla])


def test_truth_velocity_is_the_derivative_of_position(scen):
    t = np.linspace(1.0, 590.0, 2000)
    h = 1e-3
    for d in DRONE_IDS:
        fd = (scen.truth_enu(d, t + h) - scen.truth_enu(d, t - h)) / (2 * h)
        # central differences err by up to h * |jump in acceleration| (3.2 m/s^2) at lane ends
        np.testing.assert_allclose(scen.truth_vel_enu(d, t), fd, atol=4e-3)
        # 10 Hz samples are the exact truth at those times
        np.testing.assert_allclose(scen.truth_enu_m[d][::7], scen.truth_enu(d, scen.truth_t_s[::7]))
    speed = np.linalg.norm(scen.truth_vel_enu_mps["A"][:, :2], axis=1)
    np.testing.assert_allclose(speed, 8.0, atol=1e-9)
    up = scen.truth_enu_m["A"][:, 2]
    assert up.min() >= 60.0 and up.max() <= 100.0
    assert np.abs(scen.truth_vel_enu_mps["A"][:, 2]).max() < 1.0  # gentle climbs


def test_helpers_stay_30_to_80_m_from_a_and_60_deg_apart(scen):
    a = scen.truth_enu_m["A"]
    offs = {d: scen.truth_enu_m[d] - a for d in ("B", "C")}
    for d, off in offs.items():
        r = np.linalg.norm(off, axis=1)
        assert r.min() >= 30.0 and r.max() <= 80.0, d
        assert np.ptp(scen.truth_enu_m[d][:, 2] - a[:, 2]) > 1.0  # different, varying heights
    cos = (offs["B"] * offs["C"]).sum(1) / np.linalg.norm(offs["B"], axis=1) / np.linalg.norm(offs["C"], axis=1)
    assert np.degrees(np.arccos(cos)).min() >= 60.0


def test_gnss_noise_matches_sigmas(scen):
    tab = scen.table("gnss")
    for i, d in enumerate(DRONE_IDS):
        m = (tab.drone == i) & scen.gnss_valid_mask(d, tab.time_s)
        m &= tab.cols["fix_type"] == 3
        t = tab.time_s[m]
        meas = scen.frame.to_enu_points(np.stack([tab.cols[k][m] for k in ("lat_deg", "lon_deg", "alt_m")], 1))
        err = np.einsum("nij,nj->ni", _local_rot(scen, d, t), meas - scen.truth_enu(d, t))
        assert _std_ok(err[:, 0], 1.5) and _std_ok(err[:, 1], 1.5), d
        assert _std_ok(err[:, 2], 2.5), d
        assert set(np.unique(tab.cols["satellites"][m])) <= set(range(10, 15))
        assert tab.cols["hdop"][m].min() >= 0.75 and tab.cols["hdop"][m].max() <= 1.25
        np.testing.assert_allclose(np.diff(t[:50]).min(), 0.2, atol=1e-9)  # 5 Hz


def test_velocity_is_truth_plus_bias_random_walk_plus_white(scen):
    tab = scen.table("velocity")
    nm = scen.noise
    for i, d in enumerate(DRONE_IDS):
        m = tab.drone == i
        t = tab.time_s[m]
        # every 4th sample keeps the per-sample rotations cheap; statistics stay large
        sel = slice(None, None, 4)
        v_local = np.einsum("nij,nj->ni", _local_rot(scen, d, t[sel]), scen.truth_vel_enu(d, t[sel]))
        bias = scen.velocity_bias_mps[d]
        white = tab.cols["vel_enu_mps"][m][sel] - v_local - bias[sel]
        for ax in range(3):
            assert _std_ok(white[:, ax], nm.velocity_sigma_mps), (d, ax)
        steps = np.diff(bias, axis=0)
        assert _std_ok(steps.ravel(), nm.velocity_bias_walk_mps_per_sqrt_s * np.sqrt(0.1))
        assert np.all(tab.cols["sigma_mps"][m] == nm.velocity_sigma_mps)
    # initial biases across many seeds: N(0, 0.1) horizontal, N(0, 0.03) vertical
    b0 = np.array([survey_scenario(5.0, seed=s, outage=None, spoof=None).velocity_bias_mps["A"][0]
                   for s in range(120)])
    assert 0.07 < b0[:, :2].std() < 0.13 and 0.02 < b0[:, 2].std() < 0.04


def test_altitude_noise_is_half_a_metre_on_the_ellipsoidal_height(scen):
    tab = scen.table("altitude")
    for i, d in enumerate(DRONE_IDS):
        m = tab.drone == i
        err = tab.cols["alt_m"][m] - scen.truth_geodetic(d, tab.time_s[m])[:, 2]
        assert _std_ok(err, 0.5), d


def test_relative_observations_geometry_and_noise(scen):
    tab = scen.table("relative")
    assert set(np.unique(tab.drone)) == {1, 2}  # B and C observe A
    c = tab.cols
    assert c["range_true_m"].min() >= 30.0 and c["range_true_m"].max() <= 80.0
    for i, d in ((1, "B"), (2, "C")):
        m = tab.drone == i
        t = tab.time_s[m]
        off_true = scen.truth_enu("A", t) - scen.truth_enu(d, t)
        off_local = np.einsum("nij,nj->ni", _local_rot(scen, d, t), off_true)
        np.testing.assert_allclose(c["range_true_m"][m], np.linalg.norm(off_true, axis=1), rtol=1e-9)
        # the simulator evaluates the axes once per second of flight (<= 8 m away): the axes
        # differ by <= 1.3e-6 rad, i.e. <= 1e-4 m at 80 m
        np.testing.assert_allclose(c["bearing_true_enu"][m] * c["range_true_m"][m][:, None], off_local, atol=2e-4)
        # range noise 3 %, bearing 0.2 deg per perpendicular axis (angle RMS = 0.2 * sqrt(2))
        rel = c["range_m"][m] / c["range_true_m"][m] - 1.0
        assert _std_ok(rel, 0.03)
        ang = np.arccos(np.clip((c["bearing_enu"][m] * c["bearing_true_enu"][m]).sum(1), -1, 1))
        rms_deg = np.degrees(np.sqrt(np.mean(ang**2)))
        assert abs(rms_deg / (0.2 * np.sqrt(2)) - 1.0) < 5.0 / np.sqrt(4 * ang.size)
        # the reported covariance describes the error: mean NEES of a 3-dof normal is 3
        err = c["range_m"][m][:, None] * c["bearing_enu"][m] - off_local
        nees = np.einsum("ni,nij,nj->n", err, np.linalg.inv(c["cov_enu_m2"][m]), err)
        assert abs(nees.mean() - 3.0) < 5 * np.sqrt(6.0 / nees.size)
    ev = next(e for e in scen.events() if e.kind == "relative")
    obs = ev.data["obs"]
    assert isinstance(obs, RelativeObservation) and obs.target_id == "A" and obs.observer_id == ev.drone_id
    assert not obs.has_observer_position  # the observer does not know where it is
    np.testing.assert_allclose(np.linalg.eigvalsh(obs.cov_enu_m2)[-1], (0.03 * obs.range_m) ** 2, rtol=1e-6)


def test_silent_outage_and_spoof_windows():
    s = survey_scenario(500.0, seed=1, outage=("A", 200.0, 120.0), spoof=("B", 420.0, 30.0, 50.0))
    g = s.table("gnss")
    ta = g.time_s[g.drone == 0]
    assert not np.any((ta >= 200.0) & (ta < 320.0))
    assert ta[ta < 200.0].max() > 199.7 and ta[ta >= 320.0].min() < 320.3
    m = g.drone == 1
    t = g.time_s[m]
    meas = s.frame.to_enu_points(np.stack([g.cols[k][m] for k in ("lat_deg", "lon_deg", "alt_m")], 1))
    err = meas - s.truth_enu("B", t)
    win = (t >= 420.0) & (t < 450.0)
    assert np.linalg.norm(s.spoof.offset_enu_m) == pytest.approx(50.0)
    np.testing.assert_allclose(err[win].mean(0)[:2], s.spoof.offset_enu_m[:2], atol=5 * 1.5 / np.sqrt(win.sum()))
    assert np.linalg.norm(err[~win][:, :2], axis=1).max() < 10.0  # 6.7 sigma of 1.5 m per axis
    assert np.all(g.cols["fix_type"][m] == 3) and g.cols["satellites"][m][win].min() >= 10


def test_no_fix_outage_reports_fix_type_1_without_position():
    s = survey_scenario(400.0, seed=2, outage=("A", 100.0, 120.0), outage_mode="no_fix", spoof=None)
    evs = [e for e in s.events() if e.kind == "gnss" and e.drone_id == "A" and 100.0 <= e.time_s < 220.0]
    assert len(evs) == pytest.approx(120 * 5, abs=2)
    for e in evs:
        assert e.data["fix_type"] == 1 and e.data["lat_deg"] == 0.0 and e.data["lon_deg"] == 0.0
        assert e.data["h_sigma_m"] is None and e.data["satellites"] < 4
    good = [e for e in s.events() if e.kind == "gnss" and e.drone_id == "A" and e.time_s >= 220.0]
    assert good and all(e.data["fix_type"] == 3 for e in good)


def test_events_are_ordered_by_arrival_and_some_arrive_late(scen):
    arr = np.array([e.arrival_s for e in scen.events()])
    assert np.all(np.diff(arr) >= 0.0) and arr.size == scen.n_events
    lat = dict(scen.noise.latency_s)
    for kind, frac in (("gnss", 0.02), ("relative", 0.05)):
        tab = scen.table(kind)
        extra = tab.arrival_s - tab.time_s - lat[kind]
        late = extra > 1e-9
        n = late.size
        assert abs(late.mean() - frac) < 5 * np.sqrt(frac * (1 - frac) / n), kind
        assert extra[late].min() >= 0.2 and extra[late].max() <= 1.0
    # late events really overtake: some event arrives after one measured later
    times = np.array([e.time_s for e in scen.events()])
    assert np.any(np.diff(times) < -0.15)


def test_deterministic_from_seed():
    a = survey_scenario(60.0, seed=7, outage=None, spoof=None)
    b = survey_scenario(60.0, seed=7, outage=None, spoof=None)
    c = survey_scenario(60.0, seed=8, outage=None, spoof=None)
    ea, eb, ec = list(a.events()), list(b.events()), list(c.events())
    assert len(ea) == len(eb)
    for x, y in zip(ea, eb, strict=True):
        assert (x.time_s, x.arrival_s, x.kind, x.drone_id) == (y.time_s, y.arrival_s, y.kind, y.drone_id)
    va = a.table("velocity").cols["vel_enu_mps"]
    np.testing.assert_array_equal(va, b.table("velocity").cols["vel_enu_mps"])
    assert not np.allclose(va, c.table("velocity").cols["vel_enu_mps"][: len(va)])
    assert len(ec) > 0


class _Recorder:
    """Records add_* calls; signatures copy skyfix.fusion's documented API so a wrong
    keyword in an event's data fails with TypeError."""

    def __init__(self):
        self.calls = []

    def add_gnss(self, drone_id, time_s, lat_deg, lon_deg, alt_m, *, h_sigma_m=None, v_sigma_m=None,
                 fix_type=3, satellites=None, hdop=None):
        self.calls.append(("gnss", drone_id, time_s, lat_deg))

    def add_velocity(self, drone_id, time_s, vel_enu_mps, sigma_mps):
        self.calls.append(("velocity", drone_id, time_s, np.asarray(vel_enu_mps).shape))

    def add_altitude(self, drone_id, time_s, alt_m, sigma_m):
        self.calls.append(("altitude", drone_id, time_s, alt_m))

    def add_relative(self, obs):
        self.calls.append(("relative", obs.observer_id, obs.time_s, obs.range_m))


def test_feed_calls_the_matching_engine_method(scen):
    rec = _Recorder()
    evs = list(scen.events(0, 400))
    for e in evs:
        feed(rec, e)
    assert [c[:3] for c in rec.calls] == [(e.kind, e.drone_id, e.time_s) for e in evs]
    assert {c[0] for c in rec.calls} == {"gnss", "velocity", "altitude", "relative"}
    with pytest.raises(InputError, match="kind"):
        feed(rec, FusionEvent(0.0, 0.0, "sonar", "A", {}))
    # the real engine's signatures, when it exists, take these keywords
    try:
        from skyfix.fusion import FusionEngine
    except ImportError:
        return
    for kind, name in (("gnss", "add_gnss"), ("velocity", "add_velocity"), ("altitude", "add_altitude")):
        params = inspect.signature(getattr(FusionEngine, name)).parameters
        ev = next(e for e in evs if e.kind == kind)
        assert set(ev.data) <= set(params), (name, set(ev.data) - set(params))


def test_bad_arguments_raise_input_error():
    with pytest.raises(InputError, match="outage window"):
        survey_scenario(100.0, outage=("A", 50.0, 120.0), spoof=None)
    with pytest.raises(InputError, match="outage drone"):
        survey_scenario(100.0, outage=("Z", 10.0, 20.0), spoof=None)
    with pytest.raises(InputError, match="outage_mode"):
        survey_scenario(100.0, outage=("A", 10.0, 20.0), outage_mode="jammed", spoof=None)
    with pytest.raises(InputError, match="duration_s"):
        survey_scenario(float("nan"))
    with pytest.raises(InputError, match="drone_id"):
        survey_scenario(10.0, outage=None, spoof=None).truth_enu("Z", 1.0)


def test_an_hour_generates_in_seconds_and_stays_near_the_origin():
    t0 = time.perf_counter()
    s = survey_scenario(3600.0, seed=0)
    elapsed = time.perf_counter() - t0
    assert elapsed < 20.0  # ~2 s on the 2-core dev machine; generous for shared CI
    assert s.n_events > 300_000
    a = s.truth_enu_m["A"]
    assert np.abs(a[:, :2]).max() < 1000.0  # lanes centred on the origin


def test_the_engine_accepts_every_event_of_a_faulty_run():
    """Compatibility with skyfix.fusion's API: 60 s with a no-fix outage, late messages and
    a spoof are all accepted (no InputError), and the fused positions are near the truth."""
    fusion = pytest.importorskip("skyfix.fusion")
    s = survey_scenario(60.0, seed=4, outage=("A", 20.0, 15.0), outage_mode="no_fix",
                        spoof=("B", 40.0, 5.0, 50.0))
    engine = fusion.FusionEngine(origin=s.origin)
    evs = s.events()
    pending = next(evs)
    for tick in np.arange(1, 601) * 0.1:
        while pending is not None and pending.arrival_s <= tick + 1e-9:
            feed(engine, pending)
            pending = next(evs, None)
        engine.update()
    while pending is not None:  # late messages arriving after the last tick
        feed(engine, pending)
        pending = next(evs, None)
    for d in DRONE_IDS:
        est = engine.estimate(d)
        err_m = np.linalg.norm((est.enu_m - s.truth_enu(d, est.time_s)[0])[:2])
        assert err_m < 3.0, (d, err_m)  # 2 sigma of a single 1.5 m fix; fusion does far better
    engine.close()


def test_correlated_gnss_wanders_with_a_one_minute_correlation_time():
    """Gauss-Markov GNSS (1.5 m, tau 60 s) + 0.3 m white; faults follow their windows."""
    from skyfix.datasets.fusion_scenario import CORRELATED_NOISE, correlated_scenario

    # the process itself is checked in test_gauss_markov.py; here, the scenario's use of it
    s = correlated_scenario(600.0, seed=1)
    tab = s.table("gnss")
    i = DRONE_IDS.index("B")
    m = (tab.drone == i) & s.gnss_valid_mask("B", tab.time_s) & ~tab.cols["outlier"]
    meas = s.frame.to_enu_points(np.stack([tab.cols[k][m] for k in ("lat_deg", "lon_deg", "alt_m")], 1))
    err = meas - s.truth_enu("B", tab.time_s[m])
    # consecutive fixes (0.2 s apart) are nearly the same error: only the 0.3 m white part differs
    d = np.diff(err[:, 0])
    assert _std_ok(d[np.diff(tab.time_s[m]) < 0.21], np.sqrt(2 * 0.3**2 + 2 * 1.5**2 * (1 - np.exp(-0.2 / 60))))
    assert np.allclose(tab.cols["h_sigma_m"][m], np.hypot(0.3, 1.5))
    frac = tab.cols["outlier"].mean()
    assert abs(frac - CORRELATED_NOISE.gnss_outlier_frac) < 5 * np.sqrt(0.02 * 0.98 / tab.cols["outlier"].size)
    drift = next(w for w in s.spoofs if w.drone_id == "C")
    np.testing.assert_allclose(np.linalg.norm(drift.displacement(np.array([drift.start_s + 40.0]))), 20.0)
    assert not drift.displacement(np.array([drift.end_s])).any()
    r = s.table("relative").cols["range_true_m"]
    assert r.min() >= 20.0 and r.max() <= 140.0


def test_mismatch_scenario_common_error_steps_and_heavy_tails():
    """Receivers sharing 70 % of their wandering error's variance, a 2.5 m step each, 10 %
    outliers of 1-8 m. tau 2 s gives ~300 independent samples over 600 s: the standard error
    of a correlation r is (1 - r^2)/sqrt(N) = 0.03, of a 100 s mean 1.5 sqrt(2 tau / 100 s)."""
    from dataclasses import replace

    from skyfix.datasets.fusion_scenario import CORRELATED_NOISE, STEP_TIMES_S, mismatch_scenario

    noise = replace(CORRELATED_NOISE, gnss_gm_tau_s=2.0, gnss_common_frac=0.7, gnss_outlier_frac=0.1,
                    gnss_outlier_min_m=1.0, gnss_outlier_max_m=8.0)
    s = mismatch_scenario(600.0, seed=4, noise=noise, step_m=2.5)
    assert s.spoof is None and s.outage.start_s == 150.0 and s.outage.end_s == 240.0
    tab = s.table("gnss")
    grid = np.arange(250.0, 600.0, 0.2)  # after every step and the outage
    errs = {}
    for i, d in enumerate(DRONE_IDS):
        m = (tab.drone == i) & ~tab.cols["outlier"]
        meas = s.frame.to_enu_points(np.stack([tab.cols[k][m] for k in ("lat_deg", "lon_deg", "alt_m")], 1))
        err = meas - s.truth_enu(d, tab.time_s[m])
        errs[d] = np.stack([np.interp(grid, tab.time_s[m], err[:, j]) for j in range(2)], axis=1)
        step = next(f for f in s.faults if f.drone_id == d)
        assert step.start_s == STEP_TIMES_S[d] and step.end_s == 600.0
        np.testing.assert_allclose(np.linalg.norm(step.offset_enu_m), 2.5)
        before = err[(tab.time_s[m] > step.start_s - 100.0) & (tab.time_s[m] < step.start_s), :2].mean(0)
        after = err[(tab.time_s[m] >= step.start_s) & (tab.time_s[m] < step.start_s + 100.0), :2].mean(0)
        assert np.linalg.norm(after - before - step.offset_enu_m[:2]) < 5 * 1.5 * np.sqrt(2 * 2 * 2.0 / 100.0)
    for a, b in (("A", "B"), ("B", "C")):
        r = np.corrcoef(errs[a][:, 0], errs[b][:, 0])[0, 1]
        assert abs(r - 0.7) < 0.15, (a, b, r)  # 5 standard errors
    out = tab.cols["outlier"]
    assert abs(out.mean() - 0.1) < 5 * np.sqrt(0.1 * 0.9 / out.size)
