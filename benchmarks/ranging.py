"""Drone-to-drone monocular ranging: accuracy, two-helper fixes, speed, false detections.

Renders (skyfix.datasets.drone_view) a 0.5 m quadcopter into a 1920x1080, 80-degree
HFOV helper camera and measures, on the same frames:

1. range and bearing error versus distance (10-100 m) for skyfix and for the source
   paper's reference-image method (D1 = D0 * S0 / S1 with S the thresholded bounding-box
   width, S0 measured on a reference render at D0 = 20 m): single frames by moments and by
   the model fit (SilhouetteFit), and 15-frame tracks through the documented path
   (Tracker(detector, fit=SilhouetteFit) with the helper pose) and, on the same frames, a
   Tracker on moments only. The issue's accuracy goals are checked on the tracked path;
   the single-frame figures are printed next to it;
2. two helpers 40-70 m away, >= 60 degrees apart, with noisy own pose, fused by
   ``locate``: position error and how often the truth lies inside the 95 % ellipsoid;
3. CPU time per frame (``time.process_time`` with ``cv2.setNumThreads(1)``: one core)
   for full-frame search and for tracking (region of interest, with the fit), detection +
   observe, at 55 m and 100 m;
4. false detections on target-free frames: sky (single frames, random clouds and
   attitude) and terrain sequences (a helper flying over real aerial photos from
   shared/data/seneca-subset via render_ground, noisy pose) through the default
   single-frame path, the prior-gate option and the sequence path recommended for terrain
   (Tracker with a GroundMotionFilter); terrain sequences with a target show that the
   sequence path still detects it (detection rate printed);
5. bad inputs raise the documented errors.

Scene: helpers see the target from below, 5-35 degrees up, against the sky (the
operating mode skyfix recommends: a clean background); target yaw uniform, tilt 3 deg
1-sigma; camera blur sigma 0.7 px (known, ``psf_sigma_px``), noise 0.01 of full scale,
up to 0.5 px of unknown motion blur.

Exit code 0 only when every goal of issue 8 is met. ``--quick`` runs fewer frames.
"""

from __future__ import annotations

import argparse
import glob
import math
import sys
import time

import cv2
import numpy as np

from skyfix.camera import Camera, CameraPose
from skyfix.crps import (
    DroneModel,
    GroundMotionConfig,
    GroundMotionFilter,
    SilhouetteConfig,
    SilhouetteDetector,
    SilhouetteFit,
    SilhouetteFitConfig,
    Tracker,
    locate,
    observe,
    prior_gate,
    prior_window,
    range_from_reference,
    shape_consistent,
)
from skyfix.datasets.drone_view import (
    TargetPose,
    render_drone_view,
    sky_background,
    terrain_background,
)
from skyfix.datasets.render import GroundTexture
from skyfix.errors import GeometryError, InputError
from skyfix.geo import LocalFrame, destination
from skyfix.progress import progress
from skyfix.types import GeoFix

CAMERA = Camera.from_fov(1920, 1080, 80.0)
MODEL = DroneModel.quad(0.5)
BLUR_PX = 0.7
NOISE = 0.01
LAT0, LON0, ALT0 = 47.0, 8.0, 400.0
CHI2_3DOF_95 = 7.814727903251178
TRACK_FRAMES = 15  # 0.5 s at 30 frames/s
SEQ_FRAMES = 16  # terrain sequences: 0.53 s at 30 frames/s


def scene(rng: np.random.Generator, range_m: float, below: bool = True,
          elev_range=(5.0, 35.0)) -> tuple[CameraPose, TargetPose]:
    """A helper pose and a target ``range_m`` away inside the field of view."""
    elev = rng.uniform(*elev_range)
    az = rng.uniform(0.0, 360.0)
    horiz = range_m * math.cos(math.radians(elev))
    dz = range_m * math.sin(math.radians(elev)) * (1.0 if below else -1.0)
    lat, lon = destination(LAT0, LON0, az, horiz)
    # Point the camera near the target, leaving it up to +-30 deg / +-15 deg off axis.
    pitch = (elev if below else -elev) + rng.uniform(-15.0, 15.0)
    yaw = az + rng.uniform(-30.0, 30.0)
    helper = CameraPose(LAT0, LON0, ALT0, yaw_deg=yaw, gimbal_pitch_deg=pitch)
    target = TargetPose(float(lat), float(lon), ALT0 + dz, yaw_deg=rng.uniform(0, 360),
                        pitch_deg=rng.normal(0, 3.0), roll_deg=rng.normal(0, 3.0))
    return helper, target


