"""Where a recovery run's landing error comes from: its helpers' ranges and poses, and the fused fix at touchdown.

Reads the files a recovery run writes (``benchmarks/recovery.py`` without ``--no-files``, or ``skyfix demo``):
``trajectory.csv`` (the simulator's truth of every drone, the GNSS error all receivers shared, the lost
drone's fused fix) and the lost drone's MCAP log (every helper observation it fused, ``/fusion/relative``).
Scoring only: the truth is read here, never by the run. Per run folder (``RUN/trajectory.csv``, or every
``RUN/seed_<n>/recovery``):

* per helper, each observation's range error against the true distance at its exposure time (median, mean:
  a bias that fusion cannot average away), and the helper's own position error against the swarm's GNSS
  frame (the observer position it sent minus its truth minus the shared GNSS error: its own receiver's part);
* the lost drone's fused error at touchdown against the truth and against the swarm's GNSS frame, and where
  it landed from home (a drone landing on its fix lands off by that error, less its home's own GNSS error).

Positions are in the simulator's world ENU (origin: ``--origin``, the simulator's default home unless the
run used another). No goal: prints figures, exit 0 (2: no run found).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from pathlib import Path

import numpy as np

from skyfix.datasets.sim.simulator import DEFAULT_HOME
from skyfix.fusion.log_mcap import iter_messages
from skyfix.geo import LocalFrame
from skyfix.geoid import geoid_undulation_m

LOST = "d2"


def _columns(rows: list[dict], names: tuple[str, ...]) -> np.ndarray:
    return np.array([[float(r[k]) if r.get(k) not in (None, "") else np.nan for k in names] for r in rows])


def diagnose(run: Path, world: LocalFrame) -> str:
    """The figures of one run folder, as printable lines."""
    rows = list(csv.DictReader(open(run / "trajectory.csv")))
    t = _columns(rows, ("t_s",))[:, 0]
    truth = {d: _columns(rows, (f"{d}_east_m", f"{d}_north_m", f"{d}_up_m")) for d in ("d1", "d2", "d3")}
    common = np.nan_to_num(_columns(rows, ("common_east_m", "common_north_m", "common_up_m")))
    fused = _columns(rows, ("fused_east_m", "fused_north_m", "fused_up_m"))

    def at(arr: np.ndarray, ts: float) -> np.ndarray:
        return np.array([np.interp(ts, t, arr[:, i]) for i in range(3)])

    per: dict[str, dict[str, list]] = {}
    for msg in iter_messages(run / f"{LOST}.mcap", ["/fusion/relative"]):
        obs = json.loads(msg[-1])["args"]["obs"]
        h, ts = obs["observer_id"], obs["time_s"]
        if h not in truth:
            continue
        seen_from = np.array([float(v) for v in world.to_enu(obs["observer_lat_deg"], obs["observer_lon_deg"],
                                                               obs["observer_alt_m"])])
        true_range = float(np.linalg.norm(at(truth[LOST], ts) - at(truth[h], ts)))
        per.setdefault(h, {"range": [], "own": []})
        per[h]["range"].append(obs["range_m"] / true_range - 1.0)
        per[h]["own"].append(seen_from - at(truth[h], ts) - at(common, ts))
    lines = []
    for h, f in sorted(per.items()):
        r, own = np.array(f["range"]), np.array(f["own"])
        lines.append(f"  {h}: {len(r)} observations, range error median {100 * np.median(r):+.1f} %, mean "
                     f"{100 * r.mean():+.1f} %; own position vs the swarm's GNSS frame mean E {own[:, 0].mean():+.2f} "
                     f"N {own[:, 1].mean():+.2f} m (sd {own[:, 0].std():.2f}, {own[:, 1].std():.2f})")
    alt = _columns(rows, (f"{LOST}_alt_rel_m",))[:, 0]
    airborne = np.flatnonzero(alt > 0.3)
    td = min(int(airborne[-1]) + 1, len(rows) - 1) if airborne.size else len(rows) - 1
    last = max(i for i in range(td + 1) if np.isfinite(fused[i, 0]))
    err = fused[last, :2] - truth[LOST][last, :2]
    rel = err - common[last, :2]
    landed = truth[LOST][td, :2] - truth[LOST][0, :2]
    lines.append(f"  {LOST} at touchdown (t={t[td]:.1f} s): fused fix - truth E {err[0]:+.2f} N {err[1]:+.2f} m "
                 f"({math.hypot(*err):.2f} m), vs the swarm's GNSS frame E {rel[0]:+.2f} N {rel[1]:+.2f} m "
                 f"({math.hypot(*rel):.2f} m); landed E {landed[0]:+.2f} N {landed[1]:+.2f} m from home "
                 f"({math.hypot(*landed):.2f} m)")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", type=Path, nargs="+", help="run folders, or benchmark output folders (seed_<n>/recovery)")
    ap.add_argument("--origin", default=None, help="lat,lon,alt_amsl_m of the world origin (default: the "
                    "simulator's default ArduPilot home, what run_recovery flies without SITL)")
    args = ap.parse_args(argv)
    lat, lon, alt = (float(v) for v in args.origin.split(",")) if args.origin else DEFAULT_HOME["ardupilot"]
    world = LocalFrame(lat, lon, alt + geoid_undulation_m(lat, lon))
    found = 0
    for root in args.runs:
        runs = [root] if (root / "trajectory.csv").exists() else sorted(
            (p for p in root.glob("seed_*/recovery") if (p / "trajectory.csv").exists()),
            key=lambda p: int(p.parent.name.split("_")[1]))
        for run in runs:
            found += 1
            print(f"{run}:\n{diagnose(run, world)}", flush=True)
    return 0 if found else 2


if __name__ == "__main__":
    sys.exit(main())
