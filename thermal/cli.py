"""``skyfix thermal ...``: detect and locate fire hotspots from the command line.

- ``skyfix thermal detect FRAMES... --pose CSV --camera JSON --ground-alt M -o OUT.geojson``:
  every hotspot of every frame, geolocated on its own (no fusion).
- ``skyfix thermal locate FRAMES_DIR --poses CSV --camera JSON --ground-alt M -o fires.geojson``:
  a whole flight through :class:`FireTracker`; fused fires.
- ``skyfix thermal simulate``: deprecated name of ``skyfix datasets thermal-flight`` (the
  synthetic flight harness lives in :mod:`skyfix.datasets.thermal_cli`).

Every command writes GeoJSON plus PNGs to look at (annotated frame, map of fires).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

DESCRIPTION = """\
Fire hotspots in thermal frames: detect, geolocate, track.

  skyfix thermal detect FRAMES... --pose CSV --camera JSON --ground-alt M -o OUT.geojson
      every hotspot of every frame, geolocated on its own (no fusion)
  skyfix thermal locate FRAMES_DIR --poses CSV --camera JSON --ground-alt M -o fires.geojson
      a whole flight through the fire tracker: fused fires with sigma
  skyfix datasets thermal-flight OUT_DIR
      a synthetic flight (frames, poses.csv, camera.json, truth.json) that locate reads
      ('skyfix thermal simulate' still works, deprecated)

Heights are metres above the WGS84 ellipsoid unless an option says AMSL. Every command
writes GeoJSON plus PNGs to look at (annotated frame, map of fires and track).
"""

POSE_CSV_HELP = """\
pose CSV columns (header row, one row per frame):
  frame                 frame file name (looked up in the frames given / FRAMES_DIR)
  time_s                frame time, seconds
  lat_deg, lon_deg      WGS84 position
  alt_ellipsoid_m       height above the WGS84 ellipsoid
    or alt_amsl_m       height above mean sea level (then --geoid-undulation is required)
  roll_deg, pitch_deg, yaw_deg   vehicle attitude (yaw 0 = north, clockwise)
  gimbal_pitch_deg      camera pitch (-90 = straight down)
  gimbal_yaw_body_deg   camera yaw relative to the vehicle nose
    or gimbal_yaw_north_deg      camera yaw relative to north
  stabilized            1 = gimbal holds the horizon, 0 = hard-mounted camera
  gimbal_roll_deg       optional
