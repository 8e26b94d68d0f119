"""Baseline for benchmarks/fusion.py: one joint EKF over every drone (cross covariances tracked).

State, per drone: position p (3, frame ENU, m), velocity bias b (3, m/s) and, with
``gnss_gm``, the receiver's Gauss-Markov error g (3, m): GNSS = p + g + white. The
autopilot velocity is the control input (p += (v - b) dt, v extrapolated with the
last two samples' acceleration so that one drone's message can move every drone to its
time); b walks; g decays with exp(-dt/tau). Updates (filterpy ``KalmanFilter``, Joseph
form): GNSS (chi-square gate 99.9 %), barometric altitude, and relative observations as
``p_target - p_observer = offset`` on the joint state, gated with the joint covariance.
Late messages are moved to the filter time with the bias-corrected velocity and their
covariance grown by the velocity noise. Without ``gnss_gm`` the GNSS error is modelled
white with the receiver's reported sigma (what issue 15 measured the engine against).
"""

from __future__ import annotations

import math

import numpy as np
from filterpy.kalman import KalmanFilter
from scipy.stats import chi2

GATE_CHI2_3 = chi2.ppf(0.999, 3)
_ALT_REF_REFRESH_M = 100.0


class JointEKF:
    """One Kalman filter over all drones; ``ids`` fixes the block order."""

    def __init__(self, frame, ids: tuple[str, ...], vel_sigma_mps: float, vel_rate_hz: float,
                 bias_walk: float, gnss_gm: tuple[float, float, float] | None) -> None:
        self.frame, self.ids = frame, ids
        self.gm = gnss_gm  # (sigma_h_m, sigma_v_m, tau_s) or None
        self.m = 9 if gnss_gm else 6
        n = self.m * len(ids)
        self.kf = KalmanFilter(dim_x=n, dim_z=3)
        self.kf.P = np.eye(n) * 1e6
        self.ready = np.zeros(len(ids), bool)
        self.t_s = -math.inf
        self.vel_var_rate = vel_sigma_mps**2 / vel_rate_hz
        self.bias_var_rate = bias_walk**2
        self.v = [None] * len(ids)   # (t, v frame axes, acceleration)
        self.rot = [np.eye(3)] * len(ids)
        self.alt_ref = [None] * len(ids)  # (p_ref, alt_ref) for the altitude row
        self.n_gated = 0

    # -- state access
    def _blk(self, i: int) -> slice:
        return slice(self.m * i, self.m * i + self.m)

    def p(self, i: int) -> np.ndarray:
        return self.kf.x[self.m * i:self.m * i + 3, 0]

    def p_cov(self, i: int) -> np.ndarray:
        j = self.m * i
        return self.kf.P[j:j + 3, j:j + 3]

    def _vel_at(self, i: int, t: float) -> np.ndarray:
        if self.v[i] is None:
            return np.zeros(3)
        t0, v, a = self.v[i]
        return v + a * np.clip(t - t0, 0.0, 0.2) - self.kf.x[self.m * i + 3:self.m * i + 6, 0]

    # -- prediction
    def predict_to(self, t: float) -> None:
        dt = t - self.t_s
        if dt <= 0.0 or not self.ready.any():
            self.t_s = max(self.t_s, t)
            return
        n = self.kf.dim_x
        f, q, u = np.eye(n), np.zeros((n, n)), np.zeros((n, 1))
        eye3 = np.eye(3)
        for i in np.flatnonzero(self.ready):
            j = self.m * i
            f[j:j + 3, j + 3:j + 6] = -dt * eye3
            if self.v[i] is not None:
                t0, v, a = self.v[i]
                u[j:j + 3, 0] = (v + a * np.clip(0.5 * (self.t_s + t) - t0, 0.0, 0.2)) * dt
            q[j:j + 3, j:j + 3] = eye3 * self.vel_var_rate * dt
            q[j + 3:j + 6, j + 3:j + 6] = eye3 * self.bias_var_rate * dt
            if self.gm:
                sh, sv, tau = self.gm
                phi = math.exp(-dt / tau)
                f[j + 6:j + 9, j + 6:j + 9] = eye3 * phi
                q[j + 6:j + 9, j + 6:j + 9] = np.diag([sh**2, sh**2, sv**2]) * (1 - phi**2)
        self.kf.predict(u=u, B=np.eye(n), F=f, Q=q)
        self.t_s = t

    # -- inputs
    def velocity(self, i: int, t: float, vel_local: np.ndarray) -> None:
        v = self.rot[i] @ vel_local
        a = np.zeros(3)
        if self.v[i] is not None and t > self.v[i][0]:
            a = np.clip((v - self.v[i][1]) / (t - self.v[i][0]), -5.0, 5.0)
        self.predict_to(t)
        self.v[i] = (t, v, a)

    def _update(self, t: float, z: np.ndarray, h: np.ndarray, r: np.ndarray, movers: list[int],
                gate: bool) -> bool:
        if t > self.t_s:
            self.predict_to(t)
        elif t < self.t_s:  # late: move the measurement to the filter time
            late = self.t_s - t
            for i, sign in movers:
                z = z + sign * self._vel_at(i, self.t_s) * late
                r = r + np.eye(z.size) * self.vel_var_rate * late
        y = z - (h @ self.kf.x)[:, 0]
        s = h @ self.kf.P @ h.T + r
        if gate and float(y @ np.linalg.solve(s, y)) > chi2.ppf(0.999, z.size):
            self.n_gated += 1
            return False
        self.kf.update(z.reshape(-1, 1), R=r, H=h)
        return True

    def gnss(self, i: int, t: float, enu: np.ndarray, h_sigma: float, v_sigma: float) -> None:
        if not self.ready[i]:
            self._init(i, t, enu, h_sigma, v_sigma)
            return
        if self.gm:
            sh, sv, _ = self.gm
            h_sigma = math.sqrt(max(h_sigma**2 - sh**2, 0.3**2))
            v_sigma = math.sqrt(max(v_sigma**2 - sv**2, 0.5**2))
        r = self.rot[i] @ np.diag([h_sigma**2, h_sigma**2, v_sigma**2]) @ self.rot[i].T
        h = np.zeros((3, self.kf.dim_x))
        j = self.m * i
        h[:, j:j + 3] = np.eye(3)
        if self.gm:
            h[:, j + 6:j + 9] = np.eye(3)
        self._update(t, enu, h, r, [(i, -1.0)], gate=True)
        self._refresh(i)

    def _init(self, i: int, t: float, enu: np.ndarray, h_sigma: float, v_sigma: float) -> None:
        if not self.ready.any():
            self.t_s = t
        self.predict_to(t)
        blk = self._blk(i)
        x = self.kf.x.copy()
        x[blk, 0] = 0.0
        x[self.m * i:self.m * i + 3, 0] = enu
        p = self.kf.P.copy()
        p[blk, :] = 0.0
        p[:, blk] = 0.0
        diag = [h_sigma**2, h_sigma**2, v_sigma**2, 0.15**2, 0.15**2, 0.05**2]
        if self.gm:
            sh, sv, _ = self.gm
            diag += [sh**2, sh**2, sv**2]
        p[blk, blk] = np.diag(diag)
        self.kf.x, self.kf.P = x, p
        self.ready[i] = True
        self._refresh(i)

    def _refresh(self, i: int) -> None:
        ref = self.alt_ref[i]
        if ref is not None and np.linalg.norm(self.p(i) - ref[0]) < _ALT_REF_REFRESH_M:
            return
        p = self.p(i).copy()
        lat, lon, alt = (float(c) for c in self.frame.to_geodetic(*p))
        self.rot[i] = self.frame.enu_rotation_at(lat, lon)
        self.alt_ref[i] = (p, alt)

    def altitude(self, i: int, t: float, alt_m: float, sigma_m: float) -> None:
        if not self.ready[i]:
            return
        p_ref, alt_ref = self.alt_ref[i]
        up = self.rot[i][:, 2]  # d(ellipsoidal height)/dp = the local vertical
        h = np.zeros((1, self.kf.dim_x))
        h[0, self.m * i:self.m * i + 3] = up
        z = np.array([alt_m - alt_ref + up @ p_ref])
        up_v = up @ self._vel_at(i, self.t_s)
        if t < self.t_s:
            z = z + up_v * (self.t_s - t)
        self._update(max(t, self.t_s), z, h, np.array([[sigma_m**2]]), [], gate=False)

    def relative(self, i_obs: int, i_tgt: int, t: float, offset_local: np.ndarray, cov_local: np.ndarray) -> None:
        if not (self.ready[i_obs] and self.ready[i_tgt]):
            return
        rot = self.rot[i_obs]
        h = np.zeros((3, self.kf.dim_x))
        h[:, self.m * i_tgt:self.m * i_tgt + 3] = np.eye(3)
        h[:, self.m * i_obs:self.m * i_obs + 3] = -np.eye(3)
        self._update(t, rot @ offset_local, h, rot @ cov_local @ rot.T, [(i_tgt, 1.0), (i_obs, -1.0)], gate=True)


