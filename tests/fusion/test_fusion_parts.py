"""Building blocks: interval velocity integration, the source-health state machine, the window's guard."""

import numpy as np
import pytest

from skyfix.errors import EstimationError
from skyfix.fusion.health import HealthState, SourceMonitor
from skyfix.fusion.velocity import IntervalVelocity
from skyfix.fusion.window import GraphWindow


def test_interval_velocity_is_exact_for_constant_acceleration_at_any_phase():
    accel = np.array([2.0, -1.0, 0.5])
    iv = IntervalVelocity(epoch_s=0.0, dt_s=0.1, max_gap_s=1.0)
    iv.start_at(0)
    out = []
    for t in np.arange(0.037, 2.0, 0.07):  # 14.3 Hz samples, unrelated phase
        out += iv.add(float(t), accel * t, np.full(3, 0.1))
    js = [j for j, _, _ in out]
    assert js == list(range(1, len(js) + 1))  # the first interval has no sample before it
    for j, mean, _ in out:
        assert np.allclose(mean, accel * (j + 0.5) * 0.1, atol=1e-12)  # mean of a linear ramp: the midpoint


def test_interval_velocity_waits_for_the_interval_end_bridges_gaps_and_skips_long_ones():
    iv = IntervalVelocity(epoch_s=0.0, dt_s=0.1, max_gap_s=0.5, gap_accel_mps2=2.0, gap_max_s=3.0)
    iv.start_at(0)
    v = np.ones(3)
    assert iv.add(0.0, v, 0.1 * v) == []
    assert [j for j, _, _ in iv.add(0.1, v, 0.1 * v)] == [0]
    assert [j for j, _, _ in iv.add(0.2, v, 0.1 * v)] == [1]
    assert iv.add(0.2, v, 0.1 * v) == []                       # duplicate stamp
    # a 0.8 s gap, 1 -> 3 m/s: intervals 2-9 on the line between the samples, each with the sigma that makes
    # the eight together allow a G^2 / 4 displacement (2 * 0.64 / 4 = 0.32 m, twice the a G^2 / 8 worst case)
    out = iv.add(1.0, 3 * v, 0.1 * v)
    assert [j for j, _, _ in out] == list(range(2, 10))
    for j, mean, sigma in out:
        assert np.allclose(mean, 1.0 + 2.0 * ((j + 0.5) * 0.1 - 0.2) / 0.8)
        assert np.allclose(sigma * 0.1 * np.sqrt(8), 2.0 * 0.8**2 / 4)
    assert [(j, s.max()) for j, _, s in iv.add(1.1, 3 * v, 0.1 * v)] == [(10, 0.1)]   # past the gap: its own sigma
    assert [j for j, _, _ in iv.add(4.2, v, 0.1 * v)] == []    # 3.1 s: longer than gap_max_s, skipped
    assert [j for j, _, _ in iv.add(4.3, v, 0.1 * v)] == [42]


def test_monitor_rejects_after_consecutive_failures_and_readmits_after_a_consistent_spell():
    m = SourceMonitor(timeout_s=0.7, reject_after=2, readmit_after_s=5.0, now_s=0.0)
    assert m.judge(0.2, True)
    assert not m.judge(0.4, False) and m.state is HealthState.DEGRADED
    assert not m.judge(0.6, False) and m.state is HealthState.REJECTED
    assert not m.judge(0.8, True) and m.state is HealthState.REJECTED   # probation starts
    assert not m.judge(5.7, True)
    assert m.judge(5.8, True) and m.state is HealthState.OK              # 5 s consistent
    assert m.health.since_s == 5.8


def test_monitor_times_out_and_needs_probation_after_loss():
    m = SourceMonitor(timeout_s=0.7, reject_after=2, readmit_after_s=5.0, now_s=0.0)
    m.tick(0.69)
    assert m.state is HealthState.OK
    m.tick(0.71)
    assert m.state is HealthState.LOST and m.health.since_s == pytest.approx(0.7)
    assert not m.judge(3.0, True) and m.state is HealthState.LOST
    assert not m.judge(4.0, False) and m.state is HealthState.REJECTED   # back, but inconsistent
    assert m.judge(9.0, True) is False and m.judge(14.0, True) is True
    m.no_fix(15.0, "fix type 1")
    assert m.state is HealthState.LOST and m.health.reason == "fix type 1"


def test_window_refuses_a_variable_without_any_factor():
    w = GraphWindow(lag_s=2.0, dt_s=0.1, epoch_s=0.0, max_iterations=1, robust_k=2.8)
    w.new_state(0, 5, np.zeros(3), np.zeros(3))
    with pytest.raises(EstimationError, match="without any factor"):
        w.update([])


def test_window_marginalises_into_an_exact_prior():
    """A chain of position priors and odometry: the windowed answer equals the full batch answer."""
    rng = np.random.default_rng(0)
    w = GraphWindow(lag_s=0.5, dt_s=0.1, epoch_s=0.0, max_iterations=1, robust_k=1e6)
    z = rng.normal(0, 1, (40, 3))
    info, rhs = np.zeros((120, 120)), np.zeros(120)     # the same problem as dense least squares
    for k in range(40):
        w.new_state(0, k, np.zeros(3), np.zeros(3))
        if k == 0:
            w.prior_bias(0, 0, 1.0)
        else:
            w.motion(0, k - 1, 0.5, 0.01)
            i, j = 3 * (k - 1), 3 * k
            blk = np.eye(3) / 0.25
            info[i:i + 3, i:i + 3] += blk
            info[j:j + 3, j:j + 3] += blk
            info[i:i + 3, j:j + 3] -= blk
            info[j:j + 3, i:i + 3] -= blk
        w.position(0, k, z[k], np.eye(3))
        info[3 * k:3 * k + 3, 3 * k:3 * k + 3] += np.eye(3)
        rhs[3 * k:3 * k + 3] += z[k]
        w.update([w.key(0, 0, k), w.key(0, 1, k)])
    batch = np.linalg.solve(info, rhs)
    assert np.allclose(w.value(0, 0, 39), batch[-3:], atol=1e-9)
    assert np.allclose(w.covariance(0, 0, 39), np.linalg.inv(info)[-3:, -3:], atol=1e-9)
    assert w.n_factors < 40  # the window holds ~0.5 s, not the whole history


def test_monitor_reports_a_rate_drop():
    m = SourceMonitor(timeout_s=5.0, reject_after=2, readmit_after_s=5.0, now_s=0.0)
    issues = [m.rate_issue(0.2 * i) for i in range(1, 21)]          # 5 Hz
    assert not any(issues)
    issues = [m.rate_issue(4.0 + 0.5 * i) for i in range(1, 11)]    # 2 Hz
    assert issues[-1] == "rate 2.0 Hz (usually 5.0 Hz)"
    assert m.rate_issue(1.0) is None                               # a late message says nothing


def test_gate_quantiles_are_scipy_chi2_quantiles():
    """The gates use scipy.special (cheaper to load) and must equal scipy.stats.chi2.ppf exactly."""
    from scipy.stats import chi2

    from skyfix.fusion import FusionConfig

    cfg = FusionConfig()
    for dof in (1, 2, 3):
        assert cfg.gate_chi2(dof) == chi2.ppf(cfg.gate_probability, dof)
        for p in (0.95, cfg.drift_gate_probability):
            assert cfg.gate_chi2(dof, p) == chi2.ppf(p, dof)
    assert abs(cfg.gate_chi2(3) - 16.266) < 1e-3  # the table value of chi2(3) at 99.9 %
