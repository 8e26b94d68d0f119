"""Measurement-level simulation of a three-drone survey for the fusion engine.

Drone ``"A"`` flies a lawnmower survey; helpers ``"B"`` and ``"C"`` fly near it
(30-80 m, seen from A at least 60 degrees apart) and report where they see A. Every
sensor is simulated at the message level, with the same arguments the engine's
``add_*`` methods take (``skyfix.fusion``, see ``feed``):

* GNSS, 5 Hz per drone: white noise ``gnss_h_sigma_m`` per horizontal axis and
  ``gnss_v_sigma_m`` vertical, optionally plus a Gauss-Markov wander (``gnss_gm_*``) and
  multipath outliers (:func:`correlated_scenario`); fix type 3, 10-14 satellites, hdop
  0.8-1.2; the reported accuracy is the total of white and wandering parts.
* Velocity, 10 Hz per drone, in the ENU axes at the drone: truth + bias + white noise.
  The bias is a random walk (see :class:`NoiseModel`) as for an autopilot velocity that
  is not GNSS-aided (optical flow scaled by a height estimate, or IMU + drag model).
* Altitude (barometer, referred to the ellipsoid), 10 Hz: white noise and an optional
  slow random-walk drift.
* Relative observations, 5 Hz from each helper of A: the offset A - helper in the ENU
  axes at the observer, range noise 3 % and bearing noise 0.2 deg (1-sigma per axis),
  with the covariance a monocular ranger would report (the shared model of
  :mod:`skyfix.datasets.observations`). The observer's own position is
  left NaN: the observer does not know it; the engine uses its own estimate.

Faults: a GNSS outage on one drone ("silent": no messages; "no_fix": messages with
fix type 1 and lat/lon 0 as receivers report) and a spoofed jump on another (the fix
moves by a fixed horizontal offset and follows the drone, with a normal fix type and
satellite count); further spoof windows (``faults``) may drift at a constant rate. Delivery: each event has its measurement time ``time_s`` and its
arrival time ``arrival_s``; a fraction of relative observations and GNSS messages
arrive 0.2-1.0 s late, and events are ordered by arrival.

Frames: truth is in the ENU frame of :attr:`FusionScenario.frame` (metres about the
origin, heights ellipsoidal); every ENU <-> geodetic conversion goes through
:class:`skyfix.geo.LocalFrame`, and vectors measured at a drone are rotated into the
ENU axes at that drone with ``LocalFrame.enu_rotation_at``.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from skyfix import validate
from skyfix.datasets.gauss_markov import gauss_markov
from skyfix.datasets.observations import noisy_relative
from skyfix.errors import InputError
from skyfix.geo import LocalFrame
from skyfix.types import RelativeObservation

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


@dataclass(frozen=True)
class FusionEvent:
    """One message as the engine receives it.

    ``kind`` is "gnss" | "velocity" | "altitude" | "relative"; ``data`` holds the keyword
    arguments of the matching ``FusionEngine.add_*`` call after ``drone_id`` and
    ``time_s`` (for "relative": ``{"obs": RelativeObservation}``, ``drone_id`` is the
    observer). ``time_s`` is the measurement time, ``arrival_s`` when it reaches the engine.
    """

    time_s: float
    arrival_s: float
    kind: str
    drone_id: str
    data: dict[str, Any]


def feed(engine: Any, event: FusionEvent) -> None:
    """Give ``event`` to ``engine`` through the matching ``add_*`` method."""
    if event.kind == "relative":
        engine.add_relative(event.data["obs"])
    elif event.kind == "gnss":
        engine.add_gnss(event.drone_id, event.time_s, **event.data)
    elif event.kind == "velocity":
        engine.add_velocity(event.drone_id, event.time_s, **event.data)
    elif event.kind == "altitude":
        engine.add_altitude(event.drone_id, event.time_s, **event.data)
    else:
        raise InputError(f"event.kind must be one of {KINDS}, got {event.kind!r}")


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


# ------------------------------------------------------------------------- scenario

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


@dataclass
class FusionScenario:
    """A simulated survey: truth, measurement events, fault windows and noise model.

    Truth is exact at any time (:meth:`truth_enu`, :meth:`truth_geodetic`); a 10 Hz
    sampling is in :attr:`truth_t_s` / :attr:`truth_enu_m` / :attr:`truth_vel_enu_mps`.
    Events come in arrival order from :meth:`events` (built lazily: an hour is ~300 000
    messages); :meth:`table` gives one kind's messages as arrays for tests and baselines.
    """

    frame: LocalFrame
    duration_s: float
    seed: int
    noise: NoiseModel
    outage: Outage | None
    spoof: Spoof | None
    path: SurveyPath
    formations: dict[str, Formation]
    truth_t_s: np.ndarray = field(repr=False)
    truth_enu_m: dict[str, np.ndarray] = field(repr=False)
    truth_vel_enu_mps: dict[str, np.ndarray] = field(repr=False)
    velocity_bias_mps: dict[str, np.ndarray] = field(repr=False)  # (N_vel, 3) per drone, ENU at drone
    _tables: dict[str, MessageTable] = field(repr=False)
    _order: np.ndarray = field(repr=False)  # (n_events, 2): kind index, row, in arrival order

    drone_ids: tuple[str, ...] = DRONE_IDS
    faults: tuple[Spoof, ...] = ()  # further spoofs (drifts, offsets after an outage), besides ``spoof``

    @property
    def spoofs(self) -> tuple[Spoof, ...]:
        """Every spoof window: ``spoof`` first, then ``faults``."""
        return ((self.spoof,) if self.spoof is not None else ()) + self.faults

    @property
    def origin(self) -> tuple[float, float, float]:
        """(lat_deg, lon_deg, alt_m ellipsoidal) of the ENU frame."""
        return (self.frame.lat0_deg, self.frame.lon0_deg, self.frame.alt0_m)

    @property
    def n_events(self) -> int:
        return int(self._order.shape[0])

    def truth_enu(self, drone_id: str, t_s) -> np.ndarray:
        """Exact true ENU position (N, 3) m of ``drone_id`` at times ``t_s`` (scalar or (N,))."""
        return _truth(self.path, self.formations, drone_id, np.atleast_1d(np.asarray(t_s, float)))[0]

    def truth_vel_enu(self, drone_id: str, t_s) -> np.ndarray:
        """Exact true velocity (N, 3) m/s in the frame's ENU axes."""
        return _truth(self.path, self.formations, drone_id, np.atleast_1d(np.asarray(t_s, float)))[1]

    def truth_geodetic(self, drone_id: str, t_s) -> np.ndarray:
        """True (lat_deg, lon_deg, alt_m) (N, 3) of ``drone_id`` at times ``t_s``."""
        return self.frame.to_geodetic_points(self.truth_enu(drone_id, t_s))

    def table(self, kind: str) -> MessageTable:
        """All messages of ``kind`` as columns (measurement order, not arrival order)."""
        if kind not in self._tables:
            raise InputError(f"kind must be one of {KINDS}, got {kind!r}")
        return self._tables[kind]

    def gnss_valid_mask(self, drone_id: str, t_s) -> np.ndarray:
        """True where a GNSS message of ``drone_id`` at ``t_s`` is honest (no outage/spoof)."""
        t = np.atleast_1d(np.asarray(t_s, float))
        ok = np.ones(t.shape, bool)
        for w in (self.outage, *self.spoofs):
            if w is not None and w.drone_id == drone_id:
                ok &= ~((t >= w.start_s) & (t < w.end_s))
        return ok

    def events(self, start: int = 0, stop: int | None = None) -> Iterator[FusionEvent]:
        """Events ``start:stop`` in arrival order (ties: velocity, altitude, gnss, relative)."""
        ids = self.drone_ids
        for k, row in self._order[start:stop]:
            kind = KINDS[k]
            tab = self._tables[kind]
            c = tab.cols
            if kind == "velocity":
                data = {"vel_enu_mps": c["vel_enu_mps"][row].copy(), "sigma_mps": float(c["sigma_mps"][row])}
            elif kind == "altitude":
                data = {"alt_m": float(c["alt_m"][row]), "sigma_m": float(c["sigma_m"][row])}
            elif kind == "gnss":
                fix = int(c["fix_type"][row])
                data = {"lat_deg": float(c["lat_deg"][row]), "lon_deg": float(c["lon_deg"][row]),
                        "alt_m": float(c["alt_m"][row]), "fix_type": fix,
                        "satellites": int(c["satellites"][row])}
                if fix >= 2:
                    data.update(h_sigma_m=float(c["h_sigma_m"][row]), v_sigma_m=float(c["v_sigma_m"][row]),
                                hdop=float(c["hdop"][row]))
                else:  # a receiver without a fix reports no accuracy (eph/epv unknown)
                    data.update(h_sigma_m=None, v_sigma_m=None, hdop=None)
            else:
                data = {"obs": RelativeObservation(
                    observer_id=ids[int(tab.drone[row])], target_id=ids[int(c["target"][row])],
                    time_s=float(tab.time_s[row]), bearing_enu=c["bearing_enu"][row].copy(),
                    range_m=float(c["range_m"][row]), cov_enu_m2=c["cov_enu_m2"][row].copy())}
            yield FusionEvent(float(tab.time_s[row]), float(tab.arrival_s[row]), kind,
                              ids[int(tab.drone[row])], data)


