"""Synthetic thermal flights: poses that look at given ground points, and whole flights
written to disk in the layout ``skyfix thermal locate`` reads.

Layout of a flight directory: ``frames/NNNNN.png`` (16-bit radiometric counts, or 8-bit
display frames), ``poses.csv`` (one row per frame, columns of
:data:`skyfix.thermal.io.POSE_COLUMNS`), ``camera.json`` (:mod:`skyfix.camera_io` format) and ``truth.json`` (fires in
WGS84, with the scene's ground height).
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from skyfix import validate
from skyfix.camera import Camera, CameraPose
from skyfix.camera_io import save_camera
from skyfix.datasets.render import rendered_in_order
from skyfix.datasets.thermal_scene import ThermalScene, ThermalSensor, to_display
from skyfix.errors import GeometryError, InputError
from skyfix.geo import LocalFrame
from skyfix.thermal.io import POSE_COLUMNS


def pose_seeing(frame: LocalFrame, camera: Camera, target_enu_m: np.ndarray, uv_px: np.ndarray,
                agl_m: float, *, roll_deg: float, pitch_deg: float, yaw_deg: float,
                gimbal_pitch_deg: float, gimbal_yaw_deg: float = 0.0, stabilized: bool = False
                ) -> CameraPose:
    """A camera pose ``agl_m`` above the plane ``up = 0`` of ``frame`` from which the
    ground point ``target_enu_m`` ``(3,)`` appears near pixel ``uv_px`` ``(2,)`` (within
    the axis difference between the frame origin and the vehicle, ~0.01 deg per km).
    Raises :class:`GeometryError` when that pixel's ray does not point down enough."""
    target = validate.finite_array("target_enu_m", target_enu_m).reshape(3)
    agl = validate.positive_scalar("agl_m", agl_m)
    probe = CameraPose(frame.lat0_deg, frame.lon0_deg, frame.alt0_m + agl, roll_deg, pitch_deg, yaw_deg,
                       gimbal_pitch_deg, gimbal_yaw_deg, 0.0, stabilized)
    d = probe.r_enu_from_cam() @ camera.pixel_to_ray(np.asarray(uv_px, float).reshape(1, 2))[0]
    if d[2] > -0.1:
        raise GeometryError(f"pixel {list(uv_px)} looks {np.degrees(np.arcsin(-d[2])):.1f} deg below "
                            "the horizon; need > 5.7 deg")
    cam = target - (target[2] - agl) / d[2] * d
    cam[2] = target[2] + agl
    lat, lon, alt = frame.to_geodetic(cam[0], cam[1], cam[2])
    return CameraPose(float(lat), float(lon), float(alt), roll_deg, pitch_deg, yaw_deg,
                      gimbal_pitch_deg, gimbal_yaw_deg, 0.0, stabilized)


@dataclass(frozen=True)
class FlightFrame:
    """One simulated frame: true pose, time, and whether it was dropped (blank)."""

    pose: CameraPose
    time_s: float
    dropped: bool = False


