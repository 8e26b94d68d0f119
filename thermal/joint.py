"""Fire positions from every frame that saw them, with the pose errors drones really have.

One least-squares problem over a whole flight (Levenberg-Marquardt), in pixels:
each sighting (camera stamp, hotspot centroid, fire) is predicted by projecting the
fire's 3-D point into the camera the pose log says was there, corrected by

- a GNSS position error that is one Gauss-Markov process per axis, shared by every frame
  (unknowns at knots every ``knot_spacing_s``, linearly interpolated, with the process's
  own prior between knots), not independent evidence per frame;
- a slowly drifting attitude error (same structure, small rotations about the ENU axes);
- a constant boresight rotation of the thermal sensor relative to the gimbal's axes;
- a constant time offset between camera stamps and the pose log.

Each fire is three unknowns: east, north, and its height above the DEM (prior: the DEM's
1-sigma), so its point stays on the terrain while all its rays are intersected jointly.
White errors (pixel noise, per-frame attitude and GNSS noise, the knots' interpolation
error) are marginalised into a per-frame covariance of the sighting pixels (shared by the
fires of one frame) and whitened. The stated covariance is the Gauss-Newton inverse at
the solution: it carries the GNSS, boresight and time-offset uncertainty that is common
to all fires.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse
from scipy.optimize import linear_sum_assignment
from scipy.spatial.transform import Rotation

from skyfix import validate
from skyfix.camera import Camera
from skyfix.errors import EstimationError, InputError
from skyfix.geo import LocalFrame
from skyfix.thermal.ground import DemGround, FlatGround, as_ground
from skyfix.thermal.poselog import PoseLog
from skyfix.thermal.sightings import Sightings
from skyfix.thermal.tracker import Fire

_EPS_M = 0.02
_EPS_RAD = 1e-5
_EPS_S = 0.005


@dataclass(frozen=True)
class PoseErrorPrior:
    """What is known of the drone's pose errors (1-sigma; units in the names).

    Defaults: a consumer GNSS receiver (1.5 m horizontal / 2.5 m vertical wander with a
    60 s correlation time, 0.3 m white), a gimbal and AHRS (0.3 deg white per frame, 0.3
    deg drift over 30 s), an uncalibrated thermal boresight (1.5 deg per axis) and camera
    clock (0.3 s). ``knot_spacing_s``: spacing of the GNSS/attitude error unknowns.
    """

    gnss_h_sigma_m: float = 1.5
    gnss_v_sigma_m: float = 2.5
    gnss_tau_s: float = 60.0
    gnss_white_m: float = 0.3
    attitude_white_deg: float = 0.3
    attitude_drift_deg: float = 0.3
    attitude_tau_s: float = 30.0
    boresight_sigma_deg: float = 1.5
    time_offset_sigma_s: float = 0.3
    pixel_sigma_px: float = 0.5
    knot_spacing_s: float = 4.0

    def __post_init__(self) -> None:
        for name in self.__dataclass_fields__:
            validate.positive_scalar(f"PoseErrorPrior.{name}", getattr(self, name))


@dataclass(frozen=True)
class JointSolution:
    """Result of :func:`locate_jointly`. ``fires``: one :class:`Fire` per fire id of the
    sightings (``cov_en_m2`` the marginal horizontal covariance, ENU axes at the fire).
    ``boresight_deg`` ``(3,)``: rotation vector, camera axes (x right, y down, z forward),
    reported camera -> real camera, with ``boresight_cov_deg2``. ``time_offset_s``: log
    time minus camera stamp, with ``time_offset_sigma_s``. ``knot_times_s``/``gnss_error_enu_m``
    ``(K, 3)``: the estimated GNSS error (logged minus true position, ENU m).
    ``chi2``/``dof``: whitened residual sum of squares and its degrees of freedom."""

    fires: list[Fire]
    fire_enu_m: np.ndarray
    boresight_deg: np.ndarray
    boresight_cov_deg2: np.ndarray
    time_offset_s: float
    time_offset_sigma_s: float
    knot_times_s: np.ndarray
    gnss_error_enu_m: np.ndarray
    chi2: float
    dof: int


class _Problem:
    """Parameter layout, prediction and whitening of one joint problem."""

    def __init__(self, camera: Camera, log: PoseLog, s: Sightings, ground: FlatGround | DemGround,
                 frame: LocalFrame, prior: PoseErrorPrior, boresight_deg, calibration) -> None:
        self.camera, self.log, self.s, self.ground, self.frame, self.prior = camera, log, s, ground, frame, prior
        self.n_fires = s.n_fires
        lo, hi = float(s.pool[:, 0].min()), float(s.pool[:, 0].max())
        n_knots = max(int(math.ceil((hi - lo) / prior.knot_spacing_s)) + 1, 2)
        self.knots = np.linspace(lo, hi + 1e-9, n_knots)
        self.smooth = log.smoothed(8.0)
        # Height prior of each fire: the ground's sigma where it is (larger in filled DEM holes).
        lat, lon, _ = frame.to_geodetic(s.initial_en_m[:, 0], s.initial_en_m[:, 1],
                                        np.full(s.n_fires, ground.alt_m - frame.alt0_m))
        self.dh_sigma = np.maximum(ground.sigma_at(lat, lon), 0.05)
        self.rows = self.bind(s.time_s, s.fire_index)
        self._own_poses = self._poses_at(s.time_s)
        self._own_cameras: tuple[float, tuple[np.ndarray, np.ndarray]] | None = None  # (dt_s, cameras)
        self.fixed_boresight = None if boresight_deg is None else np.radians(
            validate.finite_array("boresight_deg", boresight_deg).reshape(3))
        # Prior of boresight (rad) and time offset (s): nominal zero, or an earlier calibration.
        if calibration is None:
            self.bore_mean, self.dt_mean, self.dt_sigma = np.zeros(3), 0.0, prior.time_offset_sigma_s
            self.bore_white = np.eye(3) / math.radians(prior.boresight_sigma_deg)
        else:
            if not isinstance(calibration, JointSolution):
                raise InputError(f"calibration must be a JointSolution, got {type(calibration).__name__}")
            self.bore_mean = np.radians(calibration.boresight_deg)
            cov = np.radians(np.radians(calibration.boresight_cov_deg2)) + 1e-12 * np.eye(3)
            self.bore_white = np.linalg.inv(np.linalg.cholesky(cov))
            self.dt_mean, self.dt_sigma = calibration.time_offset_s, max(calibration.time_offset_sigma_s, 1e-4)
        nf = 3 * self.n_fires
        self.sl_fire = slice(0, nf)
        self.sl_bore = slice(nf, nf + 3)
        self.i_dt = nf + 3
        self.sl_gnss = slice(nf + 4, nf + 4 + 3 * n_knots)
        self.sl_att = slice(nf + 4 + 3 * n_knots, nf + 4 + 6 * n_knots)
        self.n_params = nf + 4 + 6 * n_knots

    def bind(self, time_s: np.ndarray, fire_index: np.ndarray) -> tuple[np.ndarray, ...]:
        """(stamps, fire index, knot index, knot weight) of the rows to predict."""
        idx = np.clip(np.searchsorted(self.knots, time_s, side="right") - 1, 0, self.knots.size - 2)
        w = (time_s - self.knots[idx]) / (self.knots[idx + 1] - self.knots[idx])
        return time_s, fire_index, idx, w

    # --- model -------------------------------------------------------------------
    def _poses_at(self, time_s: np.ndarray) -> tuple[np.ndarray, ...]:
        """Logged camera (ENU, rotation) at the stamps, and the smoothed log's there."""
        t = np.clip(time_s, *self.log.span_s)
        return (*self.log.camera_in_frame(self.frame, t), *self.smooth.camera_in_frame(self.frame, t))

    def _cameras(self, rows: tuple, dt_s: float, own: bool) -> tuple[np.ndarray, np.ndarray]:
        """Cameras at stamp + ``dt_s``: the logged pose at the stamp moved by the smoothed
        log's motion over ``dt_s`` (the log's per-sample noise is not motion). The sightings' own
        are kept for the last ``dt_s`` (a Jacobian's other columns and the whitening reuse them)."""
        if own and self._own_cameras is not None and self._own_cameras[0] == dt_s:
            return self._own_cameras[1]
        cam0, r0, s_cam0, s_r0 = self._own_poses if own else self._poses_at(rows[0])
        s_cam1, s_r1 = self.smooth.camera_in_frame(self.frame, np.clip(rows[0] + dt_s, *self.log.span_s))
        out = cam0 + (s_cam1 - s_cam0), s_r1 @ np.transpose(s_r0, (0, 2, 1)) @ r0
        if own:
            for a in out:
                a.setflags(write=False)
            self._own_cameras = (dt_s, out)
        return out

    def fire_points(self, x: np.ndarray) -> np.ndarray:
        """Fire points ``(F, 3)`` in the frame: (east, north) and the ground height + dh."""
        f = x[self.sl_fire].reshape(-1, 3)
        up = np.full(len(f), self.ground.alt_m - self.frame.alt0_m)
        for _ in range(3):
            lat, lon, h = self.frame.to_geodetic(f[:, 0], f[:, 1], up)
            target = self.ground.height_at(lat, lon) + f[:, 2]
            if not np.all(np.isfinite(target)):
                raise EstimationError("a fire's position left the DEM (or fell in a no-data hole)")
            up = up + (target - h)
        return np.column_stack((f[:, :2], up))

    @staticmethod
    def _interp(x: np.ndarray, sl: slice, rows: tuple) -> np.ndarray:
        k = x[sl].reshape(-1, 3)
        idx, w = rows[2], rows[3][:, None]
        return (1.0 - w) * k[idx] + w * k[idx + 1]

    def predict(self, x: np.ndarray, d_pos=None, d_rot=None, rows: tuple | None = None) -> np.ndarray:
        """Predicted pixels ``(N, 2)`` of the sightings (or of ``rows`` from :meth:`bind`,
        NaN where a fire is behind the camera), optionally with every camera moved by
        ``d_pos`` m or rotated by ``d_rot`` rad about the frame's axes."""
        own = rows is None
        rows = self.rows if own else rows
        cam, r = self._cameras(rows, float(x[self.i_dt]), own)
        cam = cam - self._interp(x, self.sl_gnss, rows)  # logged = true + error
        rot = -self._interp(x, self.sl_att, rows)
        if d_pos is not None:
            cam = cam + d_pos
        if d_rot is not None:
            rot = rot + d_rot
        bore = self.fixed_boresight if self.fixed_boresight is not None else x[self.sl_bore]
        r_true = Rotation.from_rotvec(rot).as_matrix() @ r @ Rotation.from_rotvec(bore).as_matrix()
        pts = self.fire_points(x)[rows[1]]
        p_cam = np.einsum("nji,nj->ni", r_true, pts - cam)
        if own and np.any(p_cam[:, 2] <= 0):
            raise EstimationError("a fire moved behind a camera that saw it")
        return self.camera.project(p_cam)

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """Whitened residuals: sightings, then priors."""
        r = (self.predict(x) - self.s.uv_px).ravel()
        return np.concatenate((self.white @ r, self._prior_residuals(x)))

    def _prior_residuals(self, x: np.ndarray) -> np.ndarray:
        p = self.prior
        out = [x[self.sl_fire].reshape(-1, 3)[:, 2] / self.dh_sigma,
               self.bore_white @ (x[self.sl_bore] - self.bore_mean), [(x[self.i_dt] - self.dt_mean) / self.dt_sigma]]
        dt = np.diff(self.knots)[:, None]
        for sl, sig, tau in ((self.sl_gnss, np.array([p.gnss_h_sigma_m, p.gnss_h_sigma_m, p.gnss_v_sigma_m]),
                              p.gnss_tau_s),
                             (self.sl_att, np.full(3, math.radians(p.attitude_drift_deg)), p.attitude_tau_s)):
            k = x[sl].reshape(-1, 3)
            phi = np.exp(-dt / tau)
            out += [k[0] / sig, ((k[1:] - phi * k[:-1]) / (sig * np.sqrt(1.0 - phi * phi))).ravel()]
        return np.concatenate([np.ravel(o) for o in out])

    # --- Jacobian ------------------------------------------------------------------
    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """Dense Jacobian of :meth:`residuals` (finite differences by parameter block)."""
        n = self.s.n
        base = self.predict(x)
        j = np.zeros((2 * n, self.n_params))
        rows = np.arange(n)
        for c in range(3):  # fire east, north, dh: each sighting depends on its own fire only
            xp = x.copy()
            xp[self.sl_fire][c::3] += _EPS_M
            d = (self.predict(xp) - base) / _EPS_M
            cols = 3 * self.s.fire_index + c
            j[2 * rows, cols], j[2 * rows + 1, cols] = d[:, 0], d[:, 1]
        if self.fixed_boresight is None:
            for c in range(3):
                xp = x.copy()
                xp[self.sl_bore.start + c] += _EPS_RAD
                j[:, self.sl_bore.start + c] = ((self.predict(xp) - base) / _EPS_RAD).ravel()
        xp = x.copy()
        xp[self.i_dt] += _EPS_S
        j[:, self.i_dt] = ((self.predict(xp) - base) / _EPS_S).ravel()
        for sl, eps, kw, sign in ((self.sl_gnss, _EPS_M, "d_pos", -1.0), (self.sl_att, _EPS_RAD, "d_rot", -1.0)):
            for c in range(3):
                step = np.zeros(3)
                step[c] = eps
                d = sign * (self.predict(x, **{kw: step}) - base) / eps
                k_idx, k_w = self.rows[2], self.rows[3]
                for which, wgt in ((k_idx, 1.0 - k_w), (k_idx + 1, k_w)):
                    cols = sl.start + 3 * which + c
                    np.add.at(j, (2 * rows, cols), d[:, 0] * wgt)
                    np.add.at(j, (2 * rows + 1, cols), d[:, 1] * wgt)
        j_prior = self._prior_jacobian(x)
        return np.vstack((self.white @ j, j_prior))

    def _prior_jacobian(self, x: np.ndarray) -> np.ndarray:
        """The priors are linear: their Jacobian is built once, one difference per parameter."""
        if getattr(self, "_j_prior", None) is None:
            r0 = self._prior_residuals(x)
            j = np.zeros((r0.size, self.n_params))
            for i in range(self.n_params):
                xp = x.copy()
                xp[i] += 1.0
                j[:, i] = self._prior_residuals(xp) - r0
            self._j_prior = j
        return self._j_prior

    # --- whitening -------------------------------------------------------------------
    def set_whitening(self, x: np.ndarray) -> None:
        """Per-frame whitening of the sighting pixels: pixel noise plus the white attitude
        and GNSS errors (and the knots' interpolation error), shared by one frame's fires."""
        p = self.prior
        base = self.predict(x)
        d_pos = np.stack([(self.predict(x, d_pos=np.eye(3)[c] * _EPS_M) - base) / _EPS_M for c in range(3)], -1)
        d_rot = np.stack([(self.predict(x, d_rot=np.eye(3)[c] * _EPS_RAD) - base) / _EPS_RAD for c in range(3)], -1)
        interp_frac = p.knot_spacing_s / 3.0
        var_pos = np.array([p.gnss_white_m ** 2 + p.gnss_h_sigma_m ** 2 * interp_frac / p.gnss_tau_s] * 2
                           + [p.gnss_white_m ** 2 + p.gnss_v_sigma_m ** 2 * interp_frac / p.gnss_tau_s])
        var_rot = math.radians(p.attitude_white_deg) ** 2 + math.radians(p.attitude_drift_deg) ** 2 * (
            interp_frac / p.attitude_tau_s)
        blocks = []
        for rows in self.s.frames():
            jp = d_pos[rows].reshape(-1, 3)
            jr = d_rot[rows].reshape(-1, 3)
            cov = (jp * var_pos) @ jp.T + var_rot * (jr @ jr.T) + p.pixel_sigma_px ** 2 * np.eye(jp.shape[0])
            blocks.append(np.linalg.inv(np.linalg.cholesky(cov)))
        self.white = scipy.sparse.block_diag(blocks, format="csr")


