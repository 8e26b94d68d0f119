"""Fiducial tag localisation: skyfix tile tags vs AprilTag 36h11 (skyfix via cv2.aruco, and
pupil-apriltags, the AprilTag 3 C library) on the same rendered frames.

Setup: 640x480 camera, 60 deg HFOV, straight down on the vehicle; heights 1-3 m, roll and
pitch up to +-15 deg, random yaw; uneven lighting (up to 40 % darker), sensor noise, up to
3 px motion blur. The tile field is sized by skyfix.tags.dimensioning (c=6, n=4, as the
source chose); the AprilTag board puts a marker of the same printed size at every tag
position. Each pose is rendered twice, once per field, with the same effects (same seed).
The IMU prior is the true roll/pitch plus N(0, 0.5 deg) noise, sigma 1 deg. Speed is CPU
time per frame (time.process_time) with cv2.setNumThreads(1) and pupil nthreads=1.

Goals (issue 4): tile RMSE <= 3 cm, yaw RMSE <= 1 deg, worst outlier <= 8 cm; tile frame
rate >= 2x pupil-apriltags; RMSE at 30 % occlusion <= 1.5x unoccluded and a misread tag
moving the fix by <= 5 cm; placement of 400 tags (c=6, n=4) in <= 10 s beating random
placement's minimum adjacent distance; grey / empty / foreign frames give no fix.
Exit status 1 if any goal is missed. Last line: the headline figures.
"""

from __future__ import annotations

import os

# One thread each: BLAS/OpenMP pools would otherwise add their threads' CPU time to
# time.process_time() (and run in parallel), before numpy is imported.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import sys  # noqa: E402
import time  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

# ruff: noqa: E402
from skyfix.camera import Camera
from skyfix.datasets.tag_scene import SceneEffects, field_texture, random_poses, render_tag_frame
from skyfix.errors import EstimationError
from skyfix.tags.aruco import ArucoField, fix_from_corners, locate_aruco, make_detector
from skyfix.tags.codec import TagGeometry, TileCodec
from skyfix.tags.dimensioning import dimension
from skyfix.tags.field import TagField
from skyfix.tags.locate import locate_tiles
from skyfix.tags.placement import optimise_placement
from skyfix.tags.pose import AttitudePrior

N_POSES = 80
N_OCCLUSION = 40
FIELD_ITERATIONS = 120_000   # about what 5 s of annealing reached before


def _err(fix, fr) -> tuple[float, float]:
    return (float(np.hypot(fix.x_m - fr.x_m, fix.y_m - fr.y_m)),
            float((fix.yaw_deg - fr.yaw_deg + 180.0) % 360.0 - 180.0))


class Pupil:
    """pupil-apriltags detections turned into a fix by the same skyfix pose solver."""

    def __init__(self, board: ArucoField, camera: Camera) -> None:
        from pupil_apriltags import Detector

        self.det = Detector(families="tag36h11", nthreads=1)
        self.board, self.camera = board, camera
        self.order = None   # pupil's corner order -> OpenCV's (NW, NE, SE, SW), found once

    def detect(self, rgb):
        grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        return grey, self.det.detect(grey)

    def fix(self, grey, dets, prior):
        if not dets:
            raise EstimationError("pupil-apriltags found no tags")
        corners = np.stack([d.corners for d in dets])
        ids = np.array([d.tag_id for d in dets])
        if self.order is None:
            best = None
            for flip in (False, True):
                for shift in range(4):
                    perm = np.roll(np.arange(4)[::-1] if flip else np.arange(4), shift)
                    try:
                        f = fix_from_corners(corners[:, perm], ids, self.board, self.camera, prior=prior)
                    except EstimationError:
                        continue
                    if best is None or f.reprojection_rms_px < best[0]:
                        best = (f.reprojection_rms_px, perm)
            self.order = best[1]
            print(f"  pupil-apriltags corner order -> OpenCV order: {self.order.tolist()}")
        return fix_from_corners(corners[:, self.order], ids, self.board, self.camera, grey=grey, prior=prior)


