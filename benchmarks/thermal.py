"""Thermal hotspot localisation: the source thesis's method vs skyfix on the same rendered frames.

Frames are rendered by skyfix.datasets.thermal_scene (on render_ground) at 640x512,
HFOV 50 deg. Sections, each printing its figures and goal:

A. Perfect pose, 40-150 m AGL, vehicle roll/pitch within +-15 deg, hard-mounted
   camera at -60..-90 deg: single-frame ground error of skyfix and of the source
   method (DESIGN.md: centroid, FOV offset, altitude*tan(theta), roll ignored, flat
   earth, spherical destination), both on the same 8-bit white-hot frames.
   Goal: skyfix median <= 0.5 m and source median >= 10x skyfix.
B. Noisy pose (position sigma 1.5 m per axis, attitude sigma 0.5 deg per angle, drawn
   independently per frame), 20 frames around each fire, radiometric 16-bit frames
   with dead pixels: FireTracker fused error and honesty of its sigma.
   Goal: median fused error <= 2 m; true error <= 2 * sigma_m in >= 90 % of fires.
C. Detection + geolocation (with covariance, GeoFix out) frames/s on one core (process
   CPU time, cv2.setNumThreads(1)), 640x512, fastest of 7 repeats (the machine is
   shared; the median repeat is printed too). Goal >= 1000 frames/s for 16-bit counts
   and float C.
D. 1000 fire-free frames (sun-warmed forest, noise, 0.02 % dead pixels): false fires.
   Goal: 0 in every format.
E. Bad input (wrong dtype/shape, empty, constant frame, NaN pose): clear error.
T. Terrain (issue 23): seeded mountains (skyfix.datasets.terrain), five fires of 1.6-4 m
   on the slopes, a consumer drone's pose errors drawn per seed (Gauss-Markov GNSS,
   attitude noise and drift, boresight 0.5-1.2 deg, camera/log time offset; the
   estimator's prior is the nominal one, not the draw), 10 m AMSL GeoTIFF DEM in UTM
   with no-data holes. Per seed the calibration orbit of thermal/README.md (four laps
   clockwise, four back; 19 min, a frame every 2 s), then a two-lap orbit and a single
   straight pass at 1 Hz, radiometric frames rendered on the true terrain; the same
   detections go to skyfix's joint estimate on the DEM (self-calibrated, and with the
   calibration orbit's boresight and clock as the prior), the same on flat ground, and
   the frame-by-frame FireTracker on the DEM (the baseline that takes pose errors as
   independent). Goals: orbit mean horizontal error <= 2 m, single pass <= 4 m (both
   with the calibration); 2-dof NEES inside the 95 % band for >= 85 % of fires;
   boresight within 0.2 deg after every calibration orbit (printed: the floor the drawn
   attitude drift sets, and the stated covariance's NEES); detection + DEM location
   >= 500 frames/s on those 640x512 frames, 1000x1000 DEM.

Usage: python benchmarks/thermal.py [--quick] [--terrain-only | --terrain-throughput-only]
       [--no-timing | --timing-only]   (the accuracy run on a shared machine, the frames/s on a quiet one)
(exit status 1 when a goal is missed)
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
import warnings

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from skyfix.camera import Camera, CameraPose
from skyfix.datasets.mountain_flight import fly, lines_log, mountain_scene, orbit_log
from skyfix.datasets.pose_errors import PoseErrorModel
from skyfix.datasets.thermal_flight import pose_seeing
from skyfix.datasets.thermal_scene import FireSpec, ThermalScene, ThermalSensor, to_display
from skyfix.errors import SkyfixError
from skyfix.geo import LocalFrame, inverse
from skyfix.progress import progress
from skyfix.thermal import (
    DemGround,
    FireTracker,
    FlatGround,
    PoseUncertainty,
    RelativeTemperatureWarning,
    detect_hotspots,
    geolocate_many,
    locate_in_frame,
)
from skyfix.thermal.ground import frame_near
from skyfix.thermal.joint import locate_jointly
from skyfix.thermal.sightings import associate
from skyfix.thermal.source_method import source_method_locate

CAMERA = Camera.from_fov(640, 512, 50.0)
FRAME = LocalFrame(45.4592, -73.9191, 30.0)  # ground ellipsoidal height 30 m
SPAN_C = (0.0, 150.0)  # fixed gain of the 8-bit white-hot frames; fires saturate
SOURCE_THRESHOLD = 200  # "the white pixels" of the thesis, on that span (~118 C)


def random_view(rng: np.random.Generator, target: np.ndarray, yaw_deg: float | None = None,
                uv_out: list | None = None) -> CameraPose:
    """A hard-mounted camera pose inside the issue's envelope that sees ``target``
    (at a random pixel, appended to ``uv_out`` when given)."""
    while True:
        uv = rng.uniform([80, 80], [CAMERA.width - 80, CAMERA.height - 80])
        try:
            pose = pose_seeing(FRAME, CAMERA, target, uv, rng.uniform(40, 150),
                               roll_deg=rng.uniform(-15, 15), pitch_deg=rng.uniform(-15, 15),
                               yaw_deg=rng.uniform(0, 360) if yaw_deg is None else yaw_deg,
                               gimbal_pitch_deg=rng.uniform(-90, -60), stabilized=False)
        except SkyfixError:
            continue
        if uv_out is not None:
            uv_out.append(uv)
        return pose


def ground_error_m(lat: float, lon: float, truth: tuple[float, float]) -> float:
    return float(inverse(truth[0], truth[1], lat, lon)[1])


def source_estimate(u8: np.ndarray, pose: CameraPose) -> tuple[float, float] | None:
    return source_method_locate(
        u8, threshold_level=SOURCE_THRESHOLD, hfov_deg=CAMERA.hfov_deg, vfov_deg=CAMERA.vfov_deg,
        lat_deg=pose.lat_deg, lon_deg=pose.lon_deg, height_m=pose.alt_m - FRAME.alt0_m, heading_deg=pose.yaw_deg,
        pitch_deg=pose.pitch_deg, camera_depression_deg=-pose.gimbal_pitch_deg)


HEADLINE: dict[str, float] = {}


def section_a(n: int, rng: np.random.Generator, keep: list) -> bool:
    sensor = ThermalSensor(640, 512, noise_sigma_c=0.05, dead_pixel_fraction=0.0)
    ours, theirs, uvs = [], [], []
    for _ in range(n):
        fire = FireSpec(rng.uniform(-150, 150), rng.uniform(-150, 150), rng.uniform(0.5, 2.5), rng.uniform(300, 800))
        scene = ThermalScene(FRAME, [fire], seed=1)
        target = np.array([fire.east_m, fire.north_m, 0.0])
        truth = tuple(float(x) for x in FRAME.to_geodetic(*target)[:2])
        pose = random_view(rng, target, uv_out=uvs)
        celsius = sensor.observe(scene.render(CAMERA, pose), rng)
        u8 = to_display(celsius, span_c=SPAN_C)
        spots = detect_hotspots(u8)
        fix = geolocate_many(spots[:1], CAMERA, pose, FRAME.alt0_m)[0]
        ours.append(ground_error_m(fix.lat_deg, fix.lon_deg, truth))
        src = source_estimate(u8, pose)
        theirs.append(np.inf if src is None else ground_error_m(*src, truth))
        if len(keep) < 200:
            keep.append((sensor.to_counts(celsius), celsius, u8, pose))
    ours_a, theirs_a = np.array(ours), np.array(theirs)
    med_o, med_s = np.median(ours_a), np.median(theirs_a)
    print(f"A. perfect pose, {n} frames (40-150 m AGL, roll/pitch +-15, hard mount -60..-90):")
    print(f"   skyfix  median {med_o:.3f} m  p95 {np.percentile(ours_a, 95):.3f} m  max {ours_a.max():.3f} m")
    print(f"   source  median {med_s:.3f} m  p95 {np.percentile(theirs_a, 95):.3f} m  max {theirs_a.max():.3f} m")
    near = np.linalg.norm(np.array(uvs) - [CAMERA.cx, CAMERA.cy], axis=1) < 60.0
    if near.any():
        print(f"   source, fires within 60 px of the image centre ({near.sum()} frames): median "
              f"{np.median(theirs_a[near]):.3f} m (its sideways/roll errors shrink near the centre)")
    ratio = med_s / med_o
    HEADLINE.update(single_m=med_o, source_m=med_s, ratio=ratio)
    ok = med_o <= 0.5 and ratio >= 10.0
    print(f"   ratio source/skyfix (median) {ratio:.1f}x   goal: skyfix <= 0.5 m and ratio >= 10x -> "
          f"{'MET' if ok else 'NOT MET'}")
    return ok


def section_b(n_fires: int, rng: np.random.Generator) -> tuple[bool, float]:
    sensor = ThermalSensor(640, 512, noise_sigma_c=0.05, dead_pixel_fraction=2e-4, seed=3)
    unc = PoseUncertainty(position_sigma_m=1.5, altitude_sigma_m=1.5, tilt_sigma_deg=0.5,
                          yaw_sigma_deg=0.5, pixel_sigma_px=0.3)
    errs, sigmas, majors, nees, src_errs, single = [], [], [], [], [], 0
    for _ in range(n_fires):
        fire = FireSpec(rng.uniform(-150, 150), rng.uniform(-150, 150), rng.uniform(0.5, 2.5), rng.uniform(300, 800))
        scene = ThermalScene(FRAME, [fire], seed=2)
        target = np.array([fire.east_m, fire.north_m, 0.0])
        truth = tuple(float(x) for x in FRAME.to_geodetic(*target)[:2])
        tracker = FireTracker(CAMERA, FRAME.alt0_m, uncertainty=unc)
        yaw0 = rng.uniform(0, 360)
        src_fixes = []
        for k in range(20):
            pose = random_view(rng, target, yaw_deg=(yaw0 + 18.0 * k) % 360.0)
            counts = sensor.to_counts(sensor.observe(scene.render(CAMERA, pose, 0.5 * k), rng))
            e, nn, u = FRAME.to_enu(pose.lat_deg, pose.lon_deg, pose.alt_m)
            lat, lon, alt = FRAME.to_geodetic(e + rng.normal(0, 1.5), nn + rng.normal(0, 1.5), u + rng.normal(0, 1.5))
            noisy = CameraPose(float(lat), float(lon), float(alt), pose.roll_deg + rng.normal(0, 0.5),
                               pose.pitch_deg + rng.normal(0, 0.5), pose.yaw_deg + rng.normal(0, 0.5),
                               pose.gimbal_pitch_deg, stabilized=False)
            tracker.update(counts, noisy, 0.5 * k)
            u8 = to_display(counts.astype(np.float32) * 0.01 - 273.15, span_c=SPAN_C)
            src = source_estimate(u8, noisy)
            if src is not None:
                src_fixes.append(src)
        fires = tracker.fires
        single += len(fires) == 1
        best = max(fires, key=lambda f: f.n_observations)
        err = ground_error_m(best.lat_deg, best.lon_deg, truth)
        errs.append(err)
        sigmas.append(best.sigma_m)
        majors.append(best.sigma_major_m)
        e_vec = np.array(FRAME.to_enu(best.lat_deg, best.lon_deg, FRAME.alt0_m)[:2], float) - target[:2]
        nees.append(float(e_vec @ np.linalg.solve(best.cov_en_m2, e_vec)))
        mean_src = np.mean(np.array(src_fixes), axis=0)
        src_errs.append(ground_error_m(mean_src[0], mean_src[1], truth))
    errs_a, sig_a = np.array(errs), np.array(sigmas)
    within = float(np.mean(errs_a <= 2 * sig_a))
    within_major = float(np.mean(errs_a <= 2 * np.array(majors)))
    print(f"B. noisy pose (1.5 m, 0.5 deg), 20 frames around each of {n_fires} fires, 16-bit counts:")
    print(f"   skyfix fused  median {np.median(errs_a):.3f} m  p95 {np.percentile(errs_a, 95):.3f} m; "
          f"median reported sigma_m {np.median(sig_a):.3f} m; fires tracked as one: {single}/{n_fires}")
    print(f"   source (mean of its 20 fixes)  median {np.median(src_errs):.3f} m  p95 {np.percentile(src_errs, 95):.3f} m"
          f"  ratio {np.median(src_errs) / np.median(errs_a):.1f}x")
    print(f"   honesty: error <= 2*sigma_m (sqrt trace) in {100 * within:.0f} % of fires; "
          f"<= 2*sigma_major in {100 * within_major:.0f} %; mean NEES {np.mean(nees):.2f} (2.0 if calibrated)")
    HEADLINE.update(within=within)
    ok = np.median(errs_a) <= 2.0 and within >= 0.9
    print(f"   goal: median <= 2 m and >= 90 % within 2 sigma -> {'MET' if ok else 'NOT MET'}")
    return ok, float(np.median(errs_a))


def section_c(keep: list, repeats: int = 7) -> bool:
    """CPU time per frame over all kept frames, repeated; the machine is shared, so the
    fastest repeat estimates the uncontended cost (as timeit does) and the median shows
    the contended one. The goal is judged on the fastest repeat."""
    cv2.setNumThreads(1)
    rates = {}
    for name, idx in (("16-bit counts", 0), ("float deg C", 1), ("8-bit white-hot", 2)):
        geolocate_many(detect_hotspots(keep[0][idx])[:1], CAMERA, keep[0][3], FRAME.alt0_m)  # warm caches
        per_frame, n_fix = [], 0
        for _rep in range(repeats):
            n_fix = 0
            t0 = time.process_time()
            for item in keep:
                spots = detect_hotspots(item[idx])
                if spots:
                    n_fix += len(geolocate_many(spots, CAMERA, item[3], FRAME.alt0_m))
            per_frame.append((time.process_time() - t0) / len(keep))
        best, med = min(per_frame), float(np.median(per_frame))
        rates[name] = 1.0 / best
        print(f"C. detect + geolocate {name:16s}: {1.0 / best:7.0f} frames/s on one core, fastest of {repeats} "
              f"({1e3 * best:.3f} ms CPU/frame); median repeat {1.0 / med:.0f} frames/s; {n_fix} fixes "
              f"in {len(keep)} frames")
    HEADLINE.update(fps=min(rates["16-bit counts"], rates["float deg C"]))
    ok = min(rates["16-bit counts"], rates["float deg C"]) >= 1000.0
    print(f"   goal: >= 1000 frames/s (radiometric, fastest repeat) -> {'MET' if ok else 'NOT MET'}"
          f"{'' if rates['8-bit white-hot'] >= 1000 else ' (8-bit path below 1000 frames/s)'}")
    return ok


def section_d(n: int, rng: np.random.Generator) -> bool:
    sensor = ThermalSensor(640, 512, noise_sigma_c=0.08, dead_pixel_fraction=2e-4, seed=11)
    scene = ThermalScene(FRAME, [], ambient_c=38.0, texture_sigma_c=6.0, seed=5)  # hot afternoon
    false = {"16-bit counts (100 C)": 0, "8-bit fixed span (auto)": 0, "8-bit auto-gain (auto)": 0,
             "ironbow auto-gain (auto)": 0}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RelativeTemperatureWarning)
        for _ in range(n):
            pose = random_view(rng, np.array([rng.uniform(-150, 150), rng.uniform(-150, 150), 0.0]))
            celsius = sensor.observe(scene.render(CAMERA, pose), rng)
            false["16-bit counts (100 C)"] += len(detect_hotspots(sensor.to_counts(celsius)))
            false["8-bit fixed span (auto)"] += len(detect_hotspots(to_display(celsius, span_c=SPAN_C)))
            false["8-bit auto-gain (auto)"] += len(detect_hotspots(to_display(celsius)))
            false["ironbow auto-gain (auto)"] += len(detect_hotspots(to_display(celsius, palette="ironbow"),
                                                                     palette="ironbow"))
    print(f"D. {n} fire-free frames with noise and {len(sensor.dead_pixels[0])} stuck-hot + "
          f"{len(sensor.dead_pixels[1])} stuck-cold pixels: false fires " +
          ", ".join(f"{k}: {v}" for k, v in false.items()))
    HEADLINE.update(false=sum(false.values()))
    ok = sum(false.values()) == 0
    print(f"   goal: 0 false fires -> {'MET' if ok else 'NOT MET'}")
    return ok


def section_e(keep: list) -> bool:
    counts, _, _, pose = keep[0]
    cases = {
        "int32 frame": lambda: detect_hotspots(counts.astype(np.int32)),
        "(H, W, 4) frame": lambda: detect_hotspots(np.zeros((512, 640, 4), np.uint8)),
        "empty frame": lambda: detect_hotspots(np.zeros((0, 0), np.uint16)),
        "constant frame": lambda: detect_hotspots(np.full((512, 640), 30000, np.uint16)),
        "all-NaN frame": lambda: detect_hotspots(np.full((512, 640), np.nan, np.float32)),
        "NaN attitude": lambda: CameraPose(pose.lat_deg, pose.lon_deg, pose.alt_m, float("nan"), 0.0, 0.0),
        "NaN pixel": lambda: geolocate_many(np.array([[np.nan, 3.0]]), CAMERA, pose, FRAME.alt0_m),
        "ground above camera": lambda: geolocate_many(np.array([[320.0, 256.0]]), CAMERA, pose, pose.alt_m + 10),
    }
    rejected = 0
    for name, call in cases.items():
        try:
            call()
            print(f"E. {name}: NOT rejected")
        except SkyfixError as exc:
            rejected += 1
            print(f"E. {name}: {type(exc).__name__}: {exc}")
    tracker = FireTracker(CAMERA, FRAME.alt0_m)
    tracker.update(np.full((512, 640), 30000, np.uint16), pose, 0.0)
    tracker.update(counts, pose, 1.0)
    loop_ok = tracker.frames_dropped == 1 and tracker.frames_used == 1
    print(f"   {rejected}/{len(cases)} rejected with a skyfix error; tracker dropped the blank frame and "
          f"kept going: {loop_ok} -> {'MET' if rejected == len(cases) and loop_ok else 'NOT MET'}")
    return rejected == len(cases) and loop_ok


CHI2_2DOF_95 = (0.0506, 7.378)


def _score(fires, scene) -> list[tuple[float, float]]:
    """(horizontal error m, 2-dof NEES) of each estimated fire against the nearest true fire."""
    truth = scene.fire_enu()
    out = []
    for f in fires:
        p = np.array(scene.frame.to_enu(f.lat_deg, f.lon_deg, f.alt_m), float)
        k = int(np.argmin(np.hypot(*(truth[:, :2] - p[:2]).T)))
        lat, lon, _ = scene.frame.to_geodetic(*truth[k])
        e = p[:2] - truth[k, :2]
        out.append((ground_error_m(f.lat_deg, f.lon_deg, (float(lat), float(lon))),
                    float(e @ np.linalg.solve(f.cov_en_m2, e))))
    return out


def _terrain_flight(flight, dem, centre_en, keep: list, calibration=None, baselines: bool = True,
                    seed: int = 0) -> dict:
    """Detect on every frame once; run the joint estimate on the DEM and, with
    ``baselines``, on flat ground and the tracker; with a ``calibration`` (the same drone's
    calibration-orbit solution) also the calibrated DEM estimate."""
    detections = []
    for stamp, counts in progress(flight.frames(), desc="render+detect", total=len(flight.stamps_s), unit="frame"):
        detections.append((stamp, detect_hotspots(counts)))
        if len(keep) < 120 and len(detections) % 5 == 0:
            keep.append((counts, flight.log.pose_at(stamp), seed))
    scene = flight.scene
    lat, lon, _ = scene.frame.to_geodetic(centre_en[0], centre_en[1], 0.0)
    flat = FlatGround(float(dem.height_at(lat, lon)))
    out = {"n_frames": len(detections), "n_true": len(scene.fires)}
    runs = ([("dem", dem, None)] + ([("flat", flat, None)] if baselines else [])
            + ([("cal", dem, calibration)] if calibration else []))
    for name, ground, cal in runs:
        sol = locate_jointly(flight.camera, flight.log, associate(flight.camera, flight.log, detections, ground),
                             ground, calibration=cal)
        out[name] = _score(sol.fires, scene)
        out[name + "_sol"] = sol
    if baselines:
        tracker = FireTracker(flight.camera, dem, uncertainty=PoseUncertainty(1.5, 2.5, 0.5, 0.5, 0.5))
        for stamp, spots in detections:
            tracker.update_hotspots(spots, flight.log.pose_at(stamp), stamp)
        out["tracker"] = _score([f for f in tracker.fires if f.n_observations >= 3], scene)
    return out


def _drift_floor_deg(flight) -> float:
    """Scoring only (uses the truth): norm of the mean, over the flight's frames, of the
    logged-to-true camera rotation (deg, camera axes). The drawn AHRS/gimbal drift is about
    axes fixed in the camera while the gimbal pitch is constant, so its mean over the orbit
    looks exactly like a boresight: no estimator separates the two from these frames."""
    t = flight.stamps_s + flight.errors.time_offset_s
    _, r_log = flight.log.camera_in_frame(flight.scene.frame, t)
    _, r_true = flight.truth_log.camera_in_frame(flight.scene.frame, t)
    err = Rotation.from_matrix(np.transpose(r_log, (0, 2, 1)) @ r_true).as_rotvec()
    return float(np.degrees(np.linalg.norm(err.mean(axis=0))))


def _terrain_lines(kind: str, runs: list[dict], goal_m: float) -> tuple[bool, float]:
    """Print a flight kind's mean errors; the goal is judged on the calibrated estimate (the
    boresight and clock from the same drone's calibration orbit, as users are told to fly)."""
    keys = [k for k in ("dem", "cal", "flat", "tracker") if k in runs[0]]
    mean = {k: float(np.mean([e for r in runs for e, _ in r[k]])) for k in keys}
    judged = "cal" if "cal" in mean else "dem"
    counts = [f"{len(r[judged])}/{r['n_true']}" for r in runs]
    ok = mean[judged] <= goal_m and all(len(r[judged]) == r["n_true"] for r in runs)
    cal = f" | with the calibration orbit's boresight/clock {mean['cal']:.2f} m" if "cal" in mean else ""
    print(f"   {kind:5s}: mean horizontal error skyfix joint+DEM {mean['dem']:.2f} m{cal} | same, flat ground "
          f"{mean['flat']:.2f} m | FireTracker+DEM (independent errors) {mean['tracker']:.2f} m; fires found "
          f"{', '.join(counts)}; goal ({judged}) <= {goal_m:.0f} m -> {'MET' if ok else 'NOT MET'}")
    return ok, mean[judged]


