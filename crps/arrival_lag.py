"""The fusion lag a node needs: as long as its late inputs are late, within bounds.

Peers' camera observations reach a node a frame's pipeline late (exposure, render or capture,
detection and fit, the swarm network): a fraction of a second on an idle companion, seconds on
a loaded one. The fixed-lag smoother refuses an input older than its lag, so a fixed lag chosen
for the idle case throws away every observation once the companion is busy, and the drone
that needs them is left on dead reckoning. :class:`ArrivalLag` keeps the recent arrival delays
(the engine's time when an observation arrives minus its exposure time, s of the swarm's clock)
and proposes a lag that covers a high percentile of them with headroom, never below the
configured lag (the idle case) nor above a cap (the window's cost grows with its length, and
an input that late says little about the present).
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from skyfix import validate
from skyfix.errors import InputError

#: Delays of the last this many seconds (clock) decide: long enough for a percentile over a few
#: dozen observations (2 helpers at 2-4 frames/s), short enough to follow a load that comes and goes.
WINDOW_S = 30.0
#: The delay percentile covered, and the headroom over it: the delays measured over the window
#: trail a load that is still growing, and a refused observation is worth more than the window's
#: few extra steps.
PERCENTILE = 95.0
HEADROOM = 1.25
MIN_SAMPLES = 5        # fewer recent delays than this: no proposal (a percentile of 2 is noise)
MIN_CHANGE_S = 0.5     # a smaller change is not worth re-sizing the window for
SHRINK_AFTER_S = 10.0  # the lag shrinks at most this often (clock s): a load spike tends to come back


class ArrivalLag:
    """Lag proposals (s) between ``lag_s`` and ``max_lag_s`` from observed arrival delays (s)."""

    def __init__(self, lag_s: float, max_lag_s: float) -> None:
        self.min_lag_s = validate.positive_scalar("lag_s", lag_s)
        self.max_lag_s = validate.positive_scalar("max_lag_s", max_lag_s)
        if self.max_lag_s < self.min_lag_s:
            raise InputError(f"max_lag_s ({max_lag_s}) must be >= lag_s ({lag_s})")
        self.lag_s = self.largest_s = self.min_lag_s
        self._delays: deque[tuple[float, float]] = deque()  # (arrival clock s, delay s)
        self._changed_s = -math.inf

    def arrived(self, now_s: float, delay_s: float) -> None:
        """One input arrived at ``now_s``, ``delay_s`` after the time it describes (negative: early, ignored)."""
        if not (math.isfinite(now_s) and math.isfinite(delay_s)) or delay_s < 0.0:
            return
        self._delays.append((now_s, delay_s))
        while self._delays and self._delays[0][0] < now_s - WINDOW_S:
            self._delays.popleft()

    def propose(self, now_s: float) -> float | None:
        """The lag to switch to now, or None to keep ``lag_s`` (also when too few delays were seen)."""
        if len(self._delays) < MIN_SAMPLES or not self.max_lag_s > self.min_lag_s:
            return None
        delays = np.fromiter((d for _, d in self._delays), float, len(self._delays))
        want = float(np.clip(HEADROOM * np.percentile(delays, PERCENTILE), self.min_lag_s, self.max_lag_s))
        growing = want >= self.lag_s + MIN_CHANGE_S
        shrinking = want <= self.lag_s - MIN_CHANGE_S and now_s - self._changed_s >= SHRINK_AFTER_S
        if not (growing or shrinking):
            return None
        self.lag_s, self._changed_s = want, now_s
        self.largest_s = max(self.largest_s, want)
        return want