def render(rng, helper, target, **kw):
    kw.setdefault("motion_blur_px", rng.uniform(0.0, 0.5))
    return render_drone_view(CAMERA, helper, target, MODEL, blur_sigma_px=BLUR_PX, noise_sigma=NOISE,
                             motion_blur_angle_deg=rng.uniform(0, 180), rng=rng, **kw)


def bbox_width_px(image: np.ndarray, centre_uv: np.ndarray, half: int = 80) -> float:
    """The source method's apparent size: width of the pixels darker than half-way to the target."""
    u, v = int(round(centre_uv[0])), int(round(centre_uv[1]))
    win = image[max(v - half, 0):v + half, max(u - half, 0):u + half]
    bg = float(np.median(win))
    dark = bg - win
    mask = dark > 0.5 * float(dark.max())
    cols = np.flatnonzero(mask.any(axis=0))
    return float(cols[-1] - cols[0] + 1) if cols.size else float("nan")


def pct(x, q):
    return float(np.percentile(np.abs(x), q)) if len(x) else float("nan")


def accuracy(rng, n_per_range: int, detector, fit) -> tuple[dict, dict]:
    ranges = [10, 25, 40, 55, 70, 85, 100]
    # Reference image for the source method: level, nose-on, 20 m, no noise.
    ref_helper = CameraPose(LAT0, LON0, ALT0, yaw_deg=0.0, gimbal_pitch_deg=0.0)
    lat, lon = destination(LAT0, LON0, 0.0, 20.0)
    ref = render_drone_view(CAMERA, ref_helper, TargetPose(float(lat), float(lon), ALT0), MODEL,
                            blur_sigma_px=BLUR_PX)
    s0 = bbox_width_px(ref.image, ref.truth.centroid_uv)
    rows = {}
    allr, alls, allb, zs, zs_fit = [], [], [], [], []
    for rng_m in progress(ranges, desc="accuracy"):
        err, err_fit, sig_fit, src, berr, miss = [], [], [], [], [], 0
        for _ in range(n_per_range):
            helper, target = scene(rng, rng_m)
            view = render(rng, helper, target)
            found = [d for d in detector(view.image) if shape_consistent(CAMERA, helper, d)]
            if not found:
                miss += 1
                continue
            det = min(found, key=lambda d: float(np.linalg.norm(d.centroid_uv - view.truth.centroid_uv)))
            obs = observe(CAMERA, helper, det, 0.5, attitude_sigma_deg=0.0)
            err.append(obs.range_m / view.truth.range_m - 1.0)
            zs.append((obs.range_m - view.truth.range_m) / math.sqrt(obs.bearing_unit_enu @ obs.cov_enu_m2 @ obs.bearing_unit_enu))
            obs_fit = observe(CAMERA, helper, fit(view.image, det, helper), 0.5, attitude_sigma_deg=0.0)
            err_fit.append(obs_fit.range_m / view.truth.range_m - 1.0)
            sigma_fit_m = math.sqrt(obs_fit.bearing_unit_enu @ obs_fit.cov_enu_m2 @ obs_fit.bearing_unit_enu)
            zs_fit.append((obs_fit.range_m - view.truth.range_m) / sigma_fit_m)
            sig_fit.append(sigma_fit_m / obs_fit.range_m)
            berr.append(math.degrees(math.acos(min(1.0, float(obs.bearing_unit_enu @ view.truth.bearing_unit_enu)))))
            s1 = bbox_width_px(view.image, view.truth.centroid_uv)
            d_src = float(range_from_reference(20.0, s0, s1)[0]) if np.isfinite(s1) and s1 > 0 else np.inf
            src.append(d_src / view.truth.range_m - 1.0)
        rows[rng_m] = (err, src, berr, miss, err_fit, sig_fit)
        allr += err
        alls += src
        allb += berr
    tracked, tracked_fit, z_trk = {}, {}, []
    for rng_m in progress(ranges, desc="tracked"):
        errs, errs_fit = [], []
        for _ in range(n_per_range):
            helper, target = scene(rng, rng_m)
            tracker = Tracker(detector)
            tracker_fit = Tracker(detector, fit=fit)
            det = det_fit = None
            truth = None
            # The target drifts at 0.5 m/s in a random horizontal direction; 15 frames at 30 Hz.
            heading = rng.uniform(0, 360)
            for k in range(TRACK_FRAMES):
                lat, lon = destination(target.lat_deg, target.lon_deg, heading, 0.5 * k / 30.0)
                moved = TargetPose(float(lat), float(lon), target.alt_m, target.yaw_deg, target.pitch_deg,
                                   target.roll_deg)
                view = render(rng, helper, moved)
                det = tracker.update(view.image, k / 30.0) or det
                det_fit = tracker_fit.update(view.image, k / 30.0, helper) or det_fit
                truth = view.truth
            if det is not None and abs(det.time_s - (TRACK_FRAMES - 1) / 30.0) < 1e-9:
                errs.append(observe(CAMERA, helper, det, 0.5).range_m / truth.range_m - 1.0)
            if det_fit is not None and abs(det_fit.time_s - (TRACK_FRAMES - 1) / 30.0) < 1e-9:
                obs = observe(CAMERA, helper, det_fit, 0.5, attitude_sigma_deg=0.0)
                errs_fit.append(obs.range_m / truth.range_m - 1.0)
                z_trk.append((obs.range_m - truth.range_m) / math.sqrt(obs.bearing_unit_enu @ obs.cov_enu_m2 @ obs.bearing_unit_enu))
        tracked[rng_m] = errs
        tracked_fit[rng_m] = errs_fit
    return rows, {"all": (allr, alls, allb), "tracked": tracked, "tracked_fit": tracked_fit, "z": np.array(zs),
                  "z_fit": np.array(zs_fit), "z_trk": np.array(z_trk)}


