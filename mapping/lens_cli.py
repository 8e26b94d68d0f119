"""``skyfix lens correct|calibrate|convert``: lens correction, calibration and model conversion.

Heavy imports happen inside the command functions so ``skyfix --help`` stays fast.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from skyfix.errors import InputError
from skyfix.mapping.cli_args import flags_named, parse_size

__all__ = ["register_lens"]

log = logging.getLogger("skyfix.mapping")


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


def register_lens(subparsers: argparse._SubParsersAction) -> None:
    """Add ``lens`` and its subcommands to the ``skyfix`` command line."""
    lens = subparsers.add_parser("lens", help="lens correction, calibration and model conversion",
                                 description="Correct lens distortion in photos, calibrate cameras from board "
                                             "photos, convert between ImageMagick barrel and OpenCV models.")
    lens_sub = lens.add_subparsers(dest="lens_command", metavar="SUBCOMMAND", title="subcommands")
    lens.set_defaults(func=lambda a: (lens.print_help(), 2)[1])
    _add_correct(lens_sub)
    _add_calibrate(lens_sub)
    _add_convert(lens_sub)


def _add_correct(lens_sub: argparse._SubParsersAction) -> None:
    """``skyfix lens correct``."""
    fmt = argparse.ArgumentDefaultsHelpFormatter
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


def _add_calibrate(lens_sub: argparse._SubParsersAction) -> None:
    """``skyfix lens calibrate``."""
    fmt = argparse.ArgumentDefaultsHelpFormatter
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


def _add_convert(lens_sub: argparse._SubParsersAction) -> None:
    """``skyfix lens convert``."""
    fmt = argparse.ArgumentDefaultsHelpFormatter
    p = lens_sub.add_parser("convert", formatter_class=fmt, help="fit ImageMagick barrel <-> OpenCV models",
                            description="With --barrel and --size: the OpenCV Brown-Conrady camera closest to an "
                                        "ImageMagick barrel correction. With --calibration: the barrel coefficients "
                                        "closest to a calibrated camera. Prints the fit residual in pixels.")
    p.add_argument("--barrel", metavar="'A B C [D]'", help="ImageMagick barrel coefficients")
    p.add_argument("--size", type=parse_size, metavar="WxH", help="photo size in pixels (with --barrel)")
    p.add_argument("--focal-px", type=float, default=None, help="raw focal length in pixels (with --barrel)")
    p.add_argument("--calibration", metavar="CAL.json", help="calibrated camera to express as a barrel model")
    p.add_argument("-o", "--output", default=None, help="write the fitted camera JSON here")
    p.set_defaults(func=flags_named(_lens_convert))
