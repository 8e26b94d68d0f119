"""A recovery helper's ranging on tracks: the silhouette moments against the model fit at every extent.

In GPS-loss recovery (issue 18) a helper's camera (:class:`skyfix.crps.recovery.RecoveryConfig`: 960 x 720
px, 50 deg HFOV, ~1030 px focal) sees the 0.5 m quad from below, 10-45 m away: 12-50 px across, above the
14 px up to which :class:`skyfix.crps.SilhouetteFit` measures by default (benchmarks/ranging.py's
1920 x 1080 camera). Above it the size comes from the silhouette's second moments through the model's
shape table, whose ratio follows the target's yaw: a bias of a few per cent that stays while the target
keeps its heading, so fusion, which takes each observation as independent, cannot average it away.

Each track (``FRAMES`` frames at 4 Hz, rendered by :func:`skyfix.datasets.drone_view.render_drone_view`
on a sky background) has its own target yaw, tilt (5 deg 1-sigma per axis), a range closing or opening by
up to 2.5 m/s, a yaw rate of 0 or up to 40 deg/s (a drone turning home), the view elevation 2-17 deg from
below, a camera blur drawn in WorldCamera's defocus range (0.6-0.85 px), noise 0.01, and the helper's
camera pointing jittered 1 deg per frame. The same frames go through three trackers:

* ``moments``: ``Tracker(SilhouetteDetector(), fit=SilhouetteFit(camera, model))``, the fit's default
  extent limit (what the helpers ran before);
* ``fit, no guard``: the fit up to ``EyeConfig.fit_max_extent_px``, ``TrackerConfig(refit_z=inf)``;
* ``skyfix (helper eye)``: the fit up to ``EyeConfig.fit_max_extent_px`` with the eye's guard
  (``EyeConfig.refit_z``: a warm-started fit that strays from the moments' size is redone from the yaw search).

Printed per range band: the tracked range error (last ``SCORED`` frames of each track) median, p95 of
|error|, the RMS over tracks of each track's mean error (the bias fusion cannot average), and CPU ms per
frame (one core), then the same over all bands (a recovery's helpers see the target at all these ranges).
Goals, over all bands: the helper eye's per-track bias RMS and p95 no larger than the moments path's, as many
tracks ranged; in every band its CPU time per frame <= ``GOAL_MS`` (a helper processes 4 frames/s). Exit 0
only when met. (Beyond ~33 m the target is under 14 px and both paths fit.)
Also printed, not judged: the helper eye's error by the view's elevation over all bands (a model that reads a
near edge-on quad long shows there). ``--quick`` flies fewer tracks. Last line: headline.
"""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from skyfix.camera import Camera, CameraPose  # noqa: E402
from skyfix.crps import (  # noqa: E402
    DroneModel,
    SilhouetteDetector,
    SilhouetteFit,
    SilhouetteFitConfig,
    Tracker,
    observe,
)
from skyfix.crps.helper_eye import EyeConfig  # noqa: E402
from skyfix.crps.model import shape_table  # noqa: E402
from skyfix.crps.recovery import RecoveryConfig  # noqa: E402
from skyfix.crps.track import TrackerConfig  # noqa: E402
from skyfix.datasets.drone_view import TargetPose, render_drone_view  # noqa: E402
from skyfix.datasets.sim.world_camera import SensorConfig  # noqa: E402
from skyfix.geo import destination  # noqa: E402

LAT0, LON0, ALT0 = 47.0, 8.0, 400.0
BANDS_M = ((10.0, 20.0), (20.0, 30.0), (30.0, 45.0))
FRAMES, SCORED, FRAME_S = 14, 8, 0.25
NOISE = 0.01
GOAL_MS = 60.0


def pipelines(camera: Camera, model: DroneModel) -> dict[str, Tracker]:
    """Fresh trackers of the three pipelines (names as printed)."""
    wide = SilhouetteFitConfig(max_extent_px=EyeConfig().fit_max_extent_px)
    return {"moments": Tracker(SilhouetteDetector(), fit=SilhouetteFit(camera, model)),
            "fit, no guard": Tracker(SilhouetteDetector(), TrackerConfig(refit_z=math.inf),
                                     fit=SilhouetteFit(camera, model, wide)),
            "skyfix (helper eye)": Tracker(SilhouetteDetector(), TrackerConfig(refit_z=EyeConfig().refit_z),
                                           fit=SilhouetteFit(camera, model, wide))}