CAL_RATE_HZ = 0.5  # calibration frames: the drift's mean averages with time, not with frame count


def _logs(scene, seed: int, laps: float, cal_laps: float) -> dict:
    """True logs of one seeded drone's flights: the calibration orbit (both ways), the
    mapping orbit and the straight pass (random heading), with their frame rates."""
    orbit = orbit_log(scene, (0.0, 0.0), radius_m=180.0, height_m=100.0, laps=laps, speed_mps=8.0)
    calib = orbit_log(scene, (0.0, 0.0), radius_m=180.0, height_m=100.0, laps=cal_laps, speed_mps=8.0,
                      both_ways=True)
    heading = np.radians(np.random.default_rng(seed).uniform(0, 360))
    ends = 350.0 * np.array([[-np.sin(heading), -np.cos(heading)], [np.sin(heading), np.cos(heading)]])
    path_up = scene.terrain.up_at(*np.linspace(ends[0], ends[1], 100).T)
    line = lines_log(scene, ends, up_m=float(path_up.max()) + 110.0, gimbal_pitch_deg=-60.0)
    return {"calib": (calib, CAL_RATE_HZ), "orbit": (orbit, 1.0), "pass": (line, 1.0)}


def _fly_seed(seed: int, scene, errors, dem, flights: dict, keep: list, laps: float, cal_laps: float) -> None:
    """One seeded drone: the calibration orbit (both ways), then the two-lap orbit and the
    straight pass, each estimated self-calibrated and with the calibration flight's solution."""
    cal_sol = None
    for kind, (log, rate) in _logs(scene, seed, laps, cal_laps).items():
        runs = flights[kind]
        flight = fly(scene, CAMERA, log, errors, frame_rate_hz=rate, seed=seed + 50 * len(runs))
        r = _terrain_flight(flight, dem, (0.0, 0.0), [] if kind == "calib" else keep, cal_sol,
                            baselines=kind != "calib", seed=seed)
        runs.append(r)
        if kind in ("calib", "orbit"):
            sol = r["dem_sol"]
            d = sol.boresight_deg - np.array(errors.boresight_deg)
            r["bore"] = (float(np.linalg.norm(d)), float(d @ np.linalg.solve(sol.boresight_cov_deg2, d)),
                         float(np.sqrt(np.trace(sol.boresight_cov_deg2))), _drift_floor_deg(flight),
                         sol.time_offset_s - errors.time_offset_s, sol.time_offset_sigma_s)
        if kind == "calib":
            cal_sol = r["dem_sol"]
    c, o = flights["calib"][-1], flights["orbit"][-1]
    print(f"   seed {seed}: calibration orbit {c['n_frames']} frames (both ways), orbit {o['n_frames']}, pass "
          f"{flights['pass'][-1]['n_frames']}; boresight {np.linalg.norm(errors.boresight_deg):.2f} deg, error after "
          f"the calibration orbit {c['bore'][0]:.3f} deg (stated sigma {c['bore'][2]:.3f}, 3-dof NEES "
          f"{c['bore'][1]:.1f}; drift-mean floor {c['bore'][3]:.3f}), after the mapping orbit alone "
          f"{o['bore'][0]:.3f} deg (floor {o['bore'][3]:.3f}); clock offset {errors.time_offset_s:+.3f} s, error "
          f"{c['bore'][4]:+.3f} s (stated sigma {c['bore'][5]:.3f} s; mapping orbit alone {o['bore'][4]:+.3f} s, "
          f"sigma {o['bore'][5]:.3f} s)")