Ambiguous names (alt, alt_m, gimbal_yaw...) are refused.
"""

_GROUND_HELP = ("ground height in metres above the WGS84 ellipsoid (not AMSL: use --ground-amsl "
                "with --geoid-undulation)")


def _add_ground_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("ground (choose one; all heights end up ellipsoidal)")
    g.add_argument("--ground-alt", type=float, metavar="M", help=_GROUND_HELP)
    g.add_argument("--ground-amsl", type=float, metavar="M", help="ground height above mean sea level, metres")
    g.add_argument("--dem", type=Path, metavar="GEOTIFF", help="elevation model (band 1, metres)")
    g.add_argument("--dem-datum", choices=("ellipsoid", "amsl"), default="ellipsoid",
                   help="vertical datum of --dem (default: ellipsoid)")
    g.add_argument("--geoid-undulation", type=float, metavar="M",
                   help="geoid height above the ellipsoid at the site, metres (needed for --ground-amsl and "
                        "alt_amsl_m poses; an AMSL --dem uses the EGM96 grid cell by cell when omitted)")
    g.add_argument("--ground-sigma", type=float, default=0.0, metavar="M",
                   help="1-sigma ground height error for flat ground, metres (default 0)")


def _add_frame_args(p: argparse.ArgumentParser) -> None:
    d = p.add_argument_group("frames")
    d.add_argument("--camera", type=Path, required=True,
                   help="camera JSON (skyfix.camera_io format): width, height and fx_px, fy_px, cx_px, "
                        "cy_px [model, coefficients], or hfov_deg; older fx, fy, cx, cy files are read too")
    d.add_argument("--threshold", type=float, default=None,
                   help="hot threshold: deg C for radiometric frames (default 100), 8-bit level for "
                        "8-bit frames (default automatic)")
    d.add_argument("--palette", default="white-hot",
                   help="palette of 8-bit frames: white-hot, black-hot, ironbow, arctic (default white-hot)")
    d.add_argument("--kelvin-per-count", type=float, default=0.01,
                   help="scale of 16-bit radiometric frames, K per count (default 0.01)")
    d.add_argument("--min-area", type=int, default=4, help="minimum hot pixels per hotspot (default 4)")
    u = p.add_argument_group("pose uncertainty (1-sigma, per frame)")
    u.add_argument("--position-sigma", type=float, default=1.5, help="horizontal position, m (default 1.5)")
    u.add_argument("--altitude-sigma", type=float, default=None, help="vertical position, m (default: horizontal)")
    u.add_argument("--attitude-sigma", type=float, default=0.5, help="roll/pitch, deg (default 0.5)")
    u.add_argument("--yaw-sigma", type=float, default=None, help="heading, deg (default: attitude)")
    u.add_argument("--pixel-sigma", type=float, default=0.5, help="centroid, px (default 0.5)")


def _add_joint_args(p: argparse.ArgumentParser) -> None:
    j = p.add_argument_group("joint estimate (--joint): every fire from all its frames at once, with the pose "
                             "errors drones have")
    j.add_argument("--joint", action="store_true",
                   help="estimate the fires jointly over the flight: GNSS error shared between frames "
                        "(Gauss-Markov), attitude drift, the camera's boresight misalignment and its clock "
                        "offset to the pose log estimated; writes OUT.csv, OUT_calibration.json too")
    j.add_argument("--gnss-sigma", type=float, default=1.5, help="GNSS horizontal wander, m (default 1.5)")
    j.add_argument("--gnss-vertical-sigma", type=float, default=2.5, help="GNSS vertical wander, m (default 2.5)")
    j.add_argument("--gnss-tau", type=float, default=60.0, help="GNSS correlation time, s (default 60)")
    j.add_argument("--boresight-sigma", type=float, default=1.5,
                   help="prior on the camera's misalignment, deg per axis (default 1.5)")
    j.add_argument("--time-offset-sigma", type=float, default=0.3,
                   help="prior on the camera clock offset to the pose log, s (default 0.3)")
    j.add_argument("--calibration", type=Path, metavar="JSON",
                   help="boresight and clock offset from an earlier --joint run of the same camera "
                        "(its OUT_calibration.json), used as the prior")


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``skyfix thermal`` and its subcommands."""
    from skyfix.datasets import thermal_cli  # the deprecated 'simulate' shares its arguments
    top = subparsers.add_parser("thermal", help="fire hotspots: detect, geolocate, track",
                                description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = top.add_subparsers(dest="thermal_command", metavar="SUBCOMMAND", title="subcommands")
    top.set_defaults(func=lambda args: (top.print_help(), 2)[1])

    p = sub.add_parser("detect", help="geolocate every hotspot of each frame on its own",
                       description="Detect hotspots in each frame and geolocate each one on its own "
                                   "(no fusion). Frames are matched to pose rows by file name. Writes "
                                   "OUT.geojson and OUT.png (last frame annotated).",
                       epilog=POSE_CSV_HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("frames", nargs="+", type=Path, metavar="FRAME",
                   help="frames: 16-bit PNG/TIFF counts, 8-bit PNG (grey or palette RGB), .npy deg C")
    p.add_argument("--pose", type=Path, required=True, help="pose CSV (see skyfix.thermal.io for columns)")
    p.add_argument("-o", "--output", type=Path, required=True, help="output GeoJSON of hotspots")
    _add_frame_args(p)
    _add_ground_args(p)
    p.set_defaults(func=run_detect)

    p = sub.add_parser("locate", help="track and fuse fires over a whole flight",
                       description="Run a flight through the fire tracker: detections are associated "
                                   "across frames and fused; writes fires as GeoJSON, an annotated PNG of "
                                   "the last frame and a map PNG of fires and camera track.",
                       epilog=POSE_CSV_HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("frames_dir", type=Path, metavar="FRAMES_DIR", help="directory holding the frames")
    p.add_argument("--poses", type=Path, required=True, help="pose CSV, one row per frame")
    p.add_argument("-o", "--output", type=Path, required=True, help="output GeoJSON of fires")
    p.add_argument("--min-observations", type=int, default=2, help="frames before a fire is reported (default 2)")
    _add_frame_args(p)
    _add_ground_args(p)
    _add_joint_args(p)
    p.set_defaults(func=run_locate)

    p = sub.add_parser("simulate", help="deprecated: moved to 'skyfix datasets thermal-flight'",
                       description="Deprecated: this harness command moved to 'skyfix datasets thermal-flight' "
                                   "(same arguments). " + thermal_cli.DESCRIPTION)
    thermal_cli.add_arguments(p)
    p.set_defaults(func=run_simulate)


def _ground(args: argparse.Namespace):
    from skyfix.errors import InputError
    from skyfix.thermal.ground import DemGround, FlatGround

    chosen = [x for x in (args.ground_alt, args.ground_amsl, args.dem) if x is not None]
    if len(chosen) != 1:
        raise InputError("give exactly one of --ground-alt, --ground-amsl, --dem")
    if args.dem is not None:
        return DemGround.from_geotiff(args.dem, datum=args.dem_datum, geoid_undulation_m=args.geoid_undulation)
    if args.ground_amsl is not None:
        if args.geoid_undulation is None:
            raise InputError("--ground-amsl needs --geoid-undulation (geoid height above the ellipsoid)")
        return FlatGround.from_amsl(args.ground_amsl, geoid_undulation_m=args.geoid_undulation,
                                    sigma_m=args.ground_sigma)
    return FlatGround(args.ground_alt, args.ground_sigma)


def _uncertainty(args: argparse.Namespace):
    from skyfix.thermal.pose import PoseUncertainty

    return PoseUncertainty(args.position_sigma, args.altitude_sigma, args.attitude_sigma, args.yaw_sigma,
                           args.pixel_sigma)


def _display_rgb(frame: np.ndarray, kelvin_per_count: float) -> np.ndarray:
    """Any frame -> RGB uint8 for drawing (radiometric frames in ironbow, 1st-99.9th pct)."""
    from skyfix.thermal.palettes import apply_palette

    if frame.ndim == 3:
        return np.ascontiguousarray(frame)
    if frame.dtype == np.uint8:
        return np.ascontiguousarray(np.dstack([frame] * 3))
    img = frame.astype(np.float64) * (kelvin_per_count if frame.dtype == np.uint16 else 1.0)
    lo, hi = np.nanpercentile(img, [1, 99.9])
    level = np.clip((np.nan_to_num(img, nan=lo) - lo) / max(hi - lo, 1e-9) * 255, 0, 255).astype(np.uint8)
    return np.ascontiguousarray(apply_palette(level, "ironbow"))


def _annotate(path: Path, frame: np.ndarray, hotspots, labels: list[str], kelvin_per_count: float) -> None:
    import cv2

    rgb = _display_rgb(frame, kelvin_per_count).copy()
    for h, text in zip(hotspots, labels, strict=True):
        r = max(6, int(math.sqrt(h.area_px)))
        c = (int(round(h.u_px)), int(round(h.v_px)))
        cv2.circle(rgb, c, r, (0, 255, 0), 1, cv2.LINE_AA)
        cv2.putText(rgb, text, (c[0] + r + 2, c[1]), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 255, 0), 1, cv2.LINE_AA)
    cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))


