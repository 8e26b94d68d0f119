"""Mean velocity over each grid interval from velocity samples at any rate and phase.

The autopilot reports instantaneous velocity at its own times. Using one sample as the
mean over a state interval is first-order (forward Euler): in a 180-degree turn at
8 m/s it misplaces the drone by dv * dt / 2 = 0.8 m, coherently, and the fused track
then lags GNSS for seconds. Here samples are joined piecewise-linearly and integrated
exactly over [t_j, t_j+1] (trapezoid rule): exact for constant acceleration. An
interval is emitted once a sample at or after its end has arrived (one sample of
delay), never twice. Across a gap longer than ``max_gap_s`` (a telemetry link that dropped for
seconds) the samples on either side are still joined linearly, but each interval's sigma grows so that
the gap's intervals together allow a displacement of ``gap_accel_mps2 * G**2 / 4`` over a gap of G s:
twice the most a drone that changes its velocity at that acceleration can end up from the linear join
(``a G^2 / 8``, the change made in the gap's first half). Skipping them instead left the drone's states
across the gap tied only by the window's weak speed bound: once the link was back, its newest state sat
where the last camera observation had put it, metres behind a drone flying on (the intervals' mean is
what moves it). Gaps longer than ``gap_max_s`` are skipped.
"""

from __future__ import annotations

import bisect
import math

import numpy as np


class IntervalVelocity:
    """Per-drone sample buffer that turns velocity samples into per-interval means."""

    def __init__(self, epoch_s: float, dt_s: float, max_gap_s: float, gap_accel_mps2: float = 2.5,
                 gap_max_s: float = 10.0) -> None:
        self.epoch_s = epoch_s
        self.dt_s = dt_s
        self.max_gap_s = max_gap_s
        self.gap_accel_mps2 = gap_accel_mps2
        self.gap_max_s = gap_max_s
        self._t: list[float] = []
        self._v: list[np.ndarray] = []
        self._sigma: list[np.ndarray] = []
        self.next_interval: int | None = None  # first interval not yet emitted

    def start_at(self, k: int) -> None:
        """Emit intervals from step k on (the drone's first state)."""
        self.next_interval = k

    def add(self, t_s: float, vel_mps: np.ndarray, sigma_mps: np.ndarray) -> list[tuple[int, np.ndarray, np.ndarray]]:
        """Add a sample; return the newly complete intervals as (j, mean velocity (3,) m/s, its sigma (3,) m/s).

        Example (accelerating from 1 to 2.5 m/s: interval 0, [0, 0.2] s, averages 1.5 m/s):
            >>> iv = IntervalVelocity(epoch_s=0.0, dt_s=0.2, max_gap_s=1.0)
            >>> iv.start_at(0)
            >>> iv.add(0.0, np.array([1.0, 0.0, 0.0]), np.full(3, 0.1))
            []
            >>> [(j, mean.round(9).tolist()) for j, mean, _ in iv.add(0.3, np.array([2.5, 0.0, 0.0]), np.full(3, 0.1))]
            [(0, [1.5, 0.0, 0.0])]
        """
        i = bisect.bisect_left(self._t, t_s)
        if i < len(self._t) and self._t[i] == t_s:
            return []  # duplicate time stamp
        self._t.insert(i, t_s)
        self._v.insert(i, vel_mps)
        self._sigma.insert(i, sigma_mps)
        if self.next_interval is None:
            return []
        out = []
        while True:
            j = self.next_interval
            t0 = self.epoch_s + j * self.dt_s
            t1 = t0 + self.dt_s
            if self._t[-1] < t1 - 1e-9:
                break
            if self._t[0] > t0 + 1e-9:  # no sample at or before the interval: start at the first one
                self.next_interval = max(j + 1, int(math.ceil((self._t[0] - self.epoch_s) / self.dt_s - 1e-9)))
                continue
            mean = self._mean(t0, t1)
            if mean is not None:
                out.append((j, *mean))
            self.next_interval = j + 1
        self._trim()
        return out

    def _mean(self, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray] | None:
        t = self._t
        lo = bisect.bisect_right(t, t0 + 1e-9) - 1   # last sample at or before t0
        hi = bisect.bisect_left(t, t1 - 1e-9)        # first sample at or after t1
        knots_t = [t0] + t[lo + 1:hi] + [t1]
        gap_s = max(t[k + 1] - t[k] for k in range(lo, hi))
        if gap_s > self.gap_max_s:
            return None
        values = [self._at(x, lo, hi) for x in knots_t]
        integral = np.zeros(3)
        for a in range(len(knots_t) - 1):
            integral += 0.5 * (values[a] + values[a + 1]) * (knots_t[a + 1] - knots_t[a])
        sigma = np.max(np.array(self._sigma[lo:hi + 1]), axis=0)
        if gap_s > self.max_gap_s:  # N = gap / dt intervals of this sigma sum to a displacement sd of a G^2 / 4
            sigma = np.maximum(sigma, self.gap_accel_mps2 * gap_s**1.5 / (4.0 * math.sqrt(self.dt_s)))
        return integral / (t1 - t0), sigma

    def _at(self, x: float, lo: int, hi: int) -> np.ndarray:
        """Piecewise-linear velocity at time x within samples lo..hi."""
        t = self._t
        k = min(max(bisect.bisect_right(t, x) - 1, lo), hi - 1)
        span = t[k + 1] - t[k]
        w = 0.0 if span <= 0 else (x - t[k]) / span
        return (1.0 - w) * self._v[k] + w * self._v[k + 1]

    def _trim(self) -> None:
        """Drop samples no future interval needs (keep the last one before the next interval)."""
        if self.next_interval is None:
            keep_from = len(self._t) - 64
        else:
            t0 = self.epoch_s + self.next_interval * self.dt_s
            keep_from = bisect.bisect_right(self._t, t0 + 1e-9) - 1
        if keep_from > 0:
            del self._t[:keep_from], self._v[:keep_from], self._sigma[:keep_from]