def locate_jointly(camera: Camera, log: PoseLog, sightings: Sightings, ground, *,
                   prior: PoseErrorPrior | None = None, frame: LocalFrame | None = None,
                   boresight_deg=None, calibration: JointSolution | None = None, merge_m: float = 4.0,
                   gate_px: float = 25.0, on_iteration=None) -> JointSolution:
    """Joint estimate of every fire of ``sightings`` (see module docstring).

    ``ground``: ellipsoidal height (m), :class:`FlatGround` or :class:`DemGround`.
    ``boresight_deg``: a known boresight rotation vector (deg) to hold fixed; None
    estimates it. ``calibration``: an earlier solution of the same camera (e.g. an orbit
    that saw fires from every side) whose boresight and time offset, with their
    covariance, replace the nominal prior. ``merge_m``: fires estimated closer than this are one fire. ``gate_px``: a
    hotspot farther than this from every fire's predicted pixel is left out. ``on_iteration()``,
    when given, is called after every solver iteration (for a progress display). Raises
    :class:`EstimationError` when the problem does not converge.
    """
    if not isinstance(camera, Camera) or not isinstance(log, PoseLog) or not isinstance(sightings, Sightings):
        raise InputError("locate_jointly(camera: Camera, log: PoseLog, sightings: Sightings, ground)")
    ground = as_ground(ground)
    prior = prior or PoseErrorPrior()
    frame = frame or sightings.frame
    x_shared = None
    for _ in range(6):  # solve; merge split fires; re-associate in pixels; until stable
        prob = _Problem(camera, log, sightings, ground, frame, prior, boresight_deg, calibration)
        x = np.zeros(prob.n_params)
        x[prob.sl_fire] = np.column_stack((sightings.initial_en_m, np.zeros(sightings.n_fires))).ravel()
        x[prob.sl_bore], x[prob.i_dt] = prob.bore_mean, prob.dt_mean
        if x_shared is not None:
            x[prob.sl_fire.stop:] = x_shared
        x, chi2, dof = _solve(prob, x, on_iteration)
        x_shared = x[prob.sl_fire.stop:]
        fire_en = x[prob.sl_fire].reshape(-1, 3)[:, :2]
        merged = sightings.merged(fire_en, merge_m)
        if merged is sightings:
            assignment = _reassign(prob, x, gate_px)
            current = _current_assignment(sightings)
            if np.array_equal(assignment, current):
                break
            merged = sightings.reassigned(assignment, fire_en)
        sightings = merged
    j = scipy.sparse.csr_matrix(prob.jacobian(x))
    return _solution(prob, x, _inverse((j.T @ j).toarray()), chi2, dof)


