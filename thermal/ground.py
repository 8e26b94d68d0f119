"""The ground a ray is cast onto: a flat surface of known height, or a DEM.

Every height here is metres above the WGS84 ellipsoid. The constructors make the
datum explicit so AMSL and AGL numbers cannot be passed where an ellipsoidal height is
expected by accident: ``FlatGround.from_amsl(h, geoid_undulation_m=N)`` (h_ell = h + N),
``FlatGround.from_agl(pose, agl_m)`` (the ground is ``agl_m`` below the camera).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyproj

from skyfix import validate
from skyfix.camera import Camera, CameraPose, ground_intersection
from skyfix.errors import DataError, GeometryError, InputError
from skyfix.geo import LocalFrame


@dataclass(frozen=True)
class FlatGround:
    """Ground at one ellipsoidal height ``alt_m`` (metres above WGS84), optional 1-sigma."""

    alt_m: float
    sigma_m: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "alt_m", validate.finite_scalar("FlatGround.alt_m", self.alt_m))
        sigma = validate.finite_scalar("FlatGround.sigma_m", self.sigma_m)
        if sigma < 0:
            raise InputError(f"FlatGround.sigma_m must be >= 0, got {sigma}")
        object.__setattr__(self, "sigma_m", sigma)

    @classmethod
    def from_amsl(cls, alt_amsl_m: float, *, geoid_undulation_m: float, sigma_m: float = 0.0) -> FlatGround:
        """Ground given above mean sea level; ``geoid_undulation_m`` is N at the site
        (EGM96/EGM2008 geoid height above the ellipsoid, e.g. -33 m near Montreal)."""
        return cls(validate.finite_scalar("alt_amsl_m", alt_amsl_m)
                   + validate.finite_scalar("geoid_undulation_m", geoid_undulation_m), sigma_m)

    @classmethod
    def from_agl(cls, pose: CameraPose, agl_m: float, *, sigma_m: float = 0.0) -> FlatGround:
        """Ground ``agl_m`` metres below the camera (e.g. a rangefinder or a known
        height above the take-off point on flat land)."""
        agl = validate.positive_scalar("agl_m", agl_m)
        return cls(pose.alt_m - agl, sigma_m)

    def height_at(self, lat_deg: np.ndarray, lon_deg: np.ndarray) -> np.ndarray:
        """Ground ellipsoidal height (m) at the given points (broadcast shape)."""
        return np.full(np.broadcast(np.asarray(lat_deg), np.asarray(lon_deg)).shape, self.alt_m)


@dataclass(frozen=True, eq=False)
class DemGround:
    """A gridded elevation model: ``heights_m`` ``(H, W)`` ellipsoidal heights on a
    north-up grid in ``crs``, ``transform`` the GDAL affine (x0, dx, 0, y0, 0, dy) of the
    pixel *corners*. NaN cells are no-data. ``sigma_m`` is the DEM's 1-sigma height error.
    """

    heights_m: np.ndarray
    transform: tuple[float, float, float, float, float, float]
    crs: str = "EPSG:4326"
    sigma_m: float = 1.0
    _to_grid: pyproj.Transformer = field(init=False, repr=False)

    def __post_init__(self) -> None:
        h = np.asarray(self.heights_m, dtype=np.float64)
        if h.ndim != 2 or min(h.shape) < 2:
            raise InputError(f"DemGround.heights_m must be (H, W) with H, W >= 2, got {h.shape}")
        if not np.isfinite(h).any():
            raise InputError("DemGround.heights_m has no finite height")
        h = h.copy()
        h.setflags(write=False)
        object.__setattr__(self, "heights_m", h)
        t = tuple(float(x) for x in validate.finite_array("DemGround.transform", self.transform).reshape(-1))
        if len(t) != 6 or t[2] != 0.0 or t[4] != 0.0 or t[1] == 0.0 or t[5] == 0.0:
            raise InputError(f"DemGround.transform must be a north-up GDAL affine (x0, dx, 0, y0, 0, dy), got {t}")
        object.__setattr__(self, "transform", t)
        object.__setattr__(self, "sigma_m", validate.finite_scalar("DemGround.sigma_m", self.sigma_m))
        object.__setattr__(self, "_to_grid", pyproj.Transformer.from_crs("EPSG:4326", self.crs, always_xy=True))

    @classmethod
    def from_geotiff(cls, path: str | Path, *, datum: str, geoid_undulation_m: float | None = None,
                     sigma_m: float = 1.0) -> DemGround:
        """Load band 1 of a GeoTIFF DEM. ``datum`` is "ellipsoid" (heights above WGS84) or
        "amsl" (orthometric; then ``geoid_undulation_m`` N is added: h = H + N)."""
        import rasterio

        if datum not in ("ellipsoid", "amsl"):
            raise InputError(f"datum must be 'ellipsoid' or 'amsl', got {datum!r}")
        if datum == "amsl" and geoid_undulation_m is None:
            raise InputError("an AMSL DEM needs geoid_undulation_m (geoid height above the ellipsoid at the site)")
        try:
            with rasterio.open(path) as src:
                heights = src.read(1).astype(np.float64)
                if src.nodata is not None:
                    heights[heights == src.nodata] = np.nan
                a = src.transform
                crs = src.crs.to_string() if src.crs else None
        except rasterio.errors.RasterioIOError as exc:
            raise DataError(f"cannot read DEM {path}: {exc}") from None
        if crs is None:
            raise DataError(f"DEM {path} has no CRS")
        if datum == "amsl":
            heights = heights + validate.finite_scalar("geoid_undulation_m", geoid_undulation_m)
        return cls(heights, (a.c, a.a, a.b, a.f, a.d, a.e), crs, sigma_m)

    @property
    def alt_m(self) -> float:
        """Median ellipsoidal height of the DEM, metres (a starting guess for ray casting)."""
        return float(np.nanmedian(self.heights_m))

    def height_at(self, lat_deg, lon_deg) -> np.ndarray:
        """Bilinear ellipsoidal height (m) at the given points; NaN outside the grid."""
        lat = validate.latitude("lat_deg", lat_deg)
        lon = validate.longitude("lon_deg", lon_deg)
        x, y = self._to_grid.transform(lon, lat)
        x0, dx, _, y0, _, dy = self.transform
        col = (np.asarray(x) - x0) / dx - 0.5
        row = (np.asarray(y) - y0) / dy - 0.5
        h, w = self.heights_m.shape
        inside = (col >= 0) & (col <= w - 1) & (row >= 0) & (row <= h - 1)
        c0 = np.clip(np.floor(col), 0, w - 2).astype(int)
        r0 = np.clip(np.floor(row), 0, h - 2).astype(int)
        fc, fr = np.clip(col - c0, 0, 1), np.clip(row - r0, 0, 1)
        z = self.heights_m
        val = ((1 - fr) * ((1 - fc) * z[r0, c0] + fc * z[r0, c0 + 1])
               + fr * ((1 - fc) * z[r0 + 1, c0] + fc * z[r0 + 1, c0 + 1]))
        return np.where(inside, val, np.nan)


Ground = FlatGround | DemGround


def as_ground(ground: float | FlatGround | DemGround) -> FlatGround | DemGround:
    """A number is taken as the ground's ellipsoidal height in metres (FlatGround)."""
    if isinstance(ground, (FlatGround, DemGround)):
        return ground
    if isinstance(ground, (int, float, np.floating, np.integer)) and not isinstance(ground, bool):
        return FlatGround(float(ground))
    raise InputError(f"ground_alt_m must be an ellipsoidal height in metres, a FlatGround or a "
                     f"DemGround, got {type(ground).__name__}")


