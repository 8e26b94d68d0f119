"""Where a recovery run's landing error comes from: its helpers' ranges and poses, and the fused fix at touchdown.

Reads the files a recovery run writes (``benchmarks/recovery.py`` without ``--no-files``, or ``skyfix demo``):
``trajectory.csv`` (the simulator's truth of every drone, the GNSS error all receivers shared, the lost
drone's fused fix) and the lost drone's MCAP log (every helper observation it fused, ``/fusion/relative``).
Scoring only: the truth is read here, never by the run. Per run folder (``RUN/trajectory.csv``, or every
``RUN/seed_<n>/recovery``):

* per helper, each observation's range error against the true distance at its exposure time (median, mean:
  a bias that fusion cannot average away), and the helper's own position error against the swarm's GNSS
  frame (the observer position it sent minus its truth minus the shared GNSS error: its own receiver's part),
  also along its line of sight to the target (+ toward it; over all and over its last 20 s of observations):
  an observer whose fix sits toward the target puts the target's fix beyond it, as a long range does;
* the lost drone's fused error at touchdown against the truth and against the swarm's GNSS frame, and where
  it landed from home (a drone landing on its fix lands off by that error, less its home's own GNSS error);
* with ``--ranges``, every run's observations pooled: the range error by the target's elevation above the
  observer's horizon and by the target's speed, and per run the touchdown error against the swarm's GNSS frame
  along the observers' mean line of sight (positive: away from them, as long ranges push it);
* with ``--frames``, where the simulated autopilot records them (``ap_*`` columns): its home error, its own
  estimate's error at touchdown and how far from its home it landed on that estimate;
* where the home error comes from (``--frames``): the lost drone's fused error before take-off (its home: the
  autopilot records it on its own receiver at arming), just before the loss (its own receiver's frame then) and
  over the first 10 s of helper-based fixes (the helpers' frame), each also less the shared GNSS error (its own
  receiver's part), and what an oracle "home carried into the helpers' frame" would have landed: the landing
  less the true offset between the two frames at the loss (the best any estimate of that offset could do). A
  healthy-GNSS baseline folder next to the run (``seed_<n>/baseline``) gets the same home and touchdown lines.

Positions are in the simulator's world ENU (origin: ``--origin``, the simulator's default home unless the
run used another). No goal: prints figures, exit 0 (2: no run found).
"""

from __future__ import annotations

import argparse
import csv
import itertools
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


def _trajectory(run: Path) -> list[dict]:
    """The rows of ``run/trajectory.csv`` (the recorder's samples, strings)."""
    with open(run / "trajectory.csv", newline="") as f:
        return list(csv.DictReader(f))


def _columns(rows: list[dict], names: tuple[str, ...]) -> np.ndarray:
    return np.array([[float(r[k]) if r.get(k) not in (None, "") else np.nan for k in names] for r in rows])


def _fused_error(rows: list[dict], truth: np.ndarray) -> np.ndarray:
    """(N, 2) fused - true horizontal error per row (NaN where the row has no fix)."""
    return _columns(rows, ("fused_east_m", "fused_north_m")) - truth[:, :2]


def _loss_time_s(run: Path) -> float | None:
    """The GNSS loss time the run's ``report.json`` records (s), None without one."""
    report = json.loads((run / "report.json").read_text()) if (run / "report.json").exists() else {}
    return (report.get("figures") or {}).get("loss_time_s")