def run_methods(poses, tile_tex, tag_tex, field, board, camera, effects, seed, pupil, aruco_det, collect_time):
    rows = {"tiles": [], "apriltag_cv2": [], "pupil": []}
    times = {"tiles": [], "apriltag_cv2": [], "pupil_detect": [], "pupil_fix": []}
    rng_prior = np.random.default_rng(seed + 1)
    for i, p in enumerate(poses):
        ft = render_tag_frame(tile_tex, camera, *p, effects=effects, rng=np.random.default_rng(seed + i))
        fa = render_tag_frame(tag_tex, camera, *p, effects=effects, rng=np.random.default_rng(seed + i))
        prior = AttitudePrior(ft.roll_deg + rng_prior.normal(0, 0.5), ft.pitch_deg + rng_prior.normal(0, 0.5), 1.0)
        for name, fn, fr in (("tiles", lambda im, pr=prior: locate_tiles(im, field, camera, prior=pr), ft),
                             ("apriltag_cv2", lambda im, pr=prior: locate_aruco(im, board, camera, prior=pr,
                                                                                detector=aruco_det), fa)):
            t0 = time.process_time()
            try:
                fix = fn(fr.image)
                rows[name].append(_err(fix, fr))
            except EstimationError:
                rows[name].append(None)
            times[name].append(time.process_time() - t0)
        t0 = time.process_time()
        grey, dets = pupil.detect(fa.image)
        t1 = time.process_time()
        try:
            fix = pupil.fix(grey, dets, prior)
            rows["pupil"].append(_err(fix, fa))
        except EstimationError:
            rows["pupil"].append(None)
        times["pupil_detect"].append(t1 - t0)
        times["pupil_fix"].append(time.process_time() - t0)
    return rows, times


def summary(errs):
    ok = [e for e in errs if e is not None]
    if not ok:
        return {"rmse_m": float("inf"), "yaw_rmse_deg": float("inf"), "worst_m": float("inf"), "success": 0.0}
    pos = np.array([e[0] for e in ok])
    yaw = np.array([e[1] for e in ok])
    return {"rmse_m": float(np.sqrt(np.mean(pos ** 2))), "yaw_rmse_deg": float(np.sqrt(np.mean(yaw ** 2))),
            "worst_m": float(pos.max()), "success": len(ok) / len(errs)}


def misread_shift(field, camera, rng) -> tuple[float, int]:
    """Largest fix shift caused by one misprinted tag near the image centre, over poses."""
    worst, rejected_min = 0.0, 10 ** 6
    tex = field_texture(field)
    for k in range(8):
        x = rng.uniform(1.0, field.cols * field.spacing_m - 1.0)
        y = rng.uniform(1.0, field.rows * field.spacing_m - 1.0)
        pose = (x, y, rng.uniform(1.0, 3.0), rng.uniform(-180, 180), rng.uniform(-10, 10), rng.uniform(-10, 10))
        clean = render_tag_frame(tex, camera, *pose, rng=np.random.default_rng(k))
        prior = AttitudePrior(clean.roll_deg, clean.pitch_deg, 1.0)
        f0 = locate_tiles(clean.image, field, camera, prior=prior)
        v = field.values.copy().ravel()
        centre = int(np.argmin(np.linalg.norm(field.centres_m() - [x, y], axis=1)))
        far = int(np.argmax(np.linalg.norm(field.centres_m() - [x, y], axis=1)))
        v[centre], v[far] = v[far], v[centre]      # the misprint shows a far tag's value
        bad_tex = field_texture(TagField(field.codec, field.geometry, field.spacing_m, v.reshape(field.values.shape)))
        bad = render_tag_frame(bad_tex, camera, *pose, rng=np.random.default_rng(k))
        f1 = locate_tiles(bad.image, field, camera, prior=prior)
        worst = max(worst, float(np.hypot(f1.x_m - f0.x_m, f1.y_m - f0.y_m)))
        rejected_min = min(rejected_min, f1.rejected)
    return worst, rejected_min