def noise_free_fit(rng, detector, fit, n: int, range_m: float = 100.0) -> list[float]:
    """Single-frame fit range errors (relative) on renders without sensor noise or motion blur: what is left
    is the model error the fit cannot remove (its stated model_sigma_rel should match the RMS)."""
    errs = []
    for _ in range(n):
        helper, target = scene(rng, range_m)
        view = render_drone_view(CAMERA, helper, target, MODEL, blur_sigma_px=BLUR_PX, noise_sigma=0.0, rng=rng)
        found = [d for d in detector(view.image) if shape_consistent(CAMERA, helper, d)]
        if not found:
            continue
        det = min(found, key=lambda d: float(np.linalg.norm(d.centroid_uv - view.truth.centroid_uv)))
        obs = observe(CAMERA, helper, fit(view.image, det, helper), 0.5, attitude_sigma_deg=0.0)
        errs.append(obs.range_m / view.truth.range_m - 1.0)
    return errs


def two_helpers(rng, n: int, detector) -> tuple[np.ndarray, np.ndarray]:
    errors, maha = [], []
    for _ in progress(range(n), desc="two helpers"):
        frame = LocalFrame(LAT0, LON0, ALT0)
        az0 = rng.uniform(0, 360)
        sep = rng.uniform(60.0, 120.0)
        obs = []
        ok = True
        for az in (az0, az0 + sep):
            d = rng.uniform(40.0, 70.0)
            elev = rng.uniform(5.0, 30.0)
            # Helper below the target (at the frame origin), looking up at it.
            hlat, hlon = destination(LAT0, LON0, az + 180.0, d * math.cos(math.radians(elev)))
            halt = ALT0 - d * math.sin(math.radians(elev))
            yaw, pitch = az + rng.uniform(-20, 20), elev + rng.uniform(-10, 10)
            true_pose = CameraPose(float(hlat), float(hlon), halt, yaw_deg=yaw, gimbal_pitch_deg=pitch)
            target = TargetPose(LAT0, LON0, ALT0, yaw_deg=rng.uniform(0, 360), pitch_deg=rng.normal(0, 3),
                                roll_deg=rng.normal(0, 3))
            view = render(rng, true_pose, target)
            found = [d for d in detector(view.image) if shape_consistent(CAMERA, true_pose, d)]
            if not found:
                ok = False
                break
            # The helper knows its own pose only to GNSS/AHRS accuracy.
            e, nn, u = (float(x) for x in frame.to_enu(hlat, hlon, halt))
            pos_sigma = np.array([0.5, 0.5, 0.8])
            est = frame.to_geodetic(e + rng.normal(0, 0.5), nn + rng.normal(0, 0.5), u + rng.normal(0, 0.8))
            att_sigma = 0.3
            est_pose = CameraPose(float(est[0]), float(est[1]), float(est[2]),
                                  yaw_deg=yaw + rng.normal(0, att_sigma),
                                  gimbal_pitch_deg=pitch + rng.normal(0, att_sigma),
                                  gimbal_roll_deg=rng.normal(0, att_sigma))
            det = max(found, key=lambda dd: dd.score)
            obs.append(observe(CAMERA, est_pose, det, 0.5, attitude_sigma_deg=att_sigma,
                               observer_id=f"h{len(obs)}", target_id="t",
                               observer_cov_enu_m2=np.diag(pos_sigma ** 2)))
        if not ok:
            continue
        fix = locate(obs)
        err = np.array([float(x) for x in frame.to_enu(fix.lat_deg, fix.lon_deg, fix.alt_m)])
        errors.append(float(np.linalg.norm(err)))
        maha.append(float(err @ np.linalg.solve(fix.cov_enu_m2, err)))
    return np.array(errors), np.array(maha)


