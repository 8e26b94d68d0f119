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

import math
from collections import deque

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
        self._odo: deque[tuple[float, np.ndarray]] = deque()   # (t, integral of velocity so far)
        self._v_last: tuple[float, np.ndarray] | None = None
        self._r: deque[tuple[float, np.ndarray, float]] = deque()  # (t, z - odometer, white variance per axis)
        self.reference: tuple | None = None  # t, r, its white variance, b, P_b
        self._bias: deque[tuple[float, np.ndarray, np.ndarray]] = deque()  # (t, b (2,), P_b (2, 2)) estimates

    def velocity(self, t_s: float, vel_mps: np.ndarray) -> None:
        """A raw velocity sample (frame axes); late samples are ignored, a gap restarts the odometer."""
        v = np.asarray(vel_mps[:2], float)
        if self._v_last is not None and t_s <= self._v_last[0]:
            return
        if self._v_last is None or t_s - self._v_last[0] > self.max_gap_s:
            self._odo.clear()
            self._r.clear()
            self.reference = None
            self._odo.append((t_s, np.zeros(2)))
        else:
            t0, v0 = self._v_last
            self._odo.append((t_s, self._odo[-1][1] + 0.5 * (v0 + v) * (t_s - t0)))
        self._v_last = (t_s, v)
        horizon = t_s - 3.0 * self.window_s - 4.0 * _EDGE_S
        while len(self._odo) > 2 and self._odo[1][0] < horizon:
            self._odo.popleft()

    def residual(self, t_s: float, enu_m: np.ndarray) -> np.ndarray | None:
        """A GNSS fix's residual against the odometer (2,), or None if the odometer does not cover t."""
        odo = self._odometer(t_s)
        return None if odo is None else np.asarray(enu_m[:2], float) - odo

    def record(self, t_s: float, r: np.ndarray | None, white_var_m2: float) -> None:
        """Keep a residual (and the fix's white variance per axis) in the history the tests use
        (only fixes that count as GNSS's own track)."""
        if r is None:
            return
        if not self._r or t_s > self._r[-1][0]:
            self._r.append((t_s, r, white_var_m2))
        while self._r and self._r[0][0] < t_s - 3.0 * self.window_s - 2.0 * _EDGE_S:
            self._r.popleft()

    def bias(self, t_s: float, b: np.ndarray, p_b: np.ndarray) -> None:
        """Record the fused velocity-bias estimate (2,) and its covariance (2, 2) at ``t_s``.

        The tests use the estimate from before their window: a drift under way pulls the
        newest bias estimate along (the estimate then explains the drift away)."""
        if not self._bias or t_s > self._bias[-1][0]:
            self._bias.append((t_s, np.array(b[:2], float), np.array(p_b[:2, :2], float)))
        while len(self._bias) > 1 and self._bias[1][0] < t_s - 3.0 * self.window_s - 4.0 * _EDGE_S:
            self._bias.popleft()

    def _bias_before(self, t_s: float) -> tuple[np.ndarray, np.ndarray] | None:
        """The newest bias estimate at or before ``t_s``, its covariance grown by the walk since."""
        old = [(t, b, p) for t, b, p in self._bias if t <= t_s]
        if not old:
            return None
        t, b, p = old[-1]
        return b, p + np.eye(2) * self.walk_var * (self._bias[-1][0] - t)

    def forget(self) -> None:
        """Drop the residual history (GNSS was out of use; its old track says nothing now)."""
        self._r.clear()

    def _odometer(self, t_s: float) -> np.ndarray | None:
        if len(self._odo) < 2 or not self._odo[0][0] <= t_s <= self._odo[-1][0] + 0.2:
            return None
        ts = np.array([o[0] for o in self._odo])
        ps = np.array([o[1] for o in self._odo])
        return np.array([np.interp(t_s, ts, ps[:, 0]), np.interp(t_s, ts, ps[:, 1])])

    def _median(self, t0: float, t1: float) -> tuple[float, np.ndarray, float] | None:
        """Median time, residual and the residual median's white variance over [t0, t1]."""
        sel = [x for x in self._r if t0 <= x[0] <= t1]
        if len(sel) < _MIN_SAMPLES:
            return None
        white = np.mean([w for *_, w in sel]) * (np.pi / 2) / len(sel)  # a median's variance ~ pi/2 x the mean's
        return float(np.median([x[0] for x in sel])), np.median(np.array([x[1] for x in sel]), axis=0), float(white)

    def _nis(self, dr: np.ndarray, dt: float, b: np.ndarray, p_b: np.ndarray, white_var: float) -> float:
        cov = np.eye(2) * (2.0 * self.gm_var * (1.0 - math.exp(-dt / self.gm_tau_s))
                           + self.walk_var * dt**3 / 3.0 + white_var) + p_b * dt * dt
        innovation = dr + b * dt
        return float(innovation @ np.linalg.solve(cov, innovation))

    def window_nis(self, t_s: float, window_s: float | None = None) -> float | None:
        """NIS (2 dof) of the residual's change over the last ``window_s`` (default the test's),
        with the bias estimate from before the window; None if not covered."""
        window_s = self.window_s if window_s is None else window_s
        late = self._median(t_s - _EDGE_S, t_s)
        early = self._median(t_s - window_s - _EDGE_S, t_s - window_s)
        bias = self._bias_before(t_s - window_s - 2.0 * _EDGE_S)
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

    def agrees_with_reference(self, t_s: float, r: np.ndarray | None, white_var_m2: float, chi2_gate: float) -> bool:
        """Does the fix with residual ``r`` agree with the velocity since the reference, and has
        GNSS moved with the velocity over the last few seconds (a drift still under way fails)?"""
        if self.reference is None or r is None:
            return False
        t_ref, r_ref, ref_var, b, p_b = self.reference
        if self._nis(r - r_ref, t_s - t_ref, b, p_b, ref_var + white_var_m2) > chi2_gate:
            return False
        short = self.window_nis(t_s, _SHORT_S)
        return short is not None and short <= chi2_gate
