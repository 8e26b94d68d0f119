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
    """

    state_dt_s: float = 0.1
    max_speed_mps: float = 30.0
    velocity_model_sigma_mps: float = 0.02  # interpolation between samples (jerk), added to the white sigma
    bias_initial_sigma_mps: float = 0.3
    bias_walk_mps_per_sqrt_s: float = 0.01
    # GNSS
    gnss_uere_m: float = 1.5            # sigma per unit HDOP when the receiver gives no h_acc
    gnss_vertical_factor: float = 1.7   # v_sigma / h_sigma when the receiver gives no v_acc
    gnss_timeout_s: float = 0.7         # silent longer than this -> lost (goal: detected within 1 s)
    gnss_min_satellites: int = 6        # fewer -> degraded
    gnss_max_hdop: float = 2.5          # above -> degraded
    degraded_sigma_factor: float = 2.0  # degraded GNSS is fused with sigma x this
    # innovation gating (every absolute / relative source)
    gate_probability: float = 0.999
    reject_after: int = 2               # consecutive gate failures -> rejected
    readmit_after_s: float = 5.0        # consistent this long before a lost/rejected source is fused again
    robust_k: float = 2.8               # Huber threshold on the whitened 3-D residual norm (95 % of inliers below)
    # other sources
    velocity_timeout_s: float = 1.0
    altitude_timeout_s: float = 1.0
    fix_timeout_s: float = 5.0
    relative_timeout_s: float = 2.0
    contributing_window_s: float = 2.0  # a source "contributes" if fused this recently
    # smoother
    max_iterations: int = 1             # LM iterations per update; the problem is linear but for robust weights
    log_fsync_s: float = 1.0            # measurement log: fsync at most this often

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not value == value:
                raise InputError(f"FusionConfig.{f.name} must be a number, got {value!r}")
            if value <= 0 and f.name not in ("log_fsync_s",):
                raise InputError(f"FusionConfig.{f.name} must be > 0, got {value!r}")
        if not self.gate_probability < 1.0:
            raise InputError(f"FusionConfig.gate_probability must be in (0, 1), got {self.gate_probability}")

    def gate_chi2(self, dof: int) -> float:
        """Innovation gate: the chi-square quantile of ``gate_probability`` for ``dof``."""
        from scipy.stats import chi2

        return float(chi2.ppf(self.gate_probability, dof))

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> FusionConfig:
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise InputError(f"FusionConfig: unknown fields {sorted(unknown)}")
        return cls(**data)
