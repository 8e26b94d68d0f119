"""Message-level sensor simulation for the fusion scenarios: truth along the paths and
the GNSS, velocity, altitude and relative-observation tables (see
:mod:`skyfix.datasets.fusion_scenario` for the models and frames).
"""

from __future__ import annotations

import numpy as np

from skyfix.datasets.fusion_world import (
    DRONE_IDS,
    Formation,
    MessageTable,
    NoiseModel,
    Outage,
    Spoof,
    SurveyPath,
)
from skyfix.datasets.gauss_markov import gauss_markov
from skyfix.datasets.observations import noisy_relative
from skyfix.errors import InputError
from skyfix.geo import LocalFrame


def truth_at(path: SurveyPath, formations: dict[str, Formation], drone_id: str,
           t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pos, vel = path.position_velocity(t)
    if drone_id == "A":
        return pos, vel
    if drone_id not in formations:
        raise InputError(f"drone_id must be one of {DRONE_IDS}, got {drone_id!r}")
    off, rate = formations[drone_id].offset(t)
    return pos + off, vel + rate


def rotations_to_local(frame: LocalFrame, enu_m: np.ndarray, t_s: np.ndarray,
                        step_s: float = 1.0) -> np.ndarray:
    """Rotations (N, 3, 3) taking frame-ENU vectors into the ENU axes at each position.

    ``enu_rotation_at`` is evaluated once per ``step_s`` of flight and shared by the
    samples in that step (the axes turn by ~1.3e-6 rad per 8 m flown)."""
    key = np.floor(t_s / step_s).astype(np.int64)
    uniq, first, inv = np.unique(key, return_index=True, return_inverse=True)
    lla = frame.to_geodetic_points(enu_m[first])
    rots = np.stack([frame.enu_rotation_at(la, lo).T for la, lo, _ in lla])
    return rots[inv.ravel()]


def sample_times(duration_s: float, rate_hz: float, phase_s: float) -> np.ndarray:
    """Sample times phase_s + k / rate_hz below duration_s, rounded to the microsecond."""
    n = int(np.ceil((duration_s - phase_s) * rate_hz))
    t = np.round(phase_s + np.arange(n) / rate_hz, 6)
    return t[t < duration_s]


def late_delays(rng: np.random.Generator, n: int, frac: float, lo: float, hi: float) -> np.ndarray:
    late = rng.random(n) < frac
    return np.where(late, rng.uniform(lo, hi, n), 0.0)


def random_walk(rng: np.random.Generator, n: int, dt_s: float, sigma0: np.ndarray,
                 walk_per_sqrt_s: float) -> np.ndarray:
    """(n, len(sigma0)) random walk started from N(0, sigma0^2)."""
    steps = rng.normal(0.0, walk_per_sqrt_s * np.sqrt(dt_s), (n, sigma0.size))
    steps[0] = rng.normal(0.0, 1.0, sigma0.size) * sigma0
    return np.cumsum(steps, axis=0)


def concat_tables(parts: list[MessageTable]) -> MessageTable:
    return MessageTable(np.concatenate([p.time_s for p in parts]), np.concatenate([p.arrival_s for p in parts]),
                        np.concatenate([p.drone for p in parts]),
                        {k: np.concatenate([p.cols[k] for p in parts]) for k in parts[0].cols})


def gnss_table(frame: LocalFrame, sp: SurveyPath, forms: dict[str, Formation], d: str, i: int,
          dur: float, nm: NoiseModel, phase_s: float, rngs: tuple[np.random.Generator, np.random.Generator],
          out_w: Outage | None, spoofs: tuple[Spoof, ...], latency_s: float,
          common: tuple[np.ndarray, np.ndarray] | None = None) -> MessageTable:
    rng, rng_gm = rngs  # the correlated part has its own stream: white-only runs stay as they were
    t = sample_times(dur, nm.gnss_rate_hz, phase_s)
    p, _ = truth_at(sp, forms, d, t)
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
    r_loc = rotations_to_local(frame, p, t)
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
    late = late_delays(rng, t.size, nm.late_gnss_frac, nm.late_min_s, nm.late_max_s)
    # The receiver reports its total 1-sigma accuracy (white and wandering parts together).
    cols = {"lat_deg": lla[:, 0], "lon_deg": lla[:, 1], "alt_m": lla[:, 2], "fix_type": fix,
            "satellites": sats, "hdop": hdop, "h_sigma_m": np.full(t.size, np.hypot(sig[0], gm_sig[0])),
            "v_sigma_m": np.full(t.size, np.hypot(sig[2], gm_sig[2])), "outlier": outlier}
    return MessageTable(t[keep], (t + latency_s + late)[keep], np.full(int(keep.sum()), i),
                        {k: v[keep] for k, v in cols.items()})


def relative_table(frame: LocalFrame, sp: SurveyPath, forms: dict[str, Formation], d: str, i: int,
              dur: float, nm: NoiseModel, phase_s: float, rng: np.random.Generator,
              latency_s: float) -> MessageTable:
    """Observations by helper ``d`` of A: offset A - helper in the ENU axes at ``d``."""
    t = sample_times(dur, nm.relative_rate_hz, phase_s)
    p_obs, _ = truth_at(sp, forms, d, t)
    p_tgt, _ = truth_at(sp, forms, "A", t)
    rng_true = np.linalg.norm(p_tgt - p_obs, axis=1)
    keep = (rng_true >= nm.relative_min_range_m) & (rng_true <= nm.relative_max_range_m)
    t, p_obs, p_tgt, rng_true = t[keep], p_obs[keep], p_tgt[keep], rng_true[keep]
    # The shared ranger model: noise and the covariance the ranger reports, ENU at the observer.
    b, r, cov = noisy_relative(frame, p_obs, p_tgt, rng, range_frac=nm.relative_range_frac,
                               bearing_sigma_deg=nm.relative_bearing_sigma_deg)
    r_loc = rotations_to_local(frame, p_obs, t)
    b_true = np.einsum("nij,nj->ni", r_loc, p_tgt - p_obs) / rng_true[:, None]
    late = late_delays(rng, t.size, nm.late_relative_frac, nm.late_min_s, nm.late_max_s)
    return MessageTable(t, t + latency_s + late, np.full(t.size, i),
                        {"bearing_enu": b, "range_m": r, "cov_enu_m2": cov, "target": np.zeros(t.size, int),
                         "range_true_m": rng_true, "bearing_true_enu": b_true})


# Consumer receivers as they are (issue 15): a wandering error of 1.5 m per horizontal axis
# with a one-minute correlation time plus 0.3 m white; helpers 20-140 m from A on their own
# wandering legs, observing at 2 Hz with 2 % range and 0.5 deg bearing noise; 2 % multipath outliers.


def velocity_table(frame: LocalFrame, sp: SurveyPath, forms: dict[str, Formation], d: str, i: int,
                   dur: float, nm: NoiseModel, phase_s: float, rng: np.random.Generator,
                   latency_s: float) -> tuple[MessageTable, np.ndarray]:
    """Velocity messages of drone ``d`` (index ``i``) in the ENU axes at the drone: truth +
    bias (random walk) + white noise; also the bias (N, 3) m/s."""
    tv = sample_times(dur, nm.velocity_rate_hz, phase_s)
    p, v = truth_at(sp, forms, d, tv)
    r_loc = rotations_to_local(frame, p, tv)
    bias = random_walk(rng, tv.size, 1.0 / nm.velocity_rate_hz,
                       np.array([nm.velocity_bias_h_sigma_mps] * 2 + [nm.velocity_bias_v_sigma_mps]),
                       nm.velocity_bias_walk_mps_per_sqrt_s)
    vel_meas = np.einsum("nij,nj->ni", r_loc, v) + bias + rng.normal(0, nm.velocity_sigma_mps, v.shape)
    return MessageTable(tv, tv + latency_s, np.full(tv.size, i),
                        {"vel_enu_mps": vel_meas, "sigma_mps": np.full(tv.size, nm.velocity_sigma_mps)}), bias


def altitude_table(frame: LocalFrame, sp: SurveyPath, forms: dict[str, Formation], d: str, i: int,
                   dur: float, nm: NoiseModel, phase_s: float, rng: np.random.Generator,
                   latency_s: float) -> MessageTable:
    """Barometric altitude messages (ellipsoidal): truth + optional random-walk drift + white noise."""
    ta = sample_times(dur, nm.altitude_rate_hz, phase_s)
    pa, _ = truth_at(sp, forms, d, ta)
    alt_true = frame.to_geodetic_points(pa)[:, 2]
    drift = np.zeros(ta.size)
    if nm.altitude_drift_m_per_sqrt_s > 0:
        drift = random_walk(rng, ta.size, 1.0 / nm.altitude_rate_hz, np.zeros(1),
                            nm.altitude_drift_m_per_sqrt_s)[:, 0]
    alt_meas = alt_true + drift + rng.normal(0, nm.altitude_sigma_m, ta.size)
    return MessageTable(ta, ta + latency_s, np.full(ta.size, i),
                        {"alt_m": alt_meas, "sigma_m": np.full(ta.size, nm.altitude_sigma_m)})
