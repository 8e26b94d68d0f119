"""Every drone's chain of states in the fusion window: its mechanics, not its judgement.

A :class:`StateChains` owns the gtsam :class:`~skyfix.fusion.window.GraphWindow` (made
at the first measurement) and the state model of :class:`~skyfix.fusion.FusionConfig`:
it anchors a drone's chain, extends it forwards and backwards on the ``state_dt_s``
grid, starts a new chain when the old one was corrupted (re-anchoring), moves a
measurement from its time to the nearest grid step with the drone's bias-corrected
velocity, and answers predictions, velocities and covariances. Positions are metres in
the engine's local ENU frame (its axes, not the drone's); times are seconds on the
engine's one clock. Which measurement to fuse is decided elsewhere
(:mod:`skyfix.fusion.engine`, :mod:`skyfix.fusion.gnss`).
"""

from __future__ import annotations

import math

import numpy as np

from skyfix import validate
from skyfix.errors import InputError
from skyfix.fusion.config import FusionConfig
from skyfix.fusion.drone import DroneState
from skyfix.fusion.pointing import pointing_jacobian, white_part
from skyfix.fusion.velocity import IntervalVelocity
from skyfix.fusion.window import GraphWindow
from skyfix.geo import LocalFrame

ROTATION_REFRESH_M = 100.0  # ENU axes turn ~0.0009 deg per 100 m: refresh a drone's axes after this
EYE3 = np.eye(3)


def nis(innovation: np.ndarray, cov: np.ndarray) -> float:
    """Normalised innovation squared ``innovation' cov^-1 innovation`` (inf for a singular ``cov``).

    Example:
        >>> nis(np.array([3.0, 0.0]), np.diag([9.0, 1.0]))
        1.0
    """
    try:
        return float(innovation @ np.linalg.solve(cov, innovation))
    except np.linalg.LinAlgError:
        return math.inf


MAX_TIME_JUMP_S = 30.0  # an input this far ahead of the engine's clock is refused (units mix-up, bad clock)


class GaussMarkovChain:
    """A vector Gauss-Markov chain (``sigma`` (3,) stationary 1-sigma, correlation time ``tau_s``) under an index of
    its own in ``chains``' window (its kind-2 variables): states from its first to its last grid step, each tied to
    its neighbour; one that left the window (no measurement kept it) starts again from its stationary
    distribution. The receivers' shared GNSS error is one; each camera observer's pointing error another."""

    def __init__(self, chains: StateChains, sigma: np.ndarray, tau_s: float) -> None:
        self._chains = chains
        self.sigma = np.asarray(sigma, float)
        self.phi = math.exp(-chains.config.state_dt_s / tau_s)
        self.index: int | None = None
        self._span: list[int] | None = None

    def ensure(self, k: int) -> int:
        """Create the chain's states up to step k (forwards or backwards); its index."""
        window = self._chains.window
        span = self._span
        if span is not None and span[1] < window.oldest_alive_step():
            span = None
        if span is None:
            self.index = self._chains.new_index()
            window.new_state(self.index, k, None, None, np.zeros(3))
            window.prior(self.index, 2, k, np.zeros(3), np.diag(self.sigma**2))
            span = self._span = [k, k]
        ci, phi = self.index, self.phi
        span[0] = max(span[0], window.oldest_alive_step())
        while span[1] < k:
            window.new_state(ci, span[1] + 1, None, None, phi * window.value(ci, 2, span[1]))
            window.gauss_markov(ci, span[1], phi, self.sigma)
            span[1] += 1
        while span[0] > k:
            if span[0] - 1 < window.oldest_alive_step():
                raise InputError("measurement is older than the fusion lag")
            window.new_state(ci, span[0] - 1, None, None, window.value(ci, 2, span[0]))
            window.gauss_markov(ci, span[0] - 1, phi, self.sigma)
            span[0] -= 1
        return ci

    def holds(self, k: int) -> bool:
        """Whether the chain has a state at step k."""
        span = self._span
        return span is not None and span[0] <= k <= span[1]


