"""Geodesy on the WGS84 ellipsoid: local ENU frames and geodesic problems.

Conventions: latitude/longitude in degrees, heights in metres above the WGS84
ellipsoid (``alt_m``); a height whose datum varies (telemetry's AMSL vs GNSS's ellipsoidal)
is a :class:`Height`, which names its :class:`VerticalDatum` and converts between them. The local frame is East-North-Up metres about an explicit
origin. Everything is exact on the ellipsoid (pyproj's cart + topocentric pipeline,
pyproj.Geod for geodesics); no flat-earth shortcut is taken anywhere. All functions
are vectorised: scalars or arrays of any broadcastable shape go in, arrays of the
same shape come out (0-d inputs give 0-d arrays).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np
import pyproj

from skyfix import validate
from skyfix.errors import InputError
from skyfix.geoid import undulation_near_m
from skyfix.units import LatLonAltArray

WGS84 = pyproj.Geod(ellps="WGS84")


def _geodetic_checked(lat, lon, alt) -> tuple[np.ndarray, np.ndarray, np.ndarray] | tuple[float, float, float]:
    """Checked inputs for pyproj: three plain floats stay floats (pyproj transforms them
    ten times faster than 0-d arrays, to the same values), else broadcast arrays."""
    if isinstance(lat, float) and isinstance(lon, float) and isinstance(alt, float):
        validate.latitude("lat", lat), validate.longitude("lon", lon), validate.finite_array("alt", alt)
        return float(lat), float(lon), float(alt)
    lat_a = validate.latitude("lat", lat)
    lon_a = validate.longitude("lon", lon)
    alt_a = validate.finite_array("alt", alt)
    if lat_a.shape == lon_a.shape == alt_a.shape:  # broadcasting would return them as they are
        return lat_a, lon_a, alt_a
    return np.broadcast_arrays(lat_a, lon_a, alt_a)


def geodetic_to_ecef(lat_deg, lon_deg, alt_m) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """WGS84 geodetic (deg, deg, m ellipsoidal) -> ECEF (x, y, z) metres.

    Example:
        >>> x, y, z = geodetic_to_ecef(0.0, 90.0, 10.0)  # equator, 90 deg east: on the +y axis
        >>> print(f"{float(x):.3f} {float(y):.3f} {float(z):.3f}")
        0.000 6378147.000 0.000
    """
    lat, lon, alt = _geodetic_checked(lat_deg, lon_deg, alt_m)
    x, y, z = _TO_ECEF.transform(lon, lat, alt)
    return np.asarray(x), np.asarray(y), np.asarray(z)


def ecef_to_geodetic(x_m, y_m, z_m) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ECEF (x, y, z) metres -> WGS84 geodetic (lat_deg, lon_deg, alt_m ellipsoidal).

    Example:
        >>> lat, lon, alt = ecef_to_geodetic(*geodetic_to_ecef(47.3769, 8.5417, 408.0))
        >>> print(f"{float(lat):.7f} {float(lon):.7f} {float(alt):.4f}")
        47.3769000 8.5417000 408.0000
    """
    x, y, z = np.broadcast_arrays(*(validate.finite_array(n, v) for n, v in
                                    (("x_m", x_m), ("y_m", y_m), ("z_m", z_m))))
    lon, lat, alt = _TO_ECEF.transform(x, y, z, direction=pyproj.enums.TransformDirection.INVERSE)
    return np.asarray(lat), np.asarray(lon), np.asarray(alt)


_TO_ECEF = pyproj.Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)


def ecef_to_enu_rotation(lat_deg: float, lon_deg: float) -> np.ndarray:
    """3x3 rotation taking ECEF vectors into the ENU axes at (lat, lon); rows are E, N, U.

    Example:
        >>> ecef_to_enu_rotation(0.0, 0.0) @ [1.0, 0.0, 0.0]  # ECEF +x is "up" at (0, 0)
        array([0., 0., 1.])
    """
    lat = np.radians(lat_deg)
    lon = np.radians(lon_deg)
    sl, cl = np.sin(lat), np.cos(lat)
    so, co = np.sin(lon), np.cos(lon)
    return np.array([
        [-so, co, 0.0],
        [-sl * co, -sl * so, cl],
        [cl * co, cl * so, sl],
    ])