def _load_rows(pose_csv: Path, geoid_undulation_m: float | None):
    from skyfix.thermal.io import read_poses

    return read_poses(pose_csv, geoid_undulation_m=geoid_undulation_m)


def run_detect(args: argparse.Namespace) -> int:
    """``skyfix thermal detect``."""
    import warnings

    from skyfix.camera_io import load_camera
    from skyfix.errors import DataError, InputError, SkyfixError
    from skyfix.progress import progress
    from skyfix.thermal.detect import RelativeTemperatureWarning, detect_hotspots
    from skyfix.thermal.geolocate import geolocate_many
    from skyfix.thermal.io import read_frame

    camera = load_camera(args.camera)
    ground = _ground(args)
    unc = _uncertainty(args)
    by_name = {Path(name).name: (t, pose) for name, t, pose in _load_rows(args.pose, args.geoid_undulation)}
    feats, last = [], None
    warned = False
    for path in progress(args.frames, desc="thermal detect", unit="frame"):
        if not path.is_file():
            raise InputError(f"frame {path} does not exist" if not path.exists() else f"frame {path} is not a file")
        if path.name not in by_name:
            raise DataError(f"frame {path.name} has no row in {args.pose}")
        t, pose = by_name[path.name]
        frame = read_frame(path)
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", RelativeTemperatureWarning)
                spots = detect_hotspots(frame, threshold=args.threshold, palette=args.palette,
                                        min_area_px=args.min_area, kelvin_per_count=args.kelvin_per_count)
            if caught and not warned:
                log.warning("%s", caught[0].message)
                warned = True
            fixes = geolocate_many(spots, camera, pose, ground, uncertainty=unc, time_s=t,
                                   source_id=path.name) if spots else []
        except SkyfixError as exc:
            log.warning("frame %s skipped: %s", path.name, exc)
            continue
        for h, fix in zip(spots, fixes, strict=True):
            feats.append({"type": "Feature",
                          "geometry": {"type": "Point", "coordinates": [fix.lon_deg, fix.lat_deg, fix.alt_m]},
                          "properties": {"frame": path.name, "time_s": t, "u_px": round(h.u_px, 3),
                                         "v_px": round(h.v_px, 3), "area_px": h.area_px, "peak": round(h.peak, 2),
                                         "units": h.units, "sigma_major_m": round(fix.sigma_horizontal_m, 3),
                                         "cov_enu_m2": np.round(fix.cov_enu_m2, 4).tolist(),
                                         "alt_datum": "WGS84 ellipsoid"}})
        last = (path, frame, spots)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps({"type": "FeatureCollection", "features": feats}, indent=1))
    png = args.output.with_suffix(".png")
    if last is not None:
        _annotate(png, last[1], last[2], [f"{h.peak:.0f}" for h in last[2]], args.kelvin_per_count)
    print(f"{len(feats)} hotspot(s) in {len(args.frames)} frame(s) -> {args.output}"
          + (f", {png}" if last is not None else ""))
    return 0