def track(rng: np.random.Generator, camera: Camera, model: DroneModel, band: tuple[float, float]
          ) -> tuple[dict[str, tuple[list[float], float, int]], float]:
    """One track through every pipeline: per pipeline (scored relative range errors, CPU s, frames), and the
    view's elevation (deg above the helper's horizon)."""
    r0 = rng.uniform(*band)
    r1 = float(np.clip(r0 + rng.uniform(-2.5, 2.5) * FRAMES * FRAME_S, *band))
    elev = rng.uniform(2.0, 17.0)
    yaw0, yaw_rate = rng.uniform(0.0, 360.0), (0.0 if rng.random() < 0.5 else rng.uniform(-40.0, 40.0))
    pitch, roll = rng.normal(0.0, 5.0, 2)
    blur = rng.uniform(*SensorConfig().defocus_sigma_px)
    trackers = pipelines(camera, model)
    out = {name: ([], 0.0, 0) for name in trackers}
    for f in range(FRAMES):
        rng_m = r0 + (r1 - r0) * f / (FRAMES - 1)
        lat, lon = destination(LAT0, LON0, 0.0, rng_m * math.cos(math.radians(elev)))
        helper = CameraPose(LAT0, LON0, ALT0, yaw_deg=float(rng.normal(0.0, 1.0)),
                            gimbal_pitch_deg=elev + float(rng.normal(0.0, 1.0)))
        target = TargetPose(float(lat), float(lon), ALT0 + rng_m * math.sin(math.radians(elev)),
                            yaw_deg=(yaw0 + yaw_rate * f * FRAME_S) % 360.0, pitch_deg=float(pitch),
                            roll_deg=float(roll))
        view = render_drone_view(camera, helper, target, model, blur_sigma_px=blur, noise_sigma=NOISE, rng=rng,
                                 supersample=4)
        for name, tracker in trackers.items():
            errs, cpu, n = out[name]
            t0 = time.process_time()
            det = tracker.update(view.image, f * FRAME_S, helper)
            obs = observe(camera, helper, det, model.span_m, model=model) if det is not None else None
            cpu += time.process_time() - t0
            if obs is not None and f >= FRAMES - SCORED:
                errs.append(obs.range_m / view.truth.range_m - 1.0)
            out[name] = (errs, cpu, n + 1)
    return out, elev


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tracks", type=int, default=12, help="tracks per range band (default 12)")
    ap.add_argument("--quick", action="store_true", help="6 tracks per band")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    n_tracks = 6 if args.quick else args.tracks
    cfg = RecoveryConfig()
    camera = Camera.from_fov(*cfg.camera_px, cfg.camera_hfov_deg)
    model = DroneModel(arms=4, span_m=0.5)
    rng = np.random.default_rng(args.seed)
    shape_table(model.scaled_to(1.0))  # built once (seconds), not charged to the first pipeline timed
    print(f"helper camera {cfg.camera_px[0]}x{cfg.camera_px[1]} px, {cfg.camera_hfov_deg:.0f} deg HFOV "
          f"(focal {camera.fx:.0f} px), 0.5 m quad, {n_tracks} tracks per band, {FRAMES} frames at "
          f"{1 / FRAME_S:.0f} Hz, last {SCORED} scored; fit limit {SilhouetteFitConfig().max_extent_px:.0f} px by "
          f"default, {EyeConfig().fit_max_extent_px:.0f} px in the helper eye", flush=True)
    pooled: dict[str, dict[str, list]] = {}
    by_elevation: list[tuple[float, list[float]]] = []
    ms_ok = True
    for band in BANDS_M:
        runs, elevs = zip(*(track(rng, camera, model, band) for _ in range(n_tracks)), strict=True)
        for r, elev in zip(runs, elevs, strict=True):
            by_elevation.append((elev, r["skyfix (helper eye)"][0]))
        for name in runs[0]:
            errs = [e for r in runs for e in r[name][0]]
            bias = [float(np.mean(r[name][0])) for r in runs if r[name][0]]
            cpu_ms = 1000.0 * sum(r[name][1] for r in runs) / max(sum(r[name][2] for r in runs), 1)
            pool = pooled.setdefault(name, {"errs": [], "bias": []})
            pool["errs"] += errs
            pool["bias"] += bias
            e = np.array(errs)
            print(f"  {band[0]:.0f}-{band[1]:.0f} m {name:>20}: median {100 * np.median(e):+.2f} %, p95 |err| "
                  f"{100 * np.percentile(np.abs(e), 95):.2f} %, per-track bias RMS "
                  f"{100 * np.sqrt(np.mean(np.square(bias))):.2f} %, {cpu_ms:.1f} ms/frame, {len(bias)} of {n_tracks} "
                  f"tracks ranged", flush=True)
            if name == "skyfix (helper eye)":
                ms_ok &= cpu_ms <= GOAL_MS
    figures = {}
    for name, pool in pooled.items():
        e, bias = np.array(pool["errs"]), np.array(pool["bias"])
        figures[name] = (float(np.sqrt(np.mean(bias ** 2))), float(np.percentile(np.abs(e), 95)), len(bias))
        print(f"  all bands {name:>20}: per-track bias RMS {100 * figures[name][0]:.2f} %, p95 |err| "
              f"{100 * figures[name][1]:.2f} %, {len(bias)} tracks ranged")
    for lo, hi in ((2.0, 4.0), (4.0, 7.0), (7.0, 10.0), (10.0, 17.0)):  # a bias that follows the view's elevation?
        e = np.array([x for elev, errs in by_elevation if lo <= elev < hi for x in errs])
        if e.size:
            print(f"  elevation {lo:.0f}-{hi:.0f} deg (all bands), skyfix (helper eye): median {100 * np.median(e):+.2f} %, "
                  f"mean {100 * e.mean():+.2f} %, {e.size} scored frames")
    eye, mom = figures["skyfix (helper eye)"], figures["moments"]
    met = eye[0] <= mom[0] and eye[1] <= mom[1] and eye[2] >= mom[2] and ms_ok
    print(f"helper ranging: per-track bias RMS {100 * eye[0]:.2f} % (moments path {100 * mom[0]:.2f} %), p95 |err| "
          f"{100 * eye[1]:.2f} % ({100 * mom[1]:.2f} %), CPU per frame "
          f"{'<=' if ms_ok else 'over'} {GOAL_MS:.0f} ms in {'every band' if ms_ok else 'a band'}: "
          f"{'goals met' if met else 'a goal missed'}")
    return 0 if met else 1


if __name__ == "__main__":
    sys.exit(main())
