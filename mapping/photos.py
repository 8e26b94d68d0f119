"""Photo intake for the photo-to-model pipeline: EXIF, camera groups, GPS overlap check.

Every JPEG in a folder becomes either a :class:`Photo` (usable) or a :class:`Rejected`
entry with the reason (corrupt file, no EXIF focal length, unreadable header). Photos
without GPS are kept (they reconstruct, unreferenced) and flagged. GPS altitude is kept
as recorded, which for consumer cameras is above mean sea level (AMSL).
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from skyfix import validate
from skyfix.errors import DataError, InputError
from skyfix.mapping.batch import list_photos, reason
from skyfix.mapping.exif import PhotoMetadata, read_metadata

__all__ = ["OverlapCheck", "Photo", "Rejected", "camera_groups", "check_gps_overlap", "load_photos"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Photo:
    """A usable photo. ``focal_px`` from EXIF/XMP (``focal_source`` says which tag, see
    :class:`~skyfix.mapping.exif.FocalEstimate`); ``gps_alt_amsl_m`` as recorded (AMSL);
    ``relative_alt_m`` the drone's own height above its take-off point (DJI XMP), if any."""

    name: str
    path: str
    width: int
    height: int
    make: str | None
    model: str | None
    focal_px: float
    orientation: int | None
    gps_lat_deg: float | None
    gps_lon_deg: float | None
    gps_alt_amsl_m: float | None
    focal_source: str = ""
    relative_alt_m: float | None = None
    time_s: float | None = None

    @property
    def has_gps(self) -> bool:
        return None not in (self.gps_lat_deg, self.gps_lon_deg, self.gps_alt_amsl_m)

    @property
    def camera_key(self) -> tuple:
        """Photos with equal keys share one camera model in structure from motion."""
        return (self.make, self.model, self.width, self.height, round(self.focal_px, 1))


@dataclass(frozen=True)
class Rejected:
    """A photo left out, and why."""

    name: str
    reason: str


def _photo(path: Path) -> Photo:
    from PIL import Image

    data = path.read_bytes()
    if not data.rstrip(b"\x00").endswith(b"\xff\xd9"):
        raise DataError(f"{path.name}: corrupt JPEG (truncated: no end-of-image marker)")
    meta: PhotoMetadata = read_metadata(data, path.name, require_exif=True)
    try:
        with Image.open(path) as im:
            width, height = im.size
    except OSError as exc:
        raise DataError(f"{path.name}: corrupt JPEG ({exc})") from exc
    if meta.orientation not in (None, 1):
        # Pixels are used as stored; EXIF rotation only matters for display.
        log.info("%s: EXIF orientation %s ignored (pixels used as stored)", path.name, meta.orientation)
    focal = meta.focal_estimate(width, height)
    return Photo(name=path.name, path=str(path), width=width, height=height, make=meta.make, model=meta.model,
                 focal_px=focal.focal_px, orientation=meta.orientation,
                 gps_lat_deg=meta.gps_lat_deg, gps_lon_deg=meta.gps_lon_deg, gps_alt_amsl_m=meta.gps_alt_m,
                 focal_source=focal.source, relative_alt_m=meta.xmp.get("RelativeAltitude"), time_s=meta.time_s)


def load_photos(photos_dir: str | os.PathLike) -> tuple[list[Photo], list[Rejected]]:
    """Usable photos (sorted by name) and rejected ones with reasons.

    Raises :class:`InputError` when the folder is missing or holds no JPEG at all.
    """
    paths = list_photos(photos_dir)
    if not paths:
        raise InputError(f"photo folder {str(photos_dir)!r} holds no JPEG photos (*.jpg, *.jpeg)")
    photos, rejected = [], []
    for path in paths:
        try:
            photos.append(_photo(path))
        except (DataError, OSError) as exc:
            why = reason(exc, path)
            log.warning("rejected %s: %s", path.name, why)
            rejected.append(Rejected(path.name, why))
    without_gps = [p.name for p in photos if not p.has_gps]
    if without_gps:
        log.warning("%d photo(s) without GPS in EXIF (they reconstruct but do not georeference): %s",
                    len(without_gps), ", ".join(without_gps[:10]))
    return photos, rejected


def camera_groups(photos: list[Photo]) -> dict[tuple, list[Photo]]:
    """Photos grouped by :attr:`Photo.camera_key` (one shared camera model per group)."""
    groups: dict[tuple, list[Photo]] = {}
    for p in photos:
        groups.setdefault(p.camera_key, []).append(p)
    if len(groups) > 1:
        log.warning("mixed cameras: %s", "; ".join(f"{k[0]} {k[1]} {k[2]}x{k[3]} f={k[4]}px ({len(v)} photos)"
                                                   for k, v in groups.items()))
    return groups


@dataclass(frozen=True)
class OverlapCheck:
    """GPS-based overlap test before matching.

    ``isolated``: photos whose nearest GPS neighbour is farther than their largest possible
    footprint (at ``max_agl_m``), so they cannot overlap any other photo.
    ``nearest_m``: nearest-neighbour horizontal distance per GPS photo (same order as ``names``).
    """

    names: list[str]
    nearest_m: list[float]
    footprint_m: list[float]
    isolated: list[str]

    @property
    def ok(self) -> bool:
        return not self.isolated


def check_gps_overlap(photos: list[Photo], max_agl_m: float = 120.0) -> OverlapCheck:
    """Which GPS-tagged photos cannot overlap any other one.

    The ground height is unknown before reconstruction, so the footprint is bounded from
    above with ``max_agl_m`` (the height above ground the drone cannot exceed; 120 m is
    the usual legal ceiling): its diagonal is ``max_agl_m * diagonal_px / focal_px``.
    """
    from skyfix.geo import LocalFrame

    max_agl_m = validate.positive_scalar("max_agl_m", max_agl_m)
    gps = [p for p in photos if p.has_gps]
    if len(gps) < 2:
        return OverlapCheck([p.name for p in gps], [], [], [])
    lla = np.array([(p.gps_lat_deg, p.gps_lon_deg, p.gps_alt_amsl_m) for p in gps])
    frame = LocalFrame(*lla.mean(axis=0))
    en = frame.to_enu_points(lla)[:, :2]
    dist = np.linalg.norm(en[:, None, :] - en[None, :, :], axis=2)
    np.fill_diagonal(dist, np.inf)
    nearest = dist.min(axis=1)
    footprint = np.array([max_agl_m * math.hypot(p.width, p.height) / p.focal_px for p in gps])
    isolated = [p.name for p, d, f in zip(gps, nearest, footprint, strict=True) if d > f]
    if isolated:
        log.warning("%d photo(s) are too far from every other photo to overlap (even at %.0f m above ground): %s",
                    len(isolated), max_agl_m, ", ".join(isolated[:10]))
    return OverlapCheck([p.name for p in gps], nearest.tolist(), footprint.tolist(), isolated)
