"""``skyfix plan corners|polygon|extend|handoff``: survey planning on the command line.

Heavy imports happen inside the command functions so ``skyfix --help`` stays fast.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from skyfix.errors import InputError
from skyfix.mapping.cli_args import flags_named, parse_drone, parse_latlon, parse_size

__all__ = ["register_plan"]


def _polygon(text: str) -> list[tuple[float, float]]:
    """--polygon: a GeoJSON file (its first Polygon) or 'lat,lon;lat,lon;...'."""
    from skyfix.jsonfile import read_json

    path = Path(text)
    if path.is_file() or path.suffix.lower() in (".geojson", ".json"):
        data = read_json(path, "--polygon file", missing=InputError)
        features = data.get("features", [data]) if isinstance(data, dict) else []
        for feat in features:
            geom = feat.get("geometry", feat) if isinstance(feat, dict) else None
            if isinstance(geom, dict) and geom.get("type") == "Polygon":
                try:
                    return [(float(lat), float(lon)) for lon, lat, *_ in geom["coordinates"][0][:-1]]
                except (KeyError, IndexError, TypeError, ValueError):
                    raise InputError(f"--polygon file {text}: the Polygon's coordinates are not "
                                     "[[lon, lat], ...] rings") from None
        raise InputError(f"--polygon file {text}: no GeoJSON Polygon geometry found")
    try:
        return [parse_latlon(p) for p in text.split(";") if p.strip()]
    except argparse.ArgumentTypeError:
        raise InputError(f"--polygon {text!r} is neither a GeoJSON file nor 'lat,lon;lat,lon;...'") from None


def _drones_dict(pairs) -> dict:
    return {name: pos for name, pos in (pairs or [])}


def _finish_plan(plan, args, parts=None, extra: dict | None = None) -> int:
    from skyfix.mapping.export import write_all
    from skyfix.mapping.plan_io import save_plan
    from skyfix.mapping.split import split_survey

    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    drones = _drones_dict(getattr(args, "drone", None))
    if parts is None and len(drones) > 1:
        parts = split_survey(plan, drones)
    save_plan(out / "plan.json", plan)
    homes = {name: (*pos, 0.0) for name, pos in {**drones, **_drones_dict(getattr(args, "available", None))}.items()}
    written = write_all(out, parts or plan, home_latlon_alt=homes, speed_mps=getattr(args, "speed", None))
    summary = {"kind": plan.kind, "waypoints": plan.n_waypoints, "path_length_m": plan.path_length_m,
               "step_m": plan.step_m, "trigger_distance_m": plan.trigger_distance_m, "files": written, **(extra or {})}
    if parts:
        summary["parts"] = [{"drone_id": p.drone_id, "waypoints": p.plan.n_waypoints, "length_m": p.length_m,
                             "first_index": p.first_index, "approach_m": p.approach_m} for p in parts]
    if plan.kind == "lines" and not (extra or {}).get("handed_to"):
        from skyfix.mapping.coverage import verify_coverage

        cov = verify_coverage(plan)
        summary["coverage"] = {"area_m2": cov.area_m2, "uncovered_m2": cov.uncovered_m2, "photos": cov.n_photos,
                               "forward_overlap_min": cov.forward_overlap_min,
                               "side_overlap_min": cov.side_overlap_min}
    (out / "plan_summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    sys.stdout.write(f"{plan.kind} plan: {plan.n_waypoints} waypoints, {plan.path_length_m:.0f} m"
                     + (f", {len(parts)} drones" if parts else "") + f" -> {out}\n")
    return 0


def _plan_corners(args: argparse.Namespace) -> int:
    from skyfix.mapping.survey import plan_three_corners

    plan = plan_three_corners(*args.corners, args.step, args.alt, hold_s=args.hold)
    return _finish_plan(plan, args)


def _camera_from_args(args: argparse.Namespace):
    from skyfix.camera import Camera
    from skyfix.camera_io import load_camera

    if args.camera:
        return load_camera(args.camera)
    if args.hfov and args.size:
        return Camera.from_fov(*args.size, args.hfov)
    raise InputError("give --camera camera.json or --hfov DEG with --size WIDTHxHEIGHT")


def _plan_polygon(args: argparse.Namespace) -> int:
    from skyfix.mapping.survey import plan_polygon

    plan = plan_polygon(_polygon(args.polygon), _camera_from_args(args), args.alt, args.forward, args.side,
                        heading_deg=args.heading, turnaround_m=args.turnaround)
    return _finish_plan(plan, args)


def _plan_extend(args: argparse.Namespace) -> int:
    from skyfix.mapping.plan_io import load_plan
    from skyfix.mapping.survey import extend_survey

    old = load_plan(args.plan)
    plan = extend_survey(old, args.alarm, args.joining, growth_per_drone=args.growth)
    return _finish_plan(plan, args, extra={"extended_from_waypoints": old.n_waypoints})


def _plan_handoff(args: argparse.Namespace) -> int:
    from skyfix.mapping.plan_io import load_plan
    from skyfix.mapping.split import handoff

    plan = load_plan(args.plan)
    part = handoff(plan, args.next_index, _drones_dict(args.available), stopped_at_latlon=args.stopped_at)
    args.drone = None
    return _finish_plan(part.plan, args, parts=[part], extra={"handed_to": part.drone_id})


def register_plan(subparsers: argparse._SubParsersAction) -> None:
    """Add ``plan`` and its subcommands to the ``skyfix`` command line."""
    plan = subparsers.add_parser("plan", help="survey planning: grids, photo lines, extension, split, handoff",
                                 description="Plan coverage surveys and write plan.json, plan.geojson, plan.kml, "
                                             "plan.png, plan_summary.json and one QGC WPL mission file per drone "
                                             "(MISSION_ITEM_INT content) into --output.")
    plan_sub = plan.add_subparsers(dest="plan_command", metavar="SUBCOMMAND", title="subcommands")
    plan.set_defaults(func=lambda a: (plan.print_help(), 2)[1])
    _add_corners(plan_sub)
    _add_polygon(plan_sub)
    _add_extend(plan_sub)
    _add_handoff(plan_sub)


def _common(sp: argparse.ArgumentParser, drones: bool = True) -> None:
    """Options every plan subcommand takes."""
    sp.add_argument("-o", "--output", required=True, help="output folder (created)")
    sp.add_argument("--speed", type=float, default=None, help="ground speed set in the mission, m/s")
    if drones:
        sp.add_argument("--drone", action="append", type=parse_drone, metavar="ID=LAT,LON",
                        help="a drone and its position; with two or more the plan is split among them")


def _add_corners(plan_sub: argparse._SubParsersAction) -> None:
    """``skyfix plan corners``."""
    fmt = argparse.ArgumentDefaultsHelpFormatter
    p = plan_sub.add_parser("corners", formatter_class=fmt, help="station grid from three corners",
                            description="The source platform's grid: corners A B C span v = B - A and w = C - A; "
                                        "waypoints every --step metres along both, boustrophedon order.")
    p.add_argument("--corners", nargs=3, type=parse_latlon, required=True, metavar="LAT,LON", help="corners A B C")
    p.add_argument("--step", type=float, required=True, help="distance between waypoints, metres")
    p.add_argument("--alt", type=float, required=True, help="flight altitude above take-off, metres")
    p.add_argument("--hold", type=float, default=0.0, help="hold time at each waypoint, seconds")
    _common(p)
    p.set_defaults(func=flags_named(_plan_corners))


def _add_polygon(plan_sub: argparse._SubParsersAction) -> None:
    """``skyfix plan polygon``."""
    fmt = argparse.ArgumentDefaultsHelpFormatter
    p = plan_sub.add_parser("polygon", formatter_class=fmt, help="photo survey lines over a polygon",
                            description="Parallel photo lines over a polygon: spacing and camera trigger "
                                        "distance from the nadir footprint and the requested overlaps; coverage "
                                        "is verified on the footprints and reported in plan_summary.json.")
    p.add_argument("--polygon", required=True, help="GeoJSON file with a Polygon, or 'lat,lon;lat,lon;...'")
    p.add_argument("--camera", default=None, help="camera JSON (corrected camera, e.g. OUT_DIR/camera.json)")
    p.add_argument("--hfov", type=float, default=None, help="horizontal field of view, degrees (instead of --camera)")
    p.add_argument("--size", type=parse_size, default=None, metavar="WxH", help="image size with --hfov")
    p.add_argument("--alt", type=float, required=True, help="flight altitude above ground, metres")
    p.add_argument("--forward", type=float, default=0.75, help="forward overlap fraction [0, 1)")
    p.add_argument("--side", type=float, default=0.65, help="side overlap fraction [0, 1)")
    p.add_argument("--heading", type=float, default=None, help="line direction, degrees from north "
                                                               "(default: along the area's long side)")
    p.add_argument("--turnaround", type=float, default=None, help="run-in/run-out beyond the photos, metres "
                                                                  "(default: half the along-track footprint)")
    _common(p)
    p.set_defaults(func=flags_named(_plan_polygon))


def _add_extend(plan_sub: argparse._SubParsersAction) -> None:
    """``skyfix plan extend``."""
    fmt = argparse.ArgumentDefaultsHelpFormatter
    p = plan_sub.add_parser("extend", formatter_class=fmt, help="re-centre a plan on an alarm and grow it",
                            description="Rebuild PLAN with the same shape and step, centred on --alarm, its area "
                                        "grown by --growth per joining drone (source platform: 50 %%).")
    p.add_argument("plan", metavar="PLAN.json", help="the plan to extend (written by skyfix plan corners|polygon)")
    p.add_argument("--alarm", type=parse_latlon, required=True, metavar="LAT,LON", help="where the alarm was raised")
    p.add_argument("--joining", type=int, required=True, help="number of drones joining")
    p.add_argument("--growth", type=float, default=0.5, help="area growth per joining drone (fraction)")
    _common(p)
    p.set_defaults(func=flags_named(_plan_extend))


def _add_handoff(plan_sub: argparse._SubParsersAction) -> None:
    """``skyfix plan handoff``."""
    fmt = argparse.ArgumentDefaultsHelpFormatter
    p = plan_sub.add_parser("handoff", formatter_class=fmt, help="give a failing drone's remaining path away",
                            description="The waypoints of PLAN from --next-index on (optionally starting at "
                                        "--stopped-at) go to the nearest --available drone.")
    p.add_argument("plan", metavar="PLAN.json", help="the failing drone's plan")
    p.add_argument("--next-index", type=int, required=True, help="first waypoint the failing drone did not reach")
    p.add_argument("--stopped-at", type=parse_latlon, default=None, metavar="LAT,LON", help="where it stopped")
    p.add_argument("--available", action="append", type=parse_drone, required=True, metavar="ID=LAT,LON",
                   help="a drone that can take over (repeat)")
    _common(p, drones=False)
    p.set_defaults(func=flags_named(_plan_handoff))