def _boresight_lines(flights: dict) -> bool:
    """Boresight goal on the calibration orbits, with the honesty of the stated covariance."""
    cal, orb = [r["bore"] for r in flights["calib"]], [r["bore"] for r in flights["orbit"]]
    ok = max(b[0] for b in cal) <= 0.2
    chi2 = {"calibration orbits": [b[1] for b in cal], "mapping orbits": [b[1] for b in orb]}
    print(f"   boresight error after the calibration orbit: {', '.join(f'{b[0]:.3f}' for b in cal)} deg (floor set by "
          f"the drawn attitude drift's mean over the flight: {', '.join(f'{b[3]:.3f}' for b in cal)} deg); mapping "
          f"orbit alone {', '.join(f'{b[0]:.3f}' for b in orb)} deg (floor {', '.join(f'{b[3]:.3f}' for b in orb)}); "
          f"goal every calibration orbit <= 0.2 deg -> {'MET' if ok else 'NOT MET'}")
    for name, v in chi2.items():
        print(f"   honesty, {name}: boresight 3-dof NEES {', '.join(f'{x:.1f}' for x in v)} (mean {np.mean(v):.1f}; "
              f"3.0 if the stated covariance is right, 95 % of single values below 7.8); clock error / stated sigma "
              f"{', '.join(f'{b[4] / b[5]:+.1f}' for b in (cal if name.startswith('cal') else orb))}")
    return ok