def honesty(run: Path) -> float | None:
    """Mean of (horizontal fused error / stated sigma_h)^2 from the GNSS loss (``report.json``'s loss time) while
    airborne. sigma_h is the larger horizontal axis' 1-sigma, so an honest covariance gives 1 (a thin ellipse) to 2
    (a round one); above 2 is over-confident. None without a loss time or fused rows."""
    rows = _trajectory(run)
    t_loss = _loss_time_s(run)
    if t_loss is None:
        return None
    t = _columns(rows, ("t_s",))[:, 0]
    err = _fused_error(rows, _columns(rows, (f"{LOST}_east_m", f"{LOST}_north_m", f"{LOST}_up_m")))
    sigma = _columns(rows, ("fused_sigma_h_m",))[:, 0]
    alt = _columns(rows, (f"{LOST}_alt_rel_m",))[:, 0]
    use = (t >= t_loss) & (alt > 0.5) & np.isfinite(err[:, 0]) & (sigma > 0)
    return float(np.mean(np.sum(err[use] ** 2, axis=1) / sigma[use] ** 2)) if use.any() else None


def home_frames(run: Path) -> tuple[list[str], dict[str, np.ndarray]]:
    """The home error and the own-receiver / helpers' frame offset of one run folder (recovery or baseline):
    printable lines and the vectors (ENU m, horizontal) for the summary."""
    rows = _trajectory(run)
    t = _columns(rows, ("t_s",))[:, 0]
    truth = _columns(rows, (f"{LOST}_east_m", f"{LOST}_north_m", f"{LOST}_up_m"))
    common = np.nan_to_num(_columns(rows, ("common_east_m", "common_north_m")))
    err = _fused_error(rows, truth)
    alt = _columns(rows, (f"{LOST}_alt_rel_m",))[:, 0]
    up = np.flatnonzero(alt > 0.3)
    t_loss = _loss_time_s(run)
    if not up.size or t_loss is None:
        return [f"  {run.name}: no take-off or no loss time recorded"], {}
    lift, td = int(up[0]), min(int(up[-1]) + 1, len(rows) - 1)

    def mean_over(mask: np.ndarray) -> np.ndarray:
        ok = mask & np.isfinite(err[:, 0])
        return err[ok].mean(axis=0) if ok.any() else np.full(2, np.nan)

    # the autopilot's home is its own fix at arming, just before the lift-off; the recorder may have no fused
    # fix on the ground, then the first second of fixes (its own receiver's part decorrelates over 20 s)
    home = mean_over((t >= t[lift] - 1.0) & (t < t[lift]))
    if not np.isfinite(home[0]):
        t_fix = t[np.flatnonzero(np.isfinite(err[:, 0]))[0]]
        home = mean_over((t >= t_fix) & (t < t_fix + 1.0))
    if rows[lift].get("ap_home_east_m") not in (None, ""):  # the simulated autopilot's own home: exact
        home = _columns(rows[lift:lift + 1], ("ap_home_east_m", "ap_home_north_m"))[0] - truth[0, :2]
    landed = truth[td, :2] - truth[0, :2]
    last = max(i for i in range(td + 1) if np.isfinite(err[i, 0]))
    out = {"home": home, "home_own": home - common[lift], "landed": landed, "touchdown": err[last],
           "touchdown_own": err[last] - common[last], "off_fix": landed - home + err[last]}
    lines = [f"  {run.name}: home error (its autopilot's, else its fused fix at take-off, t={t[lift]:.0f} s) "
             f"{_vec(home)}, its own "
             f"receiver's part {_vec(out['home_own'])}; at touchdown fused error {_vec(err[last])}; landed "
             f"{_vec(landed)} from home; landed - (home error - touchdown error) {_vec(landed - home + err[last])} "
             f"(where it landed off its own fix)"]
    if rows[td].get("ap_est_east_m") not in (None, ""):  # the simulated autopilot's own estimate and home
        ap_est, ap_home = (_columns(rows[td:td + 1], (f"ap_{k}_east_m", f"ap_{k}_north_m"))[0] for k in ("est", "home"))
        est_err = ap_est - truth[td, :2]
        out.update({"ap_home": ap_home - truth[0, :2], "ap_est": est_err, "ap_off": ap_est - ap_home})
        lines.append(f"  {run.name}: its autopilot: home error {_vec(out['ap_home'])}, estimate error at touchdown "
                     f"{_vec(est_err)} (that less the fused fix's: {_vec(est_err - err[last])}), landed "
                     f"{_vec(out['ap_off'])} from its home on its own estimate (landed = home error - estimate error "
                     f"+ that)")
    relative = np.array(["relative:" in r.get("sources", "") for r in rows])
    first = np.flatnonzero(relative & (t >= t_loss))
    if first.size:
        i_loss = int(np.searchsorted(t, t_loss))
        pre = mean_over((t >= t_loss - 1.0) & (t < t_loss))
        helpers = mean_over(relative & (t >= t[first[0]]) & (t < t[first[0]] + 10.0))
        offset = pre - helpers
        j = int(first[0]) - 1  # the last dead-reckoned fix before the first helper-based one
        drift, sigma = err[j] - pre, _columns(rows[j:j + 1], ("fused_sigma_h_m",))[0, 0]
        out.update({"pre_own": pre - common[i_loss], "oracle": landed - offset})
        lines.append(f"  {run.name}: dead reckoning from the loss to the first helper-based fix ({t[first[0]] - t_loss:.1f}"
                     f" s): its error moved {_vec(drift)}, stated sigma_h {sigma:.2f} m (what an estimate of the frame "
                     f"offset from that overlap would carry)")
        lines.append(f"  {run.name}: before the loss (t={t_loss:.0f} s, {t_loss - t[lift]:.0f} s after take-off) "
                     f"fused error {_vec(pre)}, own part {_vec(out['pre_own'])}; first 10 s of helper fixes "
                     f"{_vec(helpers)}; own frame - helpers' frame {_vec(offset)}; with the home carried into the "
                     f"helpers' frame by that (true) offset it would have landed {_vec(out['oracle'])} from home")
    return lines, out


