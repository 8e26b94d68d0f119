"""The gtsam sliding-window graph behind :class:`skyfix.fusion.FusionEngine`.

Variables (all ``gtsam.Point3`` in the engine's local ENU frame, metres / m/s), per
drone per grid step k (time ``epoch + k * dt``):

- ``p`` position of the drone,
- ``b`` bias of the drone's autopilot velocity,
- ``n`` (optional) the drone's GNSS error, negated: a fix measures ``p - n`` (so GNSS is a
  ``BetweenFactorPoint3(n, p)``), and n follows a first-order Gauss-Markov process, or (with a
  common error, ``FusionConfig.gnss_common_share``) n = c + o: o the receiver's own Gauss-Markov
  part, c one chain of ``n`` variables shared by every drone, held under an index of its own,
- ``q`` (optional) the velocity's scale-factor and heading errors ``(s, psi_rad, 0)``: the
  measured velocity is ``(1 + s) R_up(psi) v_true + b`` (the third component is held at
  zero by its prior and walk). Its velocity factor is a ``gtsam.CustomFactor`` (four keys,
  nonlinear), so the option costs a Python call per interval and update.

Factors are gtsam's own C++ ones: ``PriorFactorPoint3`` (GNSS, tag fixes),
``BetweenFactorPoint3`` (relative observations, the bias random walk, the weak motion
bound), and ``LinearContainerFactor`` around a ``JacobianFactor`` for the two linear
relations that tie three variables or one axis (velocity: p_k+1 - p_k + b_k dt = v dt;
altitude: the up component of p_k). GNSS, fixes and relative observations carry a
Huber robust model (a fix is gated only, see :meth:`GraphWindow.position`).

The window is one this module marginalises itself (gtsam's fixed-lag smoothers were
measured at 3-5 ms per update here, and its incremental one has known crash and growth
bugs): at each update the factors of the window are linearised at the current
estimate and eliminated in time order with gtsam's sequential elimination, the
caller's ``tail`` (the engine's: every drone's settled step) last; its joint marginal
(a small dense information matrix) gives both its solution and covariance, and
back-substitution the rest. (A banded Cholesky in numpy instead was timed on a window's
300 unknowns: building the band and factoring it alone cost as much as gtsam's elimination.) Steps older than the lag are eliminated out of their factors and the result is
kept as a ``LinearContainerFactor`` on what remains, so memory and time per update
stay bounded. Every new variable must enter together with a factor that constrains
it (a new position with its motion factors, a new bias with its random walk or its
prior); the update refuses a graph where one does not, instead of handing gtsam an
indeterminate system.
"""

from __future__ import annotations

import logging

import gtsam
import numpy as np

from skyfix.errors import EstimationError

log = logging.getLogger(__name__)

_EYE = np.eye(3)
_UP_ROW = np.array([[0.0, 0.0, 1.0]])


_STEP_MASK = (1 << 38) - 1
KINDS = 4  # p, b, n, q
_J_UP = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])  # d R_up(a) u / da = J R_up(a) u


