"""``skyfix lens ...`` and ``skyfix plan ...``: lens correction/calibration and survey planning.

The photo-to-model pipeline (``skyfix map``) registers its own command next to these.
Heavy imports happen inside the command functions so ``skyfix --help`` stays fast.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from skyfix.errors import InputError

log = logging.getLogger("skyfix.mapping")


# --------------------------------------------------------------------------- parsing helpers

#: Library parameter names -> the flags a user typed, so errors name what the user can change.
FLAG_NAMES = {"step_m": "--step", "altitude_m": "--alt", "hold_s": "--hold", "forward_overlap": "--forward",
              "side_overlap": "--side", "heading_deg": "--heading", "turnaround_m": "--turnaround",
              "joining_drones": "--joining", "growth_per_drone": "--growth", "alarm_latlon": "--alarm",
              "next_index": "--next-index", "stopped_at_latlon": "--stopped-at", "speed_mps": "--speed",
              "jpeg_quality": "--quality", "workers": "--workers", "resolution_cm": "--resolution-cm",
              "dsm_resolution_m": "--dsm-resolution-m", "dense_scale": "--dense-scale",
              "max_ortho_mpx": "--max-ortho-mpx", "max_image_size_px": "--max-image-size",
              "max_features": "--max-features"}


def flags_named(func):
    """Wrap a command function: a skyfix error whose message names library parameters
    (``step_m``) is raised again, same type, naming the command's flags (``--step``)."""
    import functools
    import re

    from skyfix.errors import SkyfixError

    pattern = re.compile(r"\b(" + "|".join(FLAG_NAMES) + r")\b")

    @functools.wraps(func)
    def run(args: argparse.Namespace) -> int:
        try:
            return func(args)
        except SkyfixError as exc:
            text = pattern.sub(lambda m: FLAG_NAMES[m.group(1)], str(exc))
            if text == str(exc):
                raise
            try:
                renamed = type(exc)(text)
            except TypeError:
                raise exc from None
            raise renamed from exc

    return run