def _vec(v: np.ndarray) -> str:
    return f"E {v[0]:+.2f} N {v[1]:+.2f} ({math.hypot(*v[:2]):.2f} m)"


def summary(found: list[dict[str, np.ndarray]], baselines: list[dict[str, np.ndarray]]) -> list[str]:
    """Medians over the runs: the landing as flown, with the oracle frame offset, and the baselines'."""
    def med(items: list[dict], key: str) -> str:
        v = [float(np.hypot(*d[key][:2])) for d in items if key in d]
        return f"{np.median(v):.2f} m over {len(v)}" if v else "n/a"

    own = np.array([np.r_[d["home_own"], d["pre_own"]] for d in found if "pre_own" in d]).reshape(-1, 4)
    corr = float(np.corrcoef(own[:, :2].ravel(), own[:, 2:].ravel())[0, 1]) if len(own) > 2 else math.nan
    return [f"median landing from home: recovery {med(found, 'landed')}; with the home carried into the helpers' "
            f"frame by the true offset {med(found, 'oracle')}; healthy-GNSS baseline {med(baselines, 'landed')}",
            f"median parts: the fused fix at touchdown against the swarm's GNSS frame: recovery "
            f"{med(found, 'touchdown_own')}, baseline {med(baselines, 'touchdown_own')}; home's own receiver part "
            f"{med(found, 'home_own')}; landed off its own fix (landed - (home error - touchdown error)): recovery "
            f"{med(found, 'off_fix')}, baseline {med(baselines, 'off_fix')}",
            f"the lost receiver's own error (less the shared part) at take-off vs just before the loss: correlation "
            f"{corr:+.2f} over {2 * len(own)} axis pairs (the home offset carries over only as far as these agree)"]


