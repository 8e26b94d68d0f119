"""``skyfix tags ...``: generate tag fields and boards, dimension a site, locate frames."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

log = logging.getLogger("skyfix.tags")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("tags", help="fiducial floor tags: generate, board, dimension, locate",
                              description="Coloured-tile tags and AprilTag/ArUco boards for localising a "
                                          "drone with a downward camera where GPS is absent.")
    sub = p.add_subparsers(dest="tags_command", metavar="SUBCOMMAND", title="subcommands")

    g = sub.add_parser("generate", help="optimise a tile-tag field and write JSON + printable PNG/SVG",
                       description="Place tile tags on a grid so adjacent tags differ most in colour "
                                   "(annealing, each value once) and write FIELD.json, a PNG at --dpi "
                                   "and an SVG sheet.")
    g.add_argument("-o", "--output", required=True, type=Path, help="field JSON to write")
    g.add_argument("--rows", type=int, default=20, help="tag rows (south to north), default 20")
    g.add_argument("--cols", type=int, default=20, help="tag columns (west to east), default 20")
    g.add_argument("--colors", type=int, default=6, help="colours c, default 6")
    g.add_argument("--tiles", type=int, default=4, choices=(4, 9, 16), help="tiles per tag n, default 4")
    g.add_argument("--tile-m", type=float, default=0.05, help="tile side, metres (default 0.05)")
    g.add_argument("--gap-m", type=float, default=0.02, help="gap between tiles, metres (default 0.02)")
    g.add_argument("--spacing-m", type=float, default=0.25, help="tag centre spacing, metres (default 0.25)")
    g.add_argument("--time-limit-s", type=float, default=5.0, help="optimiser time budget, s (default 5)")
    g.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    g.add_argument("--dpi", type=float, default=50.0, help="PNG resolution, dots per inch (default 50)")
    g.set_defaults(func=_generate)

    b = sub.add_parser("board", help="write an AprilTag/ArUco marker board (JSON + printable PNG)",
                       description="A rows x cols grid of markers from a cv2.aruco dictionary.")
    b.add_argument("-o", "--output", required=True, type=Path, help="board JSON to write")
    b.add_argument("--dictionary", default="apriltag_36h11",
                   help="dictionary, e.g. apriltag_36h11, 4x4_250, aruco_original (default apriltag_36h11)")
    b.add_argument("--rows", type=int, default=20, help="marker rows (default 20)")
    b.add_argument("--cols", type=int, default=20, help="marker columns (default 20)")
    b.add_argument("--marker-m", type=float, default=0.15, help="marker side incl. black border, m (default 0.15)")
    b.add_argument("--spacing-m", type=float, default=0.25, help="marker centre spacing, m (default 0.25)")
    b.add_argument("--dpi", type=float, default=50.0, help="PNG resolution (default 50)")
    b.set_defaults(func=_board)

    d = sub.add_parser("dimension", help="choose tag size, spacing and the (colours, tiles) Pareto front",
                       description="Size a tile-tag field for a site from its area, the camera and the "
                                   "flight heights; prints JSON.")
    d.add_argument("--area-m", type=float, nargs=2, required=True, metavar=("X", "Y"), help="site size, metres")
    d.add_argument("--min-height-m", type=float, required=True, help="lowest flight height above the floor, m")
    d.add_argument("--max-height-m", type=float, required=True, help="highest flight height, m")
    d.add_argument("--width", type=int, default=640, help="image width, px (default 640)")
    d.add_argument("--height", type=int, default=480, help="image height, px (default 480)")
    d.add_argument("--hfov-deg", type=float, default=60.0, help="horizontal field of view, degrees (default 60)")
    d.add_argument("--tilt-deg", type=float, default=15.0, help="largest roll/pitch, degrees (default 15)")
    d.add_argument("--max-colors", type=int, default=6, help="most tile colours to consider (default 6)")
    d.set_defaults(func=_dimension)

    loc = sub.add_parser("locate", help="localise frames over a field: CSV of fixes + annotated PNGs",
                         description="Detect tags in each IMAGE, keep those consistent with the field "
                                     "layout, solve the pose and write one CSV row per image (status "
                                     "'ok' or the reason there is no fix) and an annotated PNG per image.")
    loc.add_argument("images", nargs="+", type=Path, metavar="IMAGE", help="frames (PNG/JPEG)")
    loc.add_argument("--field", required=True, type=Path, help="tile field or marker board JSON")
    cam = loc.add_mutually_exclusive_group(required=True)
    cam.add_argument("--hfov-deg", type=float, help="pinhole camera with this horizontal FOV, degrees")
    cam.add_argument("--camera", type=Path,
                     help="camera JSON (skyfix.camera_io format: fx_px, fy_px, cx_px, cy_px [width, height, model, "
                          "coefficients]; older fx, fy, cx, cy files too); rescaled to each image's size")
    loc.add_argument("--roll-deg", type=float, help="IMU roll, degrees (prior; with --pitch-deg)")
    loc.add_argument("--pitch-deg", type=float, help="IMU pitch, degrees (prior; with --roll-deg)")
    loc.add_argument("--attitude-sigma-deg", type=float, default=1.0, help="IMU 1-sigma, degrees (default 1)")
    loc.add_argument("-o", "--output", type=Path, default=Path("tag_fixes.csv"), help="CSV to write")
    loc.add_argument("--annotated-dir", type=Path, help="where annotated PNGs go (default: beside the CSV)")
    loc.set_defaults(func=_locate)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])


def _generate(args: argparse.Namespace) -> int:
    from skyfix.progress import bar
    from skyfix.tags.field import TagField

    with bar(desc="tags generate (placement search)", total=100, unit="%") as b:
        field = TagField.generate(args.rows, args.cols, colors=args.colors, tiles=args.tiles, tile_m=args.tile_m,
                                  gap_m=args.gap_m, spacing_m=args.spacing_m, time_limit_s=args.time_limit_s,
                                  seed=args.seed, on_progress=lambda f: b.update(int(100 * f) - b.n))
    _output_folder(args.output)
    out = field.save(args.output)
    png = field.write_png(out.with_suffix(".png"), args.dpi)
    svg = field.write_svg(out.with_suffix(".svg"))
    r = field.placement
    print(f"wrote {out}, {png}, {svg}")
    print(f"adjacent colour distance: min {r.min_distance:.1f} (random {r.random_min:.1f}), "
          f"mean {r.mean_distance:.1f} (random {r.random_mean:.1f}); {r.iterations} moves in {r.elapsed_s:.1f} s")
    return 0


def _board(args: argparse.Namespace) -> int:
    from skyfix.tags.aruco import ArucoField

    board = ArucoField(args.dictionary, args.rows, args.cols, args.marker_m, args.spacing_m)
    _output_folder(args.output)
    out = board.save(args.output)
    png = board.write_png(out.with_suffix(".png"), args.dpi)
    print(f"wrote {out}, {png}")
    return 0


def _output_folder(path: Path) -> None:
    """Create the folder of an output file (an -o into a new folder is what the user asked for)."""
    from skyfix.errors import InputError

    if path.is_dir():
        raise InputError(f"-o {path} is a folder; name the JSON file to write")
    path.parent.mkdir(parents=True, exist_ok=True)


def _dimension(args: argparse.Namespace) -> int:
    import json
    from dataclasses import asdict

    from skyfix.camera import Camera
    from skyfix.tags.dimensioning import dimension

    cam = Camera.from_fov(args.width, args.height, args.hfov_deg)
    dim = dimension(args.area_m[0], args.area_m[1], cam, args.min_height_m, args.max_height_m,
                    tilt_deg=args.tilt_deg, max_colors=args.max_colors)
    print(json.dumps(asdict(dim), indent=1))
    return 0


def _load_any(path: Path):
    from skyfix.jsonfile import read_json
    from skyfix.tags.aruco import FORMAT as BOARD
    from skyfix.tags.aruco import ArucoField
    from skyfix.tags.field import TagField

    d, source = read_json(path, "field file"), f"field file {path}"
    if isinstance(d, dict) and d.get("format") == BOARD:
        return ArucoField.from_dict(d, source)
    return TagField.from_dict(d, source)


def _camera(args: argparse.Namespace, width: int, height: int):
    """Camera for a ``width`` x ``height`` image: ``--hfov-deg`` pinhole or the ``--camera`` file
    (rescaled to the image when it was calibrated at another size with the same aspect ratio)."""
    from skyfix.camera import Camera
    from skyfix.camera_io import load_camera

    if args.hfov_deg is not None:
        return Camera.from_fov(width, height, args.hfov_deg)
    return load_camera(args.camera, image_size=(width, height))


def _locate(args: argparse.Namespace) -> int:
    import csv

    import cv2

    from skyfix.errors import DataError, InputError, SkyfixError
    from skyfix.imagefile import read_image
    from skyfix.progress import progress
    from skyfix.tags.aruco import ArucoField, locate_aruco
    from skyfix.tags.locate import locate_tiles
    from skyfix.tags.pose import AttitudePrior

    field = _load_any(args.field)
    if (args.roll_deg is None) != (args.pitch_deg is None):
        raise InputError("give both --roll-deg and --pitch-deg, or neither")
    prior = None if args.roll_deg is None else AttitudePrior(args.roll_deg, args.pitch_deg, args.attitude_sigma_deg)
    ann_dir = args.annotated_dir or args.output.parent
    ann_dir.mkdir(parents=True, exist_ok=True)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    cols = ["image", "status", "x_m", "y_m", "z_m", "yaw_deg", "sigma_xy_m", "sigma_yaw_deg", "n_tags",
            "rejected", "ambiguity", "motion_blur_px", "flags", "detail"]
    n_ok = n_unreadable = 0
    first_unreadable = ""
    for path in args.images:  # a mistyped name is an error before any work
        if not path.is_file():
            raise InputError(f"image {path} does not exist" if not path.exists() else f"image {path} is not a file")
    with args.output.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=cols)
        writer.writeheader()
        for path in progress(args.images, desc="tags locate", unit="frame"):
            row = {"image": str(path)}
            try:
                bgr = read_image(path, cv2.IMREAD_COLOR)
            except DataError as exc:
                if len(args.images) > 1:
                    log.warning("%s", exc)
                first_unreadable = first_unreadable or str(exc)
                n_unreadable += 1
                writer.writerow({**row, "status": "unreadable", "detail": str(exc)})
                continue
            rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
            camera = _camera(args, rgb.shape[1], rgb.shape[0])
            try:
                if isinstance(field, ArucoField):
                    fix = locate_aruco(rgb, field, camera, prior=prior)
                else:
                    fix = locate_tiles(rgb, field, camera, prior=prior)
            except (SkyfixError, DataError) as exc:
                writer.writerow({**row, "status": "no_fix", "detail": str(exc)})
                cv2.imwrite(str(ann_dir / f"{path.stem}_tags.png"), _annotate(bgr, None, str(exc)))
                continue
            n_ok += 1
            writer.writerow({**row, "status": "ok", "x_m": f"{fix.x_m:.4f}", "y_m": f"{fix.y_m:.4f}",
                             "z_m": f"{fix.z_m:.4f}", "yaw_deg": f"{fix.yaw_deg:.3f}",
                             "sigma_xy_m": f"{fix.sigma_xy_m:.5f}", "sigma_yaw_deg": f"{fix.sigma_yaw_deg:.4f}",
                             "n_tags": fix.n_tags, "rejected": fix.rejected, "ambiguity": f"{fix.ambiguity:.3f}",
                             "motion_blur_px": f"{fix.motion_blur_px:.2f}", "flags": " ".join(fix.flags),
                             "detail": ""})
            cv2.imwrite(str(ann_dir / f"{path.stem}_tags.png"), _annotate(bgr, fix, "", field, camera))
    if n_unreadable == len(args.images):
        raise DataError(first_unreadable if len(args.images) == 1
                        else f"none of the {len(args.images)} images could be read ({first_unreadable}; ...)")
    log.info("%d of %d frames localised; wrote %s", n_ok, len(args.images), args.output)
    print(f"{n_ok}/{len(args.images)} frames localised -> {args.output}")
    return 0 if n_ok else 1


def _annotate(bgr, fix, message: str, field=None, camera=None):
    """Frame with the field's tag positions reprojected from the fix and a text summary."""
    import cv2
    import numpy as np

    from skyfix.tags.aruco import ArucoField
    from skyfix.tags.pose import DOWN_MOUNT, _project

    out = bgr.copy()
    if fix is None:
        cv2.putText(out, f"no fix: {message[:70]}", (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 255), 1, cv2.LINE_AA)
        return out
    pts = (field.corners_m(field.ids).reshape(-1, 2) if isinstance(field, ArucoField)
           else field.tile_points_m().reshape(-1, 2))
    state = np.array([fix.x_m, fix.y_m, fix.z_m, fix.yaw_deg, fix.pitch_deg, fix.roll_deg])
    ground = np.concatenate((pts, np.zeros((len(pts), 1))), axis=1)
    uv = _project(state, ground, camera.K, DOWN_MOUNT)
    for u, v in uv[np.all(np.isfinite(uv), axis=1)]:
        if 0 <= u < out.shape[1] and 0 <= v < out.shape[0]:
            cv2.circle(out, (int(round(u)), int(round(v))), 3, (0, 255, 255), 1, cv2.LINE_AA)
    text = (f"x {fix.x_m:.3f} y {fix.y_m:.3f} z {fix.z_m:.3f} m  yaw {fix.yaw_deg:.1f} deg  "
            f"tags {fix.n_tags} rej {fix.rejected} {' '.join(fix.flags)}")
    cv2.putText(out, text, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(out, text, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 200, 0), 1, cv2.LINE_AA)
    return out