def section_t(n_seeds: int, laps: float, cal_laps: float, timing: bool = True) -> bool:
    """Terrain section (see module docstring); ``timing`` False leaves out the throughput."""
    import tempfile

    flights: dict[str, list] = {"calib": [], "orbit": [], "pass": []}
    keep: list = []
    for seed in range(n_seeds):
        scene = mountain_scene(seed)
        errors = PoseErrorModel.draw(np.random.default_rng(1000 + seed))
        with tempfile.TemporaryDirectory() as tmp:
            path = scene.terrain.write_dem(f"{tmp}/dem.tif", metres_per_px=10.0, datum="amsl", holes=3, seed=seed)
            dem = DemGround.from_geotiff(path, datum="amsl", sigma_m=1.0)
        _fly_seed(seed, scene, errors, dem, flights, keep, laps, cal_laps)
    print(f"T. terrain: {n_seeds} seeded mountains, 10 m AMSL DEM (UTM, holes), consumer-drone pose errors:")
    ok_o, m_o = _terrain_lines("orbit", flights["orbit"], 2.0)
    ok_p, m_p = _terrain_lines("pass", flights["pass"], 4.0)
    runs = flights["calib"] + flights["orbit"] + flights["pass"]
    nees = np.array([n for r in runs for k in ("dem", "cal") if k in r for _, n in r[k]])
    inside = float(np.mean((nees > CHI2_2DOF_95[0]) & (nees < CHI2_2DOF_95[1])))
    trk = np.array([n for r in flights["orbit"] + flights["pass"] for _, n in r["tracker"]])
    trk_in = float(np.mean((trk > CHI2_2DOF_95[0]) & (trk < CHI2_2DOF_95[1])))
    ok_n = inside >= 0.85
    print(f"   NEES (2 dof) inside [{CHI2_2DOF_95[0]}, {CHI2_2DOF_95[1]}]: skyfix joint {100 * inside:.0f} % of "
          f"{nees.size} fire estimates (calibration orbits, orbits, passes, self- and orbit-calibrated) (median "
          f"{np.median(nees):.2f}); FireTracker {100 * trk_in:.0f} % (median {np.median(trk):.1f}); goal >= 85 % -> "
          f"{'MET' if ok_n else 'NOT MET'}")
    ok_b = _boresight_lines(flights)
    ok_f, fps = _terrain_throughput(keep) if timing else (True, float("nan"))
    HEADLINE.update(t_orbit=m_o, t_pass=m_p, t_flat=float(np.mean([e for r in flights["orbit"] for e, _ in r["flat"]])),
                    t_nees=inside, t_bore=max(r["bore"][0] for r in flights["calib"]), t_fps=fps)
    return ok_o and ok_p and ok_n and ok_b and ok_f


