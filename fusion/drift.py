"""Windowed test of one drone's GNSS against its own velocity (a GNSS-independent source).

A spoofer that drags the fix slowly (0.5 m/s) stays inside the per-sample innovation
gate: each fix is only a little further off than the last, and the estimate follows.
Its signature is in the *displacement*: over a window of ``window_s`` the fixes move
differently from the velocity integrated over the same window. The residual
``r(t) = z_gnss(t) - odometer(t)`` (horizontal, frame axes; the odometer integrates the
raw velocity, trapezoid) changes between two instants only by the receiver's
Gauss-Markov error change, the velocity bias times the elapsed time, and white noise:

    r(t2) - r(t1) ~ N(-b dt, 2 sigma_gm^2 (1 - exp(-dt/tau)) + P_b dt^2 + q_b dt^3/3 + white)

Medians over ``_EDGE_S`` at both ends keep multipath outliers out. The same relation
against a reference taken before the drift (``hold_reference``) tells, after the spoof,
whether GNSS agrees with the velocity again even where it disagrees with the estimate
the spoof corrupted. The velocity used must itself be independent of GNSS (inertial or
visual odometry, optical flow); an autopilot's fused velocity is GNSS-aided and follows
a coherent spoof.
"""

from __future__ import annotations

import bisect
import math
import statistics

import numpy as np

_EDGE_S = 2.0       # median over this much at each end of the window
_MIN_SAMPLES = 4    # per end
_SHORT_S = 4.0      # window of the "moves with the velocity now" test before re-admission


