"""GNSS in the fusion engine: receiver quality to noise, gating, drift test, re-admission.

A fix's reported accuracy (or HDOP x ``gnss_uere_m``) is split into the receiver's
wandering error, a Gauss-Markov state of the chain, and a white rest. Each fix is gated
against the fused prediction of what the receiver should report; it also feeds the
windowed drift test against the drone's own velocity (:mod:`skyfix.fusion.drift`). A
drift rejects GNSS; it is re-admitted when it agrees with the velocity again, and the
drone's chain is re-anchored on it (the spoof corrupted the estimate, not the honest
receiver). Positions: metres in the engine's frame axes; times: seconds.
"""

from __future__ import annotations

import logging

import numpy as np

from skyfix.fusion.chains import EYE3, StateChains, nis
from skyfix.fusion.config import FusionConfig
from skyfix.fusion.drift import GnssDriftTest
from skyfix.fusion.drone import DroneState
from skyfix.fusion.health import SourceMonitor

log = logging.getLogger("skyfix.fusion.engine")  # one logger name for the engine's decisions


def gnss_quality(config: FusionConfig, fix_type: int, satellites: int | None, hdop: float | None,
                 h_sigma_m: float | None, v_sigma_m: float | None, rate_issue: str | None
                 ) -> tuple[float, float, str | None]:
    """1-sigma horizontal and vertical accuracy (m) a fix is fused with, and its quality issues.

    Reported sigmas win over ``hdop x gnss_uere_m``; a 2-D fix's height carries no
    information; a degraded fix (2-D, few satellites, high HDOP, slow rate) is inflated by
    ``degraded_sigma_factor``.

    Example:
        >>> gnss_quality(FusionConfig(), 3, 12, 0.8, None, None, None)
        (1.2000000000000002, 2.04, None)
        >>> gnss_quality(FusionConfig(), 3, 4, None, 1.0, 2.0, None)
        (2.0, 4.0, '4 satellites')
    """
    cfg = config
    issues = []
    if fix_type == 2:
        issues.append("2-D fix")
    if satellites is not None and satellites < cfg.gnss_min_satellites:
        issues.append(f"{satellites} satellites")
    if hdop is not None and hdop > cfg.gnss_max_hdop:
        issues.append(f"HDOP {hdop:g}")
    if rate_issue:
        issues.append(rate_issue)
    h_sigma = h_sigma_m if h_sigma_m is not None else cfg.gnss_uere_m * (hdop if hdop is not None else 1.0)
    v_sigma = v_sigma_m if v_sigma_m is not None else h_sigma * cfg.gnss_vertical_factor
    if fix_type == 2:
        v_sigma = max(v_sigma, 1e3)  # a 2-D fix's altitude carries no information
    if issues:
        h_sigma *= cfg.degraded_sigma_factor
        v_sigma *= cfg.degraded_sigma_factor
    return h_sigma, v_sigma, ", ".join(issues) or None