def _latlon(text: str) -> tuple[float, float]:
    """'lat,lon' -> (lat_deg, lon_deg)."""
    try:
        lat, lon = (float(p) for p in text.replace(" ", "").split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected 'lat,lon' in degrees, got {text!r}") from None
    return lat, lon


def _drone(text: str) -> tuple[str, tuple[float, float]]:
    """'ID=lat,lon' -> (id, (lat, lon))."""
    if "=" not in text:
        raise argparse.ArgumentTypeError(f"expected 'ID=lat,lon', got {text!r}")
    name, pos = text.split("=", 1)
    return name.strip(), _latlon(pos)


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(p) for p in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT in pixels, got {text!r}") from None
    return w, h


def _fraction(text: str) -> float:
    return float(text)


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
        return [_latlon(p) for p in text.split(";") if p.strip()]
    except argparse.ArgumentTypeError:
        raise InputError(f"--polygon {text!r} is neither a GeoJSON file nor 'lat,lon;lat,lon;...'") from None


def _drones_dict(pairs) -> dict:
    return {name: pos for name, pos in (pairs or [])}


# --------------------------------------------------------------------------- lens


def _lens_correct(args: argparse.Namespace) -> int:
    from skyfix.camera_io import load_camera
    from skyfix.mapping.batch import CorrectionSpec, correct_photos, list_photos
    from skyfix.mapping.lens import parse_barrel

    if (args.barrel is None) == (args.calibration is None):
        raise InputError("give exactly one of --barrel 'a b c [d]' or --calibration cal.json")
    spec = CorrectionSpec(barrel=parse_barrel(args.barrel) if args.barrel else None,
                          camera=load_camera(args.calibration) if args.calibration else None,
                          crop=args.crop, jpeg_quality=args.quality, require_exif=not args.allow_missing_exif,
                          interpolation=args.interpolation)
    photos = list_photos(args.in_dir)
    if not photos:
        raise InputError(f"no .jpg/.jpeg photos in {args.in_dir}")
    quiet = getattr(args, "quiet", False)
    report = correct_photos(photos, args.out_dir, spec, workers=args.workers, backend=args.backend,
                            device=args.device, progress=not quiet)
    out = Path(args.out_dir)
    summary = report.to_dict()
    summary["cameras"] = [json.loads(c) for c in summary["cameras"]]
    (out / "correction_report.json").write_text(json.dumps(summary, indent=2) + "\n")
    if report.written:
        cams = summary["cameras"]
        (out / "camera.json").write_text(json.dumps(
            {"model": "pinhole", "note": "intrinsics of the corrected photos (no distortion left)",
             **(cams[0] if len(cams) == 1 else {"cameras": cams})}, indent=2) + "\n")
        _write_preview(photos[0], Path(report.written[0].output), out / "correction_preview.png")
    sys.stdout.write(f"corrected {len(report.written)} of {len(photos)} photos in {report.seconds:.1f} s "
                     f"-> {out}\n")
    for bad in report.skipped:
        sys.stdout.write(f"skipped {bad.source}: {bad.error}\n")
    return 0 if report.written else 1


def _write_preview(raw_path: Path, corrected_path: Path, png_path: Path) -> None:
    """Side-by-side raw | corrected with a grid, downscaled, so straight lines can be checked."""
    import cv2
    import numpy as np

    raw, cor = (cv2.imread(str(p), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION) for p in (raw_path, corrected_path))
    if raw is None or cor is None:
        return
    h = 480
    tiles = []
    for img in (raw, cor):
        small = cv2.resize(img, (round(img.shape[1] * h / img.shape[0]), h), interpolation=cv2.INTER_AREA)
        for x in range(0, small.shape[1], 40):
            small[:, x] = (0, 255, 255)
        for y in range(0, h, 40):
            small[y, :] = (0, 255, 255)
        tiles.append(small)
    cv2.imwrite(str(png_path), np.hstack((tiles[0], np.full((h, 8, 3), 255, np.uint8), tiles[1])))


def _lens_calibrate(args: argparse.Namespace) -> int:
    import cv2

    from skyfix.camera_io import save_camera
    from skyfix.errors import DataError
    from skyfix.imagefile import read_image
    from skyfix.mapping.board import BoardSpec
    from skyfix.mapping.calibrate import calibrate

    paths = []
    for item in args.images:
        p = Path(item)
        if not p.exists():
            raise InputError(f"calibration image or folder {item!r} does not exist")
        paths.extend(sorted(q for q in p.iterdir() if q.suffix.lower() in (".jpg", ".jpeg", ".png", ".tif", ".tiff"))
                     if p.is_dir() else [p])
    if not paths:
        raise InputError(f"no calibration images (.jpg .png .tif) in {', '.join(args.images)}")
    images = []
    for p in paths:
        try:  # truncated files refused (OpenCV would decode them grey and libjpeg print a warning)
            images.append(read_image(p, cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION, what="calibration image"))
        except (DataError, InputError) as exc:
            log.warning("skipped %s", exc)
    if not images:
        raise DataError(f"none of the {len(paths)} calibration image(s) could be read: "
                        + ", ".join(str(p) for p in paths[:3]) + (" ..." if len(paths) > 3 else ""))
    spec = BoardSpec(kind=args.board, squares=(args.cols, args.rows), square_m=args.square_m,
                     marker_m=args.marker_m if args.marker_m else 0.75 * args.square_m, dictionary=args.dictionary)
    cal = calibrate(images, spec, model=args.model)
    save_camera(args.output, cal.camera, rms_px=cal.rms_px, views_used=len(cal.used), views_total=len(images))
    _write_residual_png(cal, Path(args.output).with_suffix(".png"))
    sys.stdout.write(f"calibrated {args.model} from {len(cal.used)}/{len(images)} views: reprojection RMS "
                     f"{cal.rms_px:.3f} px, fx={cal.camera.fx:.2f} fy={cal.camera.fy:.2f} -> {args.output}\n")
    return 0


def _write_residual_png(cal, png_path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    cam = cal.camera
    u, v = np.meshgrid(np.linspace(0, cam.width - 1, 25), np.linspace(0, cam.height - 1, 19))
    uv = np.stack((u.ravel(), v.ravel()), axis=1)
    ideal = cam.distortion.undistort(uv, cam)
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5), dpi=100)
    axes[0].quiver(uv[:, 0], uv[:, 1], ideal[:, 0] - uv[:, 0], ideal[:, 1] - uv[:, 1], angles="xy")
    axes[0].set(xlim=(0, cam.width), ylim=(cam.height, 0), aspect="equal", title="distortion: raw -> ideal (px)")
    axes[1].bar(range(len(cal.per_view_rms_px)), cal.per_view_rms_px)
    axes[1].set(xlabel="view", ylabel="reprojection RMS (px)", title=f"overall RMS {cal.rms_px:.3f} px")
    fig.tight_layout()
    fig.savefig(png_path)
    plt.close(fig)


