"""``skyfix crps ...``: drone-to-drone ranging from the command line.

``skyfix crps range IMAGE --camera HFOV_OR_JSON --size-m SPAN`` finds the drones in one
image, measures range and bearing, and writes an annotated PNG and a JSON report.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

log = logging.getLogger("skyfix.crps")

EPILOG = """\
examples:
  skyfix crps range frame.png --camera 80 --size-m 0.5
  skyfix crps range frame.jpg --camera cam.json --size-m 0.5 --pose 47.1,8.2,520,0,0,90,10 -o out/frame
  skyfix crps range frame.png --camera 80 --size-m 0.16 --marker DICT_4X4_50

--camera is either the horizontal field of view in degrees (principal point at the
image centre, square pixels) or a JSON file {"width", "height", "fx", "fy", "cx", "cy"}.
--pose is the helper camera pose lat,lon,alt_m[,roll,pitch,yaw[,gimbal_pitch[,gimbal_yaw]]]
(degrees, ellipsoidal metres, gimbal stabilised; default gimbal_pitch 0 = level). Without
it the bearing is reported for a level camera facing north at 0,0.
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``skyfix crps`` and its subcommands."""
    crps = subparsers.add_parser("crps", help="collaborative relative positioning: drone-to-drone ranging",
                                 description="Drone-to-drone monocular ranging (skyfix.crps).")
    sub = crps.add_subparsers(dest="crps_command", metavar="SUBCOMMAND", title="subcommands")
    crps.set_defaults(func=lambda args: (crps.print_help(), 2)[1])
    p = sub.add_parser("range", help="range and bearing of the drones in one image (annotated PNG + JSON)",
                       description="Detect drones (silhouette against sky/smooth ground, or a marker on the "
                                   "drone), measure range from apparent size and bearing from the pixel, "
                                   "write OUT.png and OUT.json.",
                       epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("image", type=Path, help="image file (any format OpenCV reads)")
    p.add_argument("--camera", required=True, help="horizontal FOV in degrees, or a camera JSON file")
    p.add_argument("--size-m", type=float, required=True,
                   help="target size in metres: rotor-tip span for silhouettes, marker side with --marker")
    p.add_argument("--arms", type=int, default=4, choices=(3, 4, 6, 8), help="multirotor arms (default 4)")
    p.add_argument("--marker", metavar="DICT", default=None,
                   help="detect ArUco markers of this cv2.aruco dictionary (e.g. DICT_4X4_50) instead of silhouettes")
    p.add_argument("--pose", default=None, help="helper camera pose lat,lon,alt_m[,roll,pitch,yaw[,gimbal_pitch"
                                                "[,gimbal_yaw]]]")
    p.add_argument("--attitude-sigma-deg", type=float, default=None,
                   help="helper pointing 1-sigma, deg: mostly its compass heading's error (default "
                        "skyfix.crps.observation.POINTING_SIGMA_DEG, 2)")
    p.add_argument("--psf-sigma-px", type=float, default=0.7, help="camera blur 1-sigma in pixels (default 0.7)")
    p.add_argument("--polarity", choices=("dark", "bright", "both"), default="dark",
                   help="target darker or brighter than its background (default dark)")
    p.add_argument("--no-shape-check", action="store_true",
                   help="keep silhouettes whose aspect does not fit a level drone on that bearing")
    p.add_argument("--no-fit", action="store_true",
                   help="keep the moment size for small silhouettes instead of fitting the drone model "
                        "(the fit needs --pose; it is used up to 14 px extent, about 40 m for a 0.5 m drone at "
                        "1144 px focal: at 40-100 m it cuts the single-frame p95 range error 1.4-3x in the benchmark)")
    p.add_argument("-o", "--output", type=Path, default=None,
                   help="output prefix (default: next to IMAGE, IMAGE_range.png/.json)")
    p.set_defaults(func=run_range)


def _camera(spec: str, width: int, height: int):
    """--camera: a horizontal field of view in degrees, or any skyfix camera file (skyfix.camera_io),
    rescaled to the image size."""
    from skyfix.camera import Camera
    from skyfix.camera_io import load_camera
    from skyfix.errors import InputError

    if Path(spec).suffix.lower() == ".json":
        return load_camera(spec, image_size=(width, height))
    try:
        hfov = float(spec)
    except ValueError:
        raise InputError(f"--camera must be a field of view in degrees or a .json file, got {spec!r}") from None
    return Camera.from_fov(width, height, hfov)


def _pose(spec: str | None):
    from skyfix.camera import CameraPose
    from skyfix.errors import InputError

    if spec is None:
        return CameraPose(0.0, 0.0, 0.0, gimbal_pitch_deg=0.0), False
    try:
        vals = [float(x) for x in spec.split(",")]
    except ValueError:
        raise InputError(f"--pose must be comma-separated numbers, got {spec!r}") from None
    if len(vals) < 3 or len(vals) > 8:
        raise InputError(f"--pose needs lat,lon,alt_m and up to 5 angles, got {len(vals)} values")
    names = ("lat_deg", "lon_deg", "alt_m", "roll_deg", "pitch_deg", "yaw_deg", "gimbal_pitch_deg", "gimbal_yaw_deg")
    kwargs = {"gimbal_pitch_deg": 0.0, **dict(zip(names, vals, strict=False))}
    return CameraPose(**kwargs), True


def _attitude_sigma_deg(value: float | None) -> float:
    """``--attitude-sigma-deg``, the library's default when not given; InputError when negative or not finite."""
    from skyfix import validate
    from skyfix.crps.observation import POINTING_SIGMA_DEG
    from skyfix.errors import InputError

    if value is None:
        return POINTING_SIGMA_DEG
    if validate.finite_scalar("--attitude-sigma-deg", value) < 0:
        raise InputError(f"--attitude-sigma-deg must be >= 0, got {value}")
    return float(value)


