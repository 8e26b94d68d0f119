"""Tunable numbers of the fusion engine, with the physics behind each default."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from skyfix.errors import InputError


@dataclass(frozen=True)
class FusionConfig:
    """Model and health parameters of :class:`skyfix.fusion.FusionEngine`.

    State model (per drone, on a grid of ``state_dt_s``): position p_k (ENU, m) and the
    bias b_k of the autopilot's velocity (m/s). Velocity samples are integrated exactly
    over each interval (:mod:`skyfix.fusion.velocity`), giving ``p_k+1 - p_k = (v_mean -
    b_k) dt`` with sigma ``sqrt(sigma_v^2 + velocity_model_sigma_mps^2) dt``. The bias
    walks with ``bias_walk_mps_per_sqrt_s``. Every step also carries a weak ``p_k+1 - p_k
    ~ N(0, (max_speed_mps dt)^2)`` so a drone whose velocity stops arriving stays
    constrained, with honestly growing sigma.

    GNSS: each receiver's error is a state n_k, a first-order Gauss-Markov process per axis
    (``gnss_gm_*``), so consecutive fixes are not independent evidence; the receiver's
    reported accuracy beyond that wandering part is white (at least ``gnss_white_min_sigma_m``).
    Defaults describe a consumer receiver (1.5 m horizontal per axis, 2.5 m vertical, about a
    minute of correlation); for a receiver whose errors are white set the GM sigmas small.
    Receivers near each other share most of that error (``gnss_common_share``, off by default):
    each receiver's state is then a shared chain plus its own part, so neighbours' fixes that
    position a drone do not average their common error away.

    Trust: relative observations are accepted only from observers on ``roster`` (drone ids);
    an empty roster admits a drone that has reported its own GNSS, velocity, altitude or
    fix. At most ``max_drones`` drones are ever created.
    """

    # Grid of the states. Measurements are moved to the nearest step with the drone's velocity (its
    # variance added), so the grid need not match any sensor's rate; 0.1 s cost twice the solve per
    # update for no measurable accuracy (correlated benchmark: outage RMSE 1.13 m at 0.1 s, see README).
    state_dt_s: float = 0.2
    max_speed_mps: float = 30.0
    velocity_model_sigma_mps: float = 0.02  # interpolation between samples (jerk), added to the white sigma
    bias_initial_sigma_mps: float = 0.3
    bias_walk_mps_per_sqrt_s: float = 0.01
    # A velocity gap longer than velocity_timeout_s (a telemetry link down for seconds) is bridged by the line
    # between the samples on either side, as uncertain as a drone changing its velocity at this acceleration
    # (1-sigma, m/s^2: ArduPilot's default WPNAV_ACCEL) allows; gaps longer than velocity_gap_max_s are not bridged.
    velocity_gap_accel_mps2: float = 2.5
    velocity_gap_max_s: float = 10.0
    # Optional scale-factor and heading-error states of the velocity (the main errors of an
    # autopilot's dead reckoning without GNSS: optical flow scaled by a wrong height, a compass
    # or gyro heading error). Observable in turns; off by default (a Python factor per interval).
    velocity_scale_heading: bool = False
    velocity_scale_sigma: float = 0.05          # initial 1-sigma of the scale error (5 %)
    velocity_heading_sigma_deg: float = 5.0     # initial 1-sigma of the heading error
    velocity_scale_walk_per_sqrt_s: float = 1e-4
    velocity_heading_walk_deg_per_sqrt_s: float = 0.01
    # GNSS
    gnss_uere_m: float = 1.5            # sigma per unit HDOP when the receiver gives no h_acc
    gnss_vertical_factor: float = 1.7   # v_sigma / h_sigma when the receiver gives no v_acc
    gnss_timeout_s: float = 0.7         # silent longer than this -> lost (goal: detected within 1 s)
    gnss_min_satellites: int = 6        # fewer -> degraded
    gnss_max_hdop: float = 2.5          # above -> degraded
    degraded_sigma_factor: float = 2.0  # degraded GNSS is fused with sigma x this
    gnss_gm_h_sigma_m: float = 1.5      # wandering error per horizontal axis (multipath, atmosphere, orbits)
    gnss_gm_v_sigma_m: float = 2.5      # wandering error, vertical
    gnss_gm_tau_s: float = 60.0         # its correlation time
    # Share of that wandering variance every receiver of the engine has in common (orbits, clocks, ionosphere,
    # troposphere: one sky over receivers tens of metres apart; AGI's GPS error budget puts ~90 % of a standalone
    # receiver's range-error variance there, multipath and receiver noise the rest). 0: each receiver's error its
    # own. Above 0 a receiver's error state is n = c + o: c one Gauss-Markov chain all of this engine's drones share
    # (sigma sqrt(share) x gnss_gm_*_sigma_m, gnss_common_tau_s), o its own (the rest of the variance,
    # gnss_gm_tau_s). A drone placed by its neighbours' fixes then keeps their shared error in its covariance
    # instead of averaging it away as if each neighbour's receiver erred on its own.
    gnss_common_share: float = 0.0
    gnss_common_tau_s: float = 1800.0   # the shared part changes with the atmosphere: tens of minutes
    gnss_white_min_sigma_m: float = 0.3  # white part at least this (receiver noise)
    # How much older than its stamp a fix may be (s). 0: stamped with its own time. MAVLink GPS_RAW_INT's
    # time_usec is the send time (ArduPilot: the fix's time plus the time since it): up to one receiver period,
    # 0.2 s at ArduPilot's default GPS_RATE_MS of 200; skyfix serve sets that for its autopilot's telemetry.
    gnss_fix_age_max_s: float = 0.0
    # drift: GNSS displacement over a window against the GNSS-independent velocity
    drift_window_s: float = 10.0
    drift_gate_probability: float = 0.99999  # per test, two fixes in a row (5 Hz, overlapping windows)
    # innovation gating (every absolute / relative source)
    gate_probability: float = 0.999
    reject_after: int = 2               # consecutive gate failures -> rejected
    readmit_after_s: float = 5.0        # a lost/rejected source is judged over this long before it is fused again
    readmit_fraction: float = 0.8       # ... and fused again when this fraction of its messages passed
    robust_k: float = 2.8               # Huber threshold on the whitened 3-D residual norm (95 % of inliers below)
    # Relative observations: a camera observer's pointing error is mostly its heading reference's, the same in every
    # frame of a flight, so averaging its frames does not average it away. Above 0: each observer carries a
    # Gauss-Markov pointing error (yaw, pitch; this 1-sigma, deg, and relative_pointing_tau_s) that all its
    # observations share (skyfix.fusion.pointing), and only the rest of an observation's stated covariance across
    # the line of sight, at least relative_white_min_deg, counts as its own. 0: every observation's error its own.
    relative_pointing_sigma_deg: float = 0.0
    relative_pointing_tau_s: float = 600.0
    relative_white_min_deg: float = 0.5  # centroid noise, gimbal jitter and the linearisation about the ray
    # other sources
    velocity_timeout_s: float = 1.0
    altitude_timeout_s: float = 1.0
    fix_timeout_s: float = 5.0
    relative_timeout_s: float = 2.0
    contributing_window_s: float = 2.0  # a source "contributes" if fused this recently
    # smoother
    max_iterations: int = 1             # LM iterations per update; the problem is linear but for robust weights
    log_fsync_s: float = 1.0            # measurement log: fsync at most this often
    # trust
    max_drones: int = 16                # bound on drone ids (observations cannot create more)
    roster: tuple[str, ...] = ()        # drone ids allowed to observe others; () = drones that report their own sensors

    def __post_init__(self) -> None:
        roster = self.roster
        if isinstance(roster, str) or not all(isinstance(d, str) and d.strip() for d in roster):
            raise InputError(f"FusionConfig.roster must be a sequence of non-empty drone id strings, got {roster!r}")
        object.__setattr__(self, "roster", tuple(roster))
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.type in (bool, "bool"):
                if not isinstance(value, bool):
                    raise InputError(f"FusionConfig.{f.name} must be True or False, got {value!r}")
                continue
            if f.name == "roster":
                continue
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not value == value:
                raise InputError(f"FusionConfig.{f.name} must be a number, got {value!r}")
            if value <= 0 and f.name not in ("log_fsync_s", "gnss_fix_age_max_s", "gnss_common_share",
                                             "relative_pointing_sigma_deg"):
                raise InputError(f"FusionConfig.{f.name} must be > 0, got {value!r}")
        for name in ("gate_probability", "drift_gate_probability"):
            if not getattr(self, name) < 1.0:
                raise InputError(f"FusionConfig.{name} must be in (0, 1), got {getattr(self, name)}")
        if self.relative_pointing_sigma_deg < 0:
            raise InputError(f"FusionConfig.relative_pointing_sigma_deg must be >= 0, got {self.relative_pointing_sigma_deg}")
        if self.gnss_fix_age_max_s < 0:
            raise InputError(f"FusionConfig.gnss_fix_age_max_s must be >= 0, got {self.gnss_fix_age_max_s}")
        if not 0.0 <= self.gnss_common_share < 1.0:
            raise InputError(f"FusionConfig.gnss_common_share must be in [0, 1), got {self.gnss_common_share}")
        if not self.readmit_fraction <= 1.0:
            raise InputError(f"FusionConfig.readmit_fraction must be in (0, 1], got {self.readmit_fraction}")
        if len(self.roster) > self.max_drones:
            raise InputError(f"FusionConfig.roster has {len(self.roster)} ids, more than max_drones {self.max_drones}")

    def gate_chi2(self, dof: int, probability: float | None = None) -> float:
        """Innovation gate: the chi-square quantile of ``probability`` (default ``gate_probability``) for ``dof``.

        ``2 gammaincinv(dof / 2, p)`` is what ``scipy.stats.chi2.ppf`` computes (bit for bit);
        scipy.special loads in about half the time of scipy.stats, which every engine paid at start.

        Example:
            >>> round(FusionConfig().gate_chi2(3), 2), round(FusionConfig().gate_chi2(1, 0.95), 3)
            (16.27, 3.841)
        """
        from scipy.special import gammaincinv

        return float(2.0 * gammaincinv(0.5 * dof, self.gate_probability if probability is None else probability))

    def to_dict(self) -> dict:
        out = dataclasses.asdict(self)
        out["roster"] = list(self.roster)
        return out

    @classmethod
    def from_dict(cls, data: dict) -> FusionConfig:
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise InputError(f"FusionConfig: unknown fields {sorted(unknown)}")
        return cls(**data)
