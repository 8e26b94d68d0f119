"""Measurement-level drone-to-drone observations: what a helper's camera ranger would report.

For simulations that do not render images: the true offset (target minus observer) is
expressed in the ENU axes at the observer, the range gets a relative Gaussian error and
the bearing two perpendicular angular errors, and the covariance is the one
:func:`skyfix.crps.observe` reports for such a measurement (``sigma_r^2 b b^T + r^2
sigma_theta^2 (I - b b^T)``, from the *measured* range and bearing, as a ranger would).
"""

from __future__ import annotations

import numpy as np

from skyfix import validate
from skyfix.geo import LocalFrame
from skyfix.types import RelativeObservation


def noisy_relative(frame: LocalFrame, observer_enu_m, target_enu_m, rng: np.random.Generator, *,
                   range_frac: float = 0.03, bearing_sigma_deg: float = 0.2
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Noisy (bearing (N, 3) unit, range (N,) m, covariance (N, 3, 3) m^2) of targets seen by observers.

    ``observer_enu_m``/``target_enu_m`` are (N, 3) or (3,) positions in ``frame``; bearings
    and covariances are in the ENU axes at each observer.
    """
    p_obs = validate.points("observer_enu_m", observer_enu_m, 3)
    p_tgt = validate.points("target_enu_m", target_enu_m, 3)
    frac = validate.positive_scalar("range_frac", range_frac)
    sig_th = np.radians(validate.positive_scalar("bearing_sigma_deg", bearing_sigma_deg))
    lla = frame.to_geodetic_points(p_obs)
    r_local = np.stack([frame.enu_rotation_at(lat, lon).T for lat, lon in lla[:, :2]])
    off = np.einsum("nij,nj->ni", r_local, p_tgt - p_obs)
    rng_true = np.linalg.norm(off, axis=1)
    b_true = off / rng_true[:, None]
    up = np.where(np.abs(b_true[:, 2:3]) > 0.99, [[1.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]])
    e1 = np.cross(b_true, up)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(e1, b_true)
    a = rng.normal(0.0, sig_th, (len(p_obs), 2))
    b = b_true + a[:, :1] * e1 + a[:, 1:] * e2
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    r = rng_true * (1.0 + frac * rng.normal(0.0, 1.0, len(p_obs)))
    bbt = b[:, :, None] * b[:, None, :]
    cov = (frac * r)[:, None, None] ** 2 * bbt + (r * sig_th)[:, None, None] ** 2 * (np.eye(3) - bbt)
    return b, r, 0.5 * (cov + np.transpose(cov, (0, 2, 1)))


def relative_observation(frame: LocalFrame, observer_id: str, target_id: str, time_s: float,
                         observer_enu_m, target_enu_m, rng: np.random.Generator, **noise) -> RelativeObservation:
    """One noisy :class:`RelativeObservation` of ``target_id`` by ``observer_id`` at ``time_s``."""
    b, r, cov = noisy_relative(frame, observer_enu_m, target_enu_m, rng, **noise)
    return RelativeObservation(observer_id, target_id, time_s, b[0], float(r[0]), cov[0])