class GnssFusion:
    """Gates, drift-tests and fuses every drone's GNSS fixes into ``chains``."""

    def __init__(self, config: FusionConfig, chains: StateChains) -> None:
        self.config, self.chains = config, chains
        self._gate = config.gate_chi2(3)
        self._drift_gate = config.gate_chi2(2, config.drift_gate_probability)
        self._readmit_gate = config.gate_chi2(2, 0.95)  # after a drift: agreement with the velocity, both tests

    def white_cov(self, drone: DroneState, h_sigma_m: float, v_sigma_m: float) -> np.ndarray:
        """Covariance (m2, frame axes) of a fix's white error: its accuracy less the wandering part."""
        floor2 = self.config.gnss_white_min_sigma_m**2
        white2 = np.maximum(np.array([h_sigma_m, h_sigma_m, v_sigma_m]) ** 2 - self.chains.gm_sigma_m**2, floor2)
        r = drone.r_frame_from_local
        return r @ np.diag(white2) @ r.T

    def drift_test(self, drone: DroneState) -> GnssDriftTest:
        """The drone's drift test (made on first use)."""
        if drone.drift is None:
            cfg = self.config
            drone.drift = GnssDriftTest(cfg.drift_window_s, cfg.gnss_gm_h_sigma_m, cfg.gnss_gm_tau_s,
                                        cfg.bias_walk_mps_per_sqrt_s, cfg.velocity_timeout_s)
        return drone.drift

    def age_cov(self, drone: DroneState, t_s: float) -> np.ndarray:
        """Covariance (m2, frame axes) of where a fix stamped ``t_s`` really was: taken up to
        ``gnss_fix_age_max_s`` before its stamp, uniformly, while the drone moved at its velocity v,
        so E[(v age)(v age)'] = v v' T^2 / 3 (its mean part too: a fix's age is not known)."""
        vel = self.chains.velocity_now(drone, t_s) if self.config.gnss_fix_age_max_s > 0 else None
        if vel is None:
            return np.zeros((3, 3))
        v = vel[0]
        return np.outer(v, v) * self.config.gnss_fix_age_max_s**2 / 3.0

    def fuse(self, drone: DroneState, monitor: SourceMonitor, t_s: float, enu_m: np.ndarray, cov_white_m2: np.ndarray,
              quality: str | None) -> None:
        """Gate, drift-test and fuse a GNSS fix (``cov_white_m2``: its white part, frame axes).

        In a stream stamped at send time (``gnss_fix_age_max_s`` > 0: GPS_RAW_INT goes out at the telemetry
        rate, not the receiver's) a fix identical to the previous one is the same solution sent again under a
        newer stamp: it is not fused twice.
        """
        if monitor.resent(t_s, tuple(enu_m.tolist())) and self.config.gnss_fix_age_max_s > 0:
            return
        k = self.chains.step_checked(t_s, "GNSS fix")
        cov_white_m2 = cov_white_m2 + self.age_cov(drone, t_s)
        drift = self.drift_test(drone)
        residual = drift.residual(t_s, enu_m)
        white_var = float(np.trace(cov_white_m2[:2, :2])) / 2.0
        predicted = self.chains.predict(drone, t_s, gnss=True)
        consistent = predicted is None or nis(enu_m - predicted[0], predicted[1] + cov_white_m2) <= self._gate
        after_drift = drone.drift_rejected and drift.reference is not None
        if after_drift:
            # the estimate is suspect: judge GNSS against the velocity since before the drift
            drift.record(t_s, residual, white_var)
            consistent = drift.agrees_with_reference(t_s, residual, white_var, self._readmit_gate)
        elif monitor.on_probation:
            drift.forget()  # a track GNSS had while out of use must not count in the drift test
        if not monitor.judge(t_s, consistent, quality):
            return
        if after_drift or drone.drift_rejected:
            drone.drift_rejected = False
            drift.forget()
            if after_drift:
                log.warning("GNSS re-admitted after a drift: re-anchoring the drone on it")
                self.chains.reanchor(drone, k, drift.reference_bias(t_s))
        else:
            drift.record(t_s, residual, white_var)
            if self._drifting(drone, monitor, t_s):
                return
        if not drone.anchored:
            self.chains.anchor(drone, k, enu_m)
        self.chains.ensure(drone, k)
        shift, shift_var = self.chains.shift(drone, t_s, k)
        self.chains.window.gnss(drone.index, k, enu_m + shift, cov_white_m2 + EYE3 * shift_var)

    def _drifting(self, drone: DroneState, monitor: SourceMonitor, t_s: float) -> bool:
        """Windowed drift test of the drone's GNSS against its velocity; rejects GNSS on failure."""
        cached = self.chains.latest_cov(drone) if drone.anchored else None
        if cached is None:
            return False
        k, cov = cached
        drone.drift.bias(t_s, self.chains.window.value(drone.index, 1, k), cov[3:6, 3:6])
        window_nis = drone.drift.window_nis(t_s)
        failed = window_nis is not None and window_nis > self._drift_gate
        drone.drift_strikes = drone.drift_strikes + 1 if failed else 0
        if drone.drift_strikes < 2:  # two fixes in a row: one odd window is not a drift
            return False
        drone.drift.hold_reference(t_s)
        drone.drift_rejected = True
        monitor.reject(t_s, f"drifting against the velocity over {self.config.drift_window_s:g} s (NIS {window_nis:.0f})")
        return True