class GnssDriftTest:
    """Odometer and GNSS residual history of one drone (horizontal, frame axes, metres)."""

    def __init__(self, window_s: float, gm_sigma_m: float, gm_tau_s: float,
                 bias_walk_mps_per_sqrt_s: float, max_gap_s: float) -> None:
        self.window_s = window_s
        self.gm_var = gm_sigma_m**2
        self.gm_tau_s = gm_tau_s
        self.walk_var = bias_walk_mps_per_sqrt_s**2
        self.max_gap_s = max_gap_s
        self._odo_t: list[float] = []          # velocity sample times and the odometer there (E, N)
        self._odo_e: list[float] = []
        self._odo_n: list[float] = []
        self._v_last: tuple[float, float, float] | None = None
        self._r_t: list[float] = []            # fixes in the history: time, residual (E, N), white variance
        self._r: list[tuple[float, float, float]] = []
        self.reference: tuple | None = None  # t, r, its white variance, b, P_b
        self._bias_t: list[float] = []
        self._bias: list[tuple[np.ndarray, np.ndarray]] = []  # (b (2,), P_b (2, 2)) estimates

    def velocity(self, t_s: float, vel_mps: np.ndarray) -> None:
        """A raw velocity sample (frame axes); late samples are ignored, a gap restarts the odometer."""
        ve, vn = float(vel_mps[0]), float(vel_mps[1])
        last = self._v_last
        if last is not None and t_s <= last[0]:
            return
        if last is None or t_s - last[0] > self.max_gap_s:
            self._odo_t, self._odo_e, self._odo_n = [t_s], [0.0], [0.0]
            self.forget()
            self.reference = None
        else:
            dt = t_s - last[0]
            self._odo_t.append(t_s)
            self._odo_e.append(self._odo_e[-1] + 0.5 * (last[1] + ve) * dt)
            self._odo_n.append(self._odo_n[-1] + 0.5 * (last[2] + vn) * dt)
        self._v_last = (t_s, ve, vn)
        _trim(self._odo_t, t_s - 3.0 * self.window_s - 4.0 * _EDGE_S, self._odo_e, self._odo_n)

    def residual(self, t_s: float, enu_m: np.ndarray) -> tuple[float, float] | None:
        """A GNSS fix's horizontal residual against the odometer, or None if the odometer does not cover t."""
        ts = self._odo_t
        if len(ts) < 2 or not ts[0] <= t_s <= ts[-1] + 0.3:
            return None
        i = bisect.bisect_right(ts, t_s) - 1
        if i >= len(ts) - 1:  # just after the newest sample: carry on with its velocity
            dt = t_s - ts[-1]
            e, n = self._odo_e[-1] + self._v_last[1] * dt, self._odo_n[-1] + self._v_last[2] * dt
        else:
            w = (t_s - ts[i]) / (ts[i + 1] - ts[i])
            e = self._odo_e[i] + w * (self._odo_e[i + 1] - self._odo_e[i])
            n = self._odo_n[i] + w * (self._odo_n[i + 1] - self._odo_n[i])
        return float(enu_m[0]) - e, float(enu_m[1]) - n

    def record(self, t_s: float, residual_m: tuple[float, float] | None, white_var_m2: float) -> None:
        """Keep a residual (and the fix's white variance per axis) in the history the tests use
        (only fixes that count as GNSS's own track)."""
        if residual_m is None or (self._r_t and t_s <= self._r_t[-1]):
            return
        self._r_t.append(t_s)
        self._r.append((residual_m[0], residual_m[1], white_var_m2))
        _trim(self._r_t, t_s - 3.0 * self.window_s - 2.0 * _EDGE_S, self._r)

    def bias(self, t_s: float, bias_mps: np.ndarray, bias_cov_m2ps2: np.ndarray) -> None:
        """Record the fused velocity-bias estimate (2,) and its covariance (2, 2) at ``t_s``.

        The tests use the estimate from before their window: a drift under way pulls the
        newest bias estimate along (the estimate then explains the drift away)."""
        if self._bias_t and t_s <= self._bias_t[-1]:
            return
        self._bias_t.append(t_s)
        self._bias.append((np.array(bias_mps[:2], float), np.array(bias_cov_m2ps2[:2, :2], float)))
        _trim(self._bias_t, t_s - 3.0 * self.window_s - 4.0 * _EDGE_S, self._bias)

    def _bias_before(self, t_s: float) -> tuple[np.ndarray, np.ndarray] | None:
        """The newest bias estimate at or before ``t_s``, its covariance grown by the walk since."""
        i = bisect.bisect_right(self._bias_t, t_s) - 1
        if i < 0:
            return None
        b, p = self._bias[i]
        return b, p + np.eye(2) * self.walk_var * (self._bias_t[-1] - self._bias_t[i])

    def forget(self) -> None:
        """Drop the residual history (GNSS was out of use; its old track says nothing now)."""
        self._r_t, self._r = [], []

    def _median(self, t0: float, t1: float) -> tuple[float, np.ndarray, float] | None:
        """Median time, residual and the residual median's white variance over [t0, t1]."""
        i, j = bisect.bisect_left(self._r_t, t0), bisect.bisect_right(self._r_t, t1)
        if j - i < _MIN_SAMPLES:
            return None
        sel = self._r[i:j]
        white = sum(x[2] for x in sel) / len(sel) * (math.pi / 2) / len(sel)  # a median's variance ~ pi/2 x the mean's
        r = np.array([statistics.median(x[0] for x in sel), statistics.median(x[1] for x in sel)])
        return statistics.median(self._r_t[i:j]), r, white

    def _nis(self, dr: np.ndarray, dt: float, b: np.ndarray, p_b: np.ndarray, white_var: float) -> float:
        cov = np.eye(2) * (2.0 * self.gm_var * (1.0 - math.exp(-dt / self.gm_tau_s))
                           + self.walk_var * dt**3 / 3.0 + white_var) + p_b * dt * dt
        innovation = dr + b * dt
        return float(innovation @ np.linalg.solve(cov, innovation))

    def window_nis(self, t_s: float, window_s: float | None = None,
                   bias: tuple[np.ndarray, np.ndarray] | None = None) -> float | None:
        """NIS (2 dof) of the residual's change over the last ``window_s`` (default the test's),
        with the bias estimate from before the window (or ``bias``); None if not covered."""
        window_s = self.window_s if window_s is None else window_s
        late = self._median(t_s - _EDGE_S, t_s)
        early = self._median(t_s - window_s - _EDGE_S, t_s - window_s)
        bias = self._bias_before(t_s - window_s - 2.0 * _EDGE_S) if bias is None else bias
        if late is None or early is None or bias is None:
            return None
        b, p_b = bias
        return self._nis(late[1] - early[1], late[0] - early[0], b, p_b, late[2] + early[2])

    def hold_reference(self, t_s: float) -> bool:
        """Keep the residual and bias from before a detected drift (2 windows back) as the reference."""
        t0 = t_s - 2.0 * self.window_s
        ref = self._median(t0 - _EDGE_S, t0)
        bias = self._bias_before(t0)
        self.reference = None if ref is None or bias is None else (ref[0], ref[1], ref[2], *bias)
        return self.reference is not None

    def agrees_with_reference(self, t_s: float, residual_m: tuple[float, float] | None, white_var_m2: float,
                              chi2_gate: float) -> bool:
        """Does the fix with residual ``residual_m`` agree with the velocity since the reference, and has
        GNSS moved with the velocity over the last few seconds (a drift still under way fails)?"""
        if self.reference is None or residual_m is None:
            return False
        t_ref, r_ref, ref_var, b, p_b = self.reference
        if self._nis(np.asarray(residual_m) - r_ref, t_s - t_ref, b, p_b, ref_var + white_var_m2) > chi2_gate:
            return False
        # the newer bias estimates absorbed part of the drift: use the reference's, grown by the walk
        short = self.window_nis(t_s, _SHORT_S, (b, p_b + np.eye(2) * self.walk_var * (t_s - t_ref)))
        return short is not None and short <= chi2_gate

    def reference_bias(self, t_s: float) -> tuple[np.ndarray, np.ndarray] | None:
        """The horizontal bias (2,) and covariance (2, 2) held with the reference, grown to ``t_s``."""
        if self.reference is None:
            return None
        t_ref, _, _, b, p_b = self.reference
        return b, p_b + np.eye(2) * self.walk_var * max(0.0, t_s - t_ref)


def _trim(times: list[float], before_s: float, *columns: list) -> None:
    """Drop entries older than ``before_s`` (keeping one) from ``times`` and its parallel columns."""
    k = bisect.bisect_left(times, before_s) - 1
    if k > 0:
        del times[:k]
        for col in columns:
            del col[:k]
