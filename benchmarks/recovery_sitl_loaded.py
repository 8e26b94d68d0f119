"""The ArduPilot SITL recovery flow under load: the same flight alone, then K copies at once.

Each flight is exactly what ``tests/crps/test_recovery_sitl.py`` flies: ArduPilot Copter SITL
(``../shared/sitl``) surveys between two simulated helpers, loses its receiver (SIM_GPS1_ENABLE 0)
and returns home on the position skyfix fuses from the helpers' camera frames. Baseline: the flight
alone. Loaded: K flights at once, each in its own process with its own SITL (on two cores, two at
once is what two copies of the test suite do when they reach this test together). Every flight is
judged by the test's own goals: home (landed and disarmed) within 3 m, first fused fix <= 15 s,
largest horizontal error while recovering <= 5 m, separation >= 10 m, target detected in > 30 % of
the helpers' frames. Also printed: the helpers' observation latency (p90, exposure -> observation
ready), the loaded over the alone one. ``--keep DIR`` keeps each flight's outputs and SITL's own
dataflash log (``DIR/flightN/sitl*/logs``; read it with pymavlink's DFReader: MODE, XKF1, ATT, CTUN).

``--blind-s S``: every helper's gimbal looks 90 deg away for S s from the loss (fog, glare, a helper pointed
wrong: nobody sees the lost drone), in every flight. The requester holds unobserved: it must not fly away. Then
the goals are safety goals: landed (home or not; airborne at the end fails) within BLIND_MAX_FROM_HOME_M of home
(the survey is within 60 m of home; a failsafe landing from 40 m drifts with the wind for ~30 s), and ``--rounds 0``
flies the alone flight only. Before the hold was bounded (constant injected position) such flights ended 100-620 m
away, airborne, the copter at up to 30 deg of pitch.

Exit 1 when a loaded flight misses a goal (or the alone one does). The last line is the headline.
About 2.5 minutes per round of flights; skipped (exit 0, said) where the firmware is absent.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HOME = (46.52, 6.63, 372.0, 0.0)  # the test's: lat, lon (deg), alt AMSL (m), heading (deg)
BLIND_MAX_FROM_HOME_M = 150.0
GOALS = {"landing_error_m": 3.0, "first_fix_s": 15.0, "max_error_m": 5.0, "min_separation_m": 10.0,
         "detection_share": 0.3}


def fly(out_dir: Path, blind_s: float | None = None) -> dict:
    """One flight as the test flies it (speed 1), helpers blind ``blind_s`` from the loss if given; its figures."""
    from skyfix.crps.recovery import RecoveryConfig, run_recovery
    from skyfix.datasets import sitl
    from skyfix.drivers.injection import ARDUPILOT_INJECTED_GPS2_PARAMS

    params = {**ARDUPILOT_INJECTED_GPS2_PARAMS, "WPNAV_SPEED": 500}
    with sitl.SitlFleet(1, speedup=1.0, homes=[HOME], params=params, workdir=out_dir) as fleet:
        fleet[0].release_start_wait()
        cfg = RecoveryConfig(seed=0, speed=1.0, lost_vehicle_url=fleet[0].url, output=out_dir / "recovery",
                             lost_vehicle_truth_url=fleet[0].url_secondary, lost_vehicle_home=HOME[:3],
                             loss_time_s=12.0, max_after_loss_s=100.0, helpers_blind_s=blind_s)
        r = run_recovery(cfg)
    return {"outcome": r.outcome, "landing_error_m": r.landing_error_m, "first_fix_s": r.loss_to_first_fused_fix_s,
            "max_error_m": r.max_recovery_error_h_m, "min_separation_m": r.min_separation_m,
            "detection_share": r.detection_share,
            "latency_p90_s": r.figures.get("helper_obs_latency_p90_s", math.nan),
            "backstop_disarm": any("disarming" in what for _, what in r.timeline), "blind_s": blind_s}


def missed(f: dict) -> list[str]:
    """The test's goals this flight misses (a blind flight: the safety goals)."""
    if f.get("blind_s") is not None:
        out = [] if f["outcome"] in ("home", "landed_elsewhere") else [f"outcome {f['outcome']}"]
        if not f["landing_error_m"] <= BLIND_MAX_FROM_HOME_M:
            out.append(f"landing_error_m {f['landing_error_m']:.1f} > {BLIND_MAX_FROM_HOME_M:g}")
        return out
    out = [] if f["outcome"] == "home" else [f"outcome {f['outcome']}"]
    for key in ("landing_error_m", "first_fix_s", "max_error_m"):
        if not f[key] <= GOALS[key]:
            out.append(f"{key} {f[key]:.2f} > {GOALS[key]:g}")
    if not f["min_separation_m"] >= GOALS["min_separation_m"]:
        out.append(f"separation {f['min_separation_m']:.1f} m")
    if not f["detection_share"] > GOALS["detection_share"]:
        out.append(f"detected {100 * f['detection_share']:.0f} %")
    return out


