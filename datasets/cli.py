"""``skyfix datasets ...``: synthetic data to try the library on.

- ``skyfix datasets fusion-log OUT.jsonl``: the three-drone survey of
  :mod:`skyfix.datasets.fusion_scenario` run through a recording FusionEngine, with
  ground truth, ready for ``skyfix fusion replay``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

DESCRIPTION = """\
Synthetic data sets (exact ground truth included).

  skyfix datasets fusion-log OUT.jsonl [--duration-s 600] [--seed 0]
      three drones survey a field (A flies a lawnmower, B and C follow it 30-80 m away
      and observe it with their cameras); GNSS 5 Hz, autopilot velocity 10 Hz with a
      drifting bias, barometer, relative observations 5 Hz. By default A loses GNSS for
      120 s from t = 200 s and B's GNSS is spoofed 50 m away for 30 s from t = 420 s.
      Everything is fed to a FusionEngine that records the measurement log OUT.jsonl
      (with truth). Then: skyfix fusion replay OUT.jsonl

  skyfix datasets thermal-flight OUT_DIR [--mountain orbit|pass|calibration]
      a synthetic thermal flight (frames, poses.csv, camera.json, truth.json; dem.tif
      over a mountain) for skyfix thermal locate
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("datasets", help="synthetic data sets with ground truth (e.g. a fusion log)",
                              description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="datasets_command", metavar="COMMAND", title="commands")
    f = sub.add_parser("fusion-log", help="simulate the 3-drone survey and record a fusion measurement log",
                       description="Simulate the three-drone survey (GNSS outage and spoof included unless "
                                   "disabled) and record every input of a FusionEngine, plus truth, to a "
                                   "JSON-lines measurement log for 'skyfix fusion replay'.")
    f.add_argument("out", type=Path, help="log file to create (.jsonl); must not exist")
    f.add_argument("--duration-s", type=float, default=600.0, help="simulated seconds (default 600)")
    f.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    f.add_argument("--lag-s", type=float, default=2.0, help="the engine's fixed lag, seconds (default 2)")
    f.add_argument("--no-outage", action="store_true", help="no GNSS outage of drone A")
    f.add_argument("--no-spoof", action="store_true", help="no spoofed GNSS on drone B")
    f.add_argument("--outage-mode", choices=("silent", "no_fix"), default="silent",
                   help="during the outage the receiver is silent, or reports fix type 1 (default silent)")
    f.set_defaults(func=run_fusion_log)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])
    from skyfix.datasets import thermal_cli  # `skyfix datasets thermal-flight`: thermal flights
    from skyfix.datasets.sim import cli as sim_cli  # `skyfix sim`: the MAVLink simulator harness

    thermal_cli.register(sub)

    sim_cli.register(subparsers)


def run_fusion_log(args: argparse.Namespace) -> int:
    import numpy as np

    from skyfix.datasets.fusion_scenario import feed, survey_scenario
    from skyfix.errors import InputError
    from skyfix.fusion import FusionEngine
    from skyfix.progress import progress

    if args.out.exists():
        raise InputError(f"{args.out} exists; choose a new file (logs are append-only)")
    duration = float(args.duration_s)
    outage = None if args.no_outage or duration <= 330 else ("A", 200.0, 120.0)
    spoof = None if args.no_spoof or duration <= 460 else ("B", 420.0, 30.0, 50.0)
    scenario = survey_scenario(duration, seed=args.seed, outage=outage, outage_mode=args.outage_mode, spoof=spoof)
    events = scenario.events()
    pending = next(events, None)
    with FusionEngine(scenario.origin, lag_s=args.lag_s, log_path=args.out) as engine:
        for tick in progress(np.arange(1, int(round(duration * 10)) + 1) / 10.0, desc="simulate", unit="tick"):
            while pending is not None and pending.arrival_s <= tick + 1e-9:
                feed(engine, pending)
                pending = next(events, None)
            engine.update()
            if round(tick * 10) % 5 == 0:
                for drone in scenario.drone_ids:
                    lat, lon, alt = scenario.truth_geodetic(drone, tick)[0]
                    engine.record_truth(drone, tick, lat, lon, alt)
    faults = [f"GNSS outage of A 200-320 s ({args.outage_mode})" if outage else None,
              "B spoofed 50 m 420-450 s" if spoof else None]
    print(f"wrote {args.out}: {duration:g} s, {scenario.n_events} measurements, drones "
          f"{', '.join(scenario.drone_ids)}; faults: {', '.join(f for f in faults if f) or 'none'}")
    print(f"next: skyfix fusion replay {args.out}")
    return 0
