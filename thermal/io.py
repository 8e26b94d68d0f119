"""Files of a thermal flight: pose CSV, frames, GeoJSON output.

The camera file is skyfix's one camera JSON format (:mod:`skyfix.camera_io`).

Pose CSV: a header row, one row per frame. Required columns: ``frame`` (the frame's
file name; any directory part is ignored and the file is looked up in the frames
directory given to the command), ``time_s``, ``lat_deg``, ``lon_deg``, one altitude column
(``alt_ellipsoid_m``, or ``alt_amsl_m`` with a geoid undulation given separately),
``roll_deg``, ``pitch_deg``, ``yaw_deg``, ``gimbal_pitch_deg``, one gimbal-yaw column
(``gimbal_yaw_body_deg`` relative to the nose, or ``gimbal_yaw_north_deg`` absolute),
and ``stabilized`` (1 gimbal, 0 hard-mounted). ``gimbal_roll_deg`` is optional.
Ambiguous names such as ``alt`` or ``gimbal_yaw`` are refused.
"""

from __future__ import annotations

import csv
from pathlib import Path

import cv2
import numpy as np

from skyfix.camera import CameraPose
from skyfix.errors import DataError
from skyfix.thermal.pose import camera_pose

POSE_COLUMNS = ("frame", "time_s", "lat_deg", "lon_deg", "alt_ellipsoid_m", "roll_deg", "pitch_deg",
                "yaw_deg", "gimbal_pitch_deg", "gimbal_roll_deg", "gimbal_yaw_body_deg", "stabilized")
_AMBIGUOUS = ("alt", "alt_m", "altitude", "gimbal_yaw", "gimbal_yaw_deg", "heading")


def read_poses(path: str | Path, *, geoid_undulation_m: float | None = None
               ) -> list[tuple[str, float, CameraPose]]:
    """(frame name as written, time_s, pose) per CSV row (see module docstring)."""
    path = Path(path)
    try:
        with open(path, newline="") as fh:
            rows = list(csv.DictReader(fh))
    except OSError as exc:
        raise DataError(f"cannot read pose file {path}: {exc}") from None
    if not rows:
        raise DataError(f"pose file {path} has no rows")
    cols = set(rows[0])
    bad = cols & set(_AMBIGUOUS)
    if bad:
        raise DataError(f"pose file {path}: ambiguous column(s) {sorted(bad)}; name the datum "
                        "(alt_ellipsoid_m / alt_amsl_m) and reference (gimbal_yaw_body_deg / gimbal_yaw_north_deg)")
    alt_cols = [c for c in ("alt_ellipsoid_m", "alt_amsl_m") if c in cols]
    yaw_cols = [c for c in ("gimbal_yaw_body_deg", "gimbal_yaw_north_deg") if c in cols]
    if len(alt_cols) != 1 or len(yaw_cols) != 1:
        raise DataError(f"pose file {path} needs exactly one of alt_ellipsoid_m/alt_amsl_m (has {alt_cols}) "
                        f"and one of gimbal_yaw_body_deg/gimbal_yaw_north_deg (has {yaw_cols})")
    out = []
    for i, r in enumerate(rows, start=2):
        try:
            pose = camera_pose(
                float(r["lat_deg"]), float(r["lon_deg"]), float(r[alt_cols[0]]),
                altitude_datum="ellipsoid" if alt_cols[0] == "alt_ellipsoid_m" else "amsl",
                geoid_undulation_m=geoid_undulation_m,
                roll_deg=float(r["roll_deg"]), pitch_deg=float(r["pitch_deg"]), yaw_deg=float(r["yaw_deg"]),
                gimbal_pitch_deg=float(r["gimbal_pitch_deg"]), gimbal_roll_deg=float(r.get("gimbal_roll_deg") or 0.0),
                gimbal_yaw_deg=float(r[yaw_cols[0]]),
                gimbal_yaw_reference="vehicle" if yaw_cols[0] == "gimbal_yaw_body_deg" else "north",
                stabilized=bool(int(float(r["stabilized"]))))
            out.append((r["frame"], float(r["time_s"]), pose))
        except (KeyError, ValueError, TypeError) as exc:
            raise DataError(f"pose file {path} line {i}: {exc}") from None
    return out


def read_frame(path: str | Path) -> np.ndarray:
    """A frame as stored: 16-bit counts, 8-bit grey, or 8-bit colour (returned RGB);
    ``.npy`` files may hold float deg C frames."""
    path = Path(path)
    if path.suffix == ".npy":
        try:
            return np.load(path)
        except (OSError, ValueError) as exc:
            raise DataError(f"cannot read frame {path}: {exc}") from None
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DataError(f"cannot read frame {path}")
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3], cv2.COLOR_BGR2RGB)
    return img


def fires_geojson(fires, *, track: np.ndarray | None = None) -> dict:
    """GeoJSON FeatureCollection: a Point per :class:`~skyfix.thermal.Fire` with its
    sigma and history, and optionally the camera track (``(N, 2)`` lat, lon) as a line."""
    feats = []
    for f in fires:
        feats.append({"type": "Feature", "geometry": {"type": "Point", "coordinates": [f.lon_deg, f.lat_deg, f.alt_m]},
                      "properties": {"fire_id": f.fire_id, "sigma_m": round(f.sigma_m, 3),
                                     "sigma_major_m": round(f.sigma_major_m, 3),
                                     "cov_en_m2": np.round(f.cov_en_m2, 4).tolist(),
                                     "n_observations": f.n_observations, "first_seen_s": f.first_seen_s,
                                     "last_seen_s": f.last_seen_s, "area_m2": round(f.area_m2, 2),
                                     "peak": round(f.peak, 1), "burning": f.burning,
                                     "alt_datum": "WGS84 ellipsoid"}})
    if track is not None and len(track) >= 2:
        feats.append({"type": "Feature", "geometry": {"type": "LineString",
                                                      "coordinates": [[float(lon), float(lat)] for lat, lon in track]},
                      "properties": {"kind": "camera track"}})
    return {"type": "FeatureCollection", "features": feats}


def frame_path(frames_dir: str | Path, name: str) -> Path:
    """Where frame ``name`` (from the pose CSV) lives in ``frames_dir``."""
    return Path(frames_dir) / Path(name).name