def speed(rng, detector, fit, n: int, range_m: float) -> tuple[float, float]:
    """(full-frame, tracking) frames/s of one core at ``range_m``; tracking is the documented Tracker(fit) path."""
    helper, target = scene(rng, range_m)
    views = [render(rng, helper, target) for _ in range(n)]
    t0 = time.process_time()
    for v in views:
        found = [d for d in detector(v.image) if shape_consistent(CAMERA, helper, d)]
        observe(CAMERA, helper, found[0], 0.5)
    full = (time.process_time() - t0) / n
    tracker = Tracker(detector, fit=fit)
    tracker.update(views[0].image, 0.0, helper)
    t0 = time.process_time()
    for k, v in enumerate(views[1:], start=1):
        det = tracker.update(v.image, k / 30.0, helper)
        if shape_consistent(CAMERA, helper, det):
            observe(CAMERA, helper, det, 0.5)
    roi = (time.process_time() - t0) / (n - 1)
    return 1.0 / full, 1.0 / roi


def sky_false_detections(rng, detector, n_sky: int) -> int:
    fp_sky = 0
    for _ in progress(range(n_sky), desc="sky, no target"):
        helper = CameraPose(LAT0, LON0, ALT0, yaw_deg=rng.uniform(0, 360), gimbal_pitch_deg=rng.uniform(0, 60),
                            gimbal_roll_deg=rng.normal(0, 5))
        img = sky_background(CAMERA, helper, rng, clouds=rng.uniform(0.0, 0.15), cloud_cells=int(rng.integers(4, 16)))
        img = cv2.GaussianBlur(img, (0, 0), BLUR_PX) + rng.standard_normal(img.shape, dtype=np.float32) * NOISE
        fp_sky += sum(shape_consistent(CAMERA, helper, d) for d in detector(img))
    return fp_sky


def _textures() -> list[GroundTexture]:
    frame = LocalFrame(LAT0, LON0, ALT0)
    return [GroundTexture(cv2.imread(p, cv2.IMREAD_GRAYSCALE).astype(np.float32) / 255.0, 0.15, frame)
            for p in sorted(glob.glob("/work/shared/data/seneca-subset/*.jpg"))]


class _ShapeGated:
    """The detector followed by the shape gate for the current frame's helper pose (a Detector)."""

    def __init__(self, detector) -> None:
        self.detector = detector
        self.pose: CameraPose | None = None

    def __call__(self, image, roi=None):
        return [d for d in self.detector(image, roi) if shape_consistent(CAMERA, self.pose, d)]


