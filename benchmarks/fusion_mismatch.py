"""benchmarks/fusion.py, part 3: the engine's GNSS error model against receivers that differ from it.

The correlated section draws its GNSS errors from the very model the engine assumes by
default (Gauss-Markov 1.5 m per horizontal axis, tau 60 s). Here the truth differs and the
engine is left at its defaults: a grid of stationary sigma (0.8 / 1.5 / 2.5 m horizontal,
vertical scaled alike) and correlation time (20 / 60 / 180 s), then, at the nominal
sigma/tau, three errors the model has no term for:

* step: every receiver's error steps by 2.5 m for good (a constellation change), A's at
  100 s, B's and C's during A's outage;
* heavy tails: 10 % of fixes off by 1-8 m (multipath reflections near the gate, where the
  2 % / 5-20 m outliers of the main section are easy to refuse);
* common: 70 % of the wandering error's variance shared by all receivers (nearby
  receivers see the same satellites through the same air); the engine assumes them
  independent, so helpers' observations look like independent evidence when they are not.

Each cell: :func:`skyfix.datasets.fusion_scenario.mismatch_scenario` (A silent 150-240 s,
no other fault), ``--sweep-seeds`` seeds of ``--sweep-s`` seconds, skyfix against the joint
EKF with a white GNSS model (the issue's baseline) on the same events. Printed per cell:
outage RMSE of both and the ratio, and the share of 3-dof NEES in the two-sided 95 % band
with how much falls above it (over-confident) and below it (over-cautious). The nominal
cell is the correlated section itself (its seeds, faults and goals); the others get a
verdict, not a goal.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from fusion_correlated import OUTAGE, TICK_S, WARMUP_S, _herr, sweep_row
from fusion_joint_ekf import run_joint_ekf

from skyfix.datasets.fusion_scenario import CORRELATED_NOISE, mismatch_scenario

NOMINAL = (1.5, 60.0)
SIGMAS_M = (0.8, 1.5, 2.5)
TAUS_S = (20.0, 60.0, 180.0)
EXTRAS = {  # name -> (noise changes, error step m)
    "step 2.5 m": ({}, 2.5),
    "heavy tails": ({"gnss_outlier_frac": 0.10, "gnss_outlier_min_m": 1.0, "gnss_outlier_max_m": 8.0}, 0.0),
    "70 % common": ({"gnss_common_frac": 0.7}, 0.0),
}
NEES_BAND_GOAL = (0.85, 0.99)


def cells() -> list[tuple[str, dict, float]]:
    """(name, NoiseModel changes, step m) of every cell but the nominal one."""
    out = [(_name(s, t), _gm(s, t), 0.0) for s in SIGMAS_M for t in TAUS_S if (s, t) != NOMINAL]
    out += [(name, {**_gm(*NOMINAL), **changes}, step) for name, (changes, step) in EXTRAS.items()]
    return out


def _name(sigma_m: float, tau_s: float) -> str:
    return f"GM {sigma_m:g} m / {tau_s:g} s"


def _gm(sigma_m: float, tau_s: float) -> dict:
    v_per_h = CORRELATED_NOISE.gnss_gm_v_sigma_m / CORRELATED_NOISE.gnss_gm_h_sigma_m
    return {"gnss_gm_h_sigma_m": sigma_m, "gnss_gm_v_sigma_m": sigma_m * v_per_h, "gnss_gm_tau_s": tau_s}


def mismatch_section(engine_cls, seeds, duration_s: float, lag_s: float | None, run_skyfix, nees_of,
                     nominal: dict) -> str:
    """Run every cell; print its row and verdict (``nominal``: the correlated section's row); return a headline."""
    ticks = np.round(np.arange(1, int(round(duration_s / TICK_S)) + 1) * TICK_S, 6)
    print(f"\nGNSS model mismatch: engine at its defaults (GM {NOMINAL[0]:g} m / {NOMINAL[1]:g} s), truth varied; "
          f"A silent {OUTAGE[1]:g}-{OUTAGE[2]:g} s; {len(seeds)} seeds x {duration_s:g} s per cell")
    print(f"  {'truth':<22} {'skyfix m':>8} {'joint EKF m':>11} {'ratio':>6} {'NEES band':>9} {'above':>6} "
          f"{'below':>6} {'mean':>6}  verdict")
    rows = {f"{_name(*NOMINAL)} *": nominal}
    _print_row(*next(iter(rows.items())))
    for name, changes, step_m in cells():
        rows[name] = _cell(engine_cls, seeds, duration_s, ticks, lag_s, run_skyfix, nees_of,
                           replace(CORRELATED_NOISE, **changes), step_m)
        _print_row(name, rows[name])
    print("  * the engine's own model: the correlated section above (its seeds, run length and faults, its goals)")
    covered = [n for n, r in rows.items() if _covered(r)]
    beaten = [n for n, r in rows.items() if r["ratio"] <= 1.0]
    print(f"  stated covariance covers the truth (NEES 85-99 % in band) in {len(covered)}/{len(rows)} cells; "
          f"skyfix at least as accurate as the joint EKF in {len(beaten)}/{len(rows)}")
    return f"mismatch: covered in {len(covered)}/{len(rows)} cells, RMSE <= joint EKF in {len(beaten)}/{len(rows)}"


def _cell(engine_cls, seeds, duration_s, ticks, lag_s, run_skyfix, nees_of, noise, step_m) -> dict:
    err, err_ekf, nees = [], [], []
    d, t0, t1 = OUTAGE
    for seed in seeds:
        scen = mismatch_scenario(duration_s, seed, noise, step_m)
        sk = run_skyfix(engine_cls, scen, ticks, lag_s, None)
        ekf = run_joint_ekf(scen, ticks, WARMUP_S, False)[0]
        for tracks, out in (({x: sk.tracks[x].arrays() for x in scen.drone_ids}, err), (ekf, err_ekf)):
            t, p, _ = tracks[d]
            m = (t >= t0) & (t < t1)
            out.append(_herr(scen, d, t[m], p[m]))
        nees.append(np.concatenate([nees_of(scen, x, *sk.tracks[x].arrays()) for x in scen.drone_ids]))
    return sweep_row(np.concatenate(err), np.concatenate(err_ekf), np.concatenate(nees))


def _print_row(name: str, r: dict) -> None:
    print(f"  {name:<22} {r['rmse']:8.2f} {r['rmse_ekf']:11.2f} {r['ratio']:6.2f} {100 * r['band']:8.1f}% "
          f"{100 * r['above']:5.1f}% {100 * r['below']:5.1f}% {r['mean']:6.2f}  {_verdict(r)}")


def _covered(r: dict) -> bool:
    return NEES_BAND_GOAL[0] <= r["band"] <= NEES_BAND_GOAL[1]


def _verdict(r: dict) -> str:
    if _covered(r):
        return "covered"
    # 2.5 % of a consistent estimator's NEES lie above the band and 2.5 % below it
    return "OVER-CONFIDENT (stated covariance too small)" if r["above"] > r["below"] else \
        "over-cautious (stated covariance too large)"