def frame_near(lat_deg: float, lon_deg: float, alt_m: float) -> LocalFrame:
    """A cached local ENU frame with its origin rounded to ~1 km / 10 m near the point.

    Creating a :class:`LocalFrame` builds a pyproj pipeline (~0.2 ms); rounding lets
    successive frames of one flight share it. Axes differences between a vehicle and a
    frame origin 1 km away are handled exactly by the foundation (``enu_rotation_at``).
    """
    return _frame_at(round(lat_deg, 2), round(lon_deg, 2), round(alt_m, -1))


@functools.lru_cache(maxsize=64)
def _frame_at(lat_deg: float, lon_deg: float, alt_m: float) -> LocalFrame:
    return LocalFrame(lat_deg, lon_deg, alt_m)


def intersect(camera: Camera, pose: CameraPose, uv: np.ndarray, ground: FlatGround | DemGround,
              frame: LocalFrame, *, tol_m: float = 0.01, max_iter: int = 50) -> tuple[np.ndarray, np.ndarray]:
    """Ground points ``(N, 3)`` ENU in ``frame`` and their ellipsoidal heights ``(N,)``.

    Flat ground: one exact ray/ellipsoid-height intersection (the foundation's
    :func:`ground_intersection`). DEM: per ray, iterate h <- DEM(intersection at h) with
    secant steps until the height changes by less than ``tol_m``; raises
    :class:`GeometryError` when the ray leaves the DEM or does not converge.
    """
    if isinstance(ground, FlatGround):
        pts = ground_intersection(camera, pose, uv, ground.alt_m, frame)
        return pts, np.full(pts.shape[0], ground.alt_m)
    uv = validate.points("uv", uv, 2)
    pts = np.empty((uv.shape[0], 3))
    heights = np.empty(uv.shape[0])
    for i in range(uv.shape[0]):
        pts[i], heights[i] = _dem_ray(camera, pose, uv[i:i + 1], ground, frame, tol_m, max_iter)
    return pts, heights


def _dem_ray(camera: Camera, pose: CameraPose, uv: np.ndarray, dem: DemGround, frame: LocalFrame,
             tol_m: float, max_iter: int) -> tuple[np.ndarray, float]:
    def residual(h: float) -> tuple[float, np.ndarray]:
        p = ground_intersection(camera, pose, uv, h, frame)
        lat, lon, _ = frame.to_geodetic(p[:, 0], p[:, 1], p[:, 2])
        z = float(dem.height_at(lat, lon)[0])
        if not np.isfinite(z):
            raise GeometryError(f"ray through pixel {uv[0].tolist()} leaves the DEM (or hits no-data)")
        return z - h, p[0]

    below = float(dem.height_at(pose.lat, pose.lon)[()])
    h_prev = min(below if np.isfinite(below) else dem.alt_m, pose.alt_m - 1.0)
    f_prev, p = residual(h_prev)
    h = min(h_prev + f_prev, pose.alt_m - 0.5)
    for _ in range(max_iter):
        f, p = residual(h)
        if abs(f) < tol_m:
            return p, h
        slope = (f - f_prev) / (h - h_prev) if h != h_prev else 0.0
        # Secant on g(h) = DEM(P(h)) - h; fall back to a damped fixed-point step.
        step = -f / slope if abs(slope) > 1e-6 else f
        if not np.isfinite(step) or abs(step) > 10 * (abs(f) + 1.0):
            step = 0.5 * f
        h_prev, f_prev = h, f
        h = min(h + step, pose.alt_m - 0.5)
    raise GeometryError(f"ray-terrain intersection for pixel {uv[0].tolist()} did not converge")
