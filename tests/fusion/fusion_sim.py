"""A small deterministic measurement simulator for the fusion tests (straight lines, exact truth)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from skyfix.datasets.observations import relative_observation
from skyfix.fusion import FusionConfig
from skyfix.geo import LocalFrame
from skyfix.types import RelativeObservation

ORIGIN = (47.0, 8.0, 400.0)
FRAME = LocalFrame(*ORIGIN)
GNSS_H_M, GNSS_V_M = 1.5, 2.5
VEL_SIGMA = 0.1
# This simulator's GNSS errors are white: tell the engine (its default is a consumer receiver's
# wandering error, which would make it distrust these fixes' independence).
WHITE_GNSS = FusionConfig(gnss_gm_h_sigma_m=0.05, gnss_gm_v_sigma_m=0.05)


@dataclass
class Line:
    """Straight constant-velocity flight in the local ENU frame."""

    start_enu_m: tuple[float, float, float]
    vel_enu_mps: tuple[float, float, float]

    def at(self, t_s: float) -> np.ndarray:
        return np.asarray(self.start_enu_m) + np.asarray(self.vel_enu_mps) * t_s


def gnss_args(rng, line: Line, t_s: float, offset_m=(0.0, 0.0, 0.0)) -> dict:
    p = line.at(t_s) + rng.normal(0.0, 1.0, 3) * [GNSS_H_M, GNSS_H_M, GNSS_V_M] + np.asarray(offset_m)
    lat, lon, alt = (float(c) for c in FRAME.to_geodetic(*p))
    return dict(lat_deg=lat, lon_deg=lon, alt_m=alt, h_sigma_m=GNSS_H_M, v_sigma_m=GNSS_V_M, satellites=12)


def velocity_args(rng, line: Line, bias=(0.0, 0.0, 0.0)) -> dict:
    v = np.asarray(line.vel_enu_mps) + np.asarray(bias) + rng.normal(0.0, VEL_SIGMA, 3)
    return dict(vel_enu_mps=v, sigma_mps=VEL_SIGMA)


def relative(rng, observer: str, target: str, p_obs: np.ndarray, p_tgt: np.ndarray, t_s: float) -> RelativeObservation:
    """Noisy observation of ``target`` by ``observer`` (3 % range, 0.2 deg bearing)."""
    return relative_observation(FRAME, observer, target, t_s, p_obs, p_tgt, rng)


def fly(engine, rng, lines: dict[str, Line], duration_s: float, *, gnss_off: dict | None = None,
        spoof: dict | None = None, observers: tuple[str, ...] = (), target: str | None = None,
        bias: dict | None = None, on_tick=None, t0_s: float = 0.0) -> None:
    """10 Hz ticks: velocity every tick, GNSS every other (unless ``gnss_off[d](t)``),
    relative observations of ``target`` by ``observers`` every other tick; update each tick."""
    n = int(round(duration_s * 10))
    for i in range(n + 1):
        t = t0_s + i / 10.0
        for d, line in lines.items():
            engine.add_velocity(d, t, **velocity_args(rng, line, (bias or {}).get(d, (0.0, 0.0, 0.0))))
            if i % 2 == 0 and not (gnss_off and d in gnss_off and gnss_off[d](t)):
                off = spoof[d](t) if spoof and d in spoof else (0.0, 0.0, 0.0)
                engine.add_gnss(d, t, **gnss_args(rng, line, t, off))
        if target and i % 2 == 1:
            for o in observers:
                engine.add_relative(relative(rng, o, target, lines[o].at(t), lines[target].at(t), t))
        engine.update()
        if on_tick is not None:
            on_tick(t)