def _lens_convert(args: argparse.Namespace) -> int:
    from skyfix.camera_io import load_camera, save_camera
    from skyfix.mapping.lens import barrel_to_opencv, opencv_to_barrel, parse_barrel

    if args.barrel:
        if not args.size:
            raise InputError("--barrel needs --size WIDTHxHEIGHT")
        fit = barrel_to_opencv(parse_barrel(args.barrel), *args.size, raw_focal_px=args.focal_px)
    elif args.calibration:
        fit = opencv_to_barrel(load_camera(args.calibration))
    else:
        raise InputError("give --barrel 'a b c [d]' with --size, or --calibration cal.json")
    d = fit.camera.distortion
    if args.output:
        save_camera(args.output, fit.camera, fit_rms_px=fit.rms_px, fit_max_px=fit.max_px)
    label = (f"ImageMagick barrel '{d.a:.6g} {d.b:.6g} {d.c:.6g} {d.d:.6g}'" if args.calibration else
             f"OpenCV k1={d.k1:.6g} k2={d.k2:.6g} k3={d.k3:.6g} (fx=fy={fit.camera.fx:.2f} px)")
    sys.stdout.write(f"{label}; fit residual RMS {fit.rms_px:.3f} px, max {fit.max_px:.3f} px\n")
    return 0


# --------------------------------------------------------------------------- plan


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


