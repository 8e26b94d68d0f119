"""GPS time lag: the position tag written with a photo is where the drone was ``lag_s``
earlier, so tags trail the cameras along the flight line, in opposite directions on
alternate lines. The camera's own model positions reveal it: the lag is the one that,
once each tag is moved forward by ``velocity * lag``, lets one similarity transform fit
all cameras best. On straight lines flown at constant speed a lever arm along the body
axis is the same offset (``lever_arm = speed * lag``) and is absorbed by the same term;
a single straight line cannot separate it from a translation and is left alone.

Velocities come from the tags themselves (consecutive photos by EXIF time, at most
``max_gap_s`` apart), never from the model.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from skyfix.geo import LocalFrame
from skyfix.mapping.photos import Photo

__all__ = ["LagFit", "estimate_lag", "gps_velocities"]

log = logging.getLogger(__name__)


def gps_velocities(photos: list[Photo], frame: LocalFrame, max_gap_s: float = 20.0) -> dict[str, np.ndarray]:
    """ENU velocity (m/s) at each GPS-tagged photo with a time stamp, from its neighbours in time:
    the mean of both sides on a straight stretch, the nearer side where the path turns."""
    tagged = sorted((p for p in photos if p.has_gps and p.time_s is not None), key=lambda p: p.time_s)
    if len(tagged) < 3:
        return {}
    t = np.array([p.time_s for p in tagged])
    enu = frame.to_enu_points(np.array([(p.gps_lat_deg, p.gps_lon_deg, p.gps_alt_amsl_m) for p in tagged]))
    out = {}
    for i, p in enumerate(tagged):
        sides = []
        for j in (i - 1, i + 1):
            if 0 <= j < len(t) and 0 < abs(t[j] - t[i]) <= max_gap_s:
                sides.append(((enu[j] - enu[i]) / (t[j] - t[i]), abs(t[j] - t[i])))
        if len(sides) == 2:
            (va, da), (vb, db) = sides
            cos = va @ vb / max(np.linalg.norm(va) * np.linalg.norm(vb), 1e-9)
            # At the end of a line the other neighbour lies across the turn: keep the nearer one.
            out[p.name] = 0.5 * (va + vb) if cos > 0.8 else (va if da <= db else vb)
        elif sides:
            out[p.name] = sides[0][0]
    return out


@dataclass(frozen=True)
class LagFit:
    """``lag_s`` (positive: tags are stale), RMS camera-to-tag residual (m) without and with it."""

    lag_s: float
    rms_without_m: float
    rms_with_m: float
    accepted: bool


def _rms_after_fit(src: np.ndarray, tgt: np.ndarray) -> float:
    import pycolmap

    sim = pycolmap.estimate_sim3d(src, tgt)
    if sim is None:
        return float("inf")
    m = np.asarray(sim.matrix())
    return float(np.sqrt((((src @ m[:, :3].T + m[:, 3]) - tgt) ** 2).sum(axis=1).mean()))


def estimate_lag(model_centres: np.ndarray, gps_enu: np.ndarray, velocities_enu: np.ndarray,
                 max_lag_s: float = 3.0, step_s: float = 0.05, min_f: float = 10.0) -> LagFit:
    """The lag minimising the similarity-fit RMS of ``model_centres`` to the moved tags;
    accepted when it lies inside the search range and explains more of the misfit than
    noise would: F = (SS_without - SS_with) / (SS_with / dof) > ``min_f`` with dof =
    3 N - 8 (a similarity and the lag); F > 10 is a chance below 0.3 % for dof >= 20."""
    without = _rms_after_fit(model_centres, gps_enu)
    lags = np.arange(-max_lag_s, max_lag_s + step_s / 2, step_s)
    rms = np.array([_rms_after_fit(model_centres, gps_enu + lag * velocities_enu) for lag in lags])
    best = int(np.argmin(rms))
    n = len(model_centres)
    dof = 3 * n - 8
    f_stat = (without ** 2 - rms[best] ** 2) * n / max(rms[best] ** 2 * n / max(dof, 1), 1e-12)
    accepted = bool(dof > 0 and f_stat > min_f and 0 < best < len(lags) - 1)
    fit = LagFit(float(lags[best]), without, float(rms[best]), accepted)
    log.info("GPS time lag %.2f s: RMS %.2f m -> %.2f m (%s)", fit.lag_s, without, fit.rms_with_m,
             "applied" if accepted else "not applied")
    return fit