def diagnose(run: Path, world: LocalFrame) -> tuple[str, np.ndarray, np.ndarray | None]:
    """The figures of one run folder, as printable lines; one row per helper observation: (relative range
    error, the target's elevation above the observer's horizon in deg, the target's speed in m/s); and over the
    last 8 s of observations, the horizontal error against the swarm's GNSS frame (m) of where they put the
    target, of the observers' own fixes and of their cameras' part, and the fused fix's at the last observation
    and at touchdown (None without observations)."""
    rows = _trajectory(run)
    t = _columns(rows, ("t_s",))[:, 0]
    truth = {d: _columns(rows, (f"{d}_east_m", f"{d}_north_m", f"{d}_up_m")) for d in ("d1", "d2", "d3")}
    common = np.nan_to_num(_columns(rows, ("common_east_m", "common_north_m", "common_up_m")))
    fused = _columns(rows, ("fused_east_m", "fused_north_m", "fused_up_m"))

    def at(arr: np.ndarray, ts: float) -> np.ndarray:
        return np.array([np.interp(ts, t, arr[:, i]) for i in range(3)])

    per: dict[str, dict[str, list]] = {}
    records = []
    for msg in iter_messages(run / f"{LOST}.mcap", ["/fusion/relative"]):
        obs = json.loads(msg[-1])["args"]["obs"]
        h, ts = obs["observer_id"], obs["time_s"]
        if h not in truth:
            continue
        seen_from = np.array([float(v) for v in world.to_enu(obs["observer_lat_deg"], obs["observer_lon_deg"],
                                                               obs["observer_alt_m"])])
        seen = at(truth[LOST], ts) - at(truth[h], ts)
        true_range = float(np.linalg.norm(seen))
        per.setdefault(h, {"range": [], "own": [], "los": [], "t": [], "implied": []})
        per[h]["range"].append(obs["range_m"] / true_range - 1.0)
        speed = float(np.linalg.norm(at(truth[LOST], ts + 0.25) - at(truth[LOST], ts - 0.25))) / 0.5
        bearing = np.asarray(obs["bearing_unit_enu"], float)
        stated_m = math.sqrt(float(bearing @ np.asarray(obs["cov_enu_m2"], float).reshape(3, 3) @ bearing))
        records.append((per[h]["range"][-1], math.degrees(math.asin(seen[2] / true_range)), speed, true_range,
                        (obs["range_m"] - true_range) / stated_m))
        per[h]["own"].append(seen_from - at(truth[h], ts) - at(common, ts))
        per[h]["los"].append(float(per[h]["own"][-1] @ seen) / true_range)  # + : toward the target
        per[h]["t"].append(ts)
        # where this observation alone puts the target, against the swarm's GNSS frame
        per[h]["implied"].append(seen_from + np.asarray(obs["bearing_unit_enu"], float) * obs["range_m"]
                                 - at(truth[LOST], ts) - at(common, ts))
    lines = []
    for h, f in sorted(per.items()):
        r, own, los, ts_obs = np.array(f["range"]), np.array(f["own"]), np.array(f["los"]), np.array(f["t"])
        late = ts_obs >= ts_obs.max() - 20.0
        lines.append(f"  {h}: {len(r)} observations, range error median {100 * np.median(r):+.1f} %, mean "
                     f"{100 * r.mean():+.1f} %; own position vs the swarm's GNSS frame mean E {own[:, 0].mean():+.2f} "
                     f"N {own[:, 1].mean():+.2f} m (sd {own[:, 0].std():.2f}, {own[:, 1].std():.2f}), along its line "
                     f"of sight (+ toward the target) {los.mean():+.2f} m, over its last 20 s of observations "
                     f"{los[late].mean():+.2f} m")
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
    helpers = [d for d in truth if d != LOST]
    sight = sum((truth[LOST][last, :2] - truth[d][last, :2]) / np.linalg.norm(truth[LOST][last, :2] - truth[d][last, :2])
                for d in helpers)
    lines.append(f"  {LOST} at touchdown: its error against the swarm's GNSS frame along {'+'.join(helpers)}'s mean line "
                 f"of sight (away from them) {float(rel @ sight) / np.linalg.norm(sight):+.2f} m")
    t_end = max((max(f["t"]) for f in per.values()), default=None)
    end = None
    if t_end is not None:
        own_end = [o for f in per.values() for o, ts in zip(f["own"], f["t"], strict=True) if ts >= t_end - 8.0]
        implied_end = [o for f in per.values() for o, ts in zip(f["implied"], f["t"], strict=True) if ts >= t_end - 8.0]
        implied_h, own_h = np.mean(implied_end, axis=0)[:2], np.mean(own_end, axis=0)[:2]
        lines.append(f"  {LOST} over the last 8 s of observations: where they put it, against the swarm's GNSS frame "
                     f"(mean) {np.linalg.norm(implied_h):.2f} m = the observers' own fixes {np.linalg.norm(own_h):.2f} m "
                     f"+ their cameras (range and bearing) {np.linalg.norm(implied_h - own_h):.2f} m (vectors)")
        # after the last observation the fix runs on the autopilot's velocity alone (dead reckoning) to touchdown
        i_obs = min(int(np.searchsorted(t, t_end)), last)
        at_obs = float(np.linalg.norm(fused[i_obs, :2] - truth[LOST][i_obs, :2] - common[i_obs, :2]))
        lines.append(f"  {LOST} after the last observation (t={t_end:.1f} s, {t[td] - t_end:.1f} s before touchdown, "
                     f"{truth[LOST][i_obs, 2]:.1f} m up): fused fix vs the swarm's GNSS frame {at_obs:.2f} m there, "
                     f"{math.hypot(*rel):.2f} m at touchdown")
        # the landing had the fused fix carried only the observers' own receiver errors (perfect cameras and fusion):
        # the drone lands off home by (home error - fix error), so swapping the fix's error moves the landing by it
        perfect = landed + rel - own_h
        lines.append(f"  {LOST} with perfect cameras and fusion (its fix off the swarm's GNSS frame by the observers' "
                     f"own fixes' mean over the last 8 s, nothing else) it would have landed {math.hypot(*perfect):.2f} m "
                     f"from home ({math.hypot(*landed):.2f} m as flown)")
        # and had the observers' own fixes been on the swarm's GNSS frame (cameras and fusion as they were)
        observers = landed + own_h
        lines.append(f"  {LOST} with perfect observer fixes (the observers' own fixes' mean over the last 8 s taken "
                     f"out of its fix) it would have landed {math.hypot(*observers):.2f} m from home")
        end = np.array([np.linalg.norm(implied_h), np.linalg.norm(own_h), np.linalg.norm(implied_h - own_h),
                        at_obs, math.hypot(*rel), math.hypot(*landed), math.hypot(*perfect), math.hypot(*observers)])
    return "\n".join(lines), np.array(records).reshape(-1, 5), end


