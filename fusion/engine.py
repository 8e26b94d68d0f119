"""FusionEngine: every drone's fused position from GNSS, velocity, altitude, fixes and helpers.

All states live in one local ENU frame about ``origin`` (exact WGS84 through
:class:`skyfix.geo.LocalFrame`); geodetic inputs are converted on arrival and
directions measured at a drone (velocity, relative bearings, ENU covariances) are
rotated from the ENU axes *at that drone* into the frame's axes. One gtsam window
(:mod:`skyfix.fusion.window`) holds every drone, so a relative observation ties the
observer's and the target's states with both their uncertainties; the chains of states
and their mechanics live in :mod:`skyfix.fusion.chains`.

Time: every input is stamped (seconds, one clock for all). A measurement at ``t`` is
attached to the nearest state on the ``state_dt_s`` grid, moved there with the drone's
bias-corrected velocity (the move's uncertainty is added). Inputs may arrive out of
order as long as they are inside the lag; older ones raise :class:`InputError`.

Health (:mod:`skyfix.fusion.health`): each absolute or relative measurement is gated
against the fused prediction (chi-square, ``gate_probability``; a relative observation
with the joint covariance of both drones, cross terms included) before it is fused;
failures drop it, repeated failures reject the source, and a lost or rejected source is
fused again on evidence (``readmit_after_s``, ``readmit_fraction``). GNSS also goes
through a windowed drift test against the drone's own velocity (:mod:`skyfix.fusion.gnss`,
:mod:`skyfix.fusion.drift`);
after a drift it is re-admitted when it agrees with the velocity again, and the drone's
chain is re-anchored on it (the spoof corrupted the estimate, not the honest receiver).

Trust (:mod:`skyfix.fusion.trust`): relative observations come only from observers on the
roster (see :class:`FusionConfig`); the observer's position is always its own state in the engine.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from skyfix import validate
from skyfix.errors import InputError, NotAvailableError
from skyfix.fusion.chains import EYE3, StateChains, nis
from skyfix.fusion.config import FusionConfig
from skyfix.fusion.drone import DroneState
from skyfix.fusion.drone import drone_id as _drone_id
from skyfix.fusion.estimate import Estimate
from skyfix.fusion.gnss import GnssFusion, gnss_quality
from skyfix.fusion.health import SourceHealth, SourceMonitor
from skyfix.fusion.log import MeasurementLog
from skyfix.fusion.trust import ObserverTrust
from skyfix.fusion.window import GraphWindow
from skyfix.geo import LocalFrame
from skyfix.types import GeoFix, RelativeObservation

log = logging.getLogger(__name__)


class FusionEngine:
    """Fused positions of several drones in one local ENU frame (see module docs).

    ``origin`` (lat_deg, lon_deg, alt_m ellipsoidal) fixes the frame; ``lag_s`` the
    window kept for late measurements and smoothing (longer: more latency and CPU);
    ``log_path`` records every input to a replayable measurement log. Not thread-safe:
    call it from one thread (or behind one lock).

    Example (a hovering drone; the receiver's error wanders, so three fixes are not
    three times the evidence):
        >>> engine = FusionEngine((47.0, 8.0, 400.0), lag_s=2.0)
        >>> for t_s in (0.0, 0.5, 1.0):
        ...     engine.add_gnss("A", t_s, 47.0, 8.0, 400.0, h_sigma_m=1.5, v_sigma_m=2.5)
        ...     engine.add_velocity("A", t_s, [0.0, 0.0, 0.0], 0.1)
        >>> est = engine.estimate("A")
        >>> est.time_s, est.sources, round(est.sigma_horizontal_m, 2)
        (1.0, ('gnss', 'velocity'), 1.51)
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
        self._lag0_s = self.lag_s  # set_lag moves the late-input time-outs by the lag's growth beyond this
        cfg = self.config
        self._gate = {dof: cfg.gate_chi2(dof) for dof in (1, 2, 3)}
        self._chains = StateChains(self.frame, self.lag_s, cfg)
        self._gnss = GnssFusion(cfg, self._chains)
        self._trust = ObserverTrust(cfg.roster)
        self._drones: dict[str, DroneState] = {}
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

        Example:
            >>> engine = FusionEngine((47.0, 8.0, 400.0))
            >>> engine.add_gnss("A", 0.0, 47.0, 8.0, 400.0, satellites=12, hdop=0.8)
            >>> engine.add_gnss("A", 0.2, 0.0, 0.0, 0.0, fix_type=1)  # what receivers send without a fix
            >>> engine.health("A")["gnss"].reason
            'receiver reports no fix (fix type 1)'
        """
        drone_id = _drone_id(drone_id)
        t = self._time("time_s", time_s)
        fix_type = validate.integer_in("fix_type", fix_type, 0, 8)
        if fix_type >= 2:
            lat = float(validate.latitude("lat_deg", lat_deg))
            lon = float(validate.longitude("lon_deg", lon_deg))
            alt = validate.finite_scalar("alt_m", alt_m)
        sats = None if satellites is None else validate.integer_in("satellites", satellites, 0, 255)
        hd = None if hdop is None else validate.positive_scalar("hdop", hdop)
        h = None if h_sigma_m is None else validate.positive_scalar("h_sigma_m", h_sigma_m)
        v = None if v_sigma_m is None else validate.positive_scalar("v_sigma_m", v_sigma_m)
        self._record("gnss", dict(drone_id=drone_id, time_s=t, lat_deg=lat_deg, lon_deg=lon_deg, alt_m=alt_m,
                                  h_sigma_m=h, v_sigma_m=v, fix_type=fix_type, satellites=sats, hdop=hd))
        drone = self._reporter(drone_id)
        self._chains.advance(t, drone)
        cfg = self.config
        monitor = drone.monitor("gnss", cfg.gnss_timeout_s, t, self.config)
        if monitor.repeat(t):
            log.debug("duplicate message at time_s=%s dropped", t)
            return
        if fix_type < 2:
            monitor.no_fix(t, f"receiver reports no fix (fix type {fix_type})")
            return
        h_sigma, v_sigma, quality = gnss_quality(cfg, fix_type, sats, hd, h, v, monitor.rate_issue(t))
        enu = np.array([float(c) for c in self.frame.to_enu(lat, lon, alt)])
        self._chains.refresh_axes(drone, enu)
        self._gnss.fuse(drone, monitor, t, enu, self._gnss.white_cov(drone, h_sigma, v_sigma), quality)

    def add_velocity(self, drone_id: str, time_s: float, vel_enu_mps, sigma_mps, *,
                     bias_walk_mps_per_sqrt_s: float | None = None) -> None:
        """The autopilot's velocity (m/s, ENU axes at the drone) and its white-noise 1-sigma.

        Its slowly varying bias is estimated (random walk ``bias_walk_mps_per_sqrt_s`` of the
        config). A walk given here holds for this drone's states from now on, until another is
        given (the config's again: ``FusionConfig.bias_walk_mps_per_sqrt_s``): e.g. the faster
        wandering error of an autopilot's velocity while it flies on a position fed to it.
        """
        drone_id = _drone_id(drone_id)
        t = self._time("time_s", time_s)
        vel = validate.finite_array("vel_enu_mps", vel_enu_mps)
        if vel.shape != (3,):
            raise InputError(f"vel_enu_mps must have shape (3,), got {vel.shape}")
        sigma = validate.positive_array("sigma_mps", sigma_mps) * np.ones(3)
        if sigma.shape != (3,):
            raise InputError(f"sigma_mps must be > 0 (a scalar or 3 values), got {sigma_mps!r}")
        walk = None if bias_walk_mps_per_sqrt_s is None else \
            validate.positive_scalar("bias_walk_mps_per_sqrt_s", bias_walk_mps_per_sqrt_s)
        self._record("velocity", dict(drone_id=drone_id, time_s=t, vel_enu_mps=vel, sigma_mps=sigma,
                                      **({} if walk is None else {"bias_walk_mps_per_sqrt_s": walk})))
        drone = self._reporter(drone_id)
        drone.bias_walk_mps_per_sqrt_s = walk
        self._chains.advance(t, drone)
        drone.monitor("velocity", self.config.velocity_timeout_s, t, self.config).judge(t, True)
        if drone.anchored and drone.axes_at_enu_m is None:
            self._chains.refresh_from_estimate(drone)
        vel_frame = drone.r_frame_from_local @ vel
        self._gnss.drift_test(drone).velocity(t, vel_frame)
        if drone.velocity is None or t >= drone.velocity[0]:
            drone.velocity = (t, vel_frame, float(sigma.max()) ** 2 + self.config.velocity_model_sigma_mps**2)
        scaled = self.config.velocity_scale_heading
        for j, mean, sig in self._chains.intervals(drone).add(t, vel_frame, sigma):
            if not drone.anchored or j < self._window.oldest_alive_step() or j < drone.first_k:
                continue
            self._chains.ensure(drone, j + 1)
            add = self._window.velocity_scaled if scaled else self._window.velocity
            add(drone.index, j, mean, np.hypot(sig, self.config.velocity_model_sigma_mps))

    def add_altitude(self, drone_id: str, time_s: float, alt_m: float, sigma_m: float) -> None:
        """A height (metres above the WGS84 ellipsoid, e.g. a barometer referenced to it).

        Example (a 0.5 m barometer tightens a 2.5 m GNSS height):
            >>> engine = FusionEngine((47.0, 8.0, 400.0))
            >>> engine.add_gnss("A", 0.0, 47.0, 8.0, 400.0, h_sigma_m=1.5, v_sigma_m=2.5)
            >>> engine.add_altitude("A", 0.0, 401.0, 0.5)
            >>> round(float(engine.estimate("A").cov_enu_m2[2, 2]) ** 0.5, 2)
            0.49
        """
        drone_id = _drone_id(drone_id)
        t = self._time("time_s", time_s)
        alt = validate.finite_scalar("alt_m", alt_m)
        sigma = validate.positive_scalar("sigma_m", sigma_m)
        self._record("altitude", dict(drone_id=drone_id, time_s=t, alt_m=alt, sigma_m=sigma))
        drone = self._reporter(drone_id)
        self._chains.advance(t, drone)
        monitor = drone.monitor("altitude", self.config.altitude_timeout_s, t, self.config)
        if monitor.repeat(t):
            log.debug("duplicate message at time_s=%s dropped", t)
            return
        if not drone.anchored:
            monitor.judge(t, True)
            return
        if drone.up_minus_alt_m is None:  # placed by helpers only: take the local vertical from the estimate
            self._chains.refresh_from_estimate(drone)
        up = alt + drone.up_minus_alt_m
        k = self._chains.step_checked(t, "altitude")
        predicted = self._chains.predict(drone, t)
        consistent = True
        if predicted is not None:
            p, cov = predicted
            consistent = (up - p[2]) ** 2 / (cov[2, 2] + sigma**2) <= self._gate[1]
        if not monitor.judge(t, consistent):
            return
        self._chains.ensure(drone, k)
        shift, shift_var = self._chains.shift(drone, t, k)
        self._window.altitude(drone.index, k, up + shift[2], math.sqrt(sigma**2 + shift_var))

    def add_fix(self, drone_id: str, fix: GeoFix, *, correlated: bool = False) -> None:
        """An absolute fix of the drone (e.g. from fiducial tags); source ``fix:<source_id>``.

        ``correlated``: the fix's error wanders like a GNSS receiver's, e.g. a peer's fused estimate,
        which rides on its own receiver's error. It is then a fix of the drone's position plus its
        Gauss-Markov error state (``gnss_gm_*``, as for this engine's own receivers), its stated
        covariance less that wandering part taken as white; so a peer's fixes at 2 Hz count as one
        slowly wandering fix, not as independent evidence that averages its receiver's bias away.
        (A peer stating less than the wandering sigma is taken at that sigma: conservative.)

        Example:
            >>> engine = FusionEngine((47.0, 8.0, 400.0))
            >>> engine.add_fix("A", GeoFix(47.0, 8.0, 400.0, np.eye(3) * 0.04, time_s=0.0, source_id="tags"))
            >>> engine.estimate("A").sources, round(engine.estimate("A").sigma_horizontal_m, 2)
            (('fix:tags',), 0.2)
        """
        drone_id = _drone_id(drone_id)
        if not isinstance(fix, GeoFix):
            raise InputError(f"fix must be a skyfix.types.GeoFix, got {type(fix).__name__}")
        t = self._time("fix.time_s", fix.time_s)
        validate.positive_definite("fix.cov_enu_m2", fix.cov_enu_m2)
        self._record("fix", dict(drone_id=drone_id, fix=fix, **({"correlated": True} if correlated else {})))
        drone = self._reporter(drone_id)
        self._chains.advance(t, drone)
        monitor = drone.monitor(f"fix:{fix.source_id or 'fix'}", self.config.fix_timeout_s, t, self.config)
        if monitor.repeat(t):
            log.debug("duplicate message at time_s=%s dropped", t)
            return
        enu = np.array([float(c) for c in self.frame.to_enu(fix.lat_deg, fix.lon_deg, fix.alt_m)])
        self._chains.refresh_axes(drone, enu)
        r = drone.r_frame_from_local
        cov = r @ fix.cov_enu_m2 @ r.T
        if correlated:
            self._absolute(drone, monitor, t, enu, self._chains.white_part(drone, cov), None, wandering=True)
        else:
            self._absolute(drone, monitor, t, enu, cov, None, robust=False)

    def add_relative(self, obs: RelativeObservation) -> None:
        """A helper's observation of a target (source ``relative:<observer_id>`` of the target).

        The observer must be on the roster (``FusionConfig.roster``; with none, a drone that
        reports its own sensors to this engine); otherwise :class:`InputError`, counted in
        the target's ``health()`` as ``relative:unknown``. The observer's position is its
        own state here: a position carried in the message is never used. Both drones'
        states are tied by the observation, so the observer's own uncertainty counts, and
        the gate uses their joint covariance. An observer not yet localised is ignored.

        Example (B, localised by GNSS, sees A 30 m east):
            >>> engine = FusionEngine((47.0, 8.0, 400.0))
            >>> engine.add_gnss("B", 0.0, 47.0, 8.0, 400.0, h_sigma_m=1.0, v_sigma_m=1.0)
            >>> engine.add_relative(RelativeObservation("B", "A", 0.0, [1.0, 0.0, 0.0], 30.0, np.eye(3) * 0.25))
            >>> a = engine.estimate("A")
            >>> a.sources, round(float(a.enu_m[0]), 1), round(a.sigma_horizontal_m, 2)
            (('relative:B',), 30.0, 1.61)
        """
        if not isinstance(obs, RelativeObservation):
            raise InputError(f"obs must be a skyfix.types.RelativeObservation, got {type(obs).__name__}")
        observer_id, target_id = _drone_id(obs.observer_id), _drone_id(obs.target_id)
        if observer_id == target_id:
            raise InputError(f"RelativeObservation observer and target are the same drone {observer_id!r}")
        t = self._time("obs.time_s", obs.time_s)
        validate.positive_definite("obs.cov_enu_m2", obs.cov_enu_m2)
        self._trust.check(self._drones, observer_id, target_id, t)
        self._drone(observer_id)  # a trusted observer first seen here (within max_drones)
        self._record("relative", dict(obs=obs))
        observer, target = self._drones[observer_id], self._drone(target_id)
        self._chains.advance(t, target)
        if not observer.anchored:
            log.debug("observer %s not localised: observation of %s unused", observer_id, target_id)
            return
        monitor = target.monitor(f"relative:{observer_id}", self._relative_timeout_s(), t, self.config)
        if monitor.repeat(t):
            log.debug("duplicate message at time_s=%s dropped", t)
            return
        r = observer.r_frame_from_local
        offset = r @ obs.offset_enu_m
        cov = r @ obs.cov_enu_m2 @ r.T
        k = self._chains.step_checked(t, "relative observation")
        consistent = True
        p_obs, p_tgt = self._chains.predict(observer, t), self._chains.predict(target, t)
        if p_tgt is not None:
            innovation = offset - (p_tgt[0] - p_obs[0])
            cross = self._chains.cross_cov(observer, target)
            consistent = nis(innovation, p_tgt[1] + p_obs[1] - cross - cross.T + cov) <= self._gate[3]
        if not monitor.judge(t, consistent):
            return
        self._chains.ensure(observer, k)
        if not target.anchored:
            self._chains.anchor(target, k, p_obs[0] + offset)
        self._chains.ensure(target, k)
        s_obs, v_obs = self._chains.shift(observer, t, k)
        s_tgt, v_tgt = self._chains.shift(target, t, k)
        los = offset if p_tgt is None else p_tgt[0] - p_obs[0]  # the predicted line of sight, where known
        self._chains.relative(observer, target, k, offset + s_tgt - s_obs, cov, v_obs + v_tgt, los)

    def set_lag(self, lag_s: float) -> None:
        """A new smoothing window (s, >= 3 state steps), for inputs that arrive later (or sooner) than before.

        A longer lag lets the window grow forward: inputs older than what was already marginalised stay
        refused. Relative observations' time-out and the contributing window move by as much as the lag
        (a camera observer whose observations arrive that late is not silent). Recorded in the log.

        Example:
            >>> engine = FusionEngine((47.0, 8.0, 400.0), lag_s=2.0)
            >>> engine.set_lag(6.0)
            >>> engine.lag_s
            6.0
        """
        lag = validate.positive_scalar("lag_s", lag_s)
        if lag < 3 * self.config.state_dt_s:
            raise InputError(f"lag_s must be at least 3 state steps ({3 * self.config.state_dt_s:g} s), got {lag_s}")
        self._record("lag", dict(lag_s=lag))
        self.lag_s = self._chains.lag_s = lag
        if self._window is not None:
            self._window.set_lag(lag)
        for drone in self._drones.values():
            drone.set_relative_timeout(self._relative_timeout_s())

    # -- solving and answers ----------------------------------------------------------
    def update(self) -> None:
        """Run the smoother on everything added since the last update (a no-op if nothing)."""
        if self._window is None:
            return
        # A drone that stopped reporting keeps states near the present so it stays in the window.
        keep_k = self._window.step_of(self.now_s) - self._window.lag_steps // 2
        for drone in self._drones.values():
            if drone.anchored and drone.last_k < keep_k:
                self._chains.ensure(drone, keep_k)
        if not self._window.pending:
            return
        if self._log is not None:
            self._log.record("update")
        # Joint covariance (27 x 27 for 3 drones; + the shared error there) of every drone's settled step, kept per
        # drone below: gates read it until the next update, however often asked (older steps: gtsam's Marginals).
        settled = {drone.index: self._chains.settled_step(drone) for drone in self._drones.values() if drone.anchored}
        tail = [self._window.key(i, kind, k) for i, k in settled.items() for kind in range(3)]
        self._window.update(tail + self._chains.common_tail_keys(set(settled.values())))
        oldest = self._window.oldest_alive_step()
        for drone_id, drone in self._drones.items():
            drone.cov_cache = None
            if drone.anchored and drone.last_k < oldest:
                log.warning("drone %s has no states left in the window; it must be re-anchored", drone_id)
                drone.first_k = drone.last_k = None
            elif drone.anchored:
                drone.first_k = max(drone.first_k, oldest)
                self._chains.latest_cov(drone)

    def estimate(self, drone_id: str, time_s: float | None = None) -> Estimate:
        """Fused state of ``drone_id`` at ``time_s`` (default: its newest measurement time): anywhere inside the
        lag (a smoothed answer) or ahead of the newest state (a prediction with grown covariance).
        NotAvailableError for a drone silent for longer than the lag (its newest measurement left the window)."""
        drone = self._known(drone_id)
        self.update()
        if not drone.anchored:
            raise NotAvailableError(f"drone {drone_id!r} has no absolute position yet (needs GNSS, a fix, or a "
                                    "relative observation by a localised drone)")
        t_s = drone.last_time_s if time_s is None else validate.finite_scalar("time_s", time_s)
        window = self._window
        oldest_s = window.time_of(drone.first_k) - window.dt_s / 2
        if t_s < oldest_s and time_s is None:  # its newest measurement left the window: not the caller's mistake
            raise NotAvailableError(f"drone {drone_id!r} silent for longer than lag_s {self.lag_s:g}: no estimate")
        if t_s < oldest_s:
            raise InputError(f"time_s={t_s} is before drone {drone_id!r}'s window (oldest {oldest_s:.3f} s, lag_s "
                             f"{self.lag_s:g}); record estimates as they come or replay the log")
        k = min(max(window.step_of(t_s), drone.first_k), self._chains.settled_step(drone))
        cov_k, frame_k = self._chains.position_covariances(drone, k)
        shift, shift_var = self._chains.shift(drone, t_s, k)
        enu = window.value(drone.index, 0, k) - shift  # shift moves from t to the grid; the estimate goes back
        cov = cov_k + EYE3 * shift_var
        vel, vel_cov = self._chains.velocity_estimate(drone, t_s, k)
        lat, lon, alt = (float(c) for c in self.frame.to_geodetic(*enu))
        return Estimate(drone_id=_drone_id(drone_id), time_s=t_s, lat_deg=lat, lon_deg=lon, alt_m=alt,
                        enu_m=enu, cov_enu_m2=0.5 * (cov + cov.T), vel_enu_mps=vel, vel_cov_enu_m2ps2=vel_cov,
                        sources=self._contributing(drone), health=self._health(drone),
                        cov_frame_enu_m2=None if frame_k is None else 0.5 * (frame_k + frame_k.T) + EYE3 * shift_var)

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

    @property
    def now_s(self) -> float:
        """The engine's clock: the newest measurement time seen (s; -inf before the first)."""
        return self._chains.now_s

    # -- internals ---------------------------------------------------------------------------
    @property
    def _window(self) -> GraphWindow | None:
        return self._chains.window

    def _record(self, op: str, args: dict) -> None:
        if self._log is not None:
            self._log.record(op, args)

    def _time(self, name: str, value) -> float:
        return self._chains.checked_time(name, value)

    def _drone(self, drone_id: str) -> DroneState:
        drone = self._drones.get(drone_id)
        if drone is None:
            if len(self._drones) >= self.config.max_drones:
                raise InputError(f"drone id {drone_id!r} would be drone {len(self._drones) + 1}, more than "
                                 f"FusionConfig.max_drones {self.config.max_drones}; known: {sorted(self._drones)}")
            drone = self._drones[drone_id] = DroneState(index=self._chains.new_index())
        return drone

    def _reporter(self, drone_id: str) -> DroneState:
        """The drone sending its own sensor data (it may then observe others on an open roster)."""
        drone = self._drone(drone_id)
        drone.reporting = True
        return drone

    @property
    def unknown_observations(self) -> int:
        """Relative observations refused because their observer is not on the roster."""
        return self._trust.refused

    def _known(self, drone_id) -> DroneState:
        drone = self._drones.get(_drone_id(drone_id))
        if drone is None:
            raise InputError(f"unknown drone id {drone_id!r}; known: {sorted(self._drones)}")
        return drone

    def _absolute(self, drone: DroneState, monitor: SourceMonitor, t: float, enu: np.ndarray, cov: np.ndarray,
                  quality: str | None, robust: bool = True, wandering: bool = False) -> None:
        """Gate and fuse an absolute position (frame ENU, m; ``cov`` its white part when ``wandering``: a fix
        of the position plus the chain's Gauss-Markov error, robust)."""
        k = self._chains.step_checked(t, "measurement")
        predicted = self._chains.predict(drone, t, gnss=wandering)
        consistent = True
        if predicted is not None:
            consistent = nis(enu - predicted[0], predicted[1] + cov) <= self._gate[3]
        if not monitor.judge(t, consistent, quality):
            return
        if not drone.anchored:
            self._chains.anchor(drone, k, enu)
        self._chains.ensure(drone, k)
        shift, shift_var = self._chains.shift(drone, t, k)
        if wandering:
            self._window.gnss(drone.index, k, enu + shift, cov + EYE3 * shift_var)
        else:
            self._window.position(drone.index, k, enu + shift, cov + EYE3 * shift_var, robust)

    def _relative_timeout_s(self) -> float:
        return self.config.relative_timeout_s + max(0.0, self.lag_s - self._lag0_s)

    def _tick(self) -> None:
        for drone in self._drones.values():
            for monitor in drone.monitors.values():
                monitor.tick(self.now_s)

    def _health(self, drone: DroneState) -> dict[str, SourceHealth]:
        self._tick()
        return {name: monitor.health for name, monitor in drone.monitors.items()}

    def _contributing(self, drone: DroneState) -> tuple[str, ...]:
        return drone.contributing(self.now_s, self.config.contributing_window_s + max(0.0, self.lag_s - self._lag0_s))