def orbit(scene: ThermalScene, camera: Camera, centre_en_m: tuple[float, float], *, n_frames: int,
          agl_m: float, frame_rate_hz: float, gimbal_pitch_deg: float = -70.0, stabilized: bool = True,
          wobble_deg: float = 3.0, dropout_probability: float = 0.0, seed: int = 0) -> list[FlightFrame]:
    """A full circle around ``centre_en_m`` keeping it near the image centre, with random
    roll/pitch wobble (deg, 1-sigma) and random frame drop-outs."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n_frames):
        yaw = 360.0 * k / n_frames
        uv = np.array([camera.cx, camera.cy]) + rng.normal(0.0, 20.0, 2)
        pose = pose_seeing(scene.frame, camera, np.array([*centre_en_m, 0.0]), uv, agl_m,
                           roll_deg=rng.normal(0, wobble_deg), pitch_deg=rng.normal(0, wobble_deg),
                           yaw_deg=yaw, gimbal_pitch_deg=gimbal_pitch_deg, stabilized=stabilized)
        out.append(FlightFrame(pose, k / frame_rate_hz, bool(rng.random() < dropout_probability)))
    return out


def write_poses_csv(path: str | Path, rows: list[tuple[str, float, CameraPose]]) -> Path:
    """A pose CSV (:data:`POSE_COLUMNS`, ellipsoidal altitude, gimbal yaw relative to the
    nose) from (frame name, time s, pose) rows; floats at full precision."""
    with open(path, "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(POSE_COLUMNS)
        for name, t, p in rows:
            writer.writerow([name, t, p.lat_deg, p.lon_deg, p.alt_m, p.roll_deg, p.pitch_deg, p.yaw_deg,
                             p.gimbal_pitch_deg, p.gimbal_roll_deg, p.gimbal_yaw_deg, int(p.stabilized)])
    return Path(path)


#: Files a written flight consists of (besides ``frames/``).
FLIGHT_FILES = ("poses.csv", "camera.json", "truth.json", "dem.tif")


def prepare_flight_dir(out_dir: str | Path, *, overwrite: bool = False) -> Path:
    """Make ``out_dir`` ready for a new flight: a folder that already holds one (frames or
    flight files) is refused, so old frames never sit next to new poses, unless
    ``overwrite``, which deletes that flight's files first (nothing else in the folder)."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"output folder {out} is a file")
    frames = out / "frames"
    old = [p for p in frames.iterdir() if p.is_file()] if frames.is_dir() else []
    old += [out / name for name in FLIGHT_FILES if (out / name).is_file()]
    if old and not overwrite:
        raise InputError(f"output folder {out} already holds a flight ({len(old)} files, e.g. {old[0].name}); "
                         "choose an empty folder or pass --overwrite to replace it")
    for p in old:
        p.unlink()
    frames.mkdir(parents=True, exist_ok=True)
    return out


def write_flight(out_dir: str | Path, scene: ThermalScene, camera: Camera, flight: list[FlightFrame],
                 sensor: ThermalSensor, *, output: str = "counts", palette: str = "white-hot",
                 span_c: tuple[float, float] | None = (0.0, 150.0), seed: int = 0, progress=iter,
                 threads: int = 2) -> Path:
    """Render ``flight`` and write it (see module docstring). ``output``: "counts" (16-bit
    PNG, radiometric) or "display" (8-bit ``palette``, fixed ``span_c`` or automatic
    gain when None). Dropped frames are written as blank (constant) frames. ``threads``
    frames are rendered ahead at once; the files are the same for any ``threads``."""
    out = Path(out_dir)
    (out / "frames").mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    rows = []

    def render(k: int) -> np.ndarray | None:
        ff = flight[k]
        return None if ff.dropped else scene.render(camera, ff.pose, ff.time_s)

    for k, rendered in rendered_in_order(render, progress(range(len(flight))), threads=threads):
        ff = flight[k]
        name = f"frames/{k:05d}.png"
        if rendered is None:
            img = np.zeros((camera.height, camera.width), np.uint16 if output == "counts" else np.uint8)
        else:
            celsius = sensor.observe(rendered, rng)
            img = sensor.to_counts(celsius) if output == "counts" else to_display(celsius, palette=palette, span_c=span_c)
        if img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
        cv2.imwrite(str(out / name), img)
        rows.append((name, ff.time_s, ff.pose))
    write_poses_csv(out / "poses.csv", rows)
    save_camera(out / "camera.json", camera)
    truth = {"ground_alt_m": scene.ground_alt_m, "kelvin_per_count": sensor.kelvin_per_count,
             "output": output, "palette": palette, "fires": []}
    for i, f in enumerate(scene.fires):
        lat, lon, alt = scene.frame.to_geodetic(f.east_m, f.north_m, 0.0)
        truth["fires"].append({"index": i, "lat_deg": float(lat), "lon_deg": float(lon), "alt_m": float(alt),
                               "radius_m": f.radius_m, "growth_mps": f.growth_mps,
                               "start_s": None if np.isinf(f.start_s) else f.start_s,
                               "end_s": None if np.isinf(f.end_s) else f.end_s})
    (out / "truth.json").write_text(json.dumps(truth, indent=2))
    return out