def line(name: str, f: dict) -> str:
    fails = missed(f)
    return (f"  {name}: {f['outcome']}, landed {f['landing_error_m']:.2f} m from home, first fix {f['first_fix_s']:.1f} s, "
            f"max error {f['max_error_m']:.2f} m, separation {f['min_separation_m']:.1f} m, detected "
            f"{100 * f['detection_share']:.0f} %, helper latency p90 {f['latency_p90_s']:.2f} s"
            f"{', disarmed by the backstop' if f['backstop_disarm'] else ''}: "
            f"{'pass' if not fails else 'FAIL (' + '; '.join(fails) + ')'}")


def at_once(k: int, root: Path, blind_s: float | None = None) -> list[dict]:
    """K flights at once, each in a process of its own (this script with --one)."""
    procs = []
    for n in range(k):
        d = root / f"flight{n + 1}"
        d.mkdir(parents=True, exist_ok=True)
        blind = [] if blind_s is None else ["--blind-s", str(blind_s)]
        with open(d / "stderr.log", "w") as err:  # the child keeps its own handle
            procs.append((d, subprocess.Popen([sys.executable, __file__, "--one", str(d), *blind],
                                              stdout=subprocess.PIPE, stderr=err, text=True)))
    out = []
    for d, p in procs:
        stdout, _ = p.communicate()
        if p.returncode != 0 or not stdout.strip():
            tail = (d / "stderr.log").read_text(errors="replace").strip().splitlines()[-3:]
            raise SystemExit(f"flight in {d} failed to run (exit {p.returncode}): " + " | ".join(tail))
        out.append(json.loads(stdout.strip().splitlines()[-1]))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--at-once", type=int, default=2, help="flights at once in the loaded round (default 2)")
    ap.add_argument("--rounds", type=int, default=1, help="loaded rounds (default 1)")
    ap.add_argument("--keep", type=Path, default=None, help="keep every flight's outputs and SITL logs here")
    ap.add_argument("--burners", type=int, default=0,
                    help="processes spinning one core each beside the loaded rounds (default 0): a busier companion")
    ap.add_argument("--blind-s", type=float, default=None,
                    help="every helper's camera looks away this long from the loss; safety goals (see above)")
    ap.add_argument("--one", type=Path, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.one is not None:
        print(json.dumps(fly(args.one, args.blind_s)))
        return 0
    from skyfix.datasets import sitl

    if sitl.missing_reason():
        print(f"recovery sitl loaded: skipped, {sitl.missing_reason()}")
        return 0
    if not (1 <= args.at_once <= 4 and (0 if args.blind_s is not None else 1) <= args.rounds <= 20):
        ap.error("--at-once must be 1..4 and --rounds 1..20 (0 with --blind-s)")
    if args.blind_s is not None and not args.blind_s > 0:
        ap.error("--blind-s must be > 0")
    root = args.keep or Path(tempfile.mkdtemp(prefix="skyfix-sitl-loaded-"))
    load0 = os.getloadavg()[0]
    print(f"{time.strftime('%Y-%m-%d %H:%M', time.gmtime())} UTC, load {load0:.1f} on {os.cpu_count()} cores")
    alone = at_once(1, root / "alone", args.blind_s)[0]
    print(line("alone", alone))
    loaded = []
    burners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(max(0, args.burners))]
    try:
        rounds = [at_once(args.at_once, root / f"round{r + 1}", args.blind_s) for r in range(args.rounds)]
    finally:
        for b in burners:
            b.kill()
    for r, flights in enumerate(rounds):
        for n, f in enumerate(flights):
            print(line(f"round {r + 1} flight {n + 1}", f))
        loaded += flights
    passed = sum(not missed(f) for f in loaded)
    lat = [f["latency_p90_s"] for f in loaded if math.isfinite(f["latency_p90_s"])]
    ratio = (max(lat) / alone["latency_p90_s"]) if lat and alone["latency_p90_s"] > 0 else math.nan
    ok = passed == len(loaded) and not missed(alone)
    blind = f", helpers blind {args.blind_s:g} s from the loss (safety goals)" if args.blind_s is not None else ""
    rounds_text = (f"{passed} of {len(loaded)} flights {args.at_once} at once" if loaded else "no loaded round")
    print(f"recovery sitl loaded: {rounds_text}"
          f"{f' beside {args.burners} burner(s)' if args.burners else ''}{' passed the goals' if loaded else ''} "
          f"(alone: {'pass' if not missed(alone) else 'FAIL'}), helper latency p90 up to {ratio:.1f}x the alone "
          f"flight's {alone['latency_p90_s']:.2f} s, load {load0:.1f}-{os.getloadavg()[0]:.1f}"
          f"{blind}{'' if ok else ': goal missed'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