# --------------------------------------------------------------------------- registration


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``lens`` and ``plan`` to the ``skyfix`` command line."""
    fmt = argparse.ArgumentDefaultsHelpFormatter
    lens = subparsers.add_parser("lens", help="lens correction, calibration and model conversion",
                                 description="Correct lens distortion in photos, calibrate cameras from board "
                                             "photos, convert between ImageMagick barrel and OpenCV models.")
    lens_sub = lens.add_subparsers(dest="lens_command", metavar="SUBCOMMAND", title="subcommands")
    lens.set_defaults(func=lambda a: (lens.print_help(), 2)[1])

    p = lens_sub.add_parser("correct", formatter_class=fmt, help="undistort a folder of photos",
                            description="Undistort every JPEG in IN_DIR into OUT_DIR (same names) with "
                                        "precomputed remap tables, in parallel. EXIF (GPS, camera, orientation), "
                                        "XMP and ICC are carried over; the focal length is updated for the "
                                        "corrected camera, whose intrinsics are also written to OUT_DIR/camera.json. "
                                        "Bad photos are reported and skipped (correction_report.json); "
                                        "correction_preview.png shows the first photo before/after.")
    p.add_argument("in_dir", metavar="IN_DIR", help="folder of raw .jpg photos")
    p.add_argument("out_dir", metavar="OUT_DIR", help="folder for the corrected photos (created)")
    p.add_argument("--barrel", metavar="'A B C [D]'",
                   help="ImageMagick -distort barrel coefficients, e.g. '0.1 -0.32 0'")
    p.add_argument("--calibration", metavar="CAL.json", help="camera file from 'skyfix lens calibrate'")
    p.add_argument("--crop", action="store_true", help="crop to the largest centred rectangle of valid pixels")
    p.add_argument("--workers", type=int, default=None, help="worker threads (default: all CPU cores)")
    p.add_argument("--quality", type=int, default=None,
                   help="JPEG quality of the output, 1-100 (default: each photo's own, estimated as ImageMagick does)")
    p.add_argument("--interpolation", default="linear", choices=["nearest", "linear", "cubic", "lanczos"],
                   help="resampling kernel")
    p.add_argument("--backend", default="opencv", choices=["opencv", "torch"],
                   help="'torch' remaps batches with kornia on a GPU when present (CPU otherwise)")
    p.add_argument("--device", default=None, help="torch device for --backend torch (default: cuda if available)")
    p.add_argument("--allow-missing-exif", action="store_true",
                   help="correct photos that have no EXIF instead of skipping them")
    p.set_defaults(func=flags_named(_lens_correct))

    p = lens_sub.add_parser("calibrate", formatter_class=fmt, help="calibrate a camera from board photos",
                            description="Detect a chessboard or ChArUco board in each image, fit OpenCV's "
                                        "Brown-Conrady or fisheye model and write the camera to OUTPUT (JSON) "
                                        "plus OUTPUT.png (distortion field and per-view reprojection RMS).")
    p.add_argument("images", nargs="+", metavar="IMAGE_OR_DIR", help="board photos, or folders of them")
    p.add_argument("--board", default="chessboard", choices=["chessboard", "charuco"],
                   help="calibration target: plain chessboard or ChArUco board (default chessboard)")
    p.add_argument("--cols", type=int, default=10, help="squares across the board (not inner corners)")
    p.add_argument("--rows", type=int, default=7, help="squares down the board")
    p.add_argument("--square-m", type=float, default=0.05, help="side of one square, metres")
    p.add_argument("--marker-m", type=float, default=None, help="ChArUco marker side, metres (default 0.75 square)")
    p.add_argument("--dictionary", default="DICT_5X5_100", help="ChArUco ArUco dictionary name")
    p.add_argument("--model", default="brown_conrady", choices=["brown_conrady", "fisheye"],
                   help="lens model to fit (default brown_conrady)")
    p.add_argument("-o", "--output", default="cal.json", help="camera file to write")
    p.set_defaults(func=flags_named(_lens_calibrate))

    p = lens_sub.add_parser("convert", formatter_class=fmt, help="fit ImageMagick barrel <-> OpenCV models",
                            description="With --barrel and --size: the OpenCV Brown-Conrady camera closest to an "
                                        "ImageMagick barrel correction. With --calibration: the barrel coefficients "
                                        "closest to a calibrated camera. Prints the fit residual in pixels.")
    p.add_argument("--barrel", metavar="'A B C [D]'", help="ImageMagick barrel coefficients")
    p.add_argument("--size", type=_size, metavar="WxH", help="photo size in pixels (with --barrel)")
    p.add_argument("--focal-px", type=float, default=None, help="raw focal length in pixels (with --barrel)")
    p.add_argument("--calibration", metavar="CAL.json", help="calibrated camera to express as a barrel model")
    p.add_argument("-o", "--output", default=None, help="write the fitted camera JSON here")
    p.set_defaults(func=flags_named(_lens_convert))

    plan = subparsers.add_parser("plan", help="survey planning: grids, photo lines, extension, split, handoff",
                                 description="Plan coverage surveys and write plan.json, plan.geojson, plan.kml, "
                                             "plan.png, plan_summary.json and one QGC WPL mission file per drone "
                                             "(MISSION_ITEM_INT content) into --output.")
    plan_sub = plan.add_subparsers(dest="plan_command", metavar="SUBCOMMAND", title="subcommands")
    plan.set_defaults(func=lambda a: (plan.print_help(), 2)[1])

    def common(sp, drones: bool = True) -> None:
        sp.add_argument("-o", "--output", required=True, help="output folder (created)")
        sp.add_argument("--speed", type=float, default=None, help="ground speed set in the mission, m/s")
        if drones:
            sp.add_argument("--drone", action="append", type=_drone, metavar="ID=LAT,LON",
                            help="a drone and its position; with two or more the plan is split among them")

    p = plan_sub.add_parser("corners", formatter_class=fmt, help="station grid from three corners",
                            description="The source platform's grid: corners A B C span v = B - A and w = C - A; "
                                        "waypoints every --step metres along both, boustrophedon order.")
    p.add_argument("--corners", nargs=3, type=_latlon, required=True, metavar="LAT,LON", help="corners A B C")
    p.add_argument("--step", type=float, required=True, help="distance between waypoints, metres")
    p.add_argument("--alt", type=float, required=True, help="flight altitude above take-off, metres")
    p.add_argument("--hold", type=float, default=0.0, help="hold time at each waypoint, seconds")
    common(p)
    p.set_defaults(func=flags_named(_plan_corners))

    p = plan_sub.add_parser("polygon", formatter_class=fmt, help="photo survey lines over a polygon",
                            description="Parallel photo lines over a polygon: spacing and camera trigger "
                                        "distance from the nadir footprint and the requested overlaps; coverage "
                                        "is verified on the footprints and reported in plan_summary.json.")
    p.add_argument("--polygon", required=True, help="GeoJSON file with a Polygon, or 'lat,lon;lat,lon;...'")
    p.add_argument("--camera", default=None, help="camera JSON (corrected camera, e.g. OUT_DIR/camera.json)")
    p.add_argument("--hfov", type=float, default=None, help="horizontal field of view, degrees (instead of --camera)")
    p.add_argument("--size", type=_size, default=None, metavar="WxH", help="image size with --hfov")
    p.add_argument("--alt", type=float, required=True, help="flight altitude above ground, metres")
    p.add_argument("--forward", type=_fraction, default=0.75, help="forward overlap fraction [0, 1)")
    p.add_argument("--side", type=_fraction, default=0.65, help="side overlap fraction [0, 1)")
    p.add_argument("--heading", type=float, default=None, help="line direction, degrees from north "
                                                               "(default: along the area's long side)")
    p.add_argument("--turnaround", type=float, default=None, help="run-in/run-out beyond the photos, metres "
                                                                  "(default: half the along-track footprint)")
    common(p)
    p.set_defaults(func=flags_named(_plan_polygon))

    p = plan_sub.add_parser("extend", formatter_class=fmt, help="re-centre a plan on an alarm and grow it",
                            description="Rebuild PLAN with the same shape and step, centred on --alarm, its area "
                                        "grown by --growth per joining drone (source platform: 50 %%).")
    p.add_argument("plan", metavar="PLAN.json", help="the plan to extend (written by skyfix plan corners|polygon)")
    p.add_argument("--alarm", type=_latlon, required=True, metavar="LAT,LON", help="where the alarm was raised")
    p.add_argument("--joining", type=int, required=True, help="number of drones joining")
    p.add_argument("--growth", type=float, default=0.5, help="area growth per joining drone (fraction)")
    common(p)
    p.set_defaults(func=flags_named(_plan_extend))

    p = plan_sub.add_parser("handoff", formatter_class=fmt, help="give a failing drone's remaining path away",
                            description="The waypoints of PLAN from --next-index on (optionally starting at "
                                        "--stopped-at) go to the nearest --available drone.")
    p.add_argument("plan", metavar="PLAN.json", help="the failing drone's plan")
    p.add_argument("--next-index", type=int, required=True, help="first waypoint the failing drone did not reach")
    p.add_argument("--stopped-at", type=_latlon, default=None, metavar="LAT,LON", help="where it stopped")
    p.add_argument("--available", action="append", type=_drone, required=True, metavar="ID=LAT,LON",
                   help="a drone that can take over (repeat)")
    common(p, drones=False)
    p.set_defaults(func=flags_named(_plan_handoff))

    from skyfix.mapping.map_cli import register_map

    register_map(subparsers)
