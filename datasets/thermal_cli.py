"""``skyfix datasets thermal-flight OUT_DIR``: a synthetic thermal flight (frames, poses,
camera, truth) that ``skyfix thermal locate`` reads: fires in a flat forest seen from an
orbit, or (``--mountain``) a consumer drone's orbit, straight pass or boresight
calibration orbit over a seeded mountain with a DEM. ``skyfix thermal simulate`` is the
deprecated name of the same command.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

HELP = "write a synthetic thermal flight that 'skyfix thermal locate' can read"
DESCRIPTION = ("Render a forest with fires from an orbiting drone (or, with --mountain, a flight over a "
               "mountain with a consumer drone's pose errors) and write frames/, poses.csv, camera.json and "
               "truth.json into OUT_DIR.")


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``thermal-flight`` to ``skyfix datasets``."""
    p = sub.add_parser("thermal-flight", help=HELP, description=DESCRIPTION)
    add_arguments(p)
    p.set_defaults(func=run_thermal_flight)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The command's arguments (shared with the deprecated ``skyfix thermal simulate``)."""
    p.add_argument("out_dir", type=Path, metavar="OUT_DIR",
                   help="folder to write frames/, poses.csv, camera.json and truth.json into")
    p.add_argument("--fires", type=int, default=3, help="number of fires (default 3)")
    p.add_argument("--frames", type=int, default=36, help="number of frames (default 36)")
    p.add_argument("--agl", type=float, default=80.0, help="flight height above ground, m (default 80)")
    p.add_argument("--gimbal-pitch", type=float, default=-70.0, help="camera pitch, deg (default -70)")
    p.add_argument("--hfov", type=float, default=50.0, help="horizontal field of view, deg (default 50)")
    p.add_argument("--size", default="640x512", help="image size WxH (default 640x512)")
    p.add_argument("--output-kind", choices=("counts", "display"), default="counts",
                   help="16-bit radiometric counts or 8-bit display frames (default counts)")
    p.add_argument("--palette", default="white-hot", help="palette of display frames (default white-hot)")
    p.add_argument("--dropout", type=float, default=0.05, help="probability of a blank frame (default 0.05)")
    p.add_argument("--growth", type=float, default=0.05, help="fire radius growth, m/s (default 0.05)")
    p.add_argument("--smoke", type=float, default=0.3, help="smoke plume opacity 0-1 (default 0.3)")
    p.add_argument("--lat", type=float, default=45.4592, help="scene latitude, deg")
    p.add_argument("--lon", type=float, default=-73.9191, help="scene longitude, deg")
    p.add_argument("--ground-alt", type=float, default=30.0, help="scene ground ellipsoidal height, m")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace a flight already in OUT_DIR (refused without it, so old frames never mix "
                        "with new poses)")
    p.add_argument("--mountain", choices=("orbit", "pass", "calibration"), default=None,
                   help="instead: a flight over a seeded mountain (2 km, central Corsica) with a consumer "
                        "drone's pose errors (correlated GNSS, attitude drift, boresight, clock offset); writes "
                        "dem.tif (10 m, AMSL) too: locate with --dem dem.tif --dem-datum amsl --joint. "
                        "'calibration' is the boresight calibration orbit of thermal/README.md (flown "
                        "clockwise, then back; a frame every 2 s: --frames 567 is the recommended 19 min). "
                        "--frames, --fires, --seed apply")


def run_thermal_flight(args: argparse.Namespace) -> int:
    """``skyfix datasets thermal-flight``."""
    from skyfix import validate
    from skyfix.camera import Camera
    from skyfix.datasets.thermal_flight import orbit, prepare_flight_dir, write_flight
    from skyfix.datasets.thermal_scene import ThermalScene, ThermalSensor, random_fires
    from skyfix.errors import InputError
    from skyfix.geo import LocalFrame
    from skyfix.progress import progress

    try:
        width, height = (int(x) for x in args.size.lower().split("x"))
    except ValueError:
        raise InputError(f"--size must look like 640x512, got {args.size!r}") from None
    validate.integer_in("--fires", args.fires, 0)
    validate.integer_in("--frames", args.frames, 1)
    prepare_flight_dir(args.out_dir, overwrite=args.overwrite)
    if args.mountain:
        return _simulate_mountain(args, Camera.from_fov(width, height, args.hfov))
    rng = np.random.default_rng(args.seed)
    frame = LocalFrame(args.lat, args.lon, args.ground_alt)
    fires = random_fires(args.fires, rng, half_extent_m=15.0, growth_mps=args.growth,
                         smoke_opacity=args.smoke)
    scene = ThermalScene(frame, fires, size_m=300.0, seed=args.seed)
    camera = Camera.from_fov(width, height, args.hfov)
    flight = orbit(scene, camera, (0.0, 0.0), n_frames=args.frames, agl_m=args.agl, frame_rate_hz=2.0,
                   gimbal_pitch_deg=args.gimbal_pitch, dropout_probability=args.dropout, seed=args.seed)
    sensor = ThermalSensor(width, height, seed=args.seed)
    write_flight(args.out_dir, scene, camera, flight, sensor, output=args.output_kind, palette=args.palette,
                 seed=args.seed, progress=lambda it: progress(it, desc="render", unit="frame"))
    print(f"wrote {args.frames} frame(s) with {args.fires} fire(s) to {args.out_dir} "
          f"(locate with: skyfix thermal locate {args.out_dir / 'frames'} --poses {args.out_dir / 'poses.csv'} "
          f"--camera {args.out_dir / 'camera.json'} --ground-alt {args.ground_alt} -o fires.geojson)")
    return 0


def _simulate_mountain(args: argparse.Namespace, camera) -> int:
    """``skyfix datasets thermal-flight --mountain orbit|pass|calibration``."""
    from skyfix.datasets.mountain_flight import (
        fly,
        lines_log,
        mountain_scene,
        orbit_log,
        write_mountain_flight,
    )
    from skyfix.datasets.pose_errors import PoseErrorModel
    from skyfix.progress import progress

    scene = mountain_scene(args.seed, n_fires=max(args.fires, 1))
    speed, rate_hz = 8.0, 0.5 if args.mountain == "calibration" else 1.0
    if args.mountain in ("orbit", "calibration"):
        both = args.mountain == "calibration"
        laps = args.frames / rate_hz * speed / (2 * math.pi * 180.0) / (2.0 if both else 1.0)
        log_ = orbit_log(scene, (0.0, 0.0), radius_m=180.0, height_m=100.0, laps=laps, speed_mps=speed,
                         both_ways=both)
    else:
        half = args.frames * speed / 2.0
        up = float(np.nanmax(scene.terrain.up_at(np.linspace(-half, half, 100), np.zeros(100)))) + 110.0
        log_ = lines_log(scene, [(-half, 0.0), (half, 0.0)], up_m=up, gimbal_pitch_deg=-60.0)
    errors = PoseErrorModel.draw(np.random.default_rng(1000 + args.seed))
    flight = fly(scene, camera, log_, errors, frame_rate_hz=rate_hz, seed=args.seed)
    write_mountain_flight(args.out_dir, flight, progress=lambda it: progress(it, desc="render", total=len(
        flight.stamps_s), unit="frame"))
    d = args.out_dir
    print(f"wrote {len(flight.stamps_s)} frame(s) over a mountain with {len(scene.fires)} fire(s) to {d} "
          f"(locate with: skyfix thermal locate {d / 'frames'} --poses {d / 'poses.csv'} --camera "
          f"{d / 'camera.json'} --dem {d / 'dem.tif'} --dem-datum amsl --joint -o fires.geojson)")
    return 0