def bad_inputs(field, camera, rng) -> list[tuple[str, str]]:
    out = []
    frames = {"grey": np.full((480, 640, 3), 128, np.uint8),
              "white paper": np.full((480, 640, 3), 235, np.uint8),
              "noise": rng.integers(0, 256, (480, 640, 3), dtype=np.uint8)}
    for name, img in frames.items():
        try:
            fix = locate_tiles(img, field, camera)
            out.append((name, f"FIX x={fix.x_m:.3f} y={fix.y_m:.3f} sigma={fix.sigma_xy_m:.3f} m"))
        except EstimationError as exc:
            out.append((name, f"no fix: {exc}"))
    # Frames of other fields (same design, other placements): their values exist here too.
    fixes, n = [], 0
    for k in range(4):
        other = TagField.generate(field.rows, field.cols, tile_m=field.geometry.tile_m, gap_m=field.geometry.gap_m,
                                  offset_m=field.geometry.offset_m, spacing_m=field.spacing_m,
                                  time_limit_s=0.3, seed=40 + k)
        tex = field_texture(other)
        x0, y0, x1, y1 = other.bounds_m()
        for p in random_poses(8, (x0 + 0.9, y0 + 0.9, x1 - 0.9, y1 - 0.9), rng=rng):
            eff = SceneEffects(occlusion_share=float(rng.choice([0.0, 0.3])), noise_sigma=0.015, lighting=0.4)
            img = render_tag_frame(tex, camera, *p, effects=eff, rng=rng).image
            n += 1
            try:
                fix = locate_tiles(img, field, camera)
                fixes.append(fix.sigma_xy_m)
            except EstimationError:
                pass
    out.append((f"{n} frames of 4 other fields",
                "no fix: none localised" if not fixes else f"FIX in {len(fixes)} frames, sigma {fixes}"))
    return out