def _inverse(h: np.ndarray) -> np.ndarray:
    """Covariance ``(N, N)`` from the normal matrix ``h = J^T J``: its inverse by Cholesky (the priors
    and the sightings pin every unknown, so ``h`` is positive definite; on the README's calibration
    orbit, 1723 unknowns, 0.6-1.3 s where the SVD of ``np.linalg.pinv`` took 12-44 s on 2 busy
    cores; same covariance to 1e-8 relative), the pseudo-inverse only when ``h`` is not numerically
    positive definite."""
    try:
        inv = scipy.linalg.cho_solve(scipy.linalg.cho_factor(h), np.eye(h.shape[0]))
    except (np.linalg.LinAlgError, scipy.linalg.LinAlgError):
        return np.linalg.pinv(h)
    return 0.5 * (inv + inv.T)


def _current_assignment(s: Sightings) -> np.ndarray:
    """Fire index ``(P,)`` of every pool row (-1: unused), matched on (stamp, u, v)."""
    key = {(t, u, v): f for t, (u, v), f in zip(s.time_s, s.uv_px, s.fire_index, strict=True)}
    return np.array([key.get((t, u, v), -1) for t, u, v in s.pool[:, :3]])


def _reassign(prob: _Problem, x: np.ndarray, gate_px: float, min_detection_rate: float = 0.25) -> np.ndarray:
    """Each pool hotspot to the fire predicted nearest in its frame (one-to-one per frame,
    within ``gate_px``), with the current pose corrections; -1 for none. A fire matched in
    fewer than ``min_detection_rate`` of the frames that should show it is a ghost (a
    cluster of misplaced single-frame points): its hotspots are released."""
    pool = prob.s.pool
    stamps, inverse = np.unique(pool[:, 0], return_inverse=True)
    n_f = prob.n_fires
    rows = prob.bind(np.repeat(stamps, n_f), np.tile(np.arange(n_f), stamps.size))
    pred = prob.predict(x, rows=rows).reshape(stamps.size, n_f, 2)
    out = np.full(pool.shape[0], -1)
    for k in range(stamps.size):
        members = np.flatnonzero(inverse == k)
        dist = np.hypot(*(pool[members, None, 1:3] - pred[k][None]).transpose(2, 0, 1))
        cost = np.where(np.isfinite(dist) & (dist <= gate_px), dist, 1e9)
        r, c = linear_sum_assignment(cost)
        ok = cost[r, c] < 1e9
        out[members[r[ok]]] = c[ok]
    flat = pred.reshape(-1, 2)
    in_view = np.isfinite(flat).all(axis=1)
    in_view[in_view] = prob.camera.in_image(flat[in_view])
    expected = in_view.reshape(stamps.size, n_f).sum(axis=0)
    matched = np.bincount(out[out >= 0], minlength=n_f)
    ghosts = np.flatnonzero(matched < min_detection_rate * expected)
    out[np.isin(out, ghosts)] = -1
    return out


