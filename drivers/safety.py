"""The safety gate: geofence polygons with altitude limits, speed and altitude limits.

Setpoints outside the envelope are refused before they are sent
(:class:`~skyfix.errors.SafetyViolation`); positions seen in telemetry that violate it
trigger the configured action (``"hold"``, ``"rtl"`` or ``"land"``) from the reader
thread, so the action leaves within one message-processing time of the telemetry.
Polygons are tested in an exact local ENU frame (:class:`skyfix.geo.LocalFrame`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from skyfix import validate
from skyfix.errors import InputError, SafetyViolation
from skyfix.geo import LocalFrame

ACTIONS = ("hold", "rtl", "land")


def _inside_polygon(xy: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Even-odd rule; ``xy`` (N, 2), ``poly`` (M, 2) -> (N,) bool."""
    x, y = xy[:, 0:1], xy[:, 1:2]
    x0, y0 = poly[:, 0], poly[:, 1]
    x1, y1 = np.roll(x0, -1), np.roll(y0, -1)
    crosses = (y0 > y) != (y1 > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_at = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
    return np.count_nonzero(crosses & (x < x_at), axis=1) % 2 == 1


@dataclass(frozen=True)
class Geofence:
    """Inclusion polygons (each ``(M, 2)`` of lat_deg, lon_deg, M >= 3) with an altitude band
    relative to home, metres. A position is inside when it is inside any polygon and within
    ``[min_alt_rel_m, max_alt_rel_m]``. No polygons: only the altitude band applies."""

    polygons: Sequence[np.ndarray] = ()
    min_alt_rel_m: float = -math.inf
    max_alt_rel_m: float = math.inf
    _frame: LocalFrame | None = field(init=False, repr=False, default=None)
    _polys_en: tuple[np.ndarray, ...] = field(init=False, repr=False, default=())

    def __post_init__(self) -> None:
        polys = []
        for i, p in enumerate(self.polygons):
            arr = validate.points(f"Geofence.polygons[{i}]", p, 2)
            if arr.shape[0] < 3:
                raise InputError(f"Geofence.polygons[{i}] needs at least 3 vertices, got {arr.shape[0]}")
            validate.latitude(f"Geofence.polygons[{i}] latitudes", arr[:, 0])
            validate.longitude(f"Geofence.polygons[{i}] longitudes", arr[:, 1])
            polys.append(arr)
        if math.isnan(self.min_alt_rel_m) or math.isnan(self.max_alt_rel_m) \
                or self.min_alt_rel_m >= self.max_alt_rel_m:
            raise InputError("Geofence altitude band must satisfy min_alt_rel_m < max_alt_rel_m, "
                             f"got [{self.min_alt_rel_m}, {self.max_alt_rel_m}]")
        object.__setattr__(self, "polygons", tuple(polys))
        if polys:
            frame = LocalFrame(float(polys[0][0, 0]), float(polys[0][0, 1]), 0.0)
            en = tuple(frame.to_enu_points(np.column_stack([p, np.zeros(len(p))]))[:, :2] for p in polys)
            object.__setattr__(self, "_frame", frame)
            object.__setattr__(self, "_polys_en", en)

    @classmethod
    def circle(cls, lat_deg: float, lon_deg: float, radius_m: float, *, n: int = 36,
               min_alt_rel_m: float = -math.inf, max_alt_rel_m: float = math.inf) -> Geofence:
        """A circular inclusion fence approximated by an ``n``-gon (geodesic radius)."""
        from skyfix.geo import destination
        r = validate.positive_scalar("radius_m", radius_m)
        bearings = np.linspace(0.0, 360.0, int(n), endpoint=False)
        lat, lon = destination(np.full(n, lat_deg), np.full(n, lon_deg), bearings, np.full(n, r))
        return cls([np.column_stack([lat, lon])], min_alt_rel_m, max_alt_rel_m)

    def violation(self, lat_deg: float, lon_deg: float, alt_rel_m: float) -> str:
        """Empty string when inside; otherwise what is violated, in words."""
        if alt_rel_m > self.max_alt_rel_m:
            return f"altitude {alt_rel_m:.1f} m above the fence maximum {self.max_alt_rel_m:.1f} m"
        if alt_rel_m < self.min_alt_rel_m:
            return f"altitude {alt_rel_m:.1f} m below the fence minimum {self.min_alt_rel_m:.1f} m"
        if self._frame is not None:
            e, n, _ = self._frame.to_enu(lat_deg, lon_deg, 0.0)
            xy = np.array([[float(e), float(n)]])
            if not any(_inside_polygon(xy, p)[0] for p in self._polys_en):
                return f"position {lat_deg:.7f},{lon_deg:.7f} outside the geofence polygons"
        return ""

    def contains(self, lat_deg: float, lon_deg: float, alt_rel_m: float) -> bool:
        return not self.violation(lat_deg, lon_deg, alt_rel_m)


@dataclass(frozen=True)
class SafetyGate:
    """Envelope checked for every setpoint and every telemetry position.

    ``action`` is what the vehicle is told to do on a violation seen in telemetry:
    ``"hold"`` (LOITER / AUTO.LOITER), ``"rtl"`` or ``"land"``. One action per excursion:
    the vehicle is not commanded again until telemetry shows it back inside, and until
    then :meth:`Vehicle.velocity` refuses setpoints (a ``goto`` inside is allowed).
    """

    fence: Geofence | None = None
    max_speed_mps: float = math.inf
    max_alt_rel_m: float = math.inf
    action: str = "rtl"

    def __post_init__(self) -> None:
        if self.action not in ACTIONS:
            raise InputError(f"SafetyGate.action must be one of {ACTIONS}, got {self.action!r}")
        for name in ("max_speed_mps", "max_alt_rel_m"):
            value = getattr(self, name)
            if math.isnan(value) or value <= 0:
                raise InputError(f"SafetyGate.{name} must be > 0, got {value}")

    def check_position_setpoint(self, lat_deg: float, lon_deg: float, alt_rel_m: float) -> None:
        """Raise SafetyViolation when a position target lies outside the envelope."""
        if alt_rel_m > self.max_alt_rel_m:
            raise SafetyViolation(f"setpoint altitude {alt_rel_m:.1f} m exceeds max_alt_rel_m "
                                  f"{self.max_alt_rel_m:.1f} m; refused")
        if self.fence is not None:
            why = self.fence.violation(lat_deg, lon_deg, alt_rel_m)
            if why:
                raise SafetyViolation(f"setpoint refused: {why}")

    def check_velocity_setpoint(self, north_mps: float, east_mps: float, down_mps: float) -> None:
        """Raise SafetyViolation when a velocity target is faster than ``max_speed_mps``."""
        speed = math.sqrt(north_mps ** 2 + east_mps ** 2 + down_mps ** 2)
        if speed > self.max_speed_mps:
            raise SafetyViolation(f"velocity setpoint {speed:.1f} m/s exceeds max_speed_mps "
                                  f"{self.max_speed_mps:.1f} m/s; refused")

    def violation(self, lat_deg: float, lon_deg: float, alt_rel_m: float,
                  speed_mps: float = 0.0) -> str:
        """Empty string when the state is within the envelope; otherwise the reason."""
        if alt_rel_m > self.max_alt_rel_m:
            return f"altitude {alt_rel_m:.1f} m above max_alt_rel_m {self.max_alt_rel_m:.1f} m"
        if speed_mps > self.max_speed_mps:
            return f"speed {speed_mps:.1f} m/s above max_speed_mps {self.max_speed_mps:.1f} m/s"
        if self.fence is not None:
            return self.fence.violation(lat_deg, lon_deg, alt_rel_m)
        return ""