def terrain_sequences(rng, detector, fit, textures, n_seq: int, with_target: bool) -> dict:
    """Helper flying over terrain (real aerial photos), SEQ_FRAMES frames at 30 Hz per sequence.

    Helper 30-60 m above the ground, camera 60-90 deg down, 3-8 m/s, yawing 2 deg/s; the
    pose given to skyfix has 0.3 m / 0.3 deg of independent noise per frame. Paths on
    the same frames: the default single-frame path (detector + shape gate), the prior gate
    option, and the sequence path recommended for terrain, Tracker(detector + shape gate,
    fit=SilhouetteFit, ground=GroundMotionFilter). With a target: a 0.5 m quad 12-35 m from the helper
    (below it, over the ground), drifting 0-3 m/s.
    """
    frame = LocalFrame(LAT0, LON0, ALT0)
    out = {"frames": 0, "seq_frames": 0, "single": 0, "prior": 0, "seq": 0, "single_hit": 0, "seq_hit": 0,
           "seq_wrong": 0, "seq_range": [], "cpu_s": 0.0,
           "cpu_track_s": 0.0, "track_frames": 0}
    desc = "terrain sequences, target" if with_target else "terrain sequences, no target"
    for _ in progress(range(n_seq), desc=desc):
        tex = textures[int(rng.integers(len(textures)))]
        agl = rng.uniform(30.0, 60.0)
        heading, speed = rng.uniform(0, 360), rng.uniform(3.0, 8.0)
        yaw0, pitch = rng.uniform(0, 360), rng.uniform(-90.0, -60.0)
        start = destination(LAT0, LON0, heading + 180.0, speed * SEQ_FRAMES / 60.0)
        gated = _ShapeGated(detector)
        ground = GroundMotionFilter(CAMERA, ALT0, 0.5, config=GroundMotionConfig(psf_sigma_px=BLUR_PX))
        tracker = Tracker(gated, fit=fit, ground=ground)
        target = None
        for k in range(SEQ_FRAMES):
            t = k / 30.0
            lat, lon = destination(float(start[0]), float(start[1]), heading, speed * t)
            truth = CameraPose(float(lat), float(lon), ALT0 + agl, yaw_deg=yaw0 + 2.0 * t, gimbal_pitch_deg=pitch)
            e, n, u = (float(x) for x in frame.to_enu(truth.lat_deg, truth.lon_deg, truth.alt_m))
            est = frame.to_geodetic(e + rng.normal(0, 0.3), n + rng.normal(0, 0.3), u + rng.normal(0, 0.3))
            pose = CameraPose(float(est[0]), float(est[1]), float(est[2]), yaw_deg=truth.yaw_deg + rng.normal(0, 0.3),
                              gimbal_pitch_deg=pitch + rng.normal(0, 0.3), gimbal_roll_deg=rng.normal(0, 0.3))
            if with_target:
                if target is None:
                    ray = CAMERA.pixel_to_ray(np.array([[rng.uniform(400, 1520), rng.uniform(250, 830)]]))[0]
                    cam_enu, r_frame_from_cam = truth.in_frame(frame)
                    p = cam_enu + r_frame_from_cam @ ray * rng.uniform(12.0, 35.0)
                    target = (*frame.to_geodetic(*p), rng.uniform(0, 360), rng.uniform(0, 3.0), rng.uniform(0, 360))
                tlat, tlon = destination(float(target[0]), float(target[1]), target[5], target[4] * t)
                view = render(rng, truth, TargetPose(float(tlat), float(tlon), float(target[2]), target[3],
                                                     rng.normal(0, 3), rng.normal(0, 3)), background=tex)
                img = view.image
            else:
                img = terrain_background(tex, CAMERA, truth, rng)
                img = cv2.GaussianBlur(img, (0, 0), BLUR_PX) + rng.standard_normal(img.shape, dtype=np.float32) * NOISE
            gated.pose = pose
            found = gated(img)
            t0 = time.process_time()
            det = tracker.update(img, t, pose)
            cpu = time.process_time() - t0
            out["cpu_s"] += cpu
            if tracker.tracking and not tracker.ground_checked:
                out["cpu_track_s"] += cpu
                out["track_frames"] += 1
            out["frames"] += 1
            if with_target:
                near = [d for d in found if np.linalg.norm(d.centroid_uv - view.truth.centroid_uv) < 10 + d.extent_px]
                out["single_hit"] += bool(near) and k > 0  # the frames the sequence path is scored on
                out["single"] += len(found) - len(near)
            else:
                out["single"] += len(found)
                ray = CAMERA.pixel_to_ray(np.array([[rng.uniform(300, 1620), rng.uniform(200, 880)]]))[0]
                cam_enu, r_frame_from_cam = pose.in_frame(frame)
                plat, plon, palt = frame.to_geodetic(*(cam_enu + r_frame_from_cam @ ray * rng.uniform(20.0, 40.0)))
                prior = GeoFix(float(plat), float(plon), float(palt), np.diag([25.0, 25.0, 9.0]))
                out["prior"] += len(prior_gate(prior_window(CAMERA, pose, prior), found))
            if k == 0:
                continue  # the sequence path has no earlier frame yet: it cannot report
            out["seq_frames"] += 1
            if det is None:
                continue
            if with_target and np.linalg.norm(det.centroid_uv - view.truth.centroid_uv) < 10 + det.extent_px:
                out["seq_hit"] += 1
                out["seq_range"].append(observe(CAMERA, pose, det, 0.5).range_m / view.truth.range_m - 1.0)
            elif with_target:
                out["seq_wrong"] += 1
            else:
                out["seq"] += 1
    return out


