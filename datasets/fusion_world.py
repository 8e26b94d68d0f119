"""The simulated survey's world for the fusion scenarios: drones, their paths and
formations, sensor noise and delivery, fault windows, and the columnar message table.

Frames and units as in :mod:`skyfix.datasets.fusion_scenario` (ENU metres about the
scenario's origin, ellipsoidal heights, seconds).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

DRONE_IDS: tuple[str, ...] = ("A", "B", "C")
KINDS: tuple[str, ...] = ("velocity", "altitude", "gnss", "relative")  # tie order at one arrival
OUTAGE_MODES: tuple[str, ...] = ("silent", "no_fix")


@dataclass(frozen=True)
class NoiseModel:
    """Sensor noise and delivery parameters (1-sigma values unless stated)."""

    gnss_rate_hz: float = 5.0
    gnss_h_sigma_m: float = 1.5  # per horizontal axis (E and N), white part
    gnss_v_sigma_m: float = 2.5  # vertical, white part
    # Slowly wandering part of the GNSS error (multipath, atmosphere, orbits): a first-order
    # Gauss-Markov process per axis with this stationary sigma and correlation time; 0 = off.
    gnss_gm_h_sigma_m: float = 0.0
    gnss_gm_v_sigma_m: float = 0.0
    gnss_gm_tau_s: float = 60.0
    gnss_outlier_frac: float = 0.0  # multipath outliers: this fraction of fixes jumps horizontally by
    gnss_outlier_min_m: float = 5.0  # ... a size uniform in [min, max] m, in a uniform direction
    gnss_outlier_max_m: float = 20.0
    # Share of the wandering error's variance common to every receiver (nearby receivers see the
    # same satellites through the same atmosphere); 0 = independent receivers.
    gnss_common_frac: float = 0.0
    velocity_rate_hz: float = 10.0
    velocity_sigma_mps: float = 0.1  # white, per axis
    # Bias of the autopilot's velocity when it is not GNSS-aided. Optical flow scaled by a
    # rangefinder/baro height with a 1-2 % height or scale error gives 0.1-0.15 m/s at
    # 8 m/s; an IMU + drag-model estimate drifts by a similar amount over a minute. The
    # random walk (0.01 m/s/sqrt(s): 0.1 m/s after 100 s) models the slow change of that
    # scale error with height, terrain texture and wind.
    velocity_bias_h_sigma_mps: float = 0.1  # initial bias, per horizontal axis
    velocity_bias_v_sigma_mps: float = 0.03  # initial bias, vertical
    velocity_bias_walk_mps_per_sqrt_s: float = 0.01  # random walk, every axis
    altitude_rate_hz: float = 10.0
    altitude_sigma_m: float = 0.5  # barometer white noise
    altitude_drift_m_per_sqrt_s: float = 0.0  # optional slow barometric drift (random walk)
    relative_rate_hz: float = 5.0
    relative_range_frac: float = 0.03  # range noise as a fraction of range
    relative_bearing_sigma_deg: float = 0.2  # per perpendicular axis
    relative_min_range_m: float = 30.0  # helpers report A only within this range band
    relative_max_range_m: float = 80.0
    late_gnss_frac: float = 0.02  # fraction of GNSS messages delivered late
    late_relative_frac: float = 0.05  # fraction of relative observations delivered late
    late_min_s: float = 0.2
    late_max_s: float = 1.0
    # Normal transport latency (measurement time -> arrival), seconds.
    latency_s: tuple[tuple[str, float], ...] = (
        ("velocity", 0.01), ("altitude", 0.01), ("gnss", 0.03), ("relative", 0.05))


@dataclass(frozen=True)
class Outage:
    """GNSS outage of ``drone_id`` over measurement times [start_s, start_s + duration_s)."""

    drone_id: str
    start_s: float
    duration_s: float
    mode: str = "silent"

    @property
    def end_s(self) -> float:
        return self.start_s + self.duration_s


@dataclass(frozen=True)
class Spoof:
    """Spoofed GNSS of ``drone_id``: fixes displaced by ``offset_enu_m + rate_enu_mps * (t -
    start_s)`` (3,) over [start_s, start_s + duration_s) (a jump, a slow drift, or both)."""

    drone_id: str
    start_s: float
    duration_s: float
    offset_enu_m: np.ndarray
    rate_enu_mps: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def displacement(self, t_s: np.ndarray) -> np.ndarray:
        """Offset (N, 3) m added to fixes at ``t_s`` (zero outside the window)."""
        t = np.asarray(t_s, float)
        inside = ((t >= self.start_s) & (t < self.end_s))[:, None]
        return np.where(inside, self.offset_enu_m + self.rate_enu_mps * (t - self.start_s)[:, None], 0.0)

    @property
    def end_s(self) -> float:
        return self.start_s + self.duration_s


# ----------------------------------------------------------------------------- truth

@dataclass(frozen=True)
class SurveyPath:
    """A's lawnmower: lanes along east of ``lane_length_m``, ``lane_spacing_m`` apart
    northwards, joined by half circles, flown at ``speed_mps``; height above the origin
    ``height_m`` + two slow sines (60-100 m, climbs below 1 m/s)."""

    speed_mps: float = 8.0
    lane_length_m: float = 600.0
    lane_spacing_m: float = 40.0
    start_north_m: float | None = None  # None: centre the lanes flown in the run on the origin
    height_m: float = 80.0

    def position_velocity(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """ENU position (N, 3) m and velocity (N, 3) m/s at times ``t_s`` (N,)."""
        t = np.asarray(t_s, dtype=float)
        v, half, r = self.speed_mps, self.lane_length_m / 2.0, self.lane_spacing_m / 2.0
        period_m = self.lane_length_m + np.pi * r
        s = v * t
        lane = np.floor(s / period_m)
        u = s - lane * period_m
        sign = np.where(lane % 2 == 0, 1.0, -1.0)  # +1 heading east on even lanes
        y_lane = (self.start_north_m or 0.0) + lane * self.lane_spacing_m
        straight = u < self.lane_length_m
        phi = np.where(straight, 0.0, (u - self.lane_length_m) / r)
        e = np.where(straight, sign * (-half + u), sign * (half + r * np.sin(phi)))
        n = np.where(straight, y_lane, y_lane + r - r * np.cos(phi))
        ve = np.where(straight, sign * v, sign * v * np.cos(phi))
        vn = np.where(straight, 0.0, v * np.sin(phi))
        w1, w2 = 2 * np.pi / 240.0, 2 * np.pi / 97.0
        up = self.height_m + 12.0 * np.sin(w1 * t) + 6.0 * np.sin(w2 * t + 1.0)
        vu = 12.0 * w1 * np.cos(w1 * t) + 6.0 * w2 * np.cos(w2 * t + 1.0)
        return np.stack([e, n, up], axis=1), np.stack([ve, vn, vu], axis=1)


@dataclass(frozen=True)
class Formation:
    """A helper's offset from A: horizontal distance ``range_m`` +- ``range_wander_m`` at
    compass azimuth ``azimuth_deg`` +- ``azimuth_wander_deg`` (world-fixed, behind the
    survey's northward progress, so turns of A do not whip the helper around), and
    ``dup_m`` +- 4 m above A; each wanders as a slow sine."""

    range_m: float
    azimuth_deg: float
    dup_m: float
    range_wander_m: float = 12.0
    azimuth_wander_deg: float = 15.0
    periods_s: tuple[float, float, float] = (173.0, 211.0, 131.0)
    phases_rad: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def offset(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Offset helper - A in ENU (N, 3) m and its rate (N, 3) m/s."""
        t = np.asarray(t_s, dtype=float)
        w = 2 * np.pi / np.asarray(self.periods_s)
        ph = np.asarray(self.phases_rad)
        rho = self.range_m + self.range_wander_m * np.sin(w[0] * t + ph[0])
        drho = self.range_wander_m * w[0] * np.cos(w[0] * t + ph[0])
        az = np.radians(self.azimuth_deg + self.azimuth_wander_deg * np.sin(w[1] * t + ph[1]))
        daz = np.radians(self.azimuth_wander_deg) * w[1] * np.cos(w[1] * t + ph[1])
        dz = self.dup_m + 4.0 * np.sin(w[2] * t + ph[2])
        ddz = 4.0 * w[2] * np.cos(w[2] * t + ph[2])
        se, ce = np.sin(az), np.cos(az)
        off = np.stack([rho * se, rho * ce, dz], axis=1)
        rate = np.stack([drho * se + rho * ce * daz, drho * ce - rho * se * daz, ddz], axis=1)
        return off, rate


DEFAULT_FORMATIONS: dict[str, Formation] = {
    "B": Formation(range_m=50.0, azimuth_deg=240.0, dup_m=12.0, phases_rad=(0.0, 0.7, 0.3)),
    "C": Formation(range_m=50.0, azimuth_deg=120.0, dup_m=-15.0, phases_rad=(2.1, 4.0, 1.9)),
}


@dataclass
class MessageTable:
    """Columnar messages of one kind, in measurement order: ``time_s``/``arrival_s`` (N,),
    ``drone`` (N,) index into ``DRONE_IDS``, and ``cols`` of (N, ...) arrays named like the
    ``add_*`` arguments (relative observations also carry ``range_true_m`` and
    ``bearing_true_enu``, the noise-free values)."""

    time_s: np.ndarray
    arrival_s: np.ndarray
    drone: np.ndarray
    cols: dict[str, np.ndarray]
