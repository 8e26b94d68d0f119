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
import logging
from pathlib import Path

import cv2
import numpy as np

from skyfix.camera import CameraPose
from skyfix.errors import DataError, InputError
from skyfix.imagefile import read_image
from skyfix.thermal.pose import camera_pose

log = logging.getLogger(__name__)

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
    img = read_image(path, what="frame")
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3], cv2.COLOR_BGR2RGB)
    return img


#: Scale of a 2-dof covariance ellipse holding 95 % of the probability (chi-square 2 dof).
ELLIPSE_95_CHI2 = 5.991


def ellipse_axes(cov_en_m2: np.ndarray, chi2: float = ELLIPSE_95_CHI2) -> tuple[float, float, float]:
    """(semi-major m, semi-minor m, azimuth of the major axis deg clockwise from north) of
    the ellipse x^T C^-1 x = ``chi2`` of a 2x2 (east, north) covariance."""
    vals, vecs = np.linalg.eigh(np.asarray(cov_en_m2, float))
    major = vecs[:, 1]
    azimuth = float(np.degrees(np.arctan2(major[0], major[1])) % 180.0)
    return float(np.sqrt(chi2 * vals[1])), float(np.sqrt(chi2 * max(vals[0], 0.0))), azimuth


def _ellipse_ring(f, n: int = 36) -> list[list[float]]:
    """The 95 % ellipse of a fire as a closed lon/lat ring (geodesic offsets from the fire)."""
    from skyfix.geo import destination

    a, b, az = ellipse_axes(f.cov_en_m2)
    th = np.linspace(0.0, 2 * np.pi, n + 1)
    along, across = a * np.cos(th), b * np.sin(th)
    dist = np.hypot(along, across)
    bearing = az + np.degrees(np.arctan2(across, along))
    lat, lon = destination(np.full(th.size, f.lat_deg), np.full(th.size, f.lon_deg), bearing, dist)
    ring = [[round(float(x), 9), round(float(y), 9)] for x, y in zip(lon, lat, strict=True)]
    ring[-1] = ring[0]
    return ring


def fires_geojson(fires, *, track: np.ndarray | None = None) -> dict:
    """GeoJSON FeatureCollection: a Point per :class:`~skyfix.thermal.Fire` with its
    sigma, 95 % ellipse axes and first/last-seen times, a Polygon per fire with that
    ellipse, and optionally the camera track (``(N, 2)`` lat, lon) as a line."""
    feats = []
    for f in fires:
        a, b, az = ellipse_axes(f.cov_en_m2)
        feats.append({"type": "Feature", "geometry": {"type": "Polygon", "coordinates": [_ellipse_ring(f)]},
                      "properties": {"fire_id": f.fire_id, "kind": "95 % uncertainty ellipse",
                                     "semi_major_m": round(a, 3), "semi_minor_m": round(b, 3),
                                     "azimuth_deg": round(az, 2)}})
        feats.append({"type": "Feature", "geometry": {"type": "Point", "coordinates": [f.lon_deg, f.lat_deg, f.alt_m]},
                      "properties": {"fire_id": f.fire_id, "sigma_m": round(f.sigma_m, 3),
                                     "sigma_major_m": round(f.sigma_major_m, 3),
                                     "cov_en_m2": np.round(f.cov_en_m2, 4).tolist(),
                                     "n_observations": f.n_observations, "first_seen_s": f.first_seen_s,
                                     "last_seen_s": f.last_seen_s, "area_m2": round(f.area_m2, 2),
                                     "peak": round(f.peak, 1), "burning": f.burning,
                                     "ellipse95_semi_major_m": round(a, 3), "ellipse95_semi_minor_m": round(b, 3),
                                     "ellipse95_azimuth_deg": round(az, 2), "alt_datum": "WGS84 ellipsoid"}})
    if track is not None and len(track) >= 2:
        feats.append({"type": "Feature", "geometry": {"type": "LineString",
                                                      "coordinates": [[float(lon), float(lat)] for lat, lon in track]},
                      "properties": {"kind": "camera track"}})
    return {"type": "FeatureCollection", "features": feats}


CSV_COLUMNS = ("fire_id", "lat_deg", "lon_deg", "alt_ellipsoid_m", "sigma_east_m", "sigma_north_m",
               "cov_en_m2", "ellipse95_semi_major_m", "ellipse95_semi_minor_m", "ellipse95_azimuth_deg",
               "first_seen_s", "last_seen_s", "n_observations", "area_m2", "peak", "burning")


def write_fires_csv(path: str | Path, fires) -> Path:
    """One row per fire (columns :data:`CSV_COLUMNS`; ``cov_en_m2`` the east-north
    covariance element, m^2); positions at full precision."""
    path = Path(path)
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(CSV_COLUMNS)
        for f in fires:
            a, b, az = ellipse_axes(f.cov_en_m2)
            c = f.cov_en_m2
            w.writerow([f.fire_id, f.lat_deg, f.lon_deg, round(f.alt_m, 3), round(float(np.sqrt(c[0, 0])), 3),
                        round(float(np.sqrt(c[1, 1])), 3), round(float(c[0, 1]), 4), round(a, 3), round(b, 3),
                        round(az, 2), f.first_seen_s, f.last_seen_s, f.n_observations, round(f.area_m2, 2),
                        round(f.peak, 1), int(f.burning)])
    return path


def frame_path(frames_dir: str | Path, name: str) -> Path:
    """Where frame ``name`` (from the pose CSV) lives in ``frames_dir``."""
    return Path(frames_dir) / Path(name).name


#: File name endings read as frames.
FRAME_SUFFIXES = (".png", ".tif", ".tiff", ".npy", ".jpg", ".jpeg", ".pgm")


def match_frames(frames_dir: str | Path, rows: list, pose_file: str | Path) -> tuple[list, list[str]]:
    """The pose rows whose frame is in ``frames_dir``, as ``(path, time_s, pose)``, and
    the names of the frames in the folder that have no pose row.

    Raises :class:`InputError` naming the folder when it is missing, not a folder or holds
    no frame file, and naming the pose file when none of its frames is in the folder.
    Rows whose frame file is missing are logged (named) and left out."""
    folder = Path(frames_dir)
    if not folder.exists():
        raise InputError(f"frames folder {folder} does not exist")
    if not folder.is_dir():
        raise InputError(f"frames folder {folder} is not a folder")
    on_disk = {p.name for p in folder.iterdir() if p.is_file() and p.suffix.lower() in FRAME_SUFFIXES}
    if not on_disk:
        raise InputError(f"frames folder {folder} holds no frame ({', '.join(FRAME_SUFFIXES)})")
    matched = [(frame_path(folder, name), t, pose) for name, t, pose in rows if Path(name).name in on_disk]
    missing = [Path(name).name for name, _, _ in rows if Path(name).name not in on_disk]
    if not matched:
        raise InputError(f"none of the {len(rows)} frames listed in {pose_file} is in {folder}")
    if missing:
        log.warning("%d frame(s) listed in %s are not in %s and are left out: %s", len(missing), pose_file,
                    folder, _names(missing))
    unposed = sorted(on_disk - {Path(name).name for name, _, _ in rows})
    if unposed:
        log.warning("%d frame(s) in %s have no row in %s and are left out: %s", len(unposed), folder, pose_file,
                    _names(unposed))
    return matched, unposed


def _names(names: list[str], shown: int = 5) -> str:
    return ", ".join(names[:shown]) + (f" and {len(names) - shown} more" if len(names) > shown else "")
