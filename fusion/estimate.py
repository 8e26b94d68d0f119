"""What the fusion engine answers: a drone's fused state with its uncertainty."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from skyfix.fusion.health import SourceHealth
from skyfix.types import horizontal_sigma_m


@dataclass(frozen=True)
class Estimate:
    """Fused state of one drone at ``time_s``.

    ``lat_deg``/``lon_deg``/``alt_m`` WGS84 (ellipsoidal height); ``enu_m`` the same point
    in the engine's local ENU frame; ``cov_enu_m2`` its 3x3 covariance (m^2, local ENU
    axes); ``vel_enu_mps`` velocity with the autopilot's bias removed and its covariance
    ``vel_cov_enu_m2ps2``; ``sources`` the sources fused within the engine's
    contributing window; ``health`` every known source's state. ``cov_frame_enu_m2``: the
    position's covariance in the swarm's GNSS frame, the receivers' shared error
    (``FusionConfig.gnss_common_share``) left out: how well the drone is placed against home,
    its neighbours and every fix, which all carry that error too; None where the engine
    models no shared error (then ``cov_enu_m2`` is that covariance).
    """

    drone_id: str
    time_s: float
    lat_deg: float
    lon_deg: float
    alt_m: float
    enu_m: np.ndarray
    cov_enu_m2: np.ndarray
    vel_enu_mps: np.ndarray
    vel_cov_enu_m2ps2: np.ndarray
    sources: tuple[str, ...] = ()
    health: dict[str, SourceHealth] = field(default_factory=dict)
    cov_frame_enu_m2: np.ndarray | None = None

    @property
    def sigma_horizontal_m(self) -> float:
        """Square root of the larger horizontal covariance eigenvalue, metres (1-sigma)."""
        return horizontal_sigma_m(self.cov_enu_m2)

    @property
    def sigma_frame_horizontal_m(self) -> float:
        """:attr:`sigma_horizontal_m` in the swarm's GNSS frame (``cov_frame_enu_m2``), metres (1-sigma)."""
        return horizontal_sigma_m(self.decision_cov_enu_m2)

    @property
    def decision_cov_enu_m2(self) -> np.ndarray:
        """What decisions against home and neighbours read (m^2, ENU): ``cov_frame_enu_m2`` where the engine
        models a shared error, else ``cov_enu_m2`` (then the two frames are one)."""
        return self.cov_enu_m2 if self.cov_frame_enu_m2 is None else self.cov_frame_enu_m2

    def to_dict(self) -> dict:
        """JSON-ready form (lists and plain floats)."""
        return {
            "drone_id": self.drone_id, "time_s": self.time_s,
            "lat_deg": self.lat_deg, "lon_deg": self.lon_deg, "alt_m": self.alt_m,
            "enu_m": self.enu_m.tolist(), "cov_enu_m2": self.cov_enu_m2.tolist(),
            "vel_enu_mps": self.vel_enu_mps.tolist(), "vel_cov_enu_m2ps2": self.vel_cov_enu_m2ps2.tolist(),
            "cov_frame_enu_m2": None if self.cov_frame_enu_m2 is None else self.cov_frame_enu_m2.tolist(),
            "sources": list(self.sources), "health": {k: v.to_dict() for k, v in self.health.items()},
        }