def run_joint_ekf(scen, ticks: np.ndarray, warmup_s: float, gnss_gm: bool, progress=None):
    """Feed the scenario's events by arrival; per tick (after ``warmup_s``) each drone's
    (time, position, covariance). Returns ({id: (t (N,), p (N, 3), cov (N, 3, 3))}, filter)."""
    nm, ids = scen.noise, scen.drone_ids
    gm = (nm.gnss_gm_h_sigma_m, nm.gnss_gm_v_sigma_m, nm.gnss_gm_tau_s) if gnss_gm else None
    ekf = JointEKF(scen.frame, ids, nm.velocity_sigma_mps, nm.velocity_rate_hz,
                   nm.velocity_bias_walk_mps_per_sqrt_s, gm)
    index = {d: i for i, d in enumerate(ids)}
    out = {d: ([], [], []) for d in ids}
    evs = scen.events()
    pending = next(evs, None)
    it = ticks if progress is None else progress(ticks, desc=f"joint EKF{' + GM' if gnss_gm else ''}", unit="tick")
    for tick in it:
        while pending is not None and pending.arrival_s <= tick + 1e-9:
            _event(scen.frame, ekf, index, pending)
            pending = next(evs, None)
        if tick >= warmup_s:
            for d, i in index.items():
                out[d][0].append(ekf.t_s)
                out[d][1].append(ekf.p(i).copy())
                out[d][2].append(ekf.p_cov(i).copy())
    return {d: (np.asarray(t), np.asarray(p), np.asarray(c)) for d, (t, p, c) in out.items()}, ekf


def _event(frame, ekf: JointEKF, index: dict[str, int], ev) -> None:
    i, d = index[ev.drone_id], ev.data
    if ev.kind == "velocity":
        ekf.velocity(i, ev.time_s, d["vel_enu_mps"])
    elif ev.kind == "altitude":
        ekf.altitude(i, ev.time_s, d["alt_m"], d["sigma_m"])
    elif ev.kind == "gnss":
        if d["fix_type"] >= 3:
            enu = frame.to_enu_points(np.array([[d["lat_deg"], d["lon_deg"], d["alt_m"]]]))[0]
            ekf.gnss(i, ev.time_s, enu, d["h_sigma_m"], d["v_sigma_m"])
    else:
        obs = d["obs"]
        ekf.relative(index[obs.observer_id], index[obs.target_id], obs.time_s, obs.offset_enu_m, obs.cov_enu_m2)
