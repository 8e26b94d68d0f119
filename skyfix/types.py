"""Measurement and estimate types shared between perception, fusion and drivers.

Every measurement carries a time (seconds, on the clock of whoever produced it;
use one clock per system, e.g. UNIX time), a source id and an uncertainty.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from skyfix import validate
from skyfix.errors import InputError


def _frozen_cov(name: str, value, dim: int) -> np.ndarray:
    cov = validate.covariance(name, value, dim).copy()
    cov.setflags(write=False)
    return cov


def horizontal_sigma_m(cov_enu_m2: np.ndarray) -> float:
    """Largest horizontal 1-sigma (m) of an ENU covariance ``(>= 2, >= 2)`` (m^2): the
    square root of the larger eigenvalue of its east-north block.

    Example:
        >>> horizontal_sigma_m(np.array([[3.0, 1.0, 0.0], [1.0, 3.0, 0.0], [0.0, 0.0, 9.0]]))
        2.0
    """
    return float(np.sqrt(np.linalg.eigvalsh(cov_enu_m2[:2, :2]).max()))


@dataclass(frozen=True)
class GeoFix:
    """A geodetic position with its uncertainty.

    ``lat_deg``/``lon_deg`` WGS84, ``alt_m`` ellipsoidal height; ``cov_enu_m2`` is the
    3x3 covariance in the local ENU axes at the fix, m^2.

    Example:
        >>> fix = GeoFix(47.0, 8.0, 450.0, np.diag([4.0, 1.0, 9.0]))
        >>> fix.sigma_horizontal_m, fix.sigma_up_m
        (2.0, 3.0)
    """

    lat_deg: float
    lon_deg: float
    alt_m: float
    cov_enu_m2: np.ndarray
    time_s: float = 0.0
    source_id: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "lat_deg", float(validate.latitude("GeoFix.lat_deg", self.lat_deg)))
        object.__setattr__(self, "lon_deg", float(validate.longitude("GeoFix.lon_deg", self.lon_deg)))
        object.__setattr__(self, "alt_m", validate.finite_scalar("GeoFix.alt_m", self.alt_m))
        object.__setattr__(self, "time_s", validate.finite_scalar("GeoFix.time_s", self.time_s))
        object.__setattr__(self, "cov_enu_m2", _frozen_cov("GeoFix.cov_enu_m2", self.cov_enu_m2, 3))

    @classmethod
    def many(cls, lat_deg: np.ndarray, lon_deg: np.ndarray, alt_m: np.ndarray, cov_enu_m2: np.ndarray,
             time_s: float = 0.0, source_id: str = "") -> list[GeoFix]:
        """Fixes from ``(N,)`` arrays and covariances ``(N, 3, 3)`` sharing a time and a source,
        with the constructor's checks done once over the arrays (a thermal frame gives one fix
        per fire; N constructions cost 5x more). Each fix's covariance is a read-only view.

        Example:
            >>> fixes = GeoFix.many([47.0, 47.1], [8.0, 8.1], [450.0, 460.0], [np.eye(3), 4.0 * np.eye(3)])
            >>> [(f.lat_deg, f.sigma_up_m) for f in fixes]
            [(47.0, 1.0), (47.1, 2.0)]
        """
        lat = validate.latitude("GeoFix.lat_deg", lat_deg)
        lon = validate.longitude("GeoFix.lon_deg", lon_deg)
        alt = validate.finite_array("GeoFix.alt_m", alt_m)
        cov = validate.covariances("GeoFix.cov_enu_m2", cov_enu_m2, 3).copy()
        n = cov.shape[0]
        if lat.shape != (n,) or lon.shape != (n,) or alt.shape != (n,):
            raise InputError(f"GeoFix.many: lat_deg, lon_deg, alt_m must have shape ({n},) like the covariances, "
                             f"got {lat.shape}, {lon.shape}, {alt.shape}")
        t = validate.finite_scalar("GeoFix.time_s", time_s)
        cov.setflags(write=False)
        out = []
        for la, lo, al, c in zip(lat.tolist(), lon.tolist(), alt.tolist(), cov, strict=True):
            fix = object.__new__(cls)  # the fields are checked above: skip __post_init__
            for key, value in (("lat_deg", la), ("lon_deg", lo), ("alt_m", al), ("cov_enu_m2", c), ("time_s", t),
                               ("source_id", source_id)):
                object.__setattr__(fix, key, value)
            out.append(fix)
        return out

    @property
    def sigma_horizontal_m(self) -> float:
        """Square root of the larger horizontal covariance eigenvalue, metres (1-sigma)."""
        return horizontal_sigma_m(self.cov_enu_m2)

    @property
    def sigma_up_m(self) -> float:
        """Vertical 1-sigma, metres."""
        return float(np.sqrt(self.cov_enu_m2[2, 2]))


@dataclass(frozen=True)
class RelativeObservation:
    """One vehicle's observation of another: where the target is relative to the observer.

    ``bearing_unit_enu`` is a unit vector (3,) from the observer towards the target in the
    local ENU axes at the observer; ``range_m`` the distance; ``cov_enu_m2`` the 3x3
    covariance of the relative position ``range_m * bearing_unit_enu`` (ENU, m^2), including
    the observer's attitude uncertainty but not its position uncertainty, which fusion
    takes from the observer's own estimate.

    Example:
        >>> obs = RelativeObservation("A", "B", 0.0, np.array([0.6, 0.8, 0.0]), 50.0, np.eye(3))
        >>> obs.offset_enu_m, obs.has_observer_position
        (array([30., 40.,  0.]), False)
    """

    observer_id: str
    target_id: str
    time_s: float
    bearing_unit_enu: np.ndarray
    range_m: float
    cov_enu_m2: np.ndarray
    observer_lat_deg: float = float("nan")
    observer_lon_deg: float = float("nan")
    observer_alt_m: float = float("nan")
    observer_cov_enu_m2: np.ndarray | None = field(default=None)

    def __post_init__(self) -> None:
        object.__setattr__(self, "time_s", validate.finite_scalar("RelativeObservation.time_s", self.time_s))
        rng = validate.positive_scalar("RelativeObservation.range_m", self.range_m)
        object.__setattr__(self, "range_m", rng)
        b = validate.finite_array("RelativeObservation.bearing_unit_enu", self.bearing_unit_enu)
        if b.shape != (3,) or abs(np.linalg.norm(b) - 1.0) > 1e-6:
            raise InputError(f"RelativeObservation.bearing_unit_enu must be a unit (3,) vector, got {b}")
        b = b.copy()
        b.setflags(write=False)
        object.__setattr__(self, "bearing_unit_enu", b)
        object.__setattr__(self, "cov_enu_m2", _frozen_cov("RelativeObservation.cov_enu_m2", self.cov_enu_m2, 3))
        if self.observer_cov_enu_m2 is not None:
            object.__setattr__(self, "observer_cov_enu_m2",
                               _frozen_cov("RelativeObservation.observer_cov_enu_m2", self.observer_cov_enu_m2, 3))

    @property
    def offset_enu_m(self) -> np.ndarray:
        """Observer -> target vector in ENU metres, (3,)."""
        return self.range_m * self.bearing_unit_enu

    @property
    def has_observer_position(self) -> bool:
        """True when the observer's own geodetic position was recorded with the observation."""
        return bool(np.isfinite([self.observer_lat_deg, self.observer_lon_deg, self.observer_alt_m]).all())