def run_locate(args: argparse.Namespace) -> int:
    """``skyfix thermal locate``."""
    import warnings

    from skyfix.camera_io import load_camera
    from skyfix.errors import DataError, SkyfixError
    from skyfix.progress import progress
    from skyfix.thermal.detect import RelativeTemperatureWarning, detect_hotspots
    from skyfix.thermal.ground import DemGround
    from skyfix.thermal.io import fires_geojson, match_frames, read_frame, write_fires_csv
    from skyfix.thermal.report import fires_map_png
    from skyfix.thermal.tracker import FireTracker, TrackerSettings

    camera = load_camera(args.camera)
    ground = _ground(args)
    rows = _load_rows(args.poses, args.geoid_undulation)
    matched, _ = match_frames(args.frames_dir, rows, args.poses)
    rows = [(path.name, t, pose) for path, t, pose in matched]
    settings = TrackerSettings(min_observations=args.min_observations, threshold=args.threshold,
                               palette=args.palette, min_area_px=args.min_area,
                               kelvin_per_count=args.kelvin_per_count)
    tracker = FireTracker(camera, ground, uncertainty=_uncertainty(args), settings=settings)
    if isinstance(ground, DemGround):
        ground.check_covers([p.lat_deg for _, _, p in rows], [p.lon_deg for _, _, p in rows], f"the flight in {args.poses}")
    last, track, detections = None, [], []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RelativeTemperatureWarning)
        for path, t, pose in progress(matched, desc="thermal locate", unit="frame"):
            try:
                spots = detect_hotspots(read_frame(path), threshold=args.threshold, palette=args.palette,
                                        min_area_px=args.min_area, kelvin_per_count=args.kelvin_per_count)
                seen = tracker.update_hotspots(spots, pose, t)
            except SkyfixError as exc:
                log.warning("frame %s dropped: %s", path.name, exc)
                tracker.frames_dropped += 1
                continue
            detections.append((t, spots))
            track.append((pose.lat_deg, pose.lon_deg))
            if spots:
                last = (path, spots, seen)
    if caught:
        log.warning("%s", caught[0].message)
    if not detections:
        raise DataError(f"no frame in {args.frames_dir} could be read ({len(matched)} tried; see the warnings)")
    args.output.parent.mkdir(parents=True, exist_ok=True)
    fires = _joint_fires(args, camera, rows, detections, ground) if args.joint else tracker.fires
    args.output.write_text(json.dumps(fires_geojson(fires, track=np.array(track)), indent=1))
    stem = args.output.with_suffix("")
    frame_png, map_png, csv_path = Path(f"{stem}_last_frame.png"), Path(f"{stem}_map.png"), write_fires_csv(
        Path(f"{stem}.csv"), fires)
    if last is not None:
        _annotate(frame_png, read_frame(last[0]), last[1], [f"fire {i}" for i in last[2]], args.kelvin_per_count)
    if isinstance(ground, DemGround):
        fires_map_png(map_png, fires, ground, track_latlon=np.array(track))
    else:
        _map_png(map_png, tracker, np.array(track))
    print(f"{len(fires)} fire(s) from {tracker.frames_used} frame(s) ({tracker.frames_dropped} dropped) -> "
          f"{args.output}, {csv_path}, {map_png}" + (f", {frame_png}" if last is not None else ""))
    for f in fires:
        print(f"  fire {f.fire_id}: {f.lat_deg:.7f}, {f.lon_deg:.7f}  sigma {f.sigma_m:.2f} m  "
              f"{f.n_observations} obs  {f.first_seen_s:.1f}-{f.last_seen_s:.1f} s  "
              f"{'burning' if f.burning else 'out'}")
    return 0


