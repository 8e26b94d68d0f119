"""GPS-loss recovery benchmark (issue 18): the lost drone flies home on its helpers' cameras.

Each seed is one world: three simulated ArduPilot copters surveying in wind (mean 3 m/s from a
seeded direction, 20 % gusts), correlated (Gauss-Markov) GNSS errors on every receiver (``--gnss``:
``realistic`` by default, 1.5 m per axis per receiver of which 1.4 m is common to the area's receivers
and wanders over 30 min, 0.45 m / 20 s its own multipath, 0.3 m white noise, see
:mod:`skyfix.datasets.gnss_error`; ``independent``, the stress case: each its own 1.5 m / 60 s + 0.3 m,
nothing shared; ``mild``: its own 0.4 m / 60 s + 0.15 m; each own error drawn from its steady state), one drone
losing its receiver at a seeded random moment and place along its survey. It is flown twice by
:func:`skyfix.crps.recovery.run_recovery`:

* recovery: the receiver is gone; the drone holds, asks for help, two helpers fly to vantage
  points, point their gimbal cameras (frames rendered from the simulator's truth:
  :class:`skyfix.datasets.sim.world_camera.WorldCamera`), detect and range it in the pixels; its
  fusion positions it from their observations; the injected fix takes it home; it lands.
* baseline: the same seed, the same drone flying the same RTL at the same moment on its healthy
  GNSS (what its own receiver's errors at take-off and landing allow: the floor of the landing error).

Per run: landing error (truth: horizontal distance from the true take-off point), loss -> first
fused fix resting on a helper's observation, the largest horizontal error of the lost drone's
fused fix while it recovers (against the truth, the goal's figure, and against the swarm's GNSS frame:
the truth plus the GNSS error all receivers share, which the helpers' fixes carry and no drone can
observe; the difference is what fusion could still reduce; and, as a reference only, the largest error of the
same drone's own GNSS-based fix over its healthy RTL from the loss on), the closest approach between any two drones after the loss, the
share of helper frames with the target in view in which it was detected.

Goals (issue 18): >= 9 of 10 land <= 3 m from home; median landing error <= 1.5x the baseline's;
in every run: first fused fix <= 15 s after the loss, recovery error <= 5 m, separation >= 10 m.

A run takes minutes of wall time, so seeds may be flown in several invocations (``--seeds 0-3``,
then ``--seeds 4-7`` ...) into one ``-o`` folder: every invocation writes ``seed_<n>.json`` there and
judges all the seeds the folder holds (a seed pair takes ~80 s of wall time at the default speed
2 on an idle 2-core machine: five seeds fit one 10-minute slot). Exit 0: every goal met on all ``--runs`` seeds; 1: a goal
missed; 2: fewer seeds than ``--runs`` flown so far (goals printed, not judged). Last line: headline.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

GOAL_HOME_M = 3.0
GOAL_HOME_SHARE = 0.9
GOAL_MEDIAN_RATIO = 1.5
GOAL_FIRST_FIX_S = 15.0
GOAL_RECOVERY_ERR_M = 5.0
GOAL_SEPARATION_M = 10.0
SCORES = ("landing_error_m", "loss_to_first_fused_fix_s", "max_recovery_error_h_m", "min_separation_m",
          "detection_share")


def parse_seeds(text: str) -> list[int]:
    """``"0-9"``, ``"1,4,7"`` or a mix (``"0-2,5"``) -> sorted unique seeds."""
    out: set[int] = set()
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        lo, _, hi = part.partition("-")
        try:
            a, b = int(lo), int(hi) if hi else int(lo)
        except ValueError:
            raise argparse.ArgumentTypeError(f"--seeds: {part!r} is not a seed or a range like 0-9") from None
        if a < 0 or b < a:
            raise argparse.ArgumentTypeError(f"--seeds: {part!r} is not a non-negative, increasing range")
        out.update(range(a, b + 1))
    if not out:
        raise argparse.ArgumentTypeError("--seeds: no seed given")
    return sorted(out)


def fly_one(seed: int, healthy: bool, args: argparse.Namespace) -> dict:
    """One run (the recovery, or with ``healthy`` its baseline); its scores, JSON-ready."""
    from skyfix.crps.recovery import GNSS_MODELS, RecoveryConfig, run_recovery
    from skyfix.errors import SkyfixError

    kind = "baseline" if healthy else "recovery"
    kwargs = {"seed": seed, "healthy": healthy, "gnss": GNSS_MODELS[args.gnss],
              "output": None if args.no_files else args.output / f"seed_{seed}" / kind}
    if args.speed is not None:
        kwargs["speed"] = args.speed
    if args.fusion_common_share is not None:
        kwargs["fusion_common_share"] = args.fusion_common_share
    t0 = time.monotonic()
    stage = [""]

    def progress(what: str, frac: float) -> None:
        if what != stage[0] and args.verbose:
            print(f"    seed {seed} {kind}: {what} ({frac:.0%}, {time.monotonic() - t0:.0f} s)", flush=True)
        stage[0] = what

    try:
        res = run_recovery(RecoveryConfig(**kwargs), progress=progress)
    except SkyfixError as exc:  # the run could not be flown to its end (e.g. a take-off timed out): a miss
        print(f"    seed {seed} {kind}: {exc}", flush=True)
        return {**dict.fromkeys(SCORES), "outcome": f"error: {exc}", "wall_s": time.monotonic() - t0,
                "figures": {}, "timeline": []}
    return {**{k: _num(getattr(res, k)) for k in SCORES}, "outcome": res.outcome,
            "wall_s": time.monotonic() - t0, "figures": {k: _num(v) for k, v in res.figures.items()},
            "timeline": [[round(t, 2), what] for t, what in res.timeline]}


def fly_seed(seed: int, args: argparse.Namespace) -> dict:
    """The recovery and its healthy-GNSS baseline for one seed."""
    rev, dirty = revision()
    return {"seed": seed, "speed": args.speed, "gnss": args.gnss, "fusion_common_share": args.fusion_common_share,
            "revision": rev, "uncommitted": dirty,
            "recovery": fly_one(seed, False, args), "baseline": fly_one(seed, True, args)}


def revision() -> tuple[str, list[str]]:
    """The commit flown (``+dirty`` when code the runs import has uncommitted changes) and those files."""
    import subprocess

    root = Path(__file__).resolve().parent.parent
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True,
                              check=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", "skyfix", "crps",
                                "fusion", "drivers", "datasets", "benchmarks/recovery.py"],
                               cwd=root, capture_output=True, text=True, check=True, timeout=10).stdout.split("\n")
    except (OSError, subprocess.SubprocessError):
        return "unknown", []
    files = [line[3:] for line in dirty if line.strip()]
    return head + ("+dirty" if files else ""), files


def _num(x) -> float | None:
    """JSON-safe float (NaN -> None)."""
    try:
        x = float(x)
    except (TypeError, ValueError):
        return None
    return x if math.isfinite(x) else None


def _f(x: float | None, fmt: str = ".2f") -> str:
    return "  n/a" if x is None else format(x, fmt)


def false_alarms(run: dict, before_s: float | None) -> int:
    """Holds on a healthy receiver: 'gnss rejected' / 'gnss lost' events of any drone before ``before_s``
    (the loss; None: the whole run), each a false GNSS-loss recovery."""
    end = math.inf if before_s is None else before_s
    return sum(t < end and "hold (gnss" in what for t, what in run.get("timeline", []))


def print_run(r: dict) -> None:
    rec, base = r["recovery"], r["baseline"]
    loss = rec["figures"].get("loss_time_s")
    alarms = false_alarms(rec, loss if loss is not None else -math.inf) + false_alarms(base, None)
    faults = sum(x["figures"].get("service_faults") or 0 for x in (rec, base))  # absent in older runs' files
    print(f"  seed {r['seed']:>2}: GNSS lost at t={_f(loss, '.0f')} s, "
          f"landing {_f(rec['landing_error_m'])} m (healthy RTL {_f(base['landing_error_m'])} m), "
          f"loss->first fused fix {_f(rec['loss_to_first_fused_fix_s'], '.1f')} s, "
          f"max recovery error {_f(rec['max_recovery_error_h_m'])} m "
          f"({_f(rec['figures'].get('max_recovery_error_gnss_frame_h_m'))} m vs the swarm's GNSS frame, common GNSS "
          f"error up to {_f(rec['figures'].get('common_gnss_error_max_h_m'))} m; the healthy RTL's own GNSS-based fix "
          f"up to {_f(base['figures'].get('fix_error_after_loss_max_h_m'))} m), "
          f"closest approach {_f(rec['min_separation_m'], '.1f')} m, "
          f"target detected in {_f(None if rec['detection_share'] is None else 100 * rec['detection_share'], '.0f')} % "
          f"of helper frames searched with it in view, fused-fix NEES {_f(rec['figures'].get('recovery_mean_nees_3dof'))} "
          f"(3 = honest; {_f(rec['figures'].get('recovery_mean_nees_frame_3dof'))} in the swarm's GNSS frame), "
          f"{_f(rec['figures'].get('helper_frames_dropped'), '.0f')} frame slots skipped, "
          f"{alarms} false GNSS alarm(s) on healthy receivers, {faults:.0f} service fault(s); {rec['outcome']} "
          f"(wall {rec['wall_s']:.0f} + {base['wall_s']:.0f} s)", flush=True)


def print_honesty(recoveries: list[dict]) -> None:
    """Not a goal: the median over runs of the lost drone's mean NEES while recovering, against the truth with
    its stated covariance and against the swarm's GNSS frame with the covariance it states for that frame (the
    one its decisions read); 3 is honest, more is over-confident."""
    def median(key: str) -> float:
        v = np.array([np.nan if r["figures"].get(key) is None else r["figures"][key] for r in recoveries], float)
        return float(np.nanmedian(v)) if np.isfinite(v).any() else math.nan

    print(f"  honesty (3 = honest): median NEES {median('recovery_mean_nees_3dof'):.2f} against the truth, "
          f"{median('recovery_mean_nees_frame_3dof'):.2f} in the swarm's GNSS frame")


def print_ratio_spread(records: list[dict], draws: int = 4000) -> None:
    """Not a goal: how far the landing ratio moves with which seeds were drawn. The seeds are resampled with
    replacement (each keeping its pair: recovery and healthy RTL in the same world) and the ratio of medians
    recomputed; prints its 5-95 % range and the share of draws within the goal."""
    pairs = np.array([(r["recovery"]["landing_error_m"], r["baseline"]["landing_error_m"]) for r in records
                      if r["recovery"]["landing_error_m"] is not None and r["baseline"]["landing_error_m"] is not None],
                     float)
    if len(pairs) < 3:
        return
    pick = np.random.default_rng(0).integers(0, len(pairs), size=(draws, len(pairs)))
    med = np.median(pairs[pick], axis=1)
    ratio = med[:, 0] / np.maximum(med[:, 1], 1e-9)
    lo, hi = np.percentile(ratio, [5, 95])
    print(f"  landing ratio over the seeds resampled ({draws} draws of {len(pairs)} paired seeds): 5-95 % "
          f"{lo:.2f}-{hi:.2f}x, within {GOAL_MEDIAN_RATIO}x in {100 * np.mean(ratio <= GOAL_MEDIAN_RATIO):.0f} % "
          f"(not a goal: how much {len(pairs)} seeds can tell)")


def judge(records: list[dict], runs_wanted: int) -> tuple[list[tuple[str, bool, str]], str]:
    """Goal lines (name, met, figures) over ``records`` and the headline."""
    rec = [r["recovery"] for r in records]
    n = len(rec)

    def vals(key: str, src=rec) -> np.ndarray:
        return np.array([np.nan if x[key] is None else x[key] for x in src], float)

    landing, healthy = vals("landing_error_m"), vals("landing_error_m", [r["baseline"] for r in records])
    home = int(np.sum(landing <= GOAL_HOME_M))
    med, med_h = float(np.nanmedian(landing)) if n else math.nan, float(np.nanmedian(healthy)) if n else math.nan
    ratio = med / med_h if med_h > 0 else math.inf
    first, err, sep = vals("loss_to_first_fused_fix_s"), vals("max_recovery_error_h_m"), vals("min_separation_m")
    det = vals("detection_share")
    err_frame = np.array([np.nan if r["figures"].get("max_recovery_error_gnss_frame_h_m") is None
                          else r["figures"]["max_recovery_error_gnss_frame_h_m"] for r in rec], float)
    worst_frame = np.nanmax(err_frame) if np.isfinite(err_frame).any() else math.nan
    # the reference, not a goal: the same drone's fix on its own healthy receiver over its return in the same runs
    err_healthy = np.array([np.nan if r["baseline"]["figures"].get("fix_error_after_loss_max_h_m") is None
                            else r["baseline"]["figures"]["fix_error_after_loss_max_h_m"] for r in records], float)
    worst_healthy = np.nanmax(err_healthy) if np.isfinite(err_healthy).any() else math.nan
    # a missing score (NaN: no fused fix at all, nothing recorded) counts as a miss
    goals = [
        (f">= {GOAL_HOME_SHARE:.0%} of runs land <= {GOAL_HOME_M:.0f} m from home",
         home >= math.ceil(GOAL_HOME_SHARE * n),
         f"{home} of {n}; the healthy-GNSS RTL of the same runs: {int(np.sum(healthy <= GOAL_HOME_M))} of {n}"),
        (f"median landing error <= {GOAL_MEDIAN_RATIO}x the healthy-GNSS RTL's", ratio <= GOAL_MEDIAN_RATIO,
         f"{med:.2f} m vs {med_h:.2f} m = {ratio:.2f}x"),
        (f"loss -> first fused fix <= {GOAL_FIRST_FIX_S:.0f} s in every run", bool(np.all(first <= GOAL_FIRST_FIX_S)),
         f"worst {np.nanmax(first) if np.isfinite(first).any() else math.nan:.1f} s, "
         f"{int(np.sum(first <= GOAL_FIRST_FIX_S))} of {n}"),
        (f"largest horizontal error while recovering <= {GOAL_RECOVERY_ERR_M:.0f} m in every run",
         bool(np.all(err <= GOAL_RECOVERY_ERR_M)),
         f"worst {np.nanmax(err) if np.isfinite(err).any() else math.nan:.2f} m, "
         f"{int(np.sum(err <= GOAL_RECOVERY_ERR_M))} of {n}; against the swarm's GNSS frame (truth + the GNSS "
         f"error every receiver shares, which no drone can observe): worst {worst_frame:.2f} m, "
         f"{int(np.sum(err_frame <= GOAL_RECOVERY_ERR_M))} of {n}; for reference, the same drone's own GNSS-based fix "
         f"on its healthy RTL of the same runs (from the loss to its landing): worst {worst_healthy:.2f} m, "
         f"{int(np.sum(err_healthy <= GOAL_RECOVERY_ERR_M))} of {int(np.sum(np.isfinite(err_healthy)))}"),
        (f"closest approach between drones >= {GOAL_SEPARATION_M:.0f} m in every run",
         bool(np.all(sep >= GOAL_SEPARATION_M)),
         f"closest {np.nanmin(sep) if np.isfinite(sep).any() else math.nan:.1f} m, "
         f"{int(np.sum(sep >= GOAL_SEPARATION_M))} of {n}"),
    ]
    complete = n >= runs_wanted
    all_met = complete and all(ok for _, ok, _ in goals)
    verdict = "all goals met" if all_met else (
        f"{sum(not ok for _, ok, _ in goals)} goal(s) missed" if complete else f"only {n} of {runs_wanted} seeds flown")
    headline = (f"recovery: {home}/{n} landed <= {GOAL_HOME_M:.0f} m from home, median landing {med:.2f} m "
                f"= {ratio:.2f}x healthy RTL ({med_h:.2f} m), worst first fix "
                f"{np.nanmax(first) if np.isfinite(first).any() else math.nan:.1f} s, worst recovery error "
                f"{np.nanmax(err) if np.isfinite(err).any() else math.nan:.2f} m ({worst_frame:.2f} m vs the swarm's "
                f"GNSS frame; healthy RTL's own fix up to {worst_healthy:.2f} m), closest approach "
                f"{np.nanmin(sep) if np.isfinite(sep).any() else math.nan:.1f} m, median detection "
                f"{100 * np.nanmedian(det) if np.isfinite(det).any() else math.nan:.0f} %: {verdict}")
    return goals, headline


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=parse_seeds, default=None,
                    help="seeds to fly now, e.g. 0-9 or 0,3,5 (default 0-9; --quick: 0-1)")
    ap.add_argument("--runs", type=int, default=10, help="seeds the goals are judged on (default 10)")
    ap.add_argument("--quick", action="store_true", help="two seeds, no files: a smoke test of the whole road")
    ap.add_argument("--gnss", choices=("realistic", "independent", "mild"), default="realistic",
                    help="the receivers' errors (skyfix.datasets.gnss_error): realistic (default), independent "
                         "(the stress case: nothing shared) or mild")
    ap.add_argument("--fusion-common-share", type=float, default=None, metavar="SHARE",
                    help="every node's fusion takes this share of a receiver's error as shared by the swarm "
                         "(default: skyfix serve's, 0.9; 0: each receiver's error its own, as before 2026-11-30)")
    ap.add_argument("--speed", type=float, default=None,
                    help="simulated seconds per wall second (default: RecoveryConfig's)")
    ap.add_argument("-o", "--output", type=Path, default=Path("benchmarks/out/recovery"),
                    help="folder for seed_<n>.json and each run's files (default benchmarks/out/recovery)")
    ap.add_argument("--no-files", action="store_true", help="write only seed_<n>.json, not the runs' logs and plots")
    ap.add_argument("--judge-only", action="store_true", help="fly nothing: judge the seeds already in -o")
    ap.add_argument("-v", "--verbose", action="store_true", help="print each run's stages")
    args = ap.parse_args(argv)
    # the services' warnings (a late observation refused, ...) are the runs' business: -v shows them
    logging.basicConfig(level=logging.WARNING if args.verbose else logging.ERROR, format="    %(name)s: %(message)s")
    if args.speed is not None and not (args.speed > 0 and math.isfinite(args.speed)):
        ap.error(f"--speed must be > 0, got {args.speed}")
    if args.fusion_common_share is not None and not 0.0 <= args.fusion_common_share < 1.0:
        ap.error(f"--fusion-common-share must be in [0, 1), got {args.fusion_common_share}")
    if args.quick:  # its own folder: quick runs never mix into the judged set
        args.no_files, args.output = True, args.output / "quick"
        args.seeds = args.seeds or [0, 1]
    seeds = args.seeds if args.seeds is not None else list(range(10))
    args.output.mkdir(parents=True, exist_ok=True)

    print(f"load average at start: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    if not args.judge_only:
        print(f"flying seeds {seeds} (recovery, then the healthy-GNSS RTL of the same drone):", flush=True)
        for seed in seeds:
            record = fly_seed(seed, args)
            (args.output / f"seed_{seed}.json").write_text(json.dumps(record, indent=1))
            print_run(record)
    records = sorted((json.loads(p.read_text()) for p in args.output.glob("seed_*.json")), key=lambda r: r["seed"])
    other = [r["seed"] for r in records if r.get("gnss", "mild") != args.gnss
             or r.get("fusion_common_share") != args.fusion_common_share]
    if other:  # never judge a mix of error models, or of fusion models
        print(f"seeds {other} in {args.output} were flown with another --gnss model than {args.gnss} or another "
              f"--fusion-common-share than {args.fusion_common_share}: not judged")
        records = [r for r in records if r["seed"] not in other]
    revisions = sorted({r.get("revision", "unknown") for r in records})
    print(f"all seeds in {args.output} ({len(records)}, gnss {args.gnss}, revision(s) {', '.join(revisions)}):")
    dirty = sorted({f for r in records for f in r.get("uncommitted", [])})
    if dirty:
        print(f"  flown with uncommitted changes to: {', '.join(dirty)}")
    for r in records:
        print_run(r)
    goals, headline = judge(records, 2 if args.quick else args.runs)
    for name, ok, figures in goals:
        print(f"  goal {name}: {'MET' if ok else 'NOT MET'} ({figures})")
    print_honesty([r["recovery"] for r in records])
    print_ratio_spread(records)
    print(f"load average at end: {os.getloadavg()[0]:.1f}")
    share = "" if args.fusion_common_share is None else f", fusion common share {args.fusion_common_share:g}"
    print(f"{headline} [gnss {args.gnss}{share}, revision {', '.join(revisions)}]")
    if len(records) < (2 if args.quick else args.runs):
        return 2
    return 0 if all(ok for _, ok, _ in goals) else 1


if __name__ == "__main__":
    sys.exit(main())