def main() -> int:
    cv2.setNumThreads(1)
    rng = np.random.default_rng(2026)
    camera = Camera.from_fov(640, 480, 60.0)
    dim = dimension(4.5, 4.5, camera, 1.0, 3.0, tilt_deg=15.0)
    print(f"dimensioning: tile {dim.tile_m * 100:.2f} cm, gap {dim.gap_m * 100:.2f} cm, spacing "
          f"{dim.spacing_m * 100:.1f} cm, grid {dim.rows}x{dim.cols}, Pareto (c, n) {list(dim.pareto)}, "
          f"admissible {list(dim.admissible)}")

    t0 = time.perf_counter()
    codec = TileCodec(6, 4)
    _, placement = optimise_placement(codec, 20, 20, time_limit_s=8.0)
    placement_s = time.perf_counter() - t0
    print(f"placement 20x20, c=6 n=4: {placement_s:.2f} s wall, min adjacent distance {placement.min_distance:.1f} "
          f"vs random {placement.random_min:.1f} (median of {placement.random_trials}); mean "
          f"{placement.mean_distance:.1f} vs {placement.random_mean:.1f}")

    # The benchmark's field comes from a fixed annealing budget, not a time limit: every run
    # (whatever the machine's load) measures the same field, so runs compare.
    values, report = optimise_placement(codec, dim.rows, dim.cols, time_limit_s=120.0,
                                        max_iterations=FIELD_ITERATIONS, seed=1)
    field = TagField(codec, TagGeometry(codec.tiles, dim.tile_m, dim.gap_m, dim.offset_m), dim.spacing_m,
                     values, placement=report)
    board = ArucoField("apriltag_36h11", dim.rows, dim.cols, field.geometry.size_m, dim.spacing_m)
    tile_tex, tag_tex = field_texture(field), field_texture(board)
    x0, y0, x1, y1 = field.bounds_m()
    inner = (x0 + 0.9, y0 + 0.9, x1 - 0.9, y1 - 0.9)
    pupil = Pupil(board, camera)
    aruco_det = make_detector(board)

    poses = random_poses(N_POSES, inner, heights_m=(1.0, 3.0), tilt_deg=15.0, rng=rng)
    blur = rng.uniform(0.0, 3.0, N_POSES)
    results, times = {}, {}
    rows_all = {"tiles": [], "apriltag_cv2": [], "pupil": []}
    t_all = {"tiles": [], "apriltag_cv2": [], "pupil_detect": [], "pupil_fix": []}
    for i, p in enumerate(poses):
        eff = SceneEffects(lighting=0.4, noise_sigma=0.015, motion_blur_px=float(blur[i]),
                           motion_blur_angle_deg=float(rng.uniform(0, 180)))
        r, t = run_methods([p], tile_tex, tag_tex, field, board, camera, eff, 100 + i, pupil, aruco_det, True)
        for k in rows_all:
            rows_all[k] += r[k]
        for k in t_all:
            t_all[k] += t[k]
    for k, v in rows_all.items():
        results[k] = summary(v)
    times = {k: float(np.mean(v)) for k, v in t_all.items()}
    print(f"\n{N_POSES} frames, heights 1-3 m, tilt <= 15 deg, lighting 40 %, noise 0.015, blur <= 3 px:")
    print(f"{'method':<16}{'RMSE cm':>9}{'yaw RMSE deg':>14}{'worst cm':>10}{'fixes':>8}{'ms/frame':>10}{'fps':>8}")
    labels = {"tiles": ("skyfix tiles", times["tiles"]), "apriltag_cv2": ("skyfix AprilTag", times["apriltag_cv2"]),
              "pupil": ("pupil+skyfix", times["pupil_fix"])}
    for k, (label, t) in labels.items():
        s = results[k]
        print(f"{label:<16}{s['rmse_m'] * 100:>9.2f}{s['yaw_rmse_deg']:>14.3f}{s['worst_m'] * 100:>10.2f}"
              f"{s['success'] * 100:>7.0f}%{t * 1000:>10.2f}{1 / t:>8.1f}")
    print(f"pupil-apriltags detection alone: {times['pupil_detect'] * 1000:.2f} ms/frame "
          f"({1 / times['pupil_detect']:.1f} fps)")
    speed_ratio = times["pupil_detect"] / times["tiles"]
    e2e_ratio = times["pupil_fix"] / times["tiles"]
    print(f"tile localisation vs pupil-apriltags detection alone: {speed_ratio:.2f}x the frame rate "
          f"(vs pupil detection + pose: {times['pupil_fix'] / times['tiles']:.2f}x)")

    print("\nocclusion sweep (other drones covering the frame), same effects:")
    occ = {}
    occ_poses = random_poses(N_OCCLUSION, inner, heights_m=(1.0, 3.0), tilt_deg=15.0, rng=rng)
    for share in (0.0, 0.1, 0.3, 0.5):
        eff = SceneEffects(occlusion_share=share, lighting=0.4, noise_sigma=0.015, motion_blur_px=1.5)
        r, _ = run_methods(occ_poses, tile_tex, tag_tex, field, board, camera, eff, 500, pupil, aruco_det, False)
        occ[share] = {k: summary(v) for k, v in r.items()}
        line = "  ".join(f"{k}: RMSE {s['rmse_m'] * 100:.2f} cm, worst {s['worst_m'] * 100:.2f} cm, "
                         f"{s['success'] * 100:.0f}% fixes" for k, s in occ[share].items())
        print(f"  {share * 100:>3.0f}%  {line}")
    occ_ratio = occ[0.3]["tiles"]["rmse_m"] / occ[0.0]["tiles"]["rmse_m"]
    print(f"tile RMSE at 30 % occlusion / unoccluded: {occ_ratio:.2f}")

    shift, rej = misread_shift(field, camera, np.random.default_rng(9))
    print(f"misprinted tag (shows a far tag's value) near the image centre, 8 poses: largest fix shift "
          f"{shift * 100:.2f} cm, rejected >= {rej} tag(s) in every frame")

    print("bad input:")
    bad = bad_inputs(field, camera, np.random.default_rng(3))
    for name, outcome in bad:
        print(f"  {name:<14} -> {outcome}")

    t = results["tiles"]
    goals = {
        "tile RMSE <= 3 cm": t["rmse_m"] <= 0.03,
        "tile yaw RMSE <= 1 deg": t["yaw_rmse_deg"] <= 1.0,
        "tile worst outlier <= 8 cm": t["worst_m"] <= 0.08,
        "tile localisation >= 2x the frame rate of pupil-apriltags detection + the same pose": e2e_ratio >= 2.0,
        "tile localisation >= 2x the frame rate of pupil-apriltags detection alone": speed_ratio >= 2.0,
        "RMSE at 30 % occlusion <= 1.5x unoccluded": occ_ratio <= 1.5,
        "misread tag moves fix <= 5 cm": shift <= 0.05 and rej >= 1,
        "placement <= 10 s and beats random min": placement_s <= 10.0 and placement.min_distance > placement.random_min,
        "bad input never gives a fix": all(o.startswith("no fix") for _, o in bad),
    }
    print("\ngoals:")
    for name, ok in goals.items():
        print(f"  [{'met' if ok else 'NOT MET'}] {name}")
    print(f"HEADLINE tiles RMSE {t['rmse_m'] * 100:.2f} cm, yaw {t['yaw_rmse_deg']:.3f} deg, worst "
          f"{t['worst_m'] * 100:.2f} cm, {1 / times['tiles']:.0f} fps = {e2e_ratio:.2f}x pupil+pose ({speed_ratio:.2f}x pupil detection alone); "
          f"30 % occlusion RMSE x{occ_ratio:.2f}; misread shift {shift * 100:.2f} cm; "
          f"{sum(goals.values())}/{len(goals)} goals met")
    return 0 if all(goals.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
