"""First-order Gauss-Markov processes, exactly discretised: the simulator's correlated errors.

x(t + dt) = phi x(t) + sigma sqrt(1 - phi^2) w,  phi = exp(-dt / tau),  w ~ N(0, 1) per axis,

is the exact sampling of dx = -x/tau dt + sigma sqrt(2/tau) dW for any spacing dt: the
stationary standard deviation is ``sigma`` and the autocorrelation at lag L is exp(-L/tau).
GNSS multipath and atmosphere, AHRS heading drift and wind gusts all follow it here.
:func:`gauss_markov` samples a whole series at once (vectorised), :func:`gauss_markov_step`
advances a running state (a simulator's tick); both use :func:`transition`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from skyfix import validate
from skyfix.errors import InputError

# Within one block the series is exp(-a_k) * cumsum(exp(a_j) e_j) with a = elapsed / tau;
# exp(300) ~ 2e130 keeps every term far inside float64 (max ~1.8e308).
_BLOCK_TAU = 300.0


def transition(dt_s: Any, tau_s: float) -> tuple[np.ndarray, np.ndarray]:
    """``(phi, gain)`` for steps ``dt_s`` (s, >= 0): x' = phi x + gain sigma w.

    Example:
        >>> phi, gain = transition(60.0, 60.0)
        >>> round(float(phi), 4), round(float(phi**2 + gain**2), 12)
        (0.3679, 1.0)
    """
    ratio = np.asarray(dt_s, dtype=float) / tau_s
    # sqrt(-expm1(-2 r)) = sqrt(1 - phi^2) without cancellation for steps much shorter than tau
    return np.exp(-ratio), np.sqrt(-np.expm1(-2.0 * ratio))


def _sigma(sigma: Any) -> np.ndarray:
    sig = np.atleast_1d(validate.finite_array("sigma", sigma))
    if sig.ndim != 1 or (sig < 0).any():
        raise InputError(f"gauss_markov: sigma must be a scalar or (D,) of values >= 0, got {sig}")
    return sig


def gauss_markov(rng: np.random.Generator, time_s: Any, sigma: Any, tau_s: float) -> np.ndarray:
    """Stationary samples ``(M, D)`` at non-decreasing ``time_s`` ``(M,)`` (s).

    ``sigma`` ``(D,)`` or scalar: stationary standard deviation per axis (any unit);
    ``tau_s``: correlation time. The first sample is drawn from the stationary N(0, sigma^2).

    Example:
        >>> x = gauss_markov(np.random.default_rng(0), np.arange(0.0, 5.0), [1.5, 2.5], 60.0)
        >>> x.shape
        (5, 2)
    """
    t = validate.finite_array("time_s", time_s).reshape(-1)
    sig = _sigma(sigma)
    tau = validate.positive_scalar("tau_s", tau_s)
    dt = np.diff(t)
    if (dt < 0).any():
        raise InputError("gauss_markov: time_s must be non-decreasing")
    w = rng.standard_normal((t.size, sig.size))
    out = np.empty_like(w)
    if t.size == 0:
        return out
    # innovations e_k: the stationary start, then each step's new part
    e = w * sig
    e[1:] *= transition(dt, tau)[1][:, None]
    start, carry = 0, np.zeros(sig.size)
    while start < t.size:  # x_k = exp(-a_k) (carry + sum_j exp(a_j) e_j), a = (t - t_start) / tau
        stop = int(np.searchsorted(t, t[start] + _BLOCK_TAU * tau, side="right"))
        a = ((t[start:stop] - t[start]) / tau)[:, None]
        out[start:stop] = np.exp(-a) * (carry + np.cumsum(np.exp(a) * e[start:stop], axis=0))
        if stop < t.size:  # the last state of this block, decayed to the next block's start
            carry = out[stop - 1] * np.exp(-(t[stop] - t[stop - 1]) / tau)
        start = stop
    return out


def gauss_markov_step(rng: np.random.Generator, x: np.ndarray, dt_s: float, sigma: Any,
                      tau_s: float) -> np.ndarray:
    """The state ``x`` (D,) advanced by ``dt_s`` seconds (a new array).

    Example:
        >>> gauss_markov_step(np.random.default_rng(0), np.zeros(3), 0.1, 0.4, 60.0).shape
        (3,)
    """
    phi, gain = transition(dt_s, tau_s)
    return phi * x + gain * np.asarray(sigma, dtype=float) * rng.standard_normal(np.shape(x))
