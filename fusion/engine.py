"""FusionEngine: every drone's fused position from GNSS, velocity, altitude, fixes and helpers.

All states live in one local ENU frame about ``origin`` (exact WGS84 through
:class:`skyfix.geo.LocalFrame`); geodetic inputs are converted on arrival and
directions measured at a drone (velocity, relative bearings, ENU covariances) are
rotated from the ENU axes *at that drone* into the frame's axes. One gtsam window
(:mod:`skyfix.fusion.window`) holds every drone, so a relative observation ties the
observer's and the target's states with both their uncertainties.

Time: every input is stamped (seconds, one clock for all). A measurement at ``t`` is
attached to the nearest state on the ``state_dt_s`` grid, moved there with the drone's
bias-corrected velocity (the move's uncertainty is added). Inputs may arrive out of
order as long as they are inside the lag; older ones raise :class:`InputError`.

Health (:mod:`skyfix.fusion.health`): each absolute or relative measurement is gated
against the fused prediction (chi-square, ``gate_probability``; a relative observation
with the joint covariance of both drones, cross terms included) before it is fused;
failures drop it, repeated failures reject the source, and a lost or rejected source is
fused again on evidence (``readmit_after_s``, ``readmit_fraction``). GNSS also goes
through a windowed drift test against the drone's own velocity (:mod:`skyfix.fusion.drift`);
after a drift it is re-admitted when it agrees with the velocity again, and the drone's
chain is re-anchored on it (the spoof corrupted the estimate, not the honest receiver).

Trust: relative observations come only from observers on the roster (see
:class:`FusionConfig`); the observer's position is always its own state in the engine.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from skyfix import validate
from skyfix.errors import InputError, NotAvailableError
from skyfix.fusion.config import FusionConfig
from skyfix.fusion.drift import GnssDriftTest
from skyfix.fusion.estimate import Estimate
from skyfix.fusion.health import HealthState, SourceHealth, SourceMonitor
from skyfix.fusion.log import MeasurementLog
from skyfix.fusion.velocity import IntervalVelocity
from skyfix.fusion.window import GraphWindow
from skyfix.geo import LocalFrame
from skyfix.types import GeoFix, RelativeObservation

log = logging.getLogger(__name__)

_ROTATION_REFRESH_M = 100.0  # ENU axes turn ~0.0009 deg per 100 m: refresh a drone's axes after this
_EYE3 = np.eye(3)
_MAX_TIME_JUMP_S = 30.0      # an input this far ahead of the engine's clock is refused (units mix-up, bad clock)


@dataclass
class _Drone:
    index: int
    first_k: int | None = None          # oldest and newest grid steps with states (None: not anchored)
    last_k: int | None = None
    last_time_s: float = -math.inf       # newest measurement time of this drone
    velocity: tuple[float, np.ndarray, float] | None = None  # (t, v in frame axes, per-axis variance incl. model)
    monitors: dict[str, SourceMonitor] = field(default_factory=dict)
    r_frame_from_local: np.ndarray = field(default_factory=lambda: np.eye(3))
    axes_at_enu_m: np.ndarray | None = None  # where r_frame_from_local and up_minus_alt_m were taken
    up_minus_alt_m: float | None = None      # near there: up_m = alt_m + this
    cov_cache: tuple[int, np.ndarray] | None = None
    intervals: IntervalVelocity | None = None
    drift: GnssDriftTest | None = None
    drift_rejected: bool = False             # GNSS refused by the drift test; re-admitted against the velocity
    drift_strikes: int = 0                   # consecutive fixes failing the drift test
    reporting: bool = False                  # has reported its own sensors (may observe others on an open roster)

    @property
    def anchored(self) -> bool:
        return self.last_k is not None


class FusionEngine:
    """Fused positions of several drones in one local ENU frame (see module docs).

    ``origin`` (lat_deg, lon_deg, alt_m ellipsoidal) fixes the frame; ``lag_s`` the
    window kept for late measurements and smoothing (longer: more latency and CPU);
    ``log_path`` records every input to a replayable measurement log. Not thread-safe:
    call it from one thread (or behind one lock).
    """

    def __init__(self, origin: tuple[float, float, float], lag_s: float = 2.0, config: FusionConfig | None = None,
                 log_path: str | Path | None = None) -> None:
        try:
            lat0, lon0, alt0 = origin
        except (TypeError, ValueError):
            raise InputError(f"origin must be (lat_deg, lon_deg, alt_m), got {origin!r}") from None
        self.frame = LocalFrame(lat0, lon0, alt0)
        self.origin = (self.frame.lat0_deg, self.frame.lon0_deg, self.frame.alt0_m)
        self.config = config if config is not None else FusionConfig()
        if not isinstance(self.config, FusionConfig):
            raise InputError(f"config must be a FusionConfig, got {type(self.config).__name__}")
        self.lag_s = validate.positive_scalar("lag_s", lag_s)
        if self.lag_s < 3 * self.config.state_dt_s:
            raise InputError(f"lag_s must be at least 3 state steps ({3 * self.config.state_dt_s:g} s), got {lag_s}")
        cfg = self.config
        self._gate = {dof: cfg.gate_chi2(dof) for dof in (1, 2, 3)}
        self._drift_gate = cfg.gate_chi2(2, cfg.drift_gate_probability)
        self._readmit_gate = cfg.gate_chi2(2, 0.95)  # after a drift: agreement with the velocity, both tests
        self._gm_sigma = np.array([cfg.gnss_gm_h_sigma_m, cfg.gnss_gm_h_sigma_m, cfg.gnss_gm_v_sigma_m])
        self._next_index = 0
        self._q0 = self._q_sigma = self._q_walk = None
        if cfg.velocity_scale_heading:  # (scale, heading rad, pinned 0)
            self._q0 = np.zeros(3)
            self._q_sigma = np.array([cfg.velocity_scale_sigma, math.radians(cfg.velocity_heading_sigma_deg), 1e-6])
            self._q_walk = np.array([cfg.velocity_scale_walk_per_sqrt_s,
                                     math.radians(cfg.velocity_heading_walk_deg_per_sqrt_s), 1e-9]) \
                * math.sqrt(cfg.state_dt_s)
        self._unknown_observers = 0
        self._unknown_last: tuple[str, float] | None = None
        self._vel_sigma_floor = cfg.velocity_model_sigma_mps
        self._window: GraphWindow | None = None
        self._drones: dict[str, _Drone] = {}
        self.now_s = -math.inf
        self._log: MeasurementLog | None = None
        if log_path is not None:
            self._log = MeasurementLog(log_path, {"origin": list(self.origin), "lag_s": self.lag_s,
                                                  "config": cfg.to_dict()}, fsync_s=cfg.log_fsync_s)

    # -- public inputs -------------------------------------------------------------------
    def add_gnss(self, drone_id: str, time_s: float, lat_deg: float, lon_deg: float, alt_m: float, *,
                 h_sigma_m: float | None = None, v_sigma_m: float | None = None, fix_type: int = 3,
                 satellites: int | None = None, hdop: float | None = None) -> None:
        """A GNSS position (WGS84, ellipsoidal height) with the receiver's quality figures.

        ``fix_type`` follows MAVLink GPS_FIX_TYPE (0/1 no fix, 2 2-D, 3 3-D, 4 DGPS, 5/6
        RTK); a no-fix message marks GNSS lost and is never used as a position.
        ``h_sigma_m``/``v_sigma_m`` 1-sigma accuracy; if absent, ``hdop x gnss_uere_m``.
        """
        drone_id = _drone_id(drone_id)
        t = self._time("time_s", time_s)
        fix_type = _int_in("fix_type", fix_type, 0, 8)
        if fix_type >= 2:
            lat = float(validate.latitude("lat_deg", lat_deg))
            lon = float(validate.longitude("lon_deg", lon_deg))
            alt = validate.finite_scalar("alt_m", alt_m)
        sats = None if satellites is None else _int_in("satellites", satellites, 0, 255)
        hd = None if hdop is None else validate.positive_scalar("hdop", hdop)
        h = None if h_sigma_m is None else validate.positive_scalar("h_sigma_m", h_sigma_m)
        v = None if v_sigma_m is None else validate.positive_scalar("v_sigma_m", v_sigma_m)
        self._record("gnss", dict(drone_id=drone_id, time_s=t, lat_deg=lat_deg, lon_deg=lon_deg, alt_m=alt_m,
                                  h_sigma_m=h, v_sigma_m=v, fix_type=fix_type, satellites=sats, hdop=hd))
        drone = self._reporter(drone_id)
        self._advance(t, drone)
        cfg = self.config
        monitor = self._monitor(drone, "gnss", cfg.gnss_timeout_s, t)
        if monitor.repeat(t):
            log.debug("duplicate message at time_s=%s dropped", t)
            return
        if fix_type < 2:
            monitor.no_fix(t, f"receiver reports no fix (fix type {fix_type})")
            return
        issues = []
        if fix_type == 2:
            issues.append("2-D fix")
        if sats is not None and sats < cfg.gnss_min_satellites:
            issues.append(f"{sats} satellites")
        if hd is not None and hd > cfg.gnss_max_hdop:
            issues.append(f"HDOP {hd:g}")
        slow = monitor.rate_issue(t)
        if slow:
            issues.append(slow)
        h_sigma = h if h is not None else cfg.gnss_uere_m * (hd if hd is not None else 1.0)
        v_sigma = v if v is not None else h_sigma * cfg.gnss_vertical_factor
        if fix_type == 2:
            v_sigma = max(v_sigma, 1e3)  # a 2-D fix's altitude carries no information
        if issues:
            h_sigma *= cfg.degraded_sigma_factor
            v_sigma *= cfg.degraded_sigma_factor
        # The wandering part of the reported accuracy is the error state; the rest is white.
        floor2 = cfg.gnss_white_min_sigma_m**2
        white2 = np.maximum(np.array([h_sigma, h_sigma, v_sigma]) ** 2 - self._gm_sigma**2, floor2)
        enu = np.array([float(c) for c in self.frame.to_enu(lat, lon, alt)])
        self._refresh_axes(drone, enu)
        r = drone.r_frame_from_local
        self._gnss(drone, monitor, t, enu, r @ np.diag(white2) @ r.T, ", ".join(issues) or None)

    def add_velocity(self, drone_id: str, time_s: float, vel_enu_mps, sigma_mps) -> None:
        """The autopilot's velocity (m/s, ENU axes at the drone) and its white-noise 1-sigma.

        Its slowly varying bias is estimated (random walk ``bias_walk_mps_per_sqrt_s``).
        """
        drone_id = _drone_id(drone_id)
        t = self._time("time_s", time_s)
        vel = validate.finite_array("vel_enu_mps", vel_enu_mps)
        if vel.shape != (3,):
            raise InputError(f"vel_enu_mps must have shape (3,), got {vel.shape}")
        sigma = validate.finite_array("sigma_mps", sigma_mps) * np.ones(3)
        if sigma.shape != (3,) or (sigma <= 0).any():
            raise InputError(f"sigma_mps must be > 0 (a scalar or 3 values), got {sigma_mps!r}")
        self._record("velocity", dict(drone_id=drone_id, time_s=t, vel_enu_mps=vel, sigma_mps=sigma))
        drone = self._reporter(drone_id)
        self._advance(t, drone)
        self._monitor(drone, "velocity", self.config.velocity_timeout_s, t).judge(t, True)
        if drone.anchored and drone.axes_at_enu_m is None:
            self._refresh_from_estimate(drone)
        vel_frame = drone.r_frame_from_local @ vel
        self._drift_test(drone).velocity(t, vel_frame)
        if drone.velocity is None or t >= drone.velocity[0]:
            drone.velocity = (t, vel_frame, float(sigma.max()) ** 2 + self._vel_sigma_floor**2)
        scaled = self.config.velocity_scale_heading
        for j, mean, sig in self._intervals(drone).add(t, vel_frame, sigma):
            if not drone.anchored or j < self._window.oldest_alive_step() or j < drone.first_k:
                continue
            self._ensure(drone, j + 1)
            add = self._window.velocity_scaled if scaled else self._window.velocity
            add(drone.index, j, mean, np.hypot(sig, self.config.velocity_model_sigma_mps))

    def add_altitude(self, drone_id: str, time_s: float, alt_m: float, sigma_m: float) -> None:
        """A height (metres above the WGS84 ellipsoid, e.g. a barometer referenced to it)."""
        drone_id = _drone_id(drone_id)
        t = self._time("time_s", time_s)
        alt = validate.finite_scalar("alt_m", alt_m)
        sigma = validate.positive_scalar("sigma_m", sigma_m)
        self._record("altitude", dict(drone_id=drone_id, time_s=t, alt_m=alt, sigma_m=sigma))
        drone = self._reporter(drone_id)
        self._advance(t, drone)
        monitor = self._monitor(drone, "altitude", self.config.altitude_timeout_s, t)
        if monitor.repeat(t):
            log.debug("duplicate message at time_s=%s dropped", t)
            return
        if not drone.anchored:
            monitor.judge(t, True)
            return
        if drone.up_minus_alt_m is None:  # placed by helpers only: take the local vertical from the estimate
            self._refresh_from_estimate(drone)
        up = alt + drone.up_minus_alt_m
        k = self._step_checked(t, "altitude")
        predicted = self._predict(drone, t)
        consistent = True
        if predicted is not None:
            p, cov = predicted
            consistent = (up - p[2]) ** 2 / (cov[2, 2] + sigma**2) <= self._gate[1]
        if not monitor.judge(t, consistent):
            return
        self._ensure(drone, k)
        shift, shift_var = self._shift(drone, t, k)
        self._window.altitude(drone.index, k, up + shift[2], math.sqrt(sigma**2 + shift_var))

    def add_fix(self, drone_id: str, fix: GeoFix) -> None:
        """An absolute fix of the drone (e.g. from fiducial tags); source ``fix:<source_id>``."""
        drone_id = _drone_id(drone_id)
        if not isinstance(fix, GeoFix):
            raise InputError(f"fix must be a skyfix.types.GeoFix, got {type(fix).__name__}")
        t = self._time("fix.time_s", fix.time_s)
        _positive_definite("fix.cov_enu_m2", fix.cov_enu_m2)
        self._record("fix", dict(drone_id=drone_id, fix=fix))
        drone = self._reporter(drone_id)
        self._advance(t, drone)
        monitor = self._monitor(drone, f"fix:{fix.source_id or 'fix'}", self.config.fix_timeout_s, t)
        if monitor.repeat(t):
            log.debug("duplicate message at time_s=%s dropped", t)
            return
        enu = np.array([float(c) for c in self.frame.to_enu(fix.lat_deg, fix.lon_deg, fix.alt_m)])
        self._refresh_axes(drone, enu)
        r = drone.r_frame_from_local
        self._absolute(drone, monitor, t, enu, r @ fix.cov_enu_m2 @ r.T, None, robust=False)

    def add_relative(self, obs: RelativeObservation) -> None:
        """A helper's observation of a target (source ``relative:<observer_id>`` of the target).

        The observer must be on the roster (``FusionConfig.roster``; with none, a drone that
        reports its own sensors to this engine); otherwise :class:`InputError`, counted in
        the target's ``health()`` as ``relative:unknown``. The observer's position is its
        own state here: a position carried in the message is never used. Both drones'
        states are tied by the observation, so the observer's own uncertainty counts, and
        the gate uses their joint covariance. An observer not yet localised is ignored.
        """
        if not isinstance(obs, RelativeObservation):
            raise InputError(f"obs must be a skyfix.types.RelativeObservation, got {type(obs).__name__}")
        observer_id, target_id = _drone_id(obs.observer_id), _drone_id(obs.target_id)
        if observer_id == target_id:
            raise InputError(f"RelativeObservation observer and target are the same drone {observer_id!r}")
        t = self._time("obs.time_s", obs.time_s)
        _positive_definite("obs.cov_enu_m2", obs.cov_enu_m2)
        self._check_observer(observer_id, target_id, t)
        self._record("relative", dict(obs=obs))
        observer, target = self._drones[observer_id], self._drone(target_id)
        self._advance(t, target)
        if not observer.anchored:
            log.debug("observer %s not localised: observation of %s unused", observer_id, target_id)
            return
        monitor = self._monitor(target, f"relative:{observer_id}", self.config.relative_timeout_s, t)
        if monitor.repeat(t):
            log.debug("duplicate message at time_s=%s dropped", t)
            return
        r = observer.r_frame_from_local
        offset = r @ obs.offset_enu_m
        cov = r @ obs.cov_enu_m2 @ r.T
        k = self._step_checked(t, "relative observation")
        consistent = True
        p_obs, p_tgt = self._predict(observer, t), self._predict(target, t)
        if p_tgt is not None:
            innovation = offset - (p_tgt[0] - p_obs[0])
            cross = self._cross_cov(observer, target)
            consistent = self._nis(innovation, p_tgt[1] + p_obs[1] - cross - cross.T + cov) <= self._gate[3]
        if not monitor.judge(t, consistent):
            return
        self._ensure(observer, k)
        if not target.anchored:
            self._anchor(target, k, p_obs[0] + offset)
        self._ensure(target, k)
        s_obs, v_obs = self._shift(observer, t, k)
        s_tgt, v_tgt = self._shift(target, t, k)
        self._window.relative(observer.index, target.index, k, offset + s_tgt - s_obs,
                              cov + _EYE3 * (v_obs + v_tgt))

    # -- solving and answers ----------------------------------------------------------
    def update(self) -> None:
        """Run the smoother on everything added since the last update (a no-op if nothing)."""
        if self._window is None:
            return
        # A drone that stopped reporting keeps states near the present so it stays in the window.
        keep_k = self._window.step_of(self.now_s) - self._window.lag_steps // 2
        for drone in self._drones.values():
            if drone.anchored and drone.last_k < keep_k:
                self._ensure(drone, keep_k)
        if not self._window.pending:
            return
        if self._log is not None:
            self._log.record("update")
        # Joint covariance for every drone's settled step: what gates and answers read (a 27 x 27
        # inverse for 3 drones; older steps, asked for rarely, go through gtsam's Marginals).
        tail = [self._window.key(drone.index, kind, self._settled_step(drone))
                for drone in self._drones.values() if drone.anchored for kind in range(3)]
        self._window.update(tail)
        oldest = self._window.oldest_alive_step()
        for drone_id, drone in self._drones.items():
            drone.cov_cache = None
            if drone.anchored and drone.last_k < oldest:
                log.warning("drone %s has no states left in the window; it must be re-anchored", drone_id)
                drone.first_k = drone.last_k = None
            elif drone.anchored:
                drone.first_k = max(drone.first_k, oldest)

    def estimate(self, drone_id: str, t: float | None = None) -> Estimate:
        """Fused state of ``drone_id`` at ``t`` (default: its newest measurement time).

        ``t`` may lie anywhere inside the lag (a smoothed answer) or ahead of the newest
        state (a prediction with grown covariance).
        """
        drone = self._known(drone_id)
        self.update()
        if not drone.anchored:
            raise NotAvailableError(f"drone {drone_id!r} has no absolute position yet (needs GNSS, a fix, or a "
                                    "relative observation by a localised drone)")
        t_s = drone.last_time_s if t is None else validate.finite_scalar("t", t)
        window = self._window
        oldest_s = window.time_of(drone.first_k) - window.dt_s / 2
        if t_s < oldest_s:
            raise InputError(f"t={t_s} is before drone {drone_id!r}'s window (oldest {oldest_s:.3f} s, lag_s "
                             f"{self.lag_s:g}); record estimates as they come or replay the log")
        k = min(max(window.step_of(t_s), drone.first_k), self._settled_step(drone))
        p_k = window.value(drone.index, 0, k)
        cov_k = window.covariance(drone.index, 0, k)
        shift, shift_var = self._shift(drone, t_s, k)
        enu = p_k - shift  # shift moves from t to the grid; the estimate goes the other way
        cov = cov_k + _EYE3 * shift_var
        vel, vel_cov = self._velocity_estimate(drone, t_s, k)
        lat, lon, alt = (float(c) for c in self.frame.to_geodetic(*enu))
        return Estimate(drone_id=_drone_id(drone_id), time_s=t_s, lat_deg=lat, lon_deg=lon, alt_m=alt,
                        enu_m=enu, cov_enu_m2=0.5 * (cov + cov.T), vel_enu_mps=vel, vel_cov_enu_m2ps2=vel_cov,
                        sources=self._contributing(drone), health=self._health(drone))

    def health(self, drone_id: str) -> dict[str, SourceHealth]:
        """State of every source of ``drone_id`` at the engine's current time."""
        return self._health(self._known(drone_id))

    @property
    def drone_ids(self) -> tuple[str, ...]:
        return tuple(self._drones)

    def record_truth(self, drone_id: str, time_s: float, lat_deg: float, lon_deg: float, alt_m: float) -> None:
        """Write a ground-truth position into the measurement log (simulations; not used by the engine)."""
        if self._log is not None:
            self._log.truth(_drone_id(drone_id), time_s, lat_deg, lon_deg, alt_m)

    def close(self) -> None:
        """Flush and close the measurement log."""
        if self._log is not None:
            self._log.close()

    def __enter__(self) -> FusionEngine:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- internals ---------------------------------------------------------------------------
    def _record(self, op: str, args: dict) -> None:
        if self._log is not None:
            self._log.record(op, args)

    def _time(self, name: str, value) -> float:
        t = validate.finite_scalar(name, value)
        if self._window is not None:
            oldest_s = self._window.time_of(self._window.oldest_alive_step()) - self._window.dt_s / 2
            if t < oldest_s:
                raise InputError(f"{name}={t} is older than the fusion lag allows (oldest usable {oldest_s:.3f}, "
                                 f"engine time {self.now_s:.3f}, lag_s {self.lag_s:g})")
        if self.now_s > -math.inf and t > self.now_s + _MAX_TIME_JUMP_S:
            raise InputError(f"{name}={t} jumps {t - self.now_s:.1f} s ahead of the engine time {self.now_s:.3f}; "
                             f"more than {_MAX_TIME_JUMP_S:g} s looks like a clock or unit error")
        return t

    def _drone(self, drone_id: str) -> _Drone:
        drone = self._drones.get(drone_id)
        if drone is None:
            if len(self._drones) >= self.config.max_drones:
                raise InputError(f"drone id {drone_id!r} would be drone {len(self._drones) + 1}, more than "
                                 f"FusionConfig.max_drones {self.config.max_drones}; known: {sorted(self._drones)}")
            drone = self._drones[drone_id] = _Drone(index=self._new_index())
        return drone

    def _new_index(self) -> int:
        self._next_index += 1
        return self._next_index - 1

    def _reporter(self, drone_id: str) -> _Drone:
        """The drone sending its own sensor data (it may then observe others on an open roster)."""
        drone = self._drone(drone_id)
        drone.reporting = True
        return drone

    def _check_observer(self, observer_id: str, target_id: str, t: float) -> None:
        """Refuse (InputError) an observation by a drone off the roster, or of a target off it."""
        roster = self.config.roster
        observer = self._drones.get(observer_id)
        if roster:
            trusted = observer_id in roster
        else:
            trusted = observer is not None and observer.reporting
        if trusted and roster and target_id not in roster:
            raise InputError(f"relative observation of {target_id!r}, which is not on the roster {list(roster)}")
        if trusted:
            if observer is None:
                self._drone(observer_id)
            return
        self._unknown_observers += 1
        self._unknown_last = (observer_id, t)
        target = self._drones.get(target_id)
        if target is not None:
            target.monitors.setdefault("relative:unknown", SourceMonitor(math.inf, 1, math.inf, t)).reject(
                t, f"{self._unknown_observers} observation(s) from observers not on the roster (last {observer_id!r})")
        who = f"the roster {list(roster)}" if roster else f"the drones reporting their own sensors {self._reporting()}"
        raise InputError(f"relative observation from unknown observer {observer_id!r} (not in {who}); "
                         "its observation and any position it carries are ignored")

    def _reporting(self) -> list[str]:
        return sorted(d for d, drone in self._drones.items() if drone.reporting)

    @property
    def unknown_observations(self) -> int:
        """Relative observations refused because their observer is not on the roster."""
        return self._unknown_observers

    def _known(self, drone_id) -> _Drone:
        drone = self._drones.get(_drone_id(drone_id))
        if drone is None:
            raise InputError(f"unknown drone id {drone_id!r}; known: {sorted(self._drones)}")
        return drone

    def _monitor(self, drone: _Drone, source: str, timeout_s: float, t: float) -> SourceMonitor:
        monitor = drone.monitors.get(source)
        if monitor is None:
            cfg = self.config
            monitor = drone.monitors[source] = SourceMonitor(timeout_s, cfg.reject_after, cfg.readmit_after_s, t)
        return monitor

    def _advance(self, t: float, drone: _Drone) -> None:
        if self._window is None:
            cfg = self.config
            epoch = math.floor((t - 10.0 * self.lag_s) / cfg.state_dt_s) * cfg.state_dt_s
            self._window = GraphWindow(self.lag_s, cfg.state_dt_s, epoch, cfg.max_iterations, cfg.robust_k)
        self.now_s = max(self.now_s, t)
        drone.last_time_s = max(drone.last_time_s, t)

    def _step_checked(self, t: float, what: str) -> int:
        k = self._window.step_of(t)
        if k < self._window.oldest_alive_step():
            raise InputError(f"{what} at time_s={t} is older than the fusion lag ({self.lag_s:g} s)")
        return k

    def _refresh_axes(self, drone: _Drone, enu: np.ndarray) -> None:
        """The drone's local ENU axes and height offset, taken again after it moved 100 m (frame ENU, m)."""
        if drone.axes_at_enu_m is not None and np.linalg.norm(enu - drone.axes_at_enu_m) < _ROTATION_REFRESH_M:
            return
        lat, lon, alt = (float(c) for c in self.frame.to_geodetic(*enu))
        drone.r_frame_from_local = self.frame.enu_rotation_at(lat, lon)
        drone.axes_at_enu_m = enu.copy()
        drone.up_minus_alt_m = float(enu[2]) - alt

    def _refresh_from_estimate(self, drone: _Drone) -> None:
        """Local axes at the drone's current estimate (drones placed only by helpers)."""
        self._refresh_axes(drone, self._window.value(drone.index, 0, drone.last_k))

    def _drift_test(self, drone: _Drone) -> GnssDriftTest:
        if drone.drift is None:
            cfg = self.config
            drone.drift = GnssDriftTest(cfg.drift_window_s, cfg.gnss_gm_h_sigma_m, cfg.gnss_gm_tau_s,
                                        cfg.bias_walk_mps_per_sqrt_s, cfg.velocity_timeout_s)
        return drone.drift

    def _gnss(self, drone: _Drone, monitor: SourceMonitor, t: float, enu: np.ndarray, cov_white: np.ndarray,
              quality: str | None) -> None:
        """Gate, drift-test and fuse a GNSS fix (``cov_white``: its white part, frame axes)."""
        k = self._step_checked(t, "GNSS fix")
        drift = self._drift_test(drone)
        residual = drift.residual(t, enu)
        white_var = float(np.trace(cov_white[:2, :2])) / 2.0
        predicted = self._predict(drone, t, gnss=True)
        consistent = predicted is None or self._nis(enu - predicted[0], predicted[1] + cov_white) <= self._gate[3]
        after_drift = drone.drift_rejected and drift.reference is not None
        if after_drift:
            # the estimate is suspect: judge GNSS against the velocity since before the drift
            drift.record(t, residual, white_var)
            consistent = drift.agrees_with_reference(t, residual, white_var, self._readmit_gate)
        elif monitor.on_probation:
            drift.forget()  # a track GNSS had while out of use must not count in the drift test
        if not monitor.judge(t, consistent, quality):
            return
        if after_drift or drone.drift_rejected:
            drone.drift_rejected = False
            drift.forget()
            if after_drift:
                log.warning("GNSS re-admitted after a drift: re-anchoring the drone on it")
                self._reanchor(drone, k, drift.reference_bias(t))
        else:
            drift.record(t, residual, white_var)
            if self._drifting(drone, monitor, t):
                return
        if not drone.anchored:
            self._anchor(drone, k, enu)
        self._ensure(drone, k)
        shift, shift_var = self._shift(drone, t, k)
        self._window.gnss(drone.index, k, enu + shift, cov_white + _EYE3 * shift_var)

    def _drifting(self, drone: _Drone, monitor: SourceMonitor, t: float) -> bool:
        """Windowed drift test of the drone's GNSS against its velocity; rejects GNSS on failure."""
        cached = self._latest_cov(drone) if drone.anchored else None
        if cached is None:
            return False
        k, cov = cached
        drone.drift.bias(t, self._window.value(drone.index, 1, k), cov[3:6, 3:6])
        nis = drone.drift.window_nis(t)
        drone.drift_strikes = drone.drift_strikes + 1 if nis is not None and nis > self._drift_gate else 0
        if drone.drift_strikes < 2:  # two fixes in a row: one odd window is not a drift
            return False
        drone.drift.hold_reference(t)
        drone.drift_rejected = True
        monitor.reject(t, f"drifting against the velocity over {self.config.drift_window_s:g} s (NIS {nis:.0f})")
        return True

    def _reanchor(self, drone: _Drone, k: int, horizontal_bias: tuple[np.ndarray, np.ndarray] | None) -> None:
        """Start a new state chain for the drone at step k (its history was corrupted); the
        velocity bias carries over with its covariance (horizontally the one from before the
        drift, ``horizontal_bias``, if given), the position comes from what follows."""
        old, last = drone.index, drone.last_k
        b, b_cov = np.zeros(3), _EYE3 * self.config.bias_initial_sigma_mps**2
        cached = self._latest_cov(drone) if drone.anchored else None
        if cached is not None:
            b, b_cov = self._window.value(old, 1, cached[0]).copy(), cached[1][3:6, 3:6].copy()
        if horizontal_bias is not None:
            b[:2] = horizontal_bias[0]
            b_cov[:2, :] = b_cov[:, :2] = 0.0
            b_cov[:2, :2] = horizontal_bias[1]
        p0 = self._window.value(old, 0, last) if last is not None else None
        drone.index = self._new_index()
        drone.first_k = drone.last_k = None
        drone.intervals = None
        drone.cov_cache = None
        if p0 is not None:
            self._anchor(drone, k, p0, b, b_cov, p_sigma_m=self.config.max_speed_mps)

    def _cross_cov(self, a: _Drone, b: _Drone) -> np.ndarray:
        """Cross covariance (3, 3) of two drones' newest solved positions (zero if unknown)."""
        ca, cb = self._latest_cov(a), self._latest_cov(b)
        if ca is None or cb is None:
            return np.zeros((3, 3))
        w = self._window
        joint = w.joint_covariance([w.key(a.index, 0, ca[0]), w.key(b.index, 0, cb[0])])
        return np.zeros((3, 3)) if joint is None else joint[:3, 3:]

    def _absolute(self, drone: _Drone, monitor: SourceMonitor, t: float, enu: np.ndarray, cov: np.ndarray,
                  quality: str | None, robust: bool = True) -> None:
        k = self._step_checked(t, "measurement")
        predicted = self._predict(drone, t)
        consistent = True
        if predicted is not None:
            consistent = self._nis(enu - predicted[0], predicted[1] + cov) <= self._gate[3]
        if not monitor.judge(t, consistent, quality):
            return
        if not drone.anchored:
            self._anchor(drone, k, enu)
        self._ensure(drone, k)
        shift, shift_var = self._shift(drone, t, k)
        self._window.position(drone.index, k, enu + shift, cov + _EYE3 * shift_var, robust)

    def _anchor(self, drone: _Drone, k: int, p0: np.ndarray, b0: np.ndarray | None = None,
                b_cov: np.ndarray | None = None, p_sigma_m: float | None = None) -> None:
        """First state of a drone at step k; the caller adds the factor that fixes its position
        (or ``p_sigma_m`` gives it a weak prior about ``p0``). The GNSS error starts from its
        stationary distribution."""
        window, cfg = self._window, self.config
        window.new_state(drone.index, k, p0, np.zeros(3) if b0 is None else b0, np.zeros(3), self._q0)
        if b_cov is None:
            window.prior_bias(drone.index, k, cfg.bias_initial_sigma_mps)
        else:
            window.prior(drone.index, 1, k, b0, b_cov)
        r = drone.r_frame_from_local
        window.prior(drone.index, 2, k, np.zeros(3), r @ np.diag(self._gm_sigma**2) @ r.T)
        if self._q_sigma is not None:
            window.prior(drone.index, 3, k, np.zeros(3), np.diag(self._q_sigma**2))
        if p_sigma_m is not None:
            window.prior(drone.index, 0, k, p0, _EYE3 * p_sigma_m**2)
        drone.first_k = drone.last_k = k
        self._intervals(drone).start_at(k)

    def _intervals(self, drone: _Drone) -> IntervalVelocity:
        if drone.intervals is None:
            drone.intervals = IntervalVelocity(self._window.epoch_s, self._window.dt_s, self.config.velocity_timeout_s)
        return drone.intervals

    def _ensure(self, drone: _Drone, k: int) -> None:
        """Create the drone's states up to step k (forwards or backwards), each tied to its neighbour."""
        window, cfg = self._window, self.config
        walk = cfg.max_speed_mps * cfg.state_dt_s
        bias_walk = cfg.bias_walk_mps_per_sqrt_s * math.sqrt(cfg.state_dt_s)
        phi = math.exp(-cfg.state_dt_s / cfg.gnss_gm_tau_s)
        i = drone.index
        while drone.last_k < k:
            prev = drone.last_k
            p_prev, b_prev = window.value(i, 0, prev), window.value(i, 1, prev)
            step = np.zeros(3)
            if drone.velocity is not None and abs(window.time_of(prev) - drone.velocity[0]) <= cfg.velocity_timeout_s:
                step = (drone.velocity[1] - b_prev) * window.dt_s
            window.new_state(i, prev + 1, p_prev + step, b_prev, phi * window.value(i, 2, prev),
                             None if self._q0 is None else window.value(i, 3, prev))
            window.motion(i, prev, walk, bias_walk, self._q_walk)
            window.gauss_markov(i, prev, phi, self._gm_sigma)
            drone.last_k = prev + 1
        while drone.first_k > k:
            nxt = drone.first_k
            if nxt - 1 < window.oldest_alive_step():
                raise InputError("measurement is older than the fusion lag")
            window.new_state(i, nxt - 1, window.value(i, 0, nxt), window.value(i, 1, nxt), window.value(i, 2, nxt),
                             None if self._q0 is None else window.value(i, 3, nxt))
            window.motion(i, nxt - 1, walk, bias_walk, self._q_walk)
            window.gauss_markov(i, nxt - 1, phi, self._gm_sigma)
            drone.first_k = nxt - 1

    def _velocity_now(self, drone: _Drone, t: float) -> tuple[np.ndarray, float] | None:
        """Bias-corrected velocity near ``t`` and its per-axis variance, or None if stale."""
        if drone.velocity is None or abs(t - drone.velocity[0]) > self.config.velocity_timeout_s:
            return None
        if not drone.anchored:
            return drone.velocity[1], drone.velocity[2]
        return drone.velocity[1] - self._window.value(drone.index, 1, drone.last_k), drone.velocity[2]

    def _shift(self, drone: _Drone, t: float, k: int) -> tuple[np.ndarray, float]:
        """Displacement from time t to grid step k (m) and its per-axis variance."""
        dt = self._window.time_of(k) - t
        if abs(dt) < 1e-9:
            return np.zeros(3), 0.0
        vel = self._velocity_now(drone, t)
        if vel is None:
            return np.zeros(3), (self.config.max_speed_mps * dt) ** 2
        return vel[0] * dt, vel[1] * dt * dt + (self.config.bias_initial_sigma_mps * dt) ** 2

    def _settled_step(self, drone: _Drone) -> int:
        """Newest step whose motion from the previous one is known (velocity integrated up to it).

        Later steps exist only because a measurement landed there before the velocity
        covering them arrived; answers are taken from the settled step and moved in time.
        """
        iv = drone.intervals
        if iv is None or iv.next_interval is None or drone.velocity is None \
                or self.now_s - drone.velocity[0] > self.config.velocity_timeout_s:
            return drone.last_k
        return max(drone.first_k, min(drone.last_k, iv.next_interval))

    def _latest_cov(self, drone: _Drone) -> tuple[int, np.ndarray] | None:
        """Joint covariance (9, 9) of [p, b, n] at the settled (else newest optimised) step, cached per update."""
        if drone.cov_cache is None:
            window = self._window
            for k in range(self._settled_step(drone), drone.first_k - 1, -1):
                if window.is_optimised(drone.index, 0, k):
                    keys = [window.key(drone.index, kind, k) for kind in range(3)]
                    cov = window.joint_covariance(keys)
                    if cov is None:  # not in the tail: marginals without cross terms
                        cov = np.zeros((9, 9))
                        for kind in range(3):
                            cov[3 * kind:3 * kind + 3, 3 * kind:3 * kind + 3] = window.covariance(drone.index, kind, k)
                    drone.cov_cache = (k, cov)
                    break
        return drone.cov_cache

    def _predict(self, drone: _Drone, t: float, gnss: bool = False) -> tuple[np.ndarray, np.ndarray] | None:
        """Fused prediction of the drone's position at t (without the measurement at hand);
        with ``gnss``, of what its receiver would report (position plus receiver error)."""
        if not drone.anchored:
            return None
        window = self._window
        k = min(max(window.step_of(t), drone.first_k), self._settled_step(drone))
        shift, shift_var = self._shift(drone, t, k)
        p = window.value(drone.index, 0, k) - shift
        if gnss:
            p = p - window.value(drone.index, 2, k)
        cached = self._latest_cov(drone)
        if cached is None:  # nothing optimised yet: no basis for gating
            return p, _EYE3 * 1e12
        k_cov, joint = cached
        cov = joint[:3, :3]
        if gnss:  # Cov(p - n)
            cov = cov + joint[6:9, 6:9] - joint[:3, 6:9] - joint[6:9, :3]
        gap_s = abs(t - window.time_of(k_cov))
        vel = self._velocity_now(drone, t)
        grow = (self.config.max_speed_mps * gap_s) ** 2 if vel is None else \
            vel[1] * gap_s * window.dt_s + (self.config.bias_initial_sigma_mps * gap_s) ** 2
        return p, cov + _EYE3 * (grow + shift_var)

    @staticmethod
    def _nis(innovation: np.ndarray, cov: np.ndarray) -> float:
        try:
            return float(innovation @ np.linalg.solve(cov, innovation))
        except np.linalg.LinAlgError:
            return math.inf

    def _velocity_estimate(self, drone: _Drone, t: float, k: int) -> tuple[np.ndarray, np.ndarray]:
        window = self._window
        vel = self._velocity_now(drone, t)
        if vel is not None:
            b_cov = window.covariance(drone.index, 1, min(k, self._latest_cov(drone)[0]))
            return vel[0], _EYE3 * vel[1] + b_cov
        k0 = max(drone.first_k, k - int(round(1.0 / window.dt_s)))
        if k0 == k:
            return np.zeros(3), _EYE3 * self.config.max_speed_mps**2
        span_s = (k - k0) * window.dt_s
        v = (window.value(drone.index, 0, k) - window.value(drone.index, 0, k0)) / span_s
        cov = (window.covariance(drone.index, 0, k) + window.covariance(drone.index, 0, k0)) / span_s**2
        return v, cov

    def _tick(self) -> None:
        for drone in self._drones.values():
            for monitor in drone.monitors.values():
                monitor.tick(self.now_s)

    def _health(self, drone: _Drone) -> dict[str, SourceHealth]:
        self._tick()
        return {name: monitor.health for name, monitor in drone.monitors.items()}

    def _contributing(self, drone: _Drone) -> tuple[str, ...]:
        window_s = self.config.contributing_window_s
        return tuple(sorted(name for name, m in drone.monitors.items()
                            if self.now_s - m.last_fused_s <= window_s and m.state is not HealthState.LOST))


def _drone_id(value) -> str:
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        return str(int(value))
    if not isinstance(value, str) or not value.strip():
        raise InputError(f"drone id must be a non-empty string, got {value!r}")
    return value


def _positive_definite(name: str, cov: np.ndarray) -> None:
    """Covariances become gtsam noise models: singular or indefinite ones would poison the solve."""
    eig = np.linalg.eigvalsh(0.5 * (cov + cov.T))
    if not eig[0] > 1e-12 * max(1.0, eig[-1]):
        raise InputError(f"{name} must be positive definite (a measurement with zero uncertainty cannot be "
                         f"fused), got eigenvalues {eig}")


def _int_in(name: str, value, lo: int, hi: int) -> int:
    try:
        out = int(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be an integer, got {value!r}") from None
    if out != value or not lo <= out <= hi:
        raise InputError(f"{name} must be an integer in [{lo}, {hi}], got {value!r}")
    return out