def range_lines(records: np.ndarray) -> list[str]:
    """The pooled range errors (rows of :func:`diagnose`) by the target's elevation, its speed and the true range;
    with how the stated range sigma held (the share beyond 3 sigma: 0.3 % for an honest Gaussian one)."""
    out = [f"range error over {len(records)} observations: median {100 * np.median(records[:, 0]):+.2f} %, mean "
           f"{100 * records[:, 0].mean():+.2f} %; beyond 3 stated sigma {100 * np.mean(abs(records[:, 4]) > 3):.1f} %"]
    for col, name, unit, edges in ((1, "target elevation above the observer's horizon", "deg", (-90, 0, 3, 6, 10, 20, 90)),
                                   (2, "target speed", "m/s", (0.0, 0.3, 1.0, 3.0, 100.0)),
                                   (3, "true range", "m", (0, 20, 30, 40, 45, 50, 60, 100))):
        for lo, hi in itertools.pairwise(edges):
            rows = records[(records[:, col] >= lo) & (records[:, col] < hi)]
            if rows.size:
                e, z = rows[:, 0], rows[:, 4]
                out.append(f"  {name} {lo}-{hi} {unit}: {e.size} observations, median {100 * np.median(e):+.2f} %, "
                           f"mean {100 * e.mean():+.2f} %, p90 {100 * np.percentile(e, 90):+.2f} %, RMS of "
                           f"error/stated sigma {np.sqrt(np.mean(z ** 2)):.2f} (1 honest), beyond 3 sigma "
                           f"{100 * np.mean(abs(z) > 3):.1f} %")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", type=Path, nargs="+", help="run folders, or benchmark output folders (seed_<n>/recovery)")
    ap.add_argument("--origin", default=None, help="lat,lon,alt_amsl_m of the world origin (default: the "
                    "simulator's default ArduPilot home, what run_recovery flies without SITL)")
    ap.add_argument("--ranges", action="store_true", help="also the range error of every run's observations "
                    "pooled, by the target's elevation and by its speed")
    ap.add_argument("--frames", action="store_true", help="also the home error and the frame offset lines, and "
                    "the oracle landing with the home carried into the helpers' frame (with the baselines')")
    args = ap.parse_args(argv)
    lat, lon, alt = (float(v) for v in args.origin.split(",")) if args.origin else DEFAULT_HOME["ardupilot"]
    world = LocalFrame(lat, lon, alt + geoid_undulation_m(lat, lon))
    found = 0
    frames: list[dict[str, np.ndarray]] = []
    baselines: list[dict[str, np.ndarray]] = []
    records: list[np.ndarray] = []
    ends: list[np.ndarray] = []
    honest: list[tuple[float, float | None]] = []
    for root in args.runs:
        runs = [root] if (root / "trajectory.csv").exists() else sorted(
            (p for p in root.glob("seed_*/recovery") if (p / "trajectory.csv").exists()),
            key=lambda p: int(p.parent.name.split("_")[1]))
        for run in runs:
            found += 1
            text, rows, end = diagnose(run, world)
            records.append(rows)
            base_dir = run.parent / "baseline"
            pair = (honesty(run), honesty(base_dir) if (base_dir / "trajectory.csv").exists() else None)
            if pair[0] is not None:
                honest.append(pair)
                text += (f"\n  {LOST} stated sigma against its error from the loss, mean (error_h / sigma_h)^2 (honest: "
                         f"1-2): recovering {pair[0]:.2f}" + ("" if pair[1] is None else
                                                                  f", the healthy RTL of the same seed {pair[1]:.2f}"))
            if end is not None:
                ends.append(end)
            print(f"{run}:\n{text}", flush=True)
            if args.frames:
                lines, vecs = home_frames(run)
                frames.append(vecs)
                base = run.parent / "baseline"
                if (base / "trajectory.csv").exists():
                    more, bvecs = home_frames(base)
                    lines += more
                    baselines.append(bvecs)
                print("\n".join(lines), flush=True)
    if ends:
        med = np.median(np.array(ends), axis=0)
        print(f"over the last 8 s of observations, median over {len(ends)} runs: where they put the lost drone "
              f"{med[0]:.2f} m from the swarm's GNSS frame; the observers' own fixes {med[1]:.2f} m; their cameras' "
              f"part {med[2]:.2f} m; the fused fix from the swarm's GNSS frame at the last observation {med[3]:.2f} m, "
              f"at touchdown {med[4]:.2f} m")
        print(f"median landing over {len(ends)} runs: {med[5]:.2f} m as flown, {med[6]:.2f} m with perfect cameras and "
              f"fusion (the observers' own receiver errors alone), {med[7]:.2f} m with perfect observer fixes (their "
              f"cameras and the fusion as they were)")
    if honest:
        base = [b for _, b in honest if b is not None]
        print(f"stated sigma from the loss, median over {len(honest)} runs of mean (error_h / sigma_h)^2 (honest: 1-2): "
              f"recovering {np.median([r for r, _ in honest]):.2f}"
              + (f", healthy RTL {np.median(base):.2f} over {len(base)}" if base else ""))
    if args.frames and frames:
        print("\n".join(summary(frames, baselines)))
    if args.ranges and records:
        print("\n".join(range_lines(np.vstack(records))))
    return 0 if found else 2


if __name__ == "__main__":
    sys.exit(main())