def _solve(prob: _Problem, x: np.ndarray, on_iteration=None) -> tuple[np.ndarray, float, int]:
    """Levenberg-Marquardt on the normal equations (the problem is nearly linear and has a
    few hundred unknowns: Cholesky of J^T J is far cheaper than MINPACK's pivoted QR of J),
    whitening relinearised once at the first solution."""
    for _ in range(2):
        prob.set_whitening(x)
        x, r = _levenberg_marquardt(prob, x, on_iteration=on_iteration)
    return x, float(r @ r), int(r.size - prob.n_params)


def _levenberg_marquardt(prob: _Problem, x: np.ndarray, max_iter: int = 30, on_iteration=None
                        ) -> tuple[np.ndarray, np.ndarray]:
    r = prob.residuals(x)
    cost, lam = float(r @ r), 1e-4
    for _ in range(max_iter):
        if on_iteration is not None:
            on_iteration()
        j = scipy.sparse.csr_matrix(prob.jacobian(x))  # ~20 of ~1700 columns per row: J^T J sparse, not BLAS
        h, g = (j.T @ j).toarray(), j.T @ r
        damping = np.diag(h).copy() + 1e-12
        while True:
            try:
                step = -scipy.linalg.cho_solve(scipy.linalg.cho_factor(h + lam * np.diag(damping)), g)
                r_new = prob.residuals(x + step)
                cost_new = float(r_new @ r_new)
            except (np.linalg.LinAlgError, scipy.linalg.LinAlgError, EstimationError):
                cost_new = math.inf
            if cost_new <= cost:
                break
            lam *= 10.0
            if lam > 1e10:
                return x, r  # no step lowers the cost: converged (or stuck at the prior's edge)
        x, r, done = x + step, r_new, cost - cost_new < 1e-9 * max(cost, 1.0)
        cost, lam = cost_new, max(lam / 10.0, 1e-9)
        if done:
            break
    if not np.all(np.isfinite(x)):
        raise EstimationError("joint fire estimate did not converge")
    return x, r


