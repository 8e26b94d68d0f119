"""``skyfix fusion ...``: replay a measurement log through the fusion engine.

- ``skyfix fusion replay LOG -o OUT_DIR``: estimates.csv, tracks.geojson and
  trajectory.png (truth if the log has it, GNSS, fused track, 95 % ellipses).
"""

from __future__ import annotations

import argparse
import csv
import json
import logging
import math
from pathlib import Path

log = logging.getLogger(__name__)

DESCRIPTION = """\
Fusion core: replay what an engine was given.

  skyfix fusion replay LOG -o OUT_DIR
      run a measurement log (JSON lines, written by FusionEngine(log_path=...) or the
      onboard service) through a fresh engine built from the log's header; the
      estimates are the same as when it was recorded. Writes
        OUT_DIR/estimates.csv    one row per drone per smoother update
        OUT_DIR/tracks.geojson   fused track of each drone (LineString, WGS84)
        OUT_DIR/trajectory.png   map: truth (if logged), GNSS, fused track, 95 % ellipses,
                                 GNSS lost/rejected in red; error over time if truth is logged

  A log to try: skyfix datasets fusion-log survey.jsonl
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("fusion", help="fusion core: replay a measurement log (CSV, GeoJSON, PNG)",
                              description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="fusion_command", metavar="COMMAND", title="commands")
    r = sub.add_parser("replay", help="run a measurement log through the engine; write CSV, GeoJSON and a PNG",
                       description="Replay a skyfix.fusion.log measurement log (JSON lines) through a new "
                                   "FusionEngine with the recorded origin, lag and configuration.")
    r.add_argument("log", type=Path, help="measurement log: JSON lines (format skyfix.fusion.log) or the .mcap log of skyfix serve")
    r.add_argument("-o", "--out", type=Path, default=None,
                   help="output directory (default: LOG's name without extension + '_replay')")
    r.add_argument("--drone", action="append", default=None, metavar="ID",
                   help="plot only this drone (repeatable; the CSV and GeoJSON keep every drone)")
    r.add_argument("--every", type=int, default=1, metavar="N",
                   help="take estimates after every N-th recorded update (default 1)")
    r.add_argument("--ellipse-every-s", type=float, default=10.0, metavar="S",
                   help="draw a 95 %% ellipse every S seconds of each track (default 10)")
    r.set_defaults(func=run_replay)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])


def run_replay(args: argparse.Namespace) -> int:
    from skyfix import validate
    from skyfix.errors import InputError
    from skyfix.fusion.plot import plot_replay
    from skyfix.fusion.replay import horizontal_errors_m, replay

    validate.integer_in("--every", args.every, 1)
    validate.positive_scalar("--ellipse-every-s", args.ellipse_every_s)
    out = args.out if args.out is not None else args.log.with_name(args.log.stem + "_replay")
    if out.exists() and not out.is_dir():
        raise InputError(f"-o {out}: exists and is not a directory")
    result = replay(args.log, every_update=args.every)
    if not result.fused:
        raise InputError(f"{args.log}: no drone was ever localised ({result.n_records} records)")
    unknown = sorted(set(args.drone or ()) - set(result.fused))
    if unknown:
        raise InputError(f"--drone {' '.join(unknown)}: no such drone localised in {args.log} "
                         f"(drones: {', '.join(sorted(result.fused))})")
    out.mkdir(parents=True, exist_ok=True)
    csv_path = out / "estimates.csv"
    with open(csv_path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["time_s", "drone_id", "lat_deg", "lon_deg", "alt_m", "east_m", "north_m", "up_m",
                    "sigma_east_m", "sigma_north_m", "sigma_up_m", "gnss_state", "sources"])
        for est in result.estimates:
            sig = [math.sqrt(max(v, 0.0)) for v in est.cov_enu_m2.diagonal()]
            gnss = est.health.get("gnss")
            w.writerow([f"{est.time_s:.3f}", est.drone_id, f"{est.lat_deg:.9f}", f"{est.lon_deg:.9f}",
                        f"{est.alt_m:.3f}", *(f"{v:.3f}" for v in est.enu_m), *(f"{v:.3f}" for v in sig),
                        gnss.state.value if gnss else "none", " ".join(est.sources)])
    features = []
    for drone, track in sorted(result.fused.items()):
        coords = [[round(lon, 9), round(lat, 9), round(alt, 3)] for lat, lon, alt in track.lla]
        features.append({"type": "Feature",
                         "geometry": {"type": "LineString" if len(coords) > 1 else "Point",
                                      "coordinates": coords if len(coords) > 1 else coords[0]},
                         "properties": {"drone_id": drone, "n_estimates": len(coords),
                                        "start_time_s": track.time_s[0], "end_time_s": track.time_s[-1]}})
    geojson_path = out / "tracks.geojson"
    geojson_path.write_text(json.dumps({"type": "FeatureCollection", "features": features}))
    png_path = plot_replay(result, out / "trajectory.png", drones=args.drone, ellipse_every_s=args.ellipse_every_s)
    print(f"replayed {result.n_records} records ({result.n_rejected_inputs} refused) for "
          f"{len(result.fused)} drone(s): {', '.join(sorted(result.fused))}")
    for drone, track in sorted(result.fused.items()):
        line = f"  {drone}: {len(track.time_s)} estimates, {track.time_s[0]:.1f}-{track.time_s[-1]:.1f} s"
        truth = result.truth_enu_m.get(drone)
        if truth:
            err = horizontal_errors_m(track, truth)
            line += f", horizontal error vs truth: RMSE {math.sqrt(float((err**2).mean())):.2f} m, max {err.max():.2f} m"
        print(line)
    print(f"wrote {csv_path}, {geojson_path}, {png_path}")
    return 0