@dataclass(frozen=True)
class LocalFrame:
    """East-North-Up frame in metres about a geodetic origin (WGS84, ellipsoidal height).

    ``to_enu``/``to_geodetic`` are exact inverse transforms through ECEF (pyproj's
    ``cart`` + ``topocentric`` pipeline), valid at any distance from the origin.

    Example:
        >>> frame = LocalFrame(47.0, 8.0, 400.0)
        >>> east, north, up = frame.to_enu(47.001, 8.0, 400.0)  # 0.001 deg north
        >>> print(f"{float(north):.2f} m north, {abs(float(east)):.2f} m east")
        111.18 m north, 0.00 m east
        >>> frame.to_geodetic_points([[0.0, 0.0, 10.0]]).round(6)
        array([[ 47.,   8., 410.]])
    """

    lat0_deg: float
    lon0_deg: float
    alt0_m: float = 0.0
    _fwd: pyproj.Transformer = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        lat0 = float(validate.latitude("lat0_deg", self.lat0_deg))
        lon0 = float(validate.longitude("lon0_deg", self.lon0_deg))
        alt0 = validate.finite_scalar("alt0_m", self.alt0_m)
        object.__setattr__(self, "lat0_deg", lat0)
        object.__setattr__(self, "lon0_deg", lon0)
        object.__setattr__(self, "alt0_m", alt0)
        pipeline = (
            "+proj=pipeline +step +proj=unitconvert +xy_in=deg +xy_out=rad "
            "+step +proj=cart +ellps=WGS84 "
            f"+step +proj=topocentric +ellps=WGS84 +lat_0={lat0!r} +lon_0={lon0!r} +h_0={alt0!r}"
        )
        object.__setattr__(self, "_fwd", pyproj.Transformer.from_pipeline(pipeline))

    def to_enu(self, lat_deg, lon_deg, alt_m) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Geodetic (deg, deg, m ellipsoidal) -> local (east_m, north_m, up_m)."""
        lat, lon, alt = _geodetic_checked(lat_deg, lon_deg, alt_m)
        e, n, u = self._fwd.transform(lon, lat, alt)
        return np.asarray(e), np.asarray(n), np.asarray(u)

    def to_geodetic(self, east_m, north_m, up_m) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Local (east_m, north_m, up_m) -> geodetic (lat_deg, lon_deg, alt_m ellipsoidal)."""
        e, n, u = np.broadcast_arrays(*(validate.finite_array(nm, v) for nm, v in
                                        (("east_m", east_m), ("north_m", north_m), ("up_m", up_m))))
        lon, lat, alt = self._fwd.transform(e, n, u, direction=pyproj.enums.TransformDirection.INVERSE)
        return np.asarray(lat), np.asarray(lon), np.asarray(alt)

    def _heights_unchecked(self, enu_m: np.ndarray) -> np.ndarray:
        """Ellipsoidal heights ``(N,)`` of finite ENU points ``(N, 3)``, without input
        checks (for inner loops whose points are finite by construction)."""
        _, _, alt = self._fwd.transform(enu_m[:, 0], enu_m[:, 1], enu_m[:, 2],
                                        direction=pyproj.enums.TransformDirection.INVERSE)
        return np.asarray(alt)

    def to_enu_points(self, lla: LatLonAltArray) -> np.ndarray:
        """``(N, 3)`` array of (lat_deg, lon_deg, alt_m) -> ``(N, 3)`` ENU metres."""
        pts = validate.points("lla", lla, 3)
        return np.stack(self.to_enu(pts[:, 0], pts[:, 1], pts[:, 2]), axis=1)

    def to_geodetic_points(self, enu_m: np.ndarray) -> LatLonAltArray:
        """``(N, 3)`` ENU metres -> ``(N, 3)`` array of (lat_deg, lon_deg, alt_m)."""
        pts = validate.points("enu_m", enu_m, 3)
        return np.stack(self.to_geodetic(pts[:, 0], pts[:, 1], pts[:, 2]), axis=1)

    def enu_rotation_at(self, lat_deg: float, lon_deg: float) -> np.ndarray:
        """Rotation taking vectors in the ENU axes *at (lat, lon)* into this frame's axes.

        Directions measured at a vehicle (e.g. its attitude relative to local NED) must
        be rotated by this before use in a frame whose origin is elsewhere: the axes of
        two ENU frames 10 km apart differ by about 0.09 degrees.
        """
        lat = float(validate.latitude("lat_deg", lat_deg))
        lon = float(validate.longitude("lon_deg", lon_deg))
        r_origin = ecef_to_enu_rotation(self.lat0_deg, self.lon0_deg)
        r_there = ecef_to_enu_rotation(lat, lon)
        return r_origin @ r_there.T