def _solution(prob: _Problem, x: np.ndarray, cov: np.ndarray, chi2: float, dof: int) -> JointSolution:
    pts = prob.fire_points(x)
    frame, s = prob.frame, prob.s
    lat, lon, alt = frame.to_geodetic(pts[:, 0], pts[:, 1], pts[:, 2])
    fires = []
    for i in range(prob.n_fires):
        c = cov[3 * i:3 * i + 2, 3 * i:3 * i + 2]
        r = frame.enu_rotation_at(float(lat[i]), float(lon[i]))[:2, :2]
        c_en = r.T @ c @ r
        c_en.setflags(write=False)
        seen = s.time_s[s.fire_index == i]
        fires.append(Fire(int(s.fire_ids[i]), float(lat[i]), float(lon[i]), float(alt[i]), c_en, int(seen.size),
                          float(seen.min()), float(seen.max()), float(s.area_m2[i]), float(s.peak[i]), True))
    b = prob.sl_bore
    bore = prob.fixed_boresight if prob.fixed_boresight is not None else x[b]
    return JointSolution(fires, pts, np.degrees(bore), np.degrees(np.degrees(cov[b, b])), float(x[prob.i_dt]),
                         float(math.sqrt(cov[prob.i_dt, prob.i_dt])), prob.knots,
                         x[prob.sl_gnss].reshape(-1, 3), chi2, dof)