def _r_up(angle_rad: float) -> np.ndarray:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class GraphWindow:
    """Fixed-lag factor graph over per-drone position and velocity-bias chains."""

    def __init__(self, lag_s: float, dt_s: float, epoch_s: float, max_iterations: int, robust_k: float) -> None:
        self.lag_s = float(lag_s)
        self.dt_s = float(dt_s)
        self.epoch_s = float(epoch_s)
        self.lag_steps = int(np.ceil(self.lag_s / self.dt_s))
        self.max_iterations = int(max_iterations)
        self._huber = gtsam.noiseModel.mEstimator.Huber.Create(float(robust_k))
        self._values = gtsam.Values()              # estimate (and initial guesses of new variables)
        self._value_cache: dict[int, np.ndarray] = {}  # read-only copies of _values (read ~30 times per update)
        self._graph = gtsam.NonlinearFactorGraph()  # window factors; marginalised ones leave null slots
        self._buckets: dict[int, list[int]] = {}   # oldest step a factor touches -> its slots in _graph
        self._live = 0
        self._keys_by_step: dict[int, list[int]] = {}
        self._new_keys: list[int] = []
        self._new_measurements: list[tuple[int, int]] = []  # (bucket, slot) of measurement factors since the last solve
        self._n_new_factors = 0
        self._newest_step = -1
        self._marginalised_before = 0               # every step older than this one is gone (a lag may grow)
        self._optimised: set[int] = set()
        self._tail_index: dict[int, int] = {}      # key -> row block in the tail covariance
        self._tail_cov: np.ndarray | None = None
        self._marginals: gtsam.Marginals | None = None

    # -- keys and time -------------------------------------------------------------
    @staticmethod
    def key(drone_index: int, kind: int, k: int) -> int:
        """Integer gtsam key of variable ``kind`` (0 position, 1 bias, 2 negated GNSS error) of a
        drone at step k >= 0."""
        return (drone_index << 40) | (kind << 38) | k

    def step_of(self, t_s: float) -> int:
        """Nearest grid step of time ``t_s``."""
        return int(round((t_s - self.epoch_s) / self.dt_s))

    def time_of(self, k: int) -> float:
        return self.epoch_s + k * self.dt_s

    def oldest_alive_step(self) -> int:
        """Steps at or after this one are in the window; older ones are (or will be at the next update) marginalised.
        After the lag grew (:meth:`set_lag`), steps already marginalised stay gone: the window grows forward."""
        return max(0, self._newest_step - self.lag_steps, self._marginalised_before)

    def set_lag(self, lag_s: float) -> None:
        """A new window length (s); a shorter one takes effect at the next :meth:`update`."""
        self.lag_s = float(lag_s)
        self.lag_steps = int(np.ceil(self.lag_s / self.dt_s))

    @property
    def pending(self) -> bool:
        return self._n_new_factors > 0 or bool(self._new_keys)

    @property
    def n_factors(self) -> int:
        return self._live

    # -- variables ---------------------------------------------------------------------
    def new_state(self, drone_index: int, k: int, p0_m: np.ndarray, b0_mps: np.ndarray, n0_m: np.ndarray | None = None,
                  q0: np.ndarray | None = None) -> None:
        """Insert p_k, b_k (and n_k, q_k) with initial guesses; the caller adds their constraining factors."""
        if k < 0 or k > _STEP_MASK:
            raise EstimationError(f"grid step {k} outside the window's key range")
        for kind, guess in ((0, p0_m), (1, b0_mps), (2, n0_m), (3, q0)):
            if guess is None:
                continue
            key = self.key(drone_index, kind, k)
            self._values.insert(key, gtsam.Point3(*guess))
            self._value_cache.pop(key, None)
            self._keys_by_step.setdefault(k, []).append(key)
            self._new_keys.append(key)
        self._newest_step = max(self._newest_step, k)

    def value(self, drone_index: int, kind: int, k: int) -> np.ndarray | None:
        """Current estimate of a variable (its initial guess if not yet optimised), or None."""
        key = self.key(drone_index, kind, k)
        out = self._value_cache.get(key)
        if out is None and self._values.exists(key):
            out = self._value_cache[key] = np.asarray(self._values.atPoint3(key))
            out.flags.writeable = False
        return out

    def is_optimised(self, drone_index: int, kind: int, k: int) -> bool:
        return self.key(drone_index, kind, k) in self._optimised

    def joint_covariance(self, keys: list[int]) -> np.ndarray | None:
        """Joint covariance (3n, 3n) of variables of the last update's tail (cross terms included),
        or None if one of them is not in the tail."""
        rows = [self._tail_index.get(key) for key in keys]
        if self._tail_cov is None or any(r is None for r in rows):
            return None
        if rows == list(range(rows[0], rows[0] + 3 * len(rows), 3)):  # adjacent (a drone's p, b, n): a slice
            return self._tail_cov[rows[0]:rows[0] + 3 * len(rows), rows[0]:rows[0] + 3 * len(rows)].copy()
        idx = np.concatenate([np.arange(r, r + 3) for r in rows])
        return self._tail_cov[np.ix_(idx, idx)]

    def difference_covariance(self, key_a: int, key_b: int) -> np.ndarray | None:
        """Covariance (3, 3) of ``a - b`` for two optimised variables, their cross terms included (from the
        last update's tail, else gtsam's joint marginal); None if either is not in the solved window."""
        if key_a not in self._optimised or key_b not in self._optimised:
            return None
        joint = self.joint_covariance([key_a, key_b])
        if joint is None:
            joint = self._solved_marginals().jointMarginalCovariance(gtsam.KeyVector([key_a, key_b])).fullMatrix()
        return joint[:3, :3] + joint[3:, 3:] - joint[:3, 3:] - joint[3:, :3]

    def covariance(self, drone_index: int, kind: int, k: int) -> np.ndarray:
        """Marginal covariance (3, 3) of an optimised variable after the last update."""
        key = self.key(drone_index, kind, k)
        if key not in self._optimised:
            raise EstimationError(f"variable {kind} of drone {drone_index} at step {k} is not in the solved window")
        row = self._tail_index.get(key)
        if row is not None:
            return self._tail_cov[row:row + 3, row:row + 3].copy()
        return np.asarray(self._solved_marginals().marginalCovariance(key))  # slow path: a smoothed state

    def _solved_marginals(self) -> gtsam.Marginals:
        """gtsam's marginals of the window as last solved (built on first use after an update)."""
        if self._marginals is None:
            self._marginals = gtsam.Marginals(self._graph, self._values)
        return self._marginals

    # -- factors -----------------------------------------------------------------------
    def _add(self, factor, min_step: int, new: bool = True, measurement: bool = False) -> None:
        self._graph.push_back(factor)
        slot = self._graph.size() - 1
        self._buckets.setdefault(min_step, []).append(slot)
        self._live += 1
        self._n_new_factors += new
        if measurement:
            self._new_measurements.append((min_step, slot))

    def _robust(self, cov: np.ndarray) -> gtsam.noiseModel.Base:
        return gtsam.noiseModel.Robust.Create(self._huber, gtsam.noiseModel.Gaussian.Covariance(cov))

    def prior_bias(self, drone_index: int, k: int, sigma_mps: float) -> None:
        self._add(gtsam.PriorFactorPoint3(self.key(drone_index, 1, k), gtsam.Point3(0.0, 0.0, 0.0),
                                          gtsam.noiseModel.Isotropic.Sigma(3, sigma_mps)), k)

    def prior(self, drone_index: int, kind: int, k: int, mean: np.ndarray, cov: np.ndarray) -> None:
        """Gaussian prior on one variable (e.g. the GNSS error's stationary distribution)."""
        self._add(gtsam.PriorFactorPoint3(self.key(drone_index, kind, k), gtsam.Point3(*mean),
                                          gtsam.noiseModel.Gaussian.Covariance(cov)), k)

    def gauss_markov(self, drone_index: int, k: int, phi: float, sigma_m: np.ndarray) -> None:
        """n_k+1 = phi n_k + w, w ~ N(0, (1 - phi^2) sigma^2) per axis (``sigma_m`` (3,), stationary)."""
        keys = (self.key(drone_index, 2, k), self.key(drone_index, 2, k + 1))
        factor = gtsam.JacobianFactor(keys[0], -phi * _EYE, keys[1], _EYE, np.zeros(3),
                                      gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigma_m) * np.sqrt(1.0 - phi * phi)))
        self._add(gtsam.LinearContainerFactor(factor, self._zeros(keys)), k)

    def gauss_markov_shared(self, drone_index: int, common_index: int, k: int, phi: float,
                            step_sigma_m: np.ndarray) -> None:
        """A receiver error n = c + o whose own part o is Gauss-Markov and c the chain of ``common_index``:
        n_k+1 - phi n_k - (1 - phi) c_k+1 = w, ``step_sigma_m`` (3,) per axis (o's step noise, plus the
        common chain's own step, which this three-key form takes as part of w)."""
        keys = (self.key(drone_index, 2, k), self.key(drone_index, 2, k + 1), self.key(common_index, 2, k + 1))
        factor = gtsam.JacobianFactor(keys[0], -phi * _EYE, keys[1], _EYE, keys[2], -(1.0 - phi) * _EYE, np.zeros(3),
                                      gtsam.noiseModel.Diagonal.Sigmas(np.asarray(step_sigma_m, float)))
        self._add(gtsam.LinearContainerFactor(factor, self._zeros(keys)), k)

    def own_error_prior(self, drone_index: int, common_index: int, k: int, cov_m2: np.ndarray) -> None:
        """The receiver's own error n_k - c_k ~ N(0, ``cov_m2``) (its stationary distribution)."""
        self._add(gtsam.BetweenFactorPoint3(self.key(common_index, 2, k), self.key(drone_index, 2, k),
                                            gtsam.Point3(0.0, 0.0, 0.0), gtsam.noiseModel.Gaussian.Covariance(cov_m2)), k)

    def gnss(self, drone_index: int, k: int, enu_m: np.ndarray, cov_m2: np.ndarray) -> None:
        """A GNSS fix of p_k - n_k (the drone's position plus its receiver's error), robust."""
        self._add(gtsam.BetweenFactorPoint3(self.key(drone_index, 2, k), self.key(drone_index, 0, k),
                                            gtsam.Point3(*enu_m), self._robust(cov_m2)), k, measurement=True)

    def motion(self, drone_index: int, k: int, walk_sigma_m: float, bias_walk_sigma_mps: float,
               q_walk_sigma: np.ndarray | None = None) -> None:
        """Step k -> k+1: weak bound on the position change and the bias random walk (and q's, per component)."""
        for kind, sigma in ((0, walk_sigma_m), (1, bias_walk_sigma_mps), (3, q_walk_sigma)):
            if sigma is None:
                continue
            self._add(gtsam.BetweenFactorPoint3(
                self.key(drone_index, kind, k), self.key(drone_index, kind, k + 1), gtsam.Point3(0.0, 0.0, 0.0),
                gtsam.noiseModel.Diagonal.Sigmas(np.broadcast_to(np.asarray(sigma, float), (3,)).copy())), k)

    def velocity_scaled(self, drone_index: int, k: int, vel_mps: np.ndarray, sigma_mps: np.ndarray) -> None:
        """p_k+1 - p_k = R_up(-psi) (v - b_k) dt / (1 + s), q_k = (s, psi, 0); sigma per axis ``sigma_mps * dt``."""
        dt, v = self.dt_s, np.asarray(vel_mps, float).copy()
        keys = [self.key(drone_index, 0, k), self.key(drone_index, 0, k + 1), self.key(drone_index, 1, k),
                self.key(drone_index, 3, k)]

        def error(_factor, values, jacobians):
            s, psi, _ = values.atPoint3(keys[3])
            u = v - values.atPoint3(keys[2])
            c = dt / (1.0 + s)
            rot = _r_up(-psi)
            moved = rot @ u * c
            if jacobians is not None:
                jacobians[0] = -_EYE
                jacobians[1] = _EYE.copy()
                jacobians[2] = rot * c
                jq = np.zeros((3, 3))
                jq[:, 0] = moved / (1.0 + s)
                jq[:, 1] = _J_UP @ moved
                jacobians[3] = jq
            return values.atPoint3(keys[1]) - values.atPoint3(keys[0]) - moved

        noise = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigma_mps, float) * dt)
        self._add(gtsam.CustomFactor(noise, keys, error), k)

    def velocity(self, drone_index: int, k: int, vel_mps: np.ndarray, sigma_mps: np.ndarray) -> None:
        """p_k+1 - p_k + b_k dt = v dt, sigma per axis ``sigma_mps * dt``."""
        dt = self.dt_s
        keys = (self.key(drone_index, 0, k), self.key(drone_index, 0, k + 1), self.key(drone_index, 1, k))
        factor = gtsam.JacobianFactor(keys[0], -_EYE, keys[1], _EYE, keys[2], dt * _EYE, np.asarray(vel_mps) * dt,
                                      gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigma_mps) * dt))
        self._add(gtsam.LinearContainerFactor(factor, self._zeros(keys)), k)

    def altitude(self, drone_index: int, k: int, up_m: float, sigma_m: float) -> None:
        """The up component of p_k (local ENU) is ``up_m``."""
        key = self.key(drone_index, 0, k)
        factor = gtsam.JacobianFactor(key, _UP_ROW, np.array([up_m]), gtsam.noiseModel.Isotropic.Sigma(1, sigma_m))
        self._add(gtsam.LinearContainerFactor(factor, self._zeros((key,))), k, measurement=True)

    def position(self, drone_index: int, k: int, enu_m: np.ndarray, cov_m2: np.ndarray, robust: bool = True) -> None:
        """Absolute position of p_k (GNSS robust; a precise fix, e.g. from tags, Gaussian).

        The robust kernel is evaluated at the current estimate, so a fix much more precise
        than the drone's prediction would be down-weighted as an outlier for its first update;
        such fixes are gated (chi-square on the full innovation covariance) but not re-weighted.
        """
        noise = self._robust(cov_m2) if robust else gtsam.noiseModel.Gaussian.Covariance(cov_m2)
        self._add(gtsam.PriorFactorPoint3(self.key(drone_index, 0, k), gtsam.Point3(*enu_m), noise), k,
                  measurement=True)

    def relative_pointed(self, observer_index: int, target_index: int, pointing_index: int, k: int,
                         offset_m: np.ndarray, cov_m2: np.ndarray, jacobian: np.ndarray) -> None:
        """p_target,k - p_observer,k - J e_k = offset, e_k the observer's pointing error (the kind-2 variable of
        ``pointing_index``), J = ``jacobian`` (3, 3); Gaussian (a three-variable linear relation; outliers are
        the gate's to refuse)."""
        keys = (self.key(observer_index, 0, k), self.key(target_index, 0, k), self.key(pointing_index, 2, k))
        # whitened here (gtsam's three-key JacobianFactor takes a diagonal model): L^-1 (A x - b), cov = L L'
        w = np.linalg.inv(np.linalg.cholesky(np.asarray(cov_m2, float)))
        factor = gtsam.JacobianFactor(keys[0], -w, keys[1], w.copy(), keys[2], -w @ np.asarray(jacobian, float),
                                      w @ np.asarray(offset_m, float), gtsam.noiseModel.Unit.Create(3))
        self._add(gtsam.LinearContainerFactor(factor, self._zeros(keys)), k, measurement=True)

    def relative(self, observer_index: int, target_index: int, k: int, offset_m: np.ndarray, cov_m2: np.ndarray) -> None:
        """p_target,k - p_observer,k = offset, robust."""
        self._add(gtsam.BetweenFactorPoint3(self.key(observer_index, 0, k), self.key(target_index, 0, k),
                                            gtsam.Point3(*offset_m), self._robust(cov_m2)), k, measurement=True)

    @staticmethod
    def _zeros(keys) -> gtsam.Values:
        lin = gtsam.Values()
        for key in keys:
            lin.insert(key, gtsam.Point3(0.0, 0.0, 0.0))
        return lin

    # -- solve ---------------------------------------------------------------------------
    def _compact(self) -> None:
        """Rebuild the graph without the null slots marginalisation left behind."""
        graph = gtsam.NonlinearFactorGraph()
        buckets: dict[int, list[int]] = {}
        for step in sorted(self._buckets):
            for slot in self._buckets[step]:
                graph.push_back(self._graph.at(slot))
                buckets.setdefault(step, []).append(graph.size() - 1)
        self._graph, self._buckets = graph, buckets

    def _check_constrained(self) -> None:
        """The guard: every new variable must appear in at least one factor."""
        if not self._new_keys:
            return
        touched: set[int] = set()
        for k in {key & _STEP_MASK for key in self._new_keys} | {(key & _STEP_MASK) - 1 for key in self._new_keys}:
            for slot in self._buckets.get(k, ()):
                touched.update(self._graph.at(slot).keys())
        loose = [key for key in self._new_keys if key not in touched]
        if loose:
            raise EstimationError(f"{len(loose)} new fusion variable(s) without any factor (first key {loose[0]}); "
                                  "refusing to update an indeterminate system")

    def update(self, tail_keys: list[int]) -> None:
        """Marginalise steps older than the lag, then solve; ``tail_keys`` get a cheap joint covariance.

        ``tail_keys`` must be variables of the window (the newest per drone).
        """
        if not self.pending:
            return
        self._check_constrained()
        self._marginalise(self._newest_step - self.lag_steps)
        tail = [key for key in tail_keys if self._values.exists(key)]
        try:
            tail_cov = self._solve(tail)
        except EstimationError as exc:
            if not self._new_measurements:
                raise
            # Keep the window usable: drop this batch's measurements, keep the states and their motion.
            log.error("%s; dropping the %d measurement(s) added since the last update", exc, len(self._new_measurements))
            for bucket, slot in self._new_measurements:
                if slot in self._buckets.get(bucket, ()):
                    self._buckets[bucket].remove(slot)
                    self._graph.remove(slot)
                    self._live -= 1
            self._new_measurements = []
            tail_cov = self._solve(tail)
        self._tail_index = {key: 3 * i for i, key in enumerate(tail)}
        self._tail_cov = 0.5 * (tail_cov + tail_cov.T)
        self._optimised = {key for keys in self._keys_by_step.values() for key in keys}
        self._marginals = None
        self._new_keys = []
        self._new_measurements = []
        self._n_new_factors = 0
        if self._graph.size() > 4 * self._live + 64:
            self._compact()

    def _solve(self, tail: list[int]) -> np.ndarray:
        """Gauss-Newton step(s) on the window; returns the joint covariance of ``tail``."""
        tail_set = set(tail)
        head = [key for step in sorted(self._keys_by_step) for key in self._keys_by_step[step] if key not in tail_set]
        values = self._values
        try:
            for _ in range(self.max_iterations):
                gfg = self._graph.linearize(values)
                head_net, tail_graph = gfg.eliminatePartialSequential(gtsam.Ordering(head))
                info, eta = tail_graph.hessian(gtsam.Ordering(tail))
                tail_cov = np.linalg.inv(info)
                tail_delta = tail_cov @ eta.ravel()
                if not np.isfinite(tail_delta).all():
                    raise np.linalg.LinAlgError("non-finite solution")
                given = gtsam.VectorValues()
                for i, key in enumerate(tail):
                    given.insert(key, tail_delta[3 * i:3 * i + 3])
                values = values.retract(head_net.optimize(given))  # the solution includes the given tail
        except (RuntimeError, np.linalg.LinAlgError) as exc:  # gtsam: indeterminant system
            raise EstimationError(f"fusion window solve failed: {exc}") from exc
        self._values = values
        self._value_cache = {}
        return tail_cov

    def _marginalise(self, before_step: int) -> None:
        """Eliminate every variable of steps < before_step; keep their information as a prior."""
        self._marginalised_before = max(self._marginalised_before, before_step)
        old_steps = sorted(k for k in self._keys_by_step if k < before_step)
        if not old_steps:
            return
        old_keys = [key for k in old_steps for key in self._keys_by_step[k]]
        slots = [slot for k in sorted(b for b in self._buckets if b < before_step) for slot in self._buckets.pop(k)]
        sub = gtsam.NonlinearFactorGraph()
        for slot in slots:
            sub.push_back(self._graph.at(slot))
            self._graph.remove(slot)
        self._live -= len(slots)
        _, remaining = sub.linearize(self._values).eliminatePartialSequential(gtsam.Ordering(old_keys))
        for i in range(remaining.size()):
            marginal = remaining.at(i)
            if marginal is None:
                continue
            keys = list(marginal.keys())
            if not keys:
                continue
            lin = gtsam.Values()
            for key in keys:
                lin.insert(key, self._values.atPoint3(key))
            self._add(gtsam.LinearContainerFactor(marginal, lin), min(key & _STEP_MASK for key in keys), new=False)
        for k in old_steps:
            del self._keys_by_step[k]
        for key in old_keys:
            self._values.erase(key)
            self._value_cache.pop(key, None)
            self._optimised.discard(key)