def destination(lat_deg, lon_deg, bearing_deg, distance_m) -> tuple[np.ndarray, np.ndarray]:
    """Point reached by travelling ``distance_m`` along the WGS84 geodesic.

    ``bearing_deg`` is the initial azimuth, clockwise from true north. Returns
    (lat_deg, lon_deg) with longitude in [-180, 180).

    Example:
        >>> lat, lon = destination(47.0, 8.0, 90.0, 1000.0)  # 1 km east
        >>> print(f"{float(lat):.6f} {float(lon):.6f}")
        46.999999 8.013148
    """
    lat = validate.latitude("lat_deg", lat_deg)
    lon = validate.longitude("lon_deg", lon_deg)
    az = validate.finite_array("bearing_deg", bearing_deg)
    dist = validate.finite_array("distance_m", distance_m)
    if np.any(dist < 0):
        raise InputError("distance_m must be >= 0 (use bearing + 180 to go backwards)")
    lat, lon, az, dist = np.broadcast_arrays(lat, lon, az, dist)
    lon2, lat2, _ = WGS84.fwd(lon, lat, az, dist)
    lon2 = (np.asarray(lon2) + 180.0) % 360.0 - 180.0
    return np.asarray(lat2), lon2


def inverse(lat1_deg, lon1_deg, lat2_deg, lon2_deg) -> tuple[np.ndarray, np.ndarray]:
    """Initial bearing (deg clockwise from north, in [0, 360)) and geodesic distance (m).

    Example:
        >>> bearing, dist = inverse(47.0, 8.0, *destination(47.0, 8.0, 225.0, 1500.0))
        >>> print(f"{float(bearing):.6f} {float(dist):.6f}")
        225.000000 1500.000000
    """
    lat1 = validate.latitude("lat1_deg", lat1_deg)
    lon1 = validate.longitude("lon1_deg", lon1_deg)
    lat2 = validate.latitude("lat2_deg", lat2_deg)
    lon2 = validate.longitude("lon2_deg", lon2_deg)
    lat1, lon1, lat2, lon2 = np.broadcast_arrays(lat1, lon1, lat2, lon2)
    az, _, dist = WGS84.inv(lon1, lat1, lon2, lat2)
    return np.asarray(az) % 360.0, np.asarray(dist)


class VerticalDatum(str, enum.Enum):
    """The surface a height is measured from.

    Example:
        >>> VerticalDatum("egm96") is VerticalDatum.EGM96, round(VerticalDatum.EGM96.undulation_m(0.0, 0.0), 2)
        (True, 17.16)
    """

    WGS84 = "wgs84"  #: the WGS84 ellipsoid: GNSS heights, skyfix's frames and fusion (``alt_m``)
    EGM96 = "egm96"  #: the EGM96 geoid: "AMSL" of MAVLink (ArduPilot, PX4) and most receivers
    EGM2008 = "egm2008"  #: the EGM2008 geoid: some receivers and DEMs

    def undulation_m(self, lat_deg: float, lon_deg: float) -> float:
        """Height of this surface above the WGS84 ellipsoid at (lat_deg, lon_deg), metres
        (0 for the ellipsoid; a geoid's N from PROJ's grid, ~100 m cells, < 1 cm off)."""
        return 0.0 if self is VerticalDatum.WGS84 else undulation_near_m(lat_deg, lon_deg, self.value)


@dataclass(frozen=True)
class Height:
    """``value_m`` metres above the surface ``datum`` names (a :class:`VerticalDatum` or its value).

    Example:
        >>> amsl = Height(500.0, "egm96")  # MAVLink's alt near Zurich
        >>> h = amsl.to(VerticalDatum.WGS84, 47.0, 8.0)  # the geoid is ~48.4 m above the ellipsoid there
        >>> round(h.value_m, 2), h.datum.value, h.to("egm96", 47.0, 8.0) == amsl
        (548.39, 'wgs84', True)
    """

    value_m: float
    datum: VerticalDatum

    def __post_init__(self) -> None:
        object.__setattr__(self, "value_m", validate.finite_scalar("Height.value_m", self.value_m))
        try:
            object.__setattr__(self, "datum", VerticalDatum(self.datum))
        except ValueError:
            raise InputError(f"Height.datum must be one of {[d.value for d in VerticalDatum]}, "
                             f"got {self.datum!r}") from None

    def to(self, datum: VerticalDatum | str, lat_deg: float, lon_deg: float) -> Height:
        """The same point's height above ``datum``, at (lat_deg, lon_deg) WGS84 degrees."""
        target = Height(0.0, datum).datum
        if target is self.datum:
            return self
        ellipsoidal_m = self.value_m + self.datum.undulation_m(lat_deg, lon_deg)
        return Height(ellipsoidal_m - target.undulation_m(lat_deg, lon_deg), target)
