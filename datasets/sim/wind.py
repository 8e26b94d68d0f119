"""Wind for the simulator: constant mean, gusts and an optional spatial map (ENU, m/s)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import RegularGridInterpolator

from skyfix import validate
from skyfix.datasets.gauss_markov import gauss_markov_step
from skyfix.errors import InputError


@dataclass
class WindField:
    """Wind velocity (air moving towards) in world ENU axes, m/s.

    ``mean_enu_mps`` (3,) constant part; ``gust_sigma_mps`` standard deviation of a
    first-order Gauss-Markov gust per horizontal axis (0.3 of it vertically) with
    correlation time ``gust_tau_s``;
    ``grid`` an optional spatial map ``(east_m (Nx,), north_m (Ny,), wind_en_mps (Ny, Nx, 2))``
    added to the mean, bilinear inside the grid and clamped to its edge outside.
    """

    mean_enu_mps: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gust_sigma_mps: float = 0.0
    gust_tau_s: float = 3.0
    grid: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    seed: int = 0
    _gust: np.ndarray = field(init=False, repr=False)
    _rng: np.random.Generator = field(init=False, repr=False)
    _interp: RegularGridInterpolator | None = field(init=False, repr=False, default=None)

    def __post_init__(self) -> None:
        mean = validate.finite_array("WindField.mean_enu_mps", self.mean_enu_mps)
        if mean.shape != (3,):
            raise InputError(f"WindField.mean_enu_mps must have shape (3,), got {mean.shape}")
        self.mean_enu_mps = tuple(mean)
        validate.nonnegative_scalar("WindField.gust_sigma_mps", self.gust_sigma_mps)
        validate.positive_scalar("WindField.gust_tau_s", self.gust_tau_s)
        self._rng = np.random.default_rng(self.seed)
        self._gust = np.zeros(3)
        if self.grid is not None:
            east, north, wind = (validate.finite_array(f"WindField.grid[{i}]", g)
                                 for i, g in enumerate(self.grid))
            if wind.shape != (north.size, east.size, 2):
                raise InputError("WindField.grid wind_en_mps must have shape (Ny, Nx, 2) "
                                 f"= ({north.size}, {east.size}, 2), got {wind.shape}")
            self._interp = RegularGridInterpolator((north, east), wind, bounds_error=False,
                                                   fill_value=None)
            self._east_range = (east.min(), east.max())
            self._north_range = (north.min(), north.max())

    def step(self, dt_s: float) -> None:
        """Advance the gust process by ``dt_s`` seconds (exact discretisation)."""
        if self.gust_sigma_mps <= 0.0:
            return
        self._gust = gauss_markov_step(self._rng, self._gust, dt_s, self._gust_sigma_enu_mps(), self.gust_tau_s)

    def _gust_sigma_enu_mps(self) -> np.ndarray:
        # vertical gusts are weaker near the ground: 0.3 of the horizontal sigma (until issue 22
        # the vertical state was scaled by 0.3 every step, which made it near-white and ~0.03 sigma)
        return self.gust_sigma_mps * np.array([1.0, 1.0, 0.3])

    def at(self, pos_enu_m: np.ndarray) -> np.ndarray:
        """Wind (3,) m/s at a world ENU position (3,)."""
        wind = np.asarray(self.mean_enu_mps, dtype=float) + self._gust
        if self._interp is not None:
            e = np.clip(pos_enu_m[0], *self._east_range)
            n = np.clip(pos_enu_m[1], *self._north_range)
            wind = wind.copy()
            wind[:2] += self._interp([[n, e]])[0]
        return wind
