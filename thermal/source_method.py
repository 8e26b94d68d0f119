"""The source thesis's fire-location method, kept as the baseline skyfix is measured against.

From the forest-fire drone thesis (see DESIGN.md, "Facts from the source documents"),
eqs. (5)-(15): threshold an 8-bit white-hot frame; centroid (Xc, Yc) = plain mean of
the hot pixels' coordinates; offsets from the image centre dx = W/2 - Xc,
dy = H/2 - Yc; angles are offsets times FOV/pixels (linear, no pinhole arctangent);
bearing = vehicle heading + horizontal angle; angle from nadir
theta = 90 - (frame pitch + camera depression) + vertical angle; ground distance
D = height * tan(theta) (flat terrain, roll ignored); destination on a sphere of
R = 6371 km. Two readings are charitable: the thesis adds dx to the heading, which
sends a fire left of centre to the right, so the sign is flipped here; the height is
the true height above the (flat) ground.
"""

from __future__ import annotations

import math

import numpy as np

from skyfix.errors import InputError

EARTH_RADIUS_M = 6371e3


def source_method_locate(frame_u8: np.ndarray, *, threshold_level: int, hfov_deg: float, vfov_deg: float,
                         lat_deg: float, lon_deg: float, height_m: float, heading_deg: float,
                         pitch_deg: float, camera_depression_deg: float) -> tuple[float, float] | None:
    """(lat_deg, lon_deg) of the hot-pixel centroid, or None when no pixel exceeds
    ``threshold_level``. ``pitch_deg``: vehicle pitch, nose-up positive (a nose-down
    pitch adds to the camera depression); ``camera_depression_deg``: mount angle below
    the horizon (90 = nadir)."""
    img = np.asarray(frame_u8)
    if img.dtype != np.uint8 or img.ndim != 2:
        raise InputError(f"frame_u8 must be an (H, W) uint8 white-hot frame, got {img.dtype} {img.shape}")
    vv, uu = np.nonzero(img > threshold_level)
    if uu.size == 0:
        return None
    h, w = img.shape
    xc, yc = uu.mean(), vv.mean()                                  # (5), (6)
    dx, dy = w / 2.0 - xc, h / 2.0 - yc                            # (7), (8)
    x_t = dx * hfov_deg / w                                        # (9)
    bearing = heading_deg - x_t                                    # (10), sign see docstring
    phi_t = dy * vfov_deg / h                                      # (11)
    theta = 90.0 - (-pitch_deg + camera_depression_deg) + phi_t    # (12)
    dist = height_m * math.tan(math.radians(theta))                # (13)
    lat1, lon1 = math.radians(lat_deg), math.radians(lon_deg)
    delta, brg = dist / EARTH_RADIUS_M, math.radians(bearing)
    lat2 = math.asin(math.sin(lat1) * math.cos(delta) + math.cos(lat1) * math.sin(delta) * math.cos(brg))  # (14)
    lon2 = lon1 + math.atan2(math.sin(brg) * math.sin(delta) * math.cos(lat1),
                             math.cos(delta) - math.sin(lat1) * math.sin(lat2))                         # (15)
    return math.degrees(lat2), math.degrees(lon2)