def run_range(args: argparse.Namespace) -> int:
    """The ``skyfix crps range`` command."""
    import cv2
    import numpy as np

    from skyfix import validate
    from skyfix.crps import (
        DroneModel,
        MarkerDetector,
        SilhouetteConfig,
        SilhouetteDetector,
        SilhouetteFit,
        SilhouetteFitConfig,
        observe,
        shape_consistent,
    )
    from skyfix.geo import LocalFrame
    from skyfix.imagefile import read_image

    size_m = validate.positive_scalar("--size-m", args.size_m)
    validate.positive_scalar("--psf-sigma-px", args.psf_sigma_px)
    args.attitude_sigma_deg = _attitude_sigma_deg(args.attitude_sigma_deg)
    image = read_image(args.image)  # a truncated JPEG/PNG is refused, not measured
    h, w = image.shape[:2]
    camera = _camera(args.camera, w, h)
    pose, has_pose = _pose(args.pose)
    model = DroneModel(arms=args.arms, span_m=size_m) if args.arms != 6 else DroneModel.hex(size_m)
    if args.marker:
        detections = MarkerDetector(camera, args.marker)(image)
    else:
        detector = SilhouetteDetector(SilhouetteConfig(psf_sigma_px=args.psf_sigma_px, polarity=args.polarity))
        detections = detector(image)
        if not args.no_shape_check:
            detections = [d for d in detections if shape_consistent(camera, pose, d, model)]
        if has_pose and not args.no_fit:
            # The model fit needs the view direction, hence a real pose; it leaves large targets alone.
            fit = SilhouetteFit(camera, model, SilhouetteFitConfig(psf_sigma_px=args.psf_sigma_px))
            detections = [fit(image, d, pose) for d in detections]
    out_prefix = args.output if args.output is not None else args.image.with_name(args.image.stem + "_range")
    out_prefix.parent.mkdir(parents=True, exist_ok=True)

    vis = image.copy()
    if vis.dtype != np.uint8:
        vis = cv2.normalize(vis, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    if vis.ndim == 2:
        vis = cv2.cvtColor(vis, cv2.COLOR_GRAY2BGR)
    records = []
    frame = LocalFrame(pose.lat_deg, pose.lon_deg, pose.alt_m)
    for i, det in enumerate(detections):
        obs = observe(camera, pose, det, args.size_m, model=model, attitude_sigma_deg=args.attitude_sigma_deg,
                      observer_id="helper", target_id=f"target{i}" if det.marker_id is None else None)
        sigma_r = float(np.sqrt(obs.bearing_unit_enu @ obs.cov_enu_m2 @ obs.bearing_unit_enu))
        rec = {"index": i, "kind": det.kind, "score": det.score, "marker_id": det.marker_id,
               "centroid_uv": det.centroid_uv.tolist(), "bbox_px": list(det.bbox_px),
               "range_m": obs.range_m, "range_sigma_m": sigma_r,
               "bearing_enu": obs.bearing_unit_enu.tolist(), "cov_enu_m2": obs.cov_enu_m2.tolist()}
        if has_pose:
            lat, lon, alt = (float(x) for x in frame.to_geodetic(*obs.offset_enu_m))
            rec["target_lat_deg"], rec["target_lon_deg"], rec["target_alt_m"] = lat, lon, alt
        records.append(rec)
        u0, v0, u1, v1 = det.bbox_px
        cv2.rectangle(vis, (u0 - 3, v0 - 3), (u1 + 2, v1 + 2), (0, 0, 255), 1)
        cu, cv_ = (int(round(x)) for x in det.centroid_uv)
        cv2.drawMarker(vis, (cu, cv_), (0, 255, 255), cv2.MARKER_CROSS, 12, 1)
        label = f"{obs.range_m:.1f} +- {sigma_r:.1f} m" + (f" id {det.marker_id}" if det.marker_id is not None else "")
        cv2.putText(vis, label, (u0, max(v0 - 8, 12)), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 255), 1, cv2.LINE_AA)
    png, js = out_prefix.with_suffix(".png"), out_prefix.with_suffix(".json")
    cv2.imwrite(str(png), vis)
    report = {"image": str(args.image), "camera": {"width": camera.width, "height": camera.height,
                                                   "fx": camera.fx, "fy": camera.fy, "cx": camera.cx,
                                                   "cy": camera.cy},
              "size_m": args.size_m, "pose_given": has_pose, "detections": records}
    js.write_text(json.dumps(report, indent=2))
    log.info("%d target(s); wrote %s and %s", len(records), png, js)
    for r in records:
        print(f"target {r['index']}: range {r['range_m']:.2f} +- {r['range_sigma_m']:.2f} m at pixel "
              f"({r['centroid_uv'][0]:.1f}, {r['centroid_uv'][1]:.1f})")
    return 0 if records else 1