def _joint_fires(args: argparse.Namespace, camera, rows, detections, ground) -> list:
    """``--joint``: the flight's fires from :func:`locate_jointly`; writes the calibration JSON."""
    from skyfix.errors import DataError
    from skyfix.progress import bar
    from skyfix.thermal.joint import JointSolution, PoseErrorPrior, locate_jointly
    from skyfix.thermal.poselog import PoseLog
    from skyfix.thermal.sightings import associate

    times = np.array([t for _, t, _ in rows])
    if np.any(np.diff(times) <= 0):
        raise DataError(f"{args.poses}: --joint needs strictly increasing time_s")
    pose_log = PoseLog.from_poses(times, [p for _, _, p in rows])
    prior = PoseErrorPrior(gnss_h_sigma_m=args.gnss_sigma, gnss_v_sigma_m=args.gnss_vertical_sigma,
                           gnss_tau_s=args.gnss_tau, boresight_sigma_deg=args.boresight_sigma,
                           time_offset_sigma_s=args.time_offset_sigma, pixel_sigma_px=args.pixel_sigma)
    calibration = None
    if args.calibration is not None:
        try:
            c = json.loads(args.calibration.read_text())
            calibration = JointSolution([], np.zeros((0, 3)), np.array(c["boresight_deg"], float),
                                        np.array(c["boresight_cov_deg2"], float), float(c["time_offset_s"]),
                                        float(c["time_offset_sigma_s"]), np.zeros(0), np.zeros((0, 3)), 0.0, 0)
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise DataError(f"cannot read calibration {args.calibration}: {exc}") from None
    with bar(desc="joint estimate", unit="iteration") as b:
        sol = locate_jointly(camera, pose_log, associate(camera, pose_log, detections, ground), ground,
                             prior=prior, calibration=calibration, on_iteration=lambda: b.update(1))
    out = Path(f"{args.output.with_suffix('')}_calibration.json")
    out.write_text(json.dumps({
        "boresight_deg": sol.boresight_deg.round(4).tolist(),
        "boresight_cov_deg2": sol.boresight_cov_deg2.round(6).tolist(),
        "boresight_axes": "rotation vector in the camera frame (x right, y down, z forward), gimbal -> sensor",
        "time_offset_s": round(sol.time_offset_s, 4), "time_offset_sigma_s": round(sol.time_offset_sigma_s, 4),
        "time_offset_meaning": "pose-log time minus camera stamp", "chi2": round(sol.chi2, 2), "dof": sol.dof},
        indent=1))
    print(f"joint estimate: boresight {np.round(sol.boresight_deg, 3).tolist()} deg, clock offset "
          f"{sol.time_offset_s:+.3f} +- {sol.time_offset_sigma_s:.3f} s -> {out}")
    return sol.fires


def _map_png(path: Path, tracker, track_latlon: np.ndarray) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Ellipse

    frame = tracker.frame
    fig, ax = plt.subplots(figsize=(7, 7))
    if frame is not None and len(track_latlon):
        e, n, _ = frame.to_enu(track_latlon[:, 0], track_latlon[:, 1], np.full(len(track_latlon), frame.alt0_m))
        ax.plot(e, n, "-", color="0.6", lw=1, label="camera track")
    for f in tracker.fires:
        e, n, _ = frame.to_enu(f.lat_deg, f.lon_deg, f.alt_m)
        hist = tracker.track_history(f.fire_id)
        ax.plot(hist[:, 1], hist[:, 2], ".", ms=3, alpha=0.5)
        vals, vecs = np.linalg.eigh(f.cov_en_m2)
        ang = math.degrees(math.atan2(vecs[1, 1], vecs[0, 1]))
        ax.add_patch(Ellipse((float(e), float(n)), 4 * math.sqrt(vals[1]), 4 * math.sqrt(vals[0]), angle=ang,
                             fill=False, color="red" if f.burning else "black"))
        ax.plot(float(e), float(n), "x", color="red" if f.burning else "black")
        ax.annotate(f"fire {f.fire_id} ({f.sigma_m:.2f} m)", (float(e), float(n)), textcoords="offset points",
                    xytext=(6, 6), fontsize=8)
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title("fires (x, 2-sigma ellipse), single-frame fixes (dots), camera track")
    ax.legend(loc="best", fontsize=8)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def run_simulate(args: argparse.Namespace) -> int:
    """``skyfix thermal simulate``: the deprecated name of ``skyfix datasets thermal-flight``."""
    from skyfix.datasets.thermal_cli import run_thermal_flight

    status = run_thermal_flight(args)
    # Said after the work, so that a refused input still gets its one-line error alone.
    log.warning("'skyfix thermal simulate' is deprecated: it moved to 'skyfix datasets thermal-flight' "
                "(same arguments)")
    return status