def _truth(path: SurveyPath, formations: dict[str, Formation], drone_id: str,
           t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pos, vel = path.position_velocity(t)
    if drone_id == "A":
        return pos, vel
    if drone_id not in formations:
        raise InputError(f"drone_id must be one of {DRONE_IDS}, got {drone_id!r}")
    off, rate = formations[drone_id].offset(t)
    return pos + off, vel + rate


def _rotations_to_local(frame: LocalFrame, enu_m: np.ndarray, t_s: np.ndarray,
                        step_s: float = 1.0) -> np.ndarray:
    """Rotations (N, 3, 3) taking frame-ENU vectors into the ENU axes at each position.

    ``enu_rotation_at`` is evaluated once per ``step_s`` of flight and shared by the
    samples in that step (the axes turn by ~1.3e-6 rad per 8 m flown)."""
    key = np.floor(t_s / step_s).astype(np.int64)
    uniq, first, inv = np.unique(key, return_index=True, return_inverse=True)
    lla = frame.to_geodetic_points(enu_m[first])
    rots = np.stack([frame.enu_rotation_at(la, lo).T for la, lo, _ in lla])
    return rots[inv.ravel()]


def _times(duration_s: float, rate_hz: float, phase_s: float) -> np.ndarray:
    """Sample times phase_s + k / rate_hz below duration_s, rounded to the microsecond."""
    n = int(np.ceil((duration_s - phase_s) * rate_hz))
    t = np.round(phase_s + np.arange(n) / rate_hz, 6)
    return t[t < duration_s]


def _late(rng: np.random.Generator, n: int, frac: float, lo: float, hi: float) -> np.ndarray:
    late = rng.random(n) < frac
    return np.where(late, rng.uniform(lo, hi, n), 0.0)


def _random_walk(rng: np.random.Generator, n: int, dt_s: float, sigma0: np.ndarray,
                 walk_per_sqrt_s: float) -> np.ndarray:
    """(n, len(sigma0)) random walk started from N(0, sigma0^2)."""
    steps = rng.normal(0.0, walk_per_sqrt_s * np.sqrt(dt_s), (n, sigma0.size))
    steps[0] = rng.normal(0.0, 1.0, sigma0.size) * sigma0
    return np.cumsum(steps, axis=0)


def survey_scenario(duration_s: float = 600.0, seed: int = 0, *,
                    origin: tuple[float, float, float] = (42.8716, -76.9813, 190.0),
                    outage: tuple[str, float, float] | None = ("A", 200.0, 120.0),
                    outage_mode: str = "silent",
                    spoof: tuple[str, float, float, float] | None = ("B", 420.0, 30.0, 50.0),
                    noise: NoiseModel | None = None,
                    path: SurveyPath | None = None,
                    formations: dict[str, Formation] | None = None,
                    faults: tuple[Spoof, ...] = ()) -> FusionScenario:
    """Simulate the three-drone survey for ``duration_s`` seconds, deterministically from ``seed``.

    ``origin`` (lat_deg, lon_deg, alt_m ellipsoidal) is the ground at the survey centre.
    ``outage`` = (drone_id, start_s, duration_s) with ``outage_mode`` "silent" | "no_fix";
    ``spoof`` = (drone_id, start_s, duration_s, jump_m): the horizontal jump direction is
    drawn from ``seed``. Either may be None. ``faults``: further :class:`Spoof` windows
    (drifts, offsets). Windows must lie inside the run.
    """
    dur = validate.positive_scalar("duration_s", duration_s)
    nm = noise or NoiseModel()
    sp = path or SurveyPath()
    if sp.start_north_m is None:
        n_lanes = np.ceil(sp.speed_mps * dur / (sp.lane_length_m + np.pi * sp.lane_spacing_m / 2.0))
        sp = replace(sp, start_north_m=-0.5 * (n_lanes - 1) * sp.lane_spacing_m)
    forms = dict(DEFAULT_FORMATIONS if formations is None else formations)
    frame = LocalFrame(*origin)
    if set(forms) != set(DRONE_IDS[1:]):
        raise InputError(f"formations must give helpers {DRONE_IDS[1:]}, got {sorted(forms)}")
    if outage_mode not in OUTAGE_MODES:
        raise InputError(f"outage_mode must be one of {OUTAGE_MODES}, got {outage_mode!r}")
    rng_root = np.random.SeedSequence(int(seed))
    rngs = [np.random.default_rng(s) for s in rng_root.spawn(12)]  # 8-10: correlated GNSS errors, 11: common part

    out_w = None
    if outage is not None:
        d, t0, ln = outage
        out_w = Outage(_check_id("outage drone", d), validate.finite_scalar("outage start_s", t0),
                       validate.positive_scalar("outage duration_s", ln), outage_mode)
        _check_window("outage", out_w.start_s, out_w.end_s, dur)
    spoof_w = None
    if spoof is not None:
        d, t0, ln, jump = spoof
        az = rngs[7].uniform(0.0, 2 * np.pi)
        jump_m = validate.positive_scalar("spoof jump_m", jump)
        spoof_w = Spoof(_check_id("spoof drone", d), validate.finite_scalar("spoof start_s", t0),
                        validate.positive_scalar("spoof duration_s", ln),
                        np.array([jump_m * np.sin(az), jump_m * np.cos(az), 0.0]))
        _check_window("spoof", spoof_w.start_s, spoof_w.end_s, dur)
    for f in faults:
        _check_id("fault drone", f.drone_id)
        _check_window("fault", f.start_s, f.end_s, dur)
    spoofs = ((spoof_w,) if spoof_w is not None else ()) + tuple(faults)

    truth_t = np.arange(0.0, dur + 1e-9, 0.1)
    truth_pos, truth_vel = {}, {}
    for d in DRONE_IDS:
        truth_pos[d], truth_vel[d] = _truth(sp, forms, d, truth_t)
    lat_ = dict(nm.latency_s)

    # Per-drone phases so that the sensors of different drones are not synchronous.
    phases = {"A": 0.0, "B": 0.013, "C": 0.027}
    tabs: dict[str, list[MessageTable]] = {k: [] for k in KINDS}
    biases: dict[str, np.ndarray] = {}
    common = None
    if nm.gnss_common_frac > 0.0:  # (times, error (N, 3) ENU) shared by every receiver
        t_common = _times(dur, nm.gnss_rate_hz, 0.0)
        common = (t_common, gauss_markov(rngs[11], t_common, np.array(
            [nm.gnss_gm_h_sigma_m, nm.gnss_gm_h_sigma_m, nm.gnss_gm_v_sigma_m]), nm.gnss_gm_tau_s))
    for i, d in enumerate(DRONE_IDS):
        rng = rngs[i]
        ph = phases[d]
        # --- velocity, in the ENU axes at the drone
        tv = _times(dur, nm.velocity_rate_hz, ph)
        p, v = _truth(sp, forms, d, tv)
        r_loc = _rotations_to_local(frame, p, tv)
        bias = _random_walk(rng, tv.size, 1.0 / nm.velocity_rate_hz,
                            np.array([nm.velocity_bias_h_sigma_mps] * 2 + [nm.velocity_bias_v_sigma_mps]),
                            nm.velocity_bias_walk_mps_per_sqrt_s)
        biases[d] = bias
        vel_meas = np.einsum("nij,nj->ni", r_loc, v) + bias + rng.normal(0, nm.velocity_sigma_mps, v.shape)
        tabs["velocity"].append(MessageTable(tv, tv + lat_["velocity"], np.full(tv.size, i),
                                             {"vel_enu_mps": vel_meas,
                                              "sigma_mps": np.full(tv.size, nm.velocity_sigma_mps)}))
        # --- barometric altitude (ellipsoidal)
        ta = _times(dur, nm.altitude_rate_hz, ph + 0.005)
        pa, _ = _truth(sp, forms, d, ta)
        alt_true = frame.to_geodetic_points(pa)[:, 2]
        drift = np.zeros(ta.size)
        if nm.altitude_drift_m_per_sqrt_s > 0:
            drift = _random_walk(rng, ta.size, 1.0 / nm.altitude_rate_hz, np.zeros(1),
                                 nm.altitude_drift_m_per_sqrt_s)[:, 0]
        alt_meas = alt_true + drift + rng.normal(0, nm.altitude_sigma_m, ta.size)
        tabs["altitude"].append(MessageTable(ta, ta + lat_["altitude"], np.full(ta.size, i),
                                             {"alt_m": alt_meas,
                                              "sigma_m": np.full(ta.size, nm.altitude_sigma_m)}))
        # --- GNSS
        tabs["gnss"].append(_gnss(frame, sp, forms, d, i, dur, nm, ph + 0.05, (rng, rngs[8 + i]), out_w, spoofs,
                                  lat_["gnss"], common))
    for i, d in enumerate(DRONE_IDS[1:], start=1):
        tabs["relative"].append(_relative(frame, sp, forms, d, i, dur, nm, phases[d] + 0.031,
                                          rngs[3 + i], lat_["relative"]))

    tables = {k: _concat(v) for k, v in tabs.items()}
    kind_idx = np.concatenate([np.full(tables[k].time_s.size, j) for j, k in enumerate(KINDS)])
    rows = np.concatenate([np.arange(tables[k].time_s.size) for k in KINDS])
    arr = np.concatenate([tables[k].arrival_s for k in KINDS])
    tm = np.concatenate([tables[k].time_s for k in KINDS])
    dr = np.concatenate([tables[k].drone for k in KINDS])
    order = np.lexsort((dr, kind_idx, tm, arr))
    return FusionScenario(frame=frame, duration_s=dur, seed=int(seed), noise=nm, outage=out_w,
                          spoof=spoof_w, path=sp, formations=forms, truth_t_s=truth_t,
                          truth_enu_m=truth_pos, truth_vel_enu_mps=truth_vel,
                          velocity_bias_mps=biases, _tables=tables, faults=tuple(faults),
                          _order=np.stack([kind_idx[order], rows[order]], axis=1))


def _check_id(name: str, drone_id: str) -> str:
    if drone_id not in DRONE_IDS:
        raise InputError(f"{name} must be one of {DRONE_IDS}, got {drone_id!r}")
    return drone_id


def _check_window(name: str, start_s: float, end_s: float, duration_s: float) -> None:
    if start_s < 0.0 or end_s > duration_s:
        raise InputError(f"{name} window [{start_s}, {end_s}) s must lie inside the run [0, {duration_s}] s")


def _concat(parts: list[MessageTable]) -> MessageTable:
    return MessageTable(np.concatenate([p.time_s for p in parts]), np.concatenate([p.arrival_s for p in parts]),
                        np.concatenate([p.drone for p in parts]),
                        {k: np.concatenate([p.cols[k] for p in parts]) for k in parts[0].cols})


def _gnss(frame: LocalFrame, sp: SurveyPath, forms: dict[str, Formation], d: str, i: int,
          dur: float, nm: NoiseModel, phase_s: float, rngs: tuple[np.random.Generator, np.random.Generator],
          out_w: Outage | None, spoofs: tuple[Spoof, ...], latency_s: float,
          common: tuple[np.ndarray, np.ndarray] | None = None) -> MessageTable:
    rng, rng_gm = rngs  # the correlated part has its own stream: white-only runs stay as they were
    t = _times(dur, nm.gnss_rate_hz, phase_s)
    p, _ = _truth(sp, forms, d, t)
    sig = np.array([nm.gnss_h_sigma_m, nm.gnss_h_sigma_m, nm.gnss_v_sigma_m])
    noise_local = rng.normal(0.0, 1.0, p.shape) * sig
    gm_sig = np.array([nm.gnss_gm_h_sigma_m, nm.gnss_gm_h_sigma_m, nm.gnss_gm_v_sigma_m])
    if gm_sig.any():
        own = gauss_markov(rng_gm, t, gm_sig, nm.gnss_gm_tau_s)
        if common is not None:  # same variance, a share of it common to every receiver
            shared = np.stack([np.interp(t, common[0], common[1][:, j]) for j in range(3)], axis=1)
            own = np.sqrt(1.0 - nm.gnss_common_frac) * own + np.sqrt(nm.gnss_common_frac) * shared
        noise_local += own
    outlier = rng_gm.random(t.size) < nm.gnss_outlier_frac
    if outlier.any():
        az = rng_gm.uniform(0.0, 2 * np.pi, int(outlier.sum()))
        size = rng_gm.uniform(nm.gnss_outlier_min_m, nm.gnss_outlier_max_m, az.size)
        noise_local[outlier, 0] += size * np.sin(az)
        noise_local[outlier, 1] += size * np.cos(az)
    # Noise is drawn in the ENU axes at the drone; rotate into the frame's axes.
    r_loc = _rotations_to_local(frame, p, t)
    meas = p + np.einsum("nji,nj->ni", r_loc, noise_local)
    for w in spoofs:
        if w.drone_id == d:
            meas += w.displacement(t)
    lla = frame.to_geodetic_points(meas)
    # Satellites change every ~20 s; hdop follows them (10 sats -> 1.2, 14 -> 0.8).
    n_blocks = int(np.ceil(dur / 20.0)) + 1
    sats_block = rng.integers(10, 15, n_blocks)
    sats = sats_block[np.floor(t / 20.0).astype(int)]
    hdop = 1.2 - 0.1 * (sats - 10) + rng.uniform(-0.02, 0.02, t.size)
    fix = np.full(t.size, 3)
    keep = np.ones(t.size, bool)
    if out_w is not None and out_w.drone_id == d:
        o_mask = (t >= out_w.start_s) & (t < out_w.end_s)
        if out_w.mode == "silent":
            keep = ~o_mask
        else:  # no_fix: the receiver keeps reporting, without a position
            fix[o_mask] = 1
            lla[o_mask] = 0.0
            sats[o_mask] = rng.integers(0, 4, int(o_mask.sum()))
    late = _late(rng, t.size, nm.late_gnss_frac, nm.late_min_s, nm.late_max_s)
    # The receiver reports its total 1-sigma accuracy (white and wandering parts together).
    cols = {"lat_deg": lla[:, 0], "lon_deg": lla[:, 1], "alt_m": lla[:, 2], "fix_type": fix,
            "satellites": sats, "hdop": hdop, "h_sigma_m": np.full(t.size, np.hypot(sig[0], gm_sig[0])),
            "v_sigma_m": np.full(t.size, np.hypot(sig[2], gm_sig[2])), "outlier": outlier}
    return MessageTable(t[keep], (t + latency_s + late)[keep], np.full(int(keep.sum()), i),
                        {k: v[keep] for k, v in cols.items()})


def _relative(frame: LocalFrame, sp: SurveyPath, forms: dict[str, Formation], d: str, i: int,
              dur: float, nm: NoiseModel, phase_s: float, rng: np.random.Generator,
              latency_s: float) -> MessageTable:
    """Observations by helper ``d`` of A: offset A - helper in the ENU axes at ``d``."""
    t = _times(dur, nm.relative_rate_hz, phase_s)
    p_obs, _ = _truth(sp, forms, d, t)
    p_tgt, _ = _truth(sp, forms, "A", t)
    rng_true = np.linalg.norm(p_tgt - p_obs, axis=1)
    keep = (rng_true >= nm.relative_min_range_m) & (rng_true <= nm.relative_max_range_m)
    t, p_obs, p_tgt, rng_true = t[keep], p_obs[keep], p_tgt[keep], rng_true[keep]
    # The shared ranger model: noise and the covariance the ranger reports, ENU at the observer.
    b, r, cov = noisy_relative(frame, p_obs, p_tgt, rng, range_frac=nm.relative_range_frac,
                               bearing_sigma_deg=nm.relative_bearing_sigma_deg)
    r_loc = _rotations_to_local(frame, p_obs, t)
    b_true = np.einsum("nij,nj->ni", r_loc, p_tgt - p_obs) / rng_true[:, None]
    late = _late(rng, t.size, nm.late_relative_frac, nm.late_min_s, nm.late_max_s)
    return MessageTable(t, t + latency_s + late, np.full(t.size, i),
                        {"bearing_enu": b, "range_m": r, "cov_enu_m2": cov, "target": np.zeros(t.size, int),
                         "range_true_m": rng_true, "bearing_true_enu": b_true})


# Consumer receivers as they are (issue 15): a wandering error of 1.5 m per horizontal axis
# with a one-minute correlation time plus 0.3 m white; helpers 20-140 m from A on their own
# wandering legs, observing at 2 Hz with 2 % range and 0.5 deg bearing noise; 2 % multipath outliers.
CORRELATED_NOISE = NoiseModel(gnss_h_sigma_m=0.3, gnss_v_sigma_m=0.5, gnss_gm_h_sigma_m=1.5,
                              gnss_gm_v_sigma_m=2.5, gnss_gm_tau_s=60.0, gnss_outlier_frac=0.02,
                              relative_rate_hz=2.0, relative_range_frac=0.02, relative_bearing_sigma_deg=0.5,
                              relative_min_range_m=20.0, relative_max_range_m=140.0)
CORRELATED_FORMATIONS: dict[str, Formation] = {
    "B": Formation(range_m=80.0, azimuth_deg=240.0, dup_m=12.0, range_wander_m=60.0, azimuth_wander_deg=25.0,
                   periods_s=(157.0, 233.0, 131.0), phases_rad=(0.0, 0.7, 0.3)),
    "C": Formation(range_m=80.0, azimuth_deg=120.0, dup_m=-15.0, range_wander_m=60.0, azimuth_wander_deg=25.0,
                   periods_s=(197.0, 171.0, 113.0), phases_rad=(2.1, 4.0, 1.9)),
}


def correlated_scenario(duration_s: float = 600.0, seed: int = 0, faults: bool = True,
                        return_offset: bool = True) -> FusionScenario:
    """The survey with Gauss-Markov GNSS on every drone (:data:`CORRELATED_NOISE`) and, with
    ``faults`` (needs ``duration_s`` >= 450): A silent 150-240 s, then A's GNSS 30 m off for
    30 s; B spoofed by a 50 m jump 300-330 s; C's GNSS drifting at 0.5 m/s 380-440 s, honest after.
    Jump and drift directions are drawn from ``seed``. ``return_offset=False``: A stays silent
    240-270 s instead of returning 30 m off, every other message the same (a counterfactual
    that tells what the offset GNSS moved from what the estimate would have done anyway)."""
    if not faults:
        return survey_scenario(duration_s, seed, outage=None, spoof=None, noise=CORRELATED_NOISE,
                               formations=CORRELATED_FORMATIONS)
    az = np.random.default_rng(np.random.SeedSequence([int(seed), 15])).uniform(0.0, 2 * np.pi, 2)
    horiz = np.stack([np.sin(az), np.cos(az), np.zeros(2)], axis=1)
    drift = Spoof("C", 380.0, 60.0, np.zeros(3), 0.5 * horiz[1])
    extra = (Spoof("A", 240.0, 30.0, 30.0 * horiz[0]), drift) if return_offset else (drift,)
    return survey_scenario(duration_s, seed, outage=("A", 150.0, 90.0 if return_offset else 120.0),
                           spoof=("B", 300.0, 30.0, 50.0), noise=CORRELATED_NOISE,
                           formations=CORRELATED_FORMATIONS, faults=extra)


STEP_TIMES_S: dict[str, float] = {"A": 100.0, "B": 170.0, "C": 200.0}  # mismatch_scenario's error steps


def mismatch_scenario(duration_s: float, seed: int, noise: NoiseModel, step_m: float = 0.0) -> FusionScenario:
    """The correlated survey's geometry with GNSS errors drawn from ``noise`` (e.g. another
    sigma or correlation time than a fusion engine assumes) and one fault: A silent 150-240 s
    (needs ``duration_s`` >= 240). ``step_m`` > 0: every receiver's error also steps by that
    much horizontally for the rest of the run (a constellation change), at :data:`STEP_TIMES_S`
    (B and C during A's outage), in directions drawn from ``seed``."""
    steps: tuple[Spoof, ...] = ()
    if step_m > 0.0:
        az = np.random.default_rng(np.random.SeedSequence([int(seed), 16])).uniform(0.0, 2 * np.pi, 3)
        steps = tuple(Spoof(d, t0, float(duration_s) - t0, step_m * np.array([np.sin(a), np.cos(a), 0.0]))
                      for (d, t0), a in zip(STEP_TIMES_S.items(), az, strict=True))
    return survey_scenario(duration_s, seed, outage=("A", 150.0, 90.0), spoof=None, noise=noise,
                           formations=CORRELATED_FORMATIONS, faults=steps)
