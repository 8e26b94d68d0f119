"""GNSS position errors of receivers that share a sky: a part common to the area, a part of their own.

Two receivers tens of metres apart see the same satellites through the same atmosphere, so most
of a standalone fix's error is common to both; that is why differential GNSS works at short
baselines (the code-DGPS rule of thumb loses ~1 m of it per 100 km, CSI Wireless GBX manual).
Per-axis error of receiver ``i`` at time ``t`` (ENU, m):

    e_i(t) = c(t) + o_i(t) + w,   c: common Gauss-Markov (sigma_c, tau_c), shared by every receiver
                                  o_i: the receiver's own Gauss-Markov (sigma_i, tau_i)
                                  w: white noise (sigma_w) per fix

The split, from published budgets (1-sigma, metres of range error):

- AGI's GPS error budget (blogs.agi.com/navigationAccuracy, "GPS Error Budget"): ephemeris 2.0,
  satellite clock 2.0, ionosphere 4.0 (after the broadcast Klobuchar model), troposphere 0.7 (all
  common to nearby receivers) against multipath 1.4 and receiver noise 0.5 (each receiver's own):
  ~92 % of the range-error variance is common. Today's smaller orbit/clock errors change little:
  the residual ionosphere of a single-frequency receiver dominates.
- An airborne antenna sees little multipath: Joerger & Pervan's code-multipath model uses 0.5 m at
  zenith with correlation times of 10-900 s (NAVIGATION, ION; their troposphere error: 900-2700 s).
- Consumer receivers' horizontal error decorrelates in two stages, a bend near one minute and a
  long-term part (D. L. Wilson, "Correlation of errors", Garmin 12XL, 20-day static test).

So the default (:data:`REALISTIC`) keeps issue 15's 1.5 m per axis for ONE receiver and puts
(1.4 m)^2 of its (1.5 m)^2 in the common part (87 %, a little under the budget's 92 %: an
airborne antenna's multipath is not free of its own frame's reflections): ionosphere and
troposphere change over tens of minutes (tau_c = 1800 s, inside Joerger & Pervan's 900-2700 s);
the own part is multipath on a moving vehicle, 0.45 m over 20 s (the lower end of 10-900 s: the
reflection geometry of a flying drone changes in seconds); 0.3 m white is receiver noise. Two
receivers then differ by sqrt(2 (0.45^2 + 0.3^2)) = 0.76 m per axis, ~1.9 m horizontal at 95 %:
what code DGPS over a short baseline reaches with consumer hardware (1-2 m).

:class:`CommonGnssError` is the shared part: a seeded Gauss-Markov track queried by time, so
every receiver of an area can sample it at its own times, in any order, and see the same value.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numpy as np

from skyfix import validate
from skyfix.datasets.gauss_markov import gauss_markov_step
from skyfix.errors import InputError


@dataclass(frozen=True)
class GnssErrorModel:
    """Per-axis error of every receiver of an area (ENU metres, seconds); see the module docs.

    ``common_*``: the part all receivers share (orbit, clock, atmosphere); ``own_*``: each receiver's
    own wandering part (multipath); ``white_sigma_m``: receiver noise per fix.

    Example:
        >>> round(REALISTIC.total_sigma_m, 2), round(REALISTIC.difference_sigma_m, 2)
        (1.5, 0.76)
    """

    common_sigma_m: float = 1.4
    common_tau_s: float = 1800.0
    own_sigma_m: float = 0.45
    own_tau_s: float = 20.0
    white_sigma_m: float = 0.3

    def __post_init__(self) -> None:
        for name in ("common_sigma_m", "own_sigma_m", "white_sigma_m"):
            validate.nonnegative_scalar(f"GnssErrorModel.{name}", getattr(self, name))
        for name in ("common_tau_s", "own_tau_s"):
            validate.positive_scalar(f"GnssErrorModel.{name}", getattr(self, name))

    @property
    def total_sigma_m(self) -> float:
        """One receiver's stationary error, per axis (m)."""
        return math.sqrt(self.common_sigma_m**2 + self.own_sigma_m**2 + self.white_sigma_m**2)

    @property
    def difference_sigma_m(self) -> float:
        """Two receivers' error difference at one time, per axis (m): the common part cancels."""
        return math.sqrt(2.0 * (self.own_sigma_m**2 + self.white_sigma_m**2))


REALISTIC = GnssErrorModel()
#: the stress case: every receiver its own 1.5 m / 60 s error, nothing shared (issue 15's consumer figure)
INDEPENDENT = GnssErrorModel(0.0, 1800.0, 1.5, 60.0, 0.3)
#: a good multi-band receiver under open sky, nothing shared (the simulator's own default receiver)
MILD = GnssErrorModel(0.0, 1800.0, 0.4, 60.0, 0.15)


class CommonGnssError:
    """The error every receiver of one area shares: a seeded Gauss-Markov track (ENU m, per axis).

    ``at(t_s)`` is a function of the seed and ``t_s`` only: the track is drawn on a fixed grid of
    ``step_s`` from ``t = 0`` (first point from the stationary distribution) and interpolated
    linearly between points (at 1 s against 1800 s the interpolation loses < 0.03 % of the
    variance). Thread-safe; times in seconds of the simulation clock, >= 0.

    Example:
        >>> a = CommonGnssError(7, 1.4, 1800.0)
        >>> bool(np.allclose(a.at(12.3), CommonGnssError(7, 1.4, 1800.0).at(12.3)))
        True
    """

    def __init__(self, seed: int, sigma_m: float, tau_s: float, step_s: float = 1.0) -> None:
        self.sigma_m = validate.nonnegative_scalar("sigma_m", sigma_m)
        self.tau_s = validate.positive_scalar("tau_s", tau_s)
        self.step_s = validate.positive_scalar("step_s", step_s)
        self._rng = np.random.default_rng(seed)
        self._track = [self.sigma_m * self._rng.standard_normal(3)]
        self._lock = threading.Lock()

    def at(self, t_s: float) -> np.ndarray:
        """The common error (3,) at simulation time ``t_s`` (s)."""
        t = validate.finite_scalar("t_s", t_s)
        if t < 0:
            raise InputError(f"CommonGnssError.at: t_s must be >= 0, got {t}")
        pos = t / self.step_s
        i = int(pos)
        with self._lock:
            while len(self._track) < i + 2:
                self._track.append(gauss_markov_step(self._rng, self._track[-1], self.step_s, self.sigma_m,
                                                     self.tau_s))
            a, b = self._track[i], self._track[i + 1]
        return a + (pos - i) * (b - a)