class StateChains:
    """The drones' state chains in one window over ``frame`` (see module docs)."""

    def __init__(self, frame: LocalFrame, lag_s: float, config: FusionConfig) -> None:
        self.frame, self.lag_s, self.config = frame, lag_s, config
        cfg = config
        self.gm_sigma_m = np.array([cfg.gnss_gm_h_sigma_m, cfg.gnss_gm_h_sigma_m, cfg.gnss_gm_v_sigma_m])
        self._q0 = self._q_sigma = self._q_walk = None
        if cfg.velocity_scale_heading:  # (scale, heading rad, pinned 0)
            self._q0 = np.zeros(3)
            self._q_sigma = np.array([cfg.velocity_scale_sigma, math.radians(cfg.velocity_heading_sigma_deg), 1e-6])
            self._q_walk = np.array([cfg.velocity_scale_walk_per_sqrt_s,
                                     math.radians(cfg.velocity_heading_walk_deg_per_sqrt_s), 1e-9]) \
                * math.sqrt(cfg.state_dt_s)
        self._next_index = 0
        self.window: GraphWindow | None = None
        self.now_s = -math.inf
        # the receivers' shared error (FusionConfig.gnss_common_share > 0): a chain of its own index, steps
        # [first, last] (None: no chain yet); each receiver's error state is then c plus its own part
        share = cfg.gnss_common_share
        self.common_sigma_m = self.gm_sigma_m * math.sqrt(share)
        self.own_sigma_m = self.gm_sigma_m * math.sqrt(1.0 - share)
        self._common = GaussMarkovChain(self, self.common_sigma_m, cfg.gnss_common_tau_s)
        self._phi_own = math.exp(-cfg.state_dt_s / cfg.gnss_gm_tau_s)
        self._own_step_sigma_m = np.sqrt(self.own_sigma_m**2 * (1.0 - self._phi_own**2)
                                         + self.common_sigma_m**2 * (1.0 - self._common.phi**2))
        # each camera observer's pointing error (yaw, pitch; rad), FusionConfig.relative_pointing_sigma_deg > 0
        self._pointing: dict[int, GaussMarkovChain] = {}

    def checked_time(self, name: str, value) -> float:
        """``value`` as a measurement time (s); InputError when older than the window keeps or more
        than ``MAX_TIME_JUMP_S`` ahead of the clock (a units mix-up or a bad clock)."""
        t = validate.finite_scalar(name, value)
        if self.window is not None:
            oldest_s = self.window.time_of(self.window.oldest_alive_step()) - self.window.dt_s / 2
            if t < oldest_s:
                raise InputError(f"{name}={t} is older than the fusion lag allows (oldest usable {oldest_s:.3f}, "
                                 f"engine time {self.now_s:.3f}, lag_s {self.lag_s:g})")
        if self.now_s > -math.inf and t > self.now_s + MAX_TIME_JUMP_S:
            raise InputError(f"{name}={t} jumps {t - self.now_s:.1f} s ahead of the engine time {self.now_s:.3f}; "
                             f"more than {MAX_TIME_JUMP_S:g} s looks like a clock or unit error")
        return t

    def advance(self, t_s: float, drone: DroneState) -> None:
        """Move the clock to a measurement at ``t_s`` (s); the first one places the window's grid."""
        if self.window is None:
            cfg = self.config
            epoch = math.floor((t_s - 10.0 * self.lag_s) / cfg.state_dt_s) * cfg.state_dt_s
            self.window = GraphWindow(self.lag_s, cfg.state_dt_s, epoch, cfg.max_iterations, cfg.robust_k)
        self.now_s = max(self.now_s, t_s)
        drone.last_time_s = max(drone.last_time_s, t_s)

    def new_index(self) -> int:
        self._next_index += 1
        return self._next_index - 1


    def refresh_axes(self, drone: DroneState, enu: np.ndarray) -> None:
        """The drone's local ENU axes and height offset, taken again after it moved 100 m (frame ENU, m)."""
        if drone.axes_at_enu_m is not None and np.linalg.norm(enu - drone.axes_at_enu_m) < ROTATION_REFRESH_M:
            return
        lat, lon, alt = (float(c) for c in self.frame.to_geodetic(*enu))
        drone.r_frame_from_local = self.frame.enu_rotation_at(lat, lon)
        drone.axes_at_enu_m = enu.copy()
        drone.up_minus_alt_m = float(enu[2]) - alt


    def refresh_from_estimate(self, drone: DroneState) -> None:
        """Local axes at the drone's current estimate (drones placed only by helpers)."""
        self.refresh_axes(drone, self.window.value(drone.index, 0, drone.last_k))


    def anchor(self, drone: DroneState, k: int, p0: np.ndarray, b0: np.ndarray | None = None,
                b_cov: np.ndarray | None = None, p_sigma_m: float | None = None) -> None:
        """First state of a drone at step k; the caller adds the factor that fixes its position
        (or ``p_sigma_m`` gives it a weak prior about ``p0``). The GNSS error starts from its
        stationary distribution."""
        window, cfg = self.window, self.config
        window.new_state(drone.index, k, p0, np.zeros(3) if b0 is None else b0, np.zeros(3), self._q0)
        if b_cov is None:
            window.prior_bias(drone.index, k, cfg.bias_initial_sigma_mps)
        else:
            window.prior(drone.index, 1, k, b0, b_cov)
        r = drone.r_frame_from_local
        if self.config.gnss_common_share > 0:
            self.ensure_common(k)
            window.own_error_prior(drone.index, self.common_index, k, r @ np.diag(self.own_sigma_m**2) @ r.T)
        else:
            window.prior(drone.index, 2, k, np.zeros(3), r @ np.diag(self.gm_sigma_m**2) @ r.T)
        if self._q_sigma is not None:
            window.prior(drone.index, 3, k, np.zeros(3), np.diag(self._q_sigma**2))
        if p_sigma_m is not None:
            window.prior(drone.index, 0, k, p0, EYE3 * p_sigma_m**2)
        drone.first_k = drone.last_k = k
        self.intervals(drone).start_at(k)


    def reanchor(self, drone: DroneState, k: int, horizontal_bias: tuple[np.ndarray, np.ndarray] | None) -> None:
        """Start a new state chain for the drone at step k (its history was corrupted); the
        velocity bias carries over with its covariance (horizontally the one from before the
        drift, ``horizontal_bias``, if given), the position comes from what follows."""
        old, last = drone.index, drone.last_k
        b, b_cov = np.zeros(3), EYE3 * self.config.bias_initial_sigma_mps**2
        cached = self.latest_cov(drone) if drone.anchored else None
        if cached is not None:
            b, b_cov = self.window.value(old, 1, cached[0]).copy(), cached[1][3:6, 3:6].copy()
        if horizontal_bias is not None:
            b[:2] = horizontal_bias[0]
            b_cov[:2, :] = b_cov[:, :2] = 0.0
            b_cov[:2, :2] = horizontal_bias[1]
        p0 = self.window.value(old, 0, last) if last is not None else None
        drone.index = self.new_index()
        drone.first_k = drone.last_k = None
        drone.intervals = None
        drone.cov_cache = None
        if p0 is not None:
            self.anchor(drone, k, p0, b, b_cov, p_sigma_m=self.config.max_speed_mps)


    def white_part(self, drone: DroneState, cov_m2: np.ndarray) -> np.ndarray:
        """A wandering fix's covariance (m2, frame axes) less the Gauss-Markov part of its error, each
        eigenvalue at least the receiver noise floor ``gnss_white_min_sigma_m`` squared."""
        r = drone.r_frame_from_local
        values, vectors = np.linalg.eigh(cov_m2 - r @ np.diag(self.gm_sigma_m**2) @ r.T)
        return (vectors * np.maximum(values, self.config.gnss_white_min_sigma_m**2)) @ vectors.T


    def intervals(self, drone: DroneState) -> IntervalVelocity:
        if drone.intervals is None:
            c = self.config
            drone.intervals = IntervalVelocity(self.window.epoch_s, self.window.dt_s, c.velocity_timeout_s,
                                               c.velocity_gap_accel_mps2, c.velocity_gap_max_s)
        return drone.intervals


    @property
    def common_index(self) -> int | None:
        """Index of the receivers' shared GNSS error chain (None before it exists)."""
        return self._common.index

    def ensure_common(self, k: int) -> None:
        """Create the shared GNSS error chain's states up to step k (forwards or backwards)."""
        self._common.ensure(k)

    def _common_holds(self, k: int) -> bool:
        """Whether the shared error chain has a state at step k (never, without sharing)."""
        return self._common.holds(k)

    def ensure_pointing(self, observer: DroneState, k: int) -> int:
        """The index of ``observer``'s pointing error chain, with a state at step k (made on first use)."""
        chain = self._pointing.get(observer.index)
        if chain is None:
            sigma = math.radians(self.config.relative_pointing_sigma_deg)
            # (yaw, pitch, unused): no observation moves the third (its Jacobian column is zero); a sigma like the
            # others' keeps the window's information matrix well conditioned
            chain = self._pointing[observer.index] = GaussMarkovChain(self, np.full(3, sigma),
                                                                       self.config.relative_pointing_tau_s)
        return chain.ensure(k)

    def _error_step(self, drone: DroneState, k: int) -> None:
        """The receiver error's step k -> k+1: its own part about the shared chain, or (no sharing, or a step the
        shared chain does not hold: a drone carried forward across a silence while a newer chain started, steps
        that the next update marginalises) its whole error as one Gauss-Markov chain."""
        if self._common_holds(k + 1):
            self.window.gauss_markov_shared(drone.index, self.common_index, k, self._phi_own, self._own_step_sigma_m)
        else:
            self.window.gauss_markov(drone.index, k, self._phi_own, self.gm_sigma_m)

    def ensure(self, drone: DroneState, k: int) -> None:
        """Create the drone's states up to step k (forwards or backwards), each tied to its neighbour."""
        window, cfg = self.window, self.config
        walk = cfg.max_speed_mps * cfg.state_dt_s
        bias_walk = (drone.bias_walk_mps_per_sqrt_s or cfg.bias_walk_mps_per_sqrt_s) * math.sqrt(cfg.state_dt_s)
        phi = self._phi_own
        i = drone.index
        if cfg.gnss_common_share > 0:
            self.ensure_common(k)
        while drone.last_k < k:
            prev = drone.last_k
            p_prev, b_prev = window.value(i, 0, prev), window.value(i, 1, prev)
            step = np.zeros(3)
            if drone.velocity is not None and abs(window.time_of(prev) - drone.velocity[0]) <= cfg.velocity_timeout_s:
                step = (drone.velocity[1] - b_prev) * window.dt_s
            window.new_state(i, prev + 1, p_prev + step, b_prev, phi * window.value(i, 2, prev),
                             None if self._q0 is None else window.value(i, 3, prev))
            window.motion(i, prev, walk, bias_walk, self._q_walk)
            self._error_step(drone, prev)
            drone.last_k = prev + 1
        while drone.first_k > k:
            nxt = drone.first_k
            if nxt - 1 < window.oldest_alive_step():
                raise InputError("measurement is older than the fusion lag")
            window.new_state(i, nxt - 1, window.value(i, 0, nxt), window.value(i, 1, nxt), window.value(i, 2, nxt),
                             None if self._q0 is None else window.value(i, 3, nxt))
            window.motion(i, nxt - 1, walk, bias_walk, self._q_walk)
            self._error_step(drone, nxt - 1)
            drone.first_k = nxt - 1


    def relative(self, observer: DroneState, target: DroneState, k: int, offset_m: np.ndarray, cov_m2: np.ndarray,
                 shift_var_m2: float, los_m: np.ndarray) -> None:
        """A relative observation at step k: ``offset_m`` (target minus observer, frame axes, moved to the step),
        ``cov_m2`` its stated covariance, ``shift_var_m2`` the move's variance per axis, ``los_m`` the predicted line
        of sight. With ``relative_pointing_sigma_deg`` the observer's pointing error is a state its observations
        share, linearised about ``los_m`` (not the measured ray, which carries that very error: r beta^2 off,
        0.2 m at 6 deg and 35 m, against frames averaged to centimetres); only the rest is the frame's own."""
        cfg = self.config
        if cfg.relative_pointing_sigma_deg <= 0:
            self.window.relative(observer.index, target.index, k, offset_m, cov_m2 + EYE3 * shift_var_m2)
            return
        white = white_part(cov_m2, los_m, math.radians(cfg.relative_pointing_sigma_deg),
                           math.radians(cfg.relative_white_min_deg))
        self.window.relative_pointed(observer.index, target.index, self.ensure_pointing(observer, k), k, offset_m,
                                     white + EYE3 * shift_var_m2, pointing_jacobian(los_m))

    def velocity_now(self, drone: DroneState, t_s: float) -> tuple[np.ndarray, float] | None:
        """Bias-corrected velocity near ``t_s`` and its per-axis variance, or None if stale."""
        if drone.velocity is None or abs(t_s - drone.velocity[0]) > self.config.velocity_timeout_s:
            return None
        if not drone.anchored:
            return drone.velocity[1], drone.velocity[2]
        return drone.velocity[1] - self.window.value(drone.index, 1, drone.last_k), drone.velocity[2]


    def shift(self, drone: DroneState, t_s: float, k: int) -> tuple[np.ndarray, float]:
        """Displacement from time t_s to grid step k (m) and its per-axis variance."""
        dt = self.window.time_of(k) - t_s
        if abs(dt) < 1e-9:
            return np.zeros(3), 0.0
        vel = self.velocity_now(drone, t_s)
        if vel is None:
            return np.zeros(3), (self.config.max_speed_mps * dt) ** 2
        return vel[0] * dt, vel[1] * dt * dt + (self.config.bias_initial_sigma_mps * dt) ** 2


    def settled_step(self, drone: DroneState) -> int:
        """Newest step whose motion from the previous one is known (velocity integrated up to it).

        Later steps exist only because a measurement landed there before the velocity
        covering them arrived; answers are taken from the settled step and moved in time.
        """
        iv = drone.intervals
        if iv is None or iv.next_interval is None or drone.velocity is None \
                or self.now_s - drone.velocity[0] > self.config.velocity_timeout_s:
            return drone.last_k
        return max(drone.first_k, min(drone.last_k, iv.next_interval))


    def latest_cov(self, drone: DroneState) -> tuple[int, np.ndarray] | None:
        """Joint covariance (9, 9) of [p, b, n] at the settled (else newest optimised) step, cached per update
        (the engine takes it right after each update, from the tail it solved for: gating does not depend on
        when answers are asked)."""
        if drone.cov_cache is None:
            window = self.window
            for k in range(self.settled_step(drone), drone.first_k - 1, -1):
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


    def position_covariances(self, drone: DroneState, k: int) -> tuple[np.ndarray, np.ndarray | None]:
        """The drone's position covariance (3, 3) at step k, and Cov(p - c): the same position in the swarm's
        GNSS frame, where the receivers' shared error c has moved it (home, neighbours and every fix sit in that
        frame); None without a shared chain at k."""
        window = self.window
        cov = window.covariance(drone.index, 0, k)
        if not self._common_holds(k):
            return cov, None
        return cov, window.difference_covariance(window.key(drone.index, 0, k), window.key(self.common_index, 2, k))

    def common_tail_keys(self, steps: set[int]) -> list[int]:
        """Keys of the shared error chain at ``steps`` (the drones' settled steps), for the update's tail."""
        return [self.window.key(self.common_index, 2, k) for k in sorted(steps) if self._common_holds(k)]

    def predict(self, drone: DroneState, t_s: float, gnss: bool = False) -> tuple[np.ndarray, np.ndarray] | None:
        """Fused prediction of the drone's position at t_s (without the measurement at hand);
        with ``gnss``, of what its receiver would report (position plus receiver error)."""
        if not drone.anchored:
            return None
        window = self.window
        k = min(max(window.step_of(t_s), drone.first_k), self.settled_step(drone))
        cached = self.latest_cov(drone)
        if cached is not None:  # a step newer than the last solve holds only its initial guess (its predecessor's
            k = min(k, cached[0])  # value, not moved by the velocity): predict from the solved one
        shift, shift_var = self.shift(drone, t_s, k)
        p = window.value(drone.index, 0, k) - shift
        if gnss:
            p = p - window.value(drone.index, 2, k)
        if cached is None:  # nothing optimised yet: no basis for gating
            return p, EYE3 * 1e12
        k_cov, joint = cached
        cov = joint[:3, :3]
        if gnss:  # Cov(p - n)
            cov = cov + joint[6:9, 6:9] - joint[:3, 6:9] - joint[6:9, :3]
        gap_s = abs(t_s - window.time_of(k_cov))
        vel = self.velocity_now(drone, t_s)
        grow = (self.config.max_speed_mps * gap_s) ** 2 if vel is None else \
            vel[1] * gap_s * window.dt_s + (self.config.bias_initial_sigma_mps * gap_s) ** 2
        return p, cov + EYE3 * (grow + shift_var)


    def velocity_estimate(self, drone: DroneState, t_s: float, k: int) -> tuple[np.ndarray, np.ndarray]:
        window = self.window
        vel = self.velocity_now(drone, t_s)
        if vel is not None:
            b_cov = window.covariance(drone.index, 1, min(k, self.latest_cov(drone)[0]))
            return vel[0], EYE3 * vel[1] + b_cov
        k0 = max(drone.first_k, k - int(round(1.0 / window.dt_s)))
        if k0 == k:
            return np.zeros(3), EYE3 * self.config.max_speed_mps**2
        span_s = (k - k0) * window.dt_s
        v = (window.value(drone.index, 0, k) - window.value(drone.index, 0, k0)) / span_s
        cov = (window.covariance(drone.index, 0, k) + window.covariance(drone.index, 0, k0)) / span_s**2
        return v, cov


    def cross_cov(self, a: DroneState, b: DroneState) -> np.ndarray:
        """Cross covariance (3, 3) of two drones' newest solved positions (zero if unknown)."""
        ca, cb = self.latest_cov(a), self.latest_cov(b)
        if ca is None or cb is None:
            return np.zeros((3, 3))
        w = self.window
        joint = w.joint_covariance([w.key(a.index, 0, ca[0]), w.key(b.index, 0, cb[0])])
        return np.zeros((3, 3)) if joint is None else joint[:3, 3:]


    def step_checked(self, t_s: float, what: str) -> int:
        k = self.window.step_of(t_s)
        if k < self.window.oldest_alive_step():
            raise InputError(f"{what} at time_s={t_s} is older than the fusion lag ({self.lag_s:g} s)")
        return k