def throughput_only() -> bool:
    """Section T's throughput alone, on the frames section T keeps (every 5th frame of seed
    0's mapping orbit and pass, then seed 1's orbit; the same renders), for a re-run at a
    quieter moment."""
    keep: list = []
    for seed in (0, 1):
        scene = mountain_scene(seed)
        errors = PoseErrorModel.draw(np.random.default_rng(1000 + seed))
        for kind, (log, rate) in _logs(scene, seed, 2.0, 4.0).items():
            if kind == "calib" or len(keep) >= 120:
                continue
            flight = fly(scene, CAMERA, log, errors, frame_rate_hz=rate, seed=51 * seed)
            for k, (stamp, counts) in enumerate(flight.frames()):
                if len(keep) < 120 and (k + 1) % 5 == 0:
                    keep.append((counts, flight.log.pose_at(stamp), seed))
    ok, fps = _terrain_throughput(keep)
    HEADLINE.update(t_fps=fps)
    return ok


def _terrain_throughput(keep: list, repeats: int = 7) -> tuple[bool, float]:
    """Detection + DEM location CPU time per frame (fastest of ``repeats``, one core), each
    frame on a 1000x1000 DEM (2 m) of its own flight's mountain. Every DEM's local grid and
    frame are built before the clock starts (a flight builds them once); both paths run on
    the same frames."""
    cv2.setNumThreads(1)
    dems = {seed: mountain_scene(seed).terrain.dem_ground(metres_per_px=2.0, half_size_m=1002.0)
            for seed in sorted({k[2] for k in keep})}
    frames = {}
    for counts, pose, seed in keep:  # warm-up: local grids, frames, frame-to-frame motions
        spots = detect_hotspots(counts)
        if spots:
            geolocate_many(spots, CAMERA, pose, dems[seed])
        frames.setdefault(seed, frame_near(pose.lat_deg, pose.lon_deg, dems[seed].alt_m))
    per_frame, enu_frame, n_fix = [], [], 0
    for _ in range(repeats):
        n_fix = 0
        t0 = time.process_time()
        for counts, pose, seed in keep:
            spots = detect_hotspots(counts)
            if spots:
                n_fix += len(geolocate_many(spots, CAMERA, pose, dems[seed]))
        per_frame.append((time.process_time() - t0) / len(keep))
        # The tracker's and the joint estimate's path: ENU points with covariances, no GeoFix objects.
        t0 = time.process_time()
        for counts, pose, seed in keep:
            spots = detect_hotspots(counts)
            if spots:
                locate_in_frame(CAMERA, pose, np.array([[h.u_px, h.v_px] for h in spots]), dems[seed], frames[seed])
        enu_frame.append((time.process_time() - t0) / len(keep))
    best = min(per_frame)
    ok = 1.0 / best >= 500.0
    dem = dems[keep[0][2]]
    print(f"   detect + locate on a {dem.heights_m.shape[1]}x{dem.heights_m.shape[0]} DEM: {1.0 / best:.0f} frames/s "
          f"with GeoFix out (fastest of {repeats}; median repeat {1.0 / float(np.median(per_frame)):.0f}), "
          f"{1.0 / min(enu_frame):.0f} frames/s for ENU points + covariance (the tracker's path); "
          f"{n_fix / len(keep):.1f} fires per frame; goal (GeoFix) >= 500 frames/s -> {'MET' if ok else 'NOT MET'}")
    return ok, 1.0 / best


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="fewer frames (for a smoke run)")
    parser.add_argument("--terrain-only", action="store_true", help="only section T (terrain)")
    parser.add_argument("--terrain-throughput-only", action="store_true",
                        help="only section T's detection + DEM location throughput (its frames, ~2 min)")
    timing = parser.add_mutually_exclusive_group()
    timing.add_argument("--no-timing", action="store_true",
                        help="every section but the frames/s measurements (C, T's throughput): the accuracy "
                             "run, which may share the machine; run --timing-only on a quiet machine for them")
    timing.add_argument("--timing-only", action="store_true",
                        help="only the frames/s goals: C on section A's frames and T's throughput on its "
                             "frames (~3 min)")
    args = parser.parse_args()
    if args.terrain_throughput_only:
        ok = throughput_only()
        print(f"thermal terrain throughput: {'MET' if ok else 'NOT MET'}: {HEADLINE['t_fps']:.0f} frames/s on a DEM")
        return 0 if ok else 1
    # The tracker logs the frames it drops (section E); show them in order with the rest.
    logging.basicConfig(level=logging.WARNING, format="   log: %(message)s", stream=sys.stdout)
    n_a, n_b, n_d = (40, 10, 100) if args.quick else (200, 40, 1000)
    rng = np.random.default_rng(2026)
    keep: list = []
    warnings.simplefilter("ignore", RelativeTemperatureWarning)
    if args.timing_only:
        section_a(n_a, rng, keep)  # renders C's frames (its accuracy goal is judged in the full run)
        ok_c, ok_f = section_c(keep), throughput_only()
        print(f"thermal timing: goals {'ALL MET' if ok_c and ok_f else 'NOT ALL MET'} (C {ok_c}, T throughput "
              f"{ok_f}): {HEADLINE['fps']:.0f} frames/s detect + geolocate on flat ground (goal 1000), "
              f"{HEADLINE['t_fps']:.0f} frames/s on a DEM (goal 500)")
        return 0 if ok_c and ok_f else 1
    ok_t = section_t(1 if args.quick else 3, 1.0 if args.quick else 2.0, 1.0 if args.quick else 4.0,
                     timing=not args.no_timing)
    h = HEADLINE
    terrain = (f"terrain: orbit {h['t_orbit']:.2f} m (flat ground {h['t_flat']:.1f} m), pass {h['t_pass']:.2f} m, "
               f"NEES in band {100 * h['t_nees']:.0f} %, boresight within {h['t_bore']:.3f} deg, "
               + ("frames/s not measured (--no-timing)" if args.no_timing else f"{h['t_fps']:.0f} frames/s on a DEM"))
    if args.terrain_only:
        print(f"thermal terrain: goals {'ALL MET' if ok_t else 'NOT ALL MET'}: {terrain}")
        return 0 if ok_t else 1
    ok_a = section_a(n_a, rng, keep)
    ok_b, fused = section_b(n_b, rng)
    ok_c = True if args.no_timing else section_c(keep)
    ok_d = section_d(n_d, rng)
    ok_e = section_e(keep)
    all_ok = ok_a and ok_b and ok_c and ok_d and ok_e and ok_t
    fps = "C not run (--no-timing)" if args.no_timing else f"{h['fps']:.0f} frames/s"
    print(f"thermal: goals {'ALL MET' if all_ok else 'NOT ALL MET'}{' but timing' if args.no_timing else ''} "
          f"(A {ok_a}, B {ok_b}, C {ok_c}, D {ok_d}, E {ok_e}, T {ok_t}): single-frame median {h['single_m']:.3f} m vs "
          f"source {h['source_m']:.1f} m ({h['ratio']:.0f}x); fused {fused:.2f} m, {100 * h['within']:.0f} % within "
          f"2 sigma; {fps}; {h['false']:.0f} false fires; {terrain}")
    return 0 if all_ok else 1


if __name__ == "__main__":
    sys.exit(main())