def bad_inputs() -> list[str]:
    lines = []
    det = SilhouetteDetector()
    helper = CameraPose(LAT0, LON0, ALT0, gimbal_pitch_deg=0.0)
    rng = np.random.default_rng(0)
    view = render_drone_view(CAMERA, helper, TargetPose(*destination(LAT0, LON0, 0.0, 20.0), ALT0), MODEL,
                             blur_sigma_px=BLUR_PX, noise_sigma=NOISE, rng=rng)
    d = det(view.image)[0]
    cases = {
        "zero size": lambda: observe(CAMERA, helper, d, 0.0),
        "NaN pose": lambda: CameraPose(float("nan"), LON0, ALT0),
        "target behind camera": lambda: render_drone_view(
            CAMERA, helper, TargetPose(*destination(LAT0, LON0, 180.0, 20.0), ALT0), MODEL),
        "empty image": lambda: det(np.zeros((0, 0), np.uint8)),
    }
    for name, fn in cases.items():
        try:
            fn()
            lines.append(f"  {name}: NO ERROR")
        except (InputError, GeometryError) as exc:
            lines.append(f"  {name}: {type(exc).__name__}: {exc}")
    return lines


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="fewer frames (not enough for the 1/1000 claim)")
    ap.add_argument("--seed", type=int, default=8)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    rng = np.random.default_rng(args.seed)
    detector = SilhouetteDetector(SilhouetteConfig(psf_sigma_px=BLUR_PX))
    fit = SilhouetteFit(CAMERA, MODEL, SilhouetteFitConfig(psf_sigma_px=BLUR_PX))
    n_acc, n_two, n_fp = (12, 40, 100) if args.quick else (40, 200, 1000)
    n_seq_free, n_seq_target = (6, 3) if args.quick else (70, 20)
    goals = {}

    rows, extra = accuracy(rng, n_acc, detector, fit)
    print("1. range / bearing vs distance (sky, seen from 5-35 deg below). Single frames: 'moments' = detector +")
    print("   observe; 'fit' = detector + SilhouetteFit (model least squares; extent <= 14 px, else moments) + observe;")
    print("   'sigma' = the fit path's median stated range 1-sigma (relative).")
    print(f"   TRACKED = the documented path, Tracker(detector, fit=SilhouetteFit) with the helper pose, "
          f"{TRACK_FRAMES} frames at 30 Hz, last frame's observe; 'trk mom' = Tracker(detector) (moments only) on "
          "the same frames.")
    print(f"{'range':>6} {'n':>4} {'miss':>4} | {'moments med':>11} {'p95':>6} | {'fit med':>7} {'p95':>6} "
          f"{'sigma':>6} | "
          f"{'bearing p95':>11} | {'source med':>10} {'p95':>6} | {'TRACKED med':>11} {'p95':>6} {'n':>3} | "
          f"{'trk mom med':>11} {'p95':>6}")
    for rng_m, (err, src, berr, miss, err_fit, sig_fit) in rows.items():
        trk, trkm = extra["tracked_fit"][rng_m], extra["tracked"][rng_m]
        print(f"{rng_m:5d}m {len(err):4d} {miss:4d} | {pct(err, 50) * 100:10.2f}% {pct(err, 95) * 100:5.2f}% | "
              f"{pct(err_fit, 50) * 100:6.2f}% {pct(err_fit, 95) * 100:5.2f}% {pct(sig_fit, 50) * 100:5.2f}% | "
              f"{pct(berr, 95):10.4f}° | "
              f"{pct(src, 50) * 100:9.2f}% {pct(src, 95) * 100:5.2f}% | "
              f"{pct(trk, 50) * 100:10.2f}% {pct(trk, 95) * 100:5.2f}% {len(trk):3d} | "
              f"{pct(trkm, 50) * 100:10.2f}% {pct(trkm, 95) * 100:5.2f}%")
    allr, alls, allb = extra["all"]
    allf = [e for r in rows.values() for e in r[4]]
    n_miss = sum(r[3] for r in rows.values())
    tracked_all = [e for v in extra["tracked_fit"].values() for e in v]
    print(f"  all: single-frame moments median {pct(allr, 50) * 100:.2f}% p95 {pct(allr, 95) * 100:.2f}%, single-frame "
          f"fit median {pct(allf, 50) * 100:.2f}% p95 {pct(allf, 95) * 100:.2f}%, bearing median "
          f"{pct(allb, 50):.4f}° max {max(allb):.4f}°, missed {n_miss}; source median "
          f"{pct(alls, 50) * 100:.2f}% p95 {pct(alls, 95) * 100:.2f}%; TRACKED ({TRACK_FRAMES} frames) median "
          f"{pct(tracked_all, 50) * 100:.2f}% p95 {pct(tracked_all, 95) * 100:.2f}%")
    for name, z in (("moments", extra["z"]), ("fit", extra["z_fit"])):
        print(f"  single-frame {name} range error / stated sigma: within 1.96 sigma in "
              f"{np.mean(np.abs(z) <= 1.96) * 100:.1f}% (95% expected), RMS {np.sqrt(np.mean(z ** 2)):.2f} (1 expected)")
    z_trk = extra["z_trk"]
    print(f"  TRACKED range error / stated sigma: within 1.96 sigma in {np.mean(np.abs(z_trk) <= 1.96) * 100:.1f}% "
          f"(95% expected), RMS {np.sqrt(np.mean(z_trk ** 2)):.2f}")
    nf = np.array(noise_free_fit(rng, detector, fit, 12 if args.quick else 40))
    print(f"  [info] noise-free single frames at 100 m (no sensor noise, no motion blur), fit: n={len(nf)}, "
          f"mean {nf.mean() * 100:+.2f}%, RMS {np.sqrt(np.mean(nf ** 2)) * 100:.2f}%, "
          f"p95 |error| {pct(np.abs(nf), 95) * 100:.2f}% (model error the fit keeps; stated model_sigma_rel "
          f"{fit.config.model_sigma_rel * 100:.1f}%)")
    single_med = all(pct(r[4], 50) <= 0.03 for r in rows.values())
    single_p95 = max(pct(r[4], 95) for r in rows.values())
    print(f"  [info, not the documented path] single frame (fit): median <= 3% at every distance: "
          f"{'yes' if single_med else 'no'}; worst p95 {single_p95 * 100:.2f}% (goal 6%: "
          f"{'yes' if single_p95 <= 0.06 else 'no'}; one frame at 85-100 m is limited by its noise, "
          "its stated 1-sigma there is in the 'sigma' column; 1.96 sigma bounds 95%)")
    tracked = extra["tracked_fit"]
    goals["TRACKED range median <= 3% (every distance)"] = all(pct(e, 50) <= 0.03 for e in tracked.values())
    goals["TRACKED range p95 <= 6% (every distance)"] = all(pct(e, 95) <= 0.06 for e in tracked.values())
    goals["bearing error <= 0.1 deg (p95)"] = pct(allb, 95) <= 0.1

    errors, maha = two_helpers(rng, n_two, detector)
    inside = float(np.mean(maha <= CHI2_3DOF_95)) if maha.size else 0.0
    print(f"2. two helpers 40-70 m, 60-120 deg apart, helper pose noise 0.5/0.8 m and 0.3 deg: n={errors.size} "
          f"median {np.median(errors):.2f} m, p95 {np.percentile(errors, 95):.2f} m; truth inside the 95% "
          f"ellipsoid in {inside * 100:.1f}% of fixes, mean NEES {np.mean(maha):.2f} (3 expected)")
    goals["two-helper median <= 1.5 m"] = float(np.median(errors)) <= 1.5
    goals["95% ellipsoid holds the truth 90-99% of the time"] = 0.90 <= inside <= 0.99

    full_fps, roi_fps = speed(rng, detector, fit, 12 if args.quick else 40, 55.0)
    full_far, roi_far = speed(rng, detector, fit, 12 if args.quick else 40, 100.0)
    print(f"3. one core (process_time, cv2.setNumThreads(1)), 1920x1080, detect + observe: full-frame "
          f"{full_fps:.1f} frames/s at 55 m, {full_far:.1f} at 100 m; tracking (ROI, Tracker with the fit) "
          f"{roi_fps:.1f} frames/s at 55 m, {roi_far:.1f} at 100 m")
    full_fps, roi_fps = min(full_fps, full_far), min(roi_fps, roi_far)
    goals["tracking >= 30 frames/s"] = roi_fps >= 30.0
    goals["full-frame >= 5 frames/s"] = full_fps >= 5.0

    fp_sky = sky_false_detections(rng, detector, n_fp)
    textures = _textures()
    free = terrain_sequences(rng, detector, fit, textures, n_seq_free, with_target=False)
    tgt = terrain_sequences(rng, detector, fit, textures, n_seq_target, with_target=True)
    print(f"4. false detections without a target. Sky, single frames (random attitude, clouds): {fp_sky}/{n_fp}.")
    print(f"   Terrain: {n_seq_free} sequences x {SEQ_FRAMES} frames over real aerial photos, helper 30-60 m up, "
          "3-8 m/s, pose noise 0.3 m / 0.3 deg per frame:")
    print(f"   - DEFAULT single-frame path (detector + shape gate): {free['single']}/{free['frames']} frames "
          f"({free['single'] / free['frames'] * 1000:.1f} per 1000)")
    print(f"   - option, single frame + prior gate (last known position 20-40 m, 5 m 1-sigma): "
          f"{free['prior']}/{free['frames']}")
    print(f"   - SEQUENCE path for terrain (Tracker + GroundMotionFilter), frames after the first of each sequence: "
          f"{free['seq']}/{free['seq_frames']} ({free['seq'] / free['seq_frames'] * 1000:.2f} per 1000)")
    hit_single = tgt["single_hit"] / max(tgt["seq_frames"], 1)
    hit_seq = tgt["seq_hit"] / max(tgt["seq_frames"], 1)
    print(f"   With a target over terrain ({n_seq_target} sequences, 0.5 m quad 12-35 m away below the helper, "
          f"0-3 m/s), frames after the first: target detected in {hit_single * 100:.1f}% of frames by the "
          f"single-frame path, {hit_seq * 100:.1f}% by the sequence path ({tgt['seq_hit']}/{tgt['seq_frames']}); "
          f"the sequence path reported something else in {tgt['seq_wrong']}/{tgt['seq_frames']} frames, the "
          f"single-frame path {tgt['single']} times; sequence-path range median "
          f"{pct(tgt['seq_range'], 50) * 100:.2f}% p95 {pct(tgt['seq_range'], 95) * 100:.2f}%")
    track_fps = tgt["track_frames"] / tgt["cpu_track_s"] if tgt["cpu_track_s"] > 0 else float("nan")
    print(f"   sequence path speed, one core (process_time): {free['frames'] / free['cpu_s']:.1f} frames/s "
          f"without a track (full-frame search + ground check); on the target sequences {tgt['frames'] / tgt['cpu_s']:.1f} "
          f"frames/s overall, {track_fps:.1f} frames/s on the {tgt['track_frames']} confirmed-track frames "
          "(ROI, fit, ground check every 10th frame)")
    goals["sky: <= 1 false detection per 1000 frames (single frame)"] = fp_sky <= max(1, n_fp // 1000)
    fp_terrain = free["seq"] + tgt["seq_wrong"]
    n_terrain = free["seq_frames"] + tgt["seq_frames"]
    goals["terrain: <= 1 false detection per 1000 frames (sequence path, the documented one for terrain)"] = (
        fp_terrain <= max(1, n_terrain // 1000))
    # Guard, not an issue goal: a ground filter that dropped everything would meet the line above.
    goals["terrain: the sequence path keeps >= 80% of the single-frame path's target detections"] = (
        hit_seq >= 0.8 * hit_single and tgt["seq_hit"] > 0)
    print("5. bad inputs:")
    lines = bad_inputs()
    print("\n".join(lines))
    goals["bad inputs raise clear errors"] = not any("NO ERROR" in ln for ln in lines)

    for name, ok in goals.items():
        print(f"   [{'met' if ok else 'NOT MET'}] {name}")
    met = sum(goals.values())
    worst_p95 = max(pct(e, 95) for e in extra["tracked_fit"].values())
    print(f"ranging: {met}/{len(goals)} goals met; TRACKED range median {pct(tracked_all, 50) * 100:.2f}% "
          f"(worst distance p95 {worst_p95 * 100:.2f}%; single-frame fit median {pct(allf, 50) * 100:.2f}%, "
          f"source {pct(alls, 50) * 100:.2f}%), two-helper median {np.median(errors):.2f} m, "
          f"{roi_fps:.0f}/{full_fps:.0f} fps ROI/full, false detections sky {fp_sky}/{n_fp}, terrain "
          f"{fp_terrain}/{n_terrain} (sequence path; single-frame {free['single']}/{free['frames']})")
    return 0 if met == len(goals) else 1


if __name__ == "__main__":
    sys.exit(main())
