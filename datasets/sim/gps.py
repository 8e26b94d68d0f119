"""GPS receiver model with fault injection (loss, degraded accuracy, jump, spoof)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from skyfix import validate
from skyfix.datasets.gauss_markov import gauss_markov_step
from skyfix.datasets.gnss_error import CommonGnssError
from skyfix.errors import InputError

FAULT_KINDS = ("loss", "degraded", "jump", "spoof")


@dataclass(frozen=True)
class GpsFault:
    """A GPS fault active for ``start_s <= t < start_s + duration_s`` (simulation time).

    ``loss``: no fix. ``degraded``: horizontal accuracy ``eph_m`` (noise of that sigma,
    5 satellites). ``jump``: the fix is displaced by ``offset_enu_m`` at once.
    ``spoof``: the fix is dragged away along ``offset_enu_m``'s direction at ``drift_mps``
    (up to ``|offset_enu_m|``) while still reporting good accuracy.
    """

    kind: str
    start_s: float
    duration_s: float = math.inf
    eph_m: float = 15.0
    offset_enu_m: tuple[float, float, float] = (50.0, 0.0, 0.0)
    drift_mps: float = 2.0

    def __post_init__(self) -> None:
        if self.kind not in FAULT_KINDS:
            raise InputError(f"GpsFault.kind must be one of {FAULT_KINDS}, got {self.kind!r}")
        validate.finite_scalar("GpsFault.start_s", self.start_s)
        if not self.duration_s > 0:  # inf: until the end of the run
            raise InputError(f"GpsFault.duration_s must be > 0, got {self.duration_s}")
        validate.positive_scalar("GpsFault.eph_m", self.eph_m)
        off = validate.finite_array("GpsFault.offset_enu_m", self.offset_enu_m)
        if off.shape != (3,):
            raise InputError(f"GpsFault.offset_enu_m must have shape (3,), got {off.shape}")

    def active(self, t_s: float) -> bool:
        return self.start_s <= t_s < self.start_s + self.duration_s


@dataclass(frozen=True)
class GpsReading:
    """One receiver output: position in world ENU metres, 1-sigma accuracies in metres,
    dilutions of precision (unitless), fix type (GPS_FIX_TYPE)."""

    pos_enu_m: np.ndarray
    vel_enu_mps: np.ndarray
    fix_type: int
    satellites: int
    eph_m: float
    epv_m: float
    hdop: float = math.nan
    vdop: float = math.nan


class GpsReceiver:
    """A u-blox-like receiver: a slowly varying bias per axis (first-order Gauss-Markov,
    stationary sigma ``bias_sigma_m``, correlation time ``bias_tau_s``) plus white noise
    of ``noise_sigma_m``, all in metres, ENU; plus, when ``common`` is set, the error every
    receiver of the area shares (:class:`skyfix.datasets.gnss_error.CommonGnssError`, sampled at
    the fix's time). The attributes may be changed between steps (a scenario with larger
    correlated errors); the bias keeps its current value."""

    def __init__(self, seed: int = 0, *, bias_sigma_m: float = 0.4, bias_tau_s: float = 60.0,
                 noise_sigma_m: float = 0.15, common: CommonGnssError | None = None) -> None:
        self.faults: list[GpsFault] = []
        self.disabled = False
        self.glitch_enu_m = np.zeros(3)
        self.bias_sigma_m = validate.nonnegative_scalar("bias_sigma_m", bias_sigma_m)
        self.bias_tau_s = validate.positive_scalar("bias_tau_s", bias_tau_s)
        self.noise_sigma_m = validate.nonnegative_scalar("noise_sigma_m", noise_sigma_m)
        self.common = common
        self._rng = np.random.default_rng(seed)
        self._bias = np.zeros(3)

    def step(self, dt_s: float) -> None:
        self._bias = gauss_markov_step(self._rng, self._bias, dt_s, self.bias_sigma_m, self.bias_tau_s)

    def read(self, t_s: float, true_pos_enu_m: np.ndarray, true_vel_enu_mps: np.ndarray) -> GpsReading:
        """The fix at simulation time ``t_s`` for the vehicle's true state."""
        pos = true_pos_enu_m + self._bias + self.noise_sigma_m * self._rng.standard_normal(3) + self.glitch_enu_m
        if self.common is not None:
            pos = pos + self.common.at(t_s)
        # a healthy receiver: HDOP 1.2 / VDOP 1.9 with 14 satellites (as SITL's u-blox reports),
        # accuracies in metres that are not the DOPs (a client mixing them up is visibly wrong)
        eph, epv, sats, fix, hdop, vdop = 0.8, 1.2, 14, 3, 1.2, 1.9
        for fault in self.faults:
            if not fault.active(t_s):
                continue
            if fault.kind == "loss":
                return GpsReading(pos * np.nan, true_vel_enu_mps * np.nan, 1, 0, math.inf, math.inf)
            if fault.kind == "degraded":
                eph, epv, sats, hdop, vdop = fault.eph_m, 1.5 * fault.eph_m, 5, 4.5, 7.0
                pos = pos + fault.eph_m * self._rng.standard_normal(3) * np.array([1, 1, 1.5])
            elif fault.kind == "jump":
                pos = pos + np.asarray(fault.offset_enu_m)
            elif fault.kind == "spoof":
                off = np.asarray(fault.offset_enu_m, dtype=float)
                norm = float(np.linalg.norm(off))
                if norm > 0:
                    pos = pos + off / norm * min(norm, fault.drift_mps * (t_s - fault.start_s))
        if self.disabled:
            return GpsReading(pos * np.nan, true_vel_enu_mps * np.nan, 1, 0, math.inf, math.inf)
        vel = true_vel_enu_mps + 0.05 * self._rng.standard_normal(3)
        return GpsReading(pos, vel, fix, sats, eph, epv, hdop, vdop)
