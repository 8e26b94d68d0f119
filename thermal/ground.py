"""The ground a ray is cast onto: a flat surface of known height, or a DEM.

Every height here is metres above the WGS84 ellipsoid. The constructors make the
datum explicit so AMSL and AGL numbers cannot be passed where an ellipsoidal height is
expected by accident: ``FlatGround.from_amsl(h, geoid_undulation_m=N)`` (h_ell = h + N),
``FlatGround.from_agl(pose, agl_m)`` (the ground is ``agl_m`` below the camera).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyproj

from skyfix import validate
from skyfix.camera import Camera, CameraPose, ground_intersection
from skyfix.errors import DataError, InputError
from skyfix.geo import LocalFrame
from skyfix.thermal.demcast import LocalDem


@dataclass(frozen=True)
class FlatGround:
    """Ground at one ellipsoidal height ``alt_m`` (metres above WGS84), optional 1-sigma.

    Example:
        >>> FlatGround.from_amsl(219.0, geoid_undulation_m=-34.0).alt_m  # h = H + N
        185.0
        >>> FlatGround.from_agl(CameraPose(47.0, 8.0, 500.0), 100.0, sigma_m=2.0)
        FlatGround(alt_m=400.0, sigma_m=2.0)
    """

    alt_m: float
    sigma_m: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "alt_m", validate.finite_scalar("FlatGround.alt_m", self.alt_m))
        object.__setattr__(self, "sigma_m", validate.nonnegative_scalar("FlatGround.sigma_m", self.sigma_m))

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

    def sigma_at(self, lat_deg, lon_deg) -> np.ndarray:
        """1-sigma height error (m) at the given points: ``sigma_m`` everywhere."""
        return np.full(np.broadcast(np.asarray(lat_deg), np.asarray(lon_deg)).shape, self.sigma_m)


@dataclass(frozen=True, eq=False)
class DemGround:
    """A gridded elevation model: ``heights_m`` ``(H, W)`` ellipsoidal heights on a
    north-up grid in ``crs``, ``transform`` the GDAL affine (x0, dx, 0, y0, 0, dy) of the
    pixel *corners*. NaN cells are no-data: filled by linear interpolation when
    ``fill_holes`` (``hole_fraction`` says how much; :meth:`sigma_at` grows inside them),
    else refused when a ray meets them. ``sigma_m`` is the DEM's 1-sigma height error.
    """

    heights_m: np.ndarray
    transform: tuple[float, float, float, float, float, float]
    crs: str = "EPSG:4326"
    sigma_m: float = 1.0
    fill_holes: bool = True
    _to_grid: pyproj.Transformer = field(init=False, repr=False)
    hole_fraction: float = field(init=False, default=0.0)
    _median_m: float = field(init=False, repr=False, default=0.0)
    _fill_dist_m: np.ndarray | None = field(init=False, repr=False, default=None)
    _local: list = field(init=False, repr=False, default_factory=list)

    def __post_init__(self) -> None:
        h = np.asarray(self.heights_m, dtype=np.float64)
        if h.ndim != 2 or min(h.shape) < 2:
            raise InputError(f"DemGround.heights_m must be (H, W) with H, W >= 2, got {h.shape}")
        if not np.isfinite(h).any():
            raise InputError("DemGround.heights_m has no finite height")
        h = h.copy()
        holes = ~np.isfinite(h)
        if self.fill_holes and holes.any():
            h = _fill(h, holes)
        h.setflags(write=False)
        object.__setattr__(self, "heights_m", h)
        object.__setattr__(self, "hole_fraction", float(holes.mean()))
        object.__setattr__(self, "_median_m", float(np.nanmedian(h)))
        t = tuple(float(x) for x in validate.finite_array("DemGround.transform", self.transform).reshape(-1))
        if len(t) != 6 or t[2] != 0.0 or t[4] != 0.0 or t[1] == 0.0 or t[5] == 0.0:
            raise InputError(f"DemGround.transform must be a north-up GDAL affine (x0, dx, 0, y0, 0, dy), got {t}")
        object.__setattr__(self, "transform", t)
        object.__setattr__(self, "sigma_m", validate.finite_scalar("DemGround.sigma_m", self.sigma_m))
        object.__setattr__(self, "_to_grid", pyproj.Transformer.from_crs("EPSG:4326", self.crs, always_xy=True))
        if self.fill_holes and holes.any():
            from scipy.ndimage import distance_transform_edt

            cell_m = abs(t[1])
            if pyproj.CRS(self.crs).is_geographic:  # degrees: metres at the grid's middle latitude
                lat_mid = t[3] + t[5] * h.shape[0] / 2.0
                cell_m *= 111_320.0 * math.cos(math.radians(lat_mid))
            object.__setattr__(self, "_fill_dist_m", distance_transform_edt(holes) * cell_m)

    @classmethod
    def from_geotiff(cls, path: str | Path, *, datum: str, geoid_undulation_m: float | None = None,
                     sigma_m: float = 1.0, fill_holes: bool = True) -> DemGround:
        """Load band 1 of a GeoTIFF DEM in any CRS (projected or geographic). ``datum``:
        "ellipsoid" (heights above WGS84) or "amsl" (above the geoid: the EGM96 undulation
        N of every cell is added from :mod:`skyfix.geoid`, or the constant
        ``geoid_undulation_m`` when given). No-data cells are filled from their
        neighbours (``fill_holes``) or left NaN (rays meeting them are refused)."""
        import rasterio

        if datum not in ("ellipsoid", "amsl"):
            raise InputError(f"datum must be 'ellipsoid' or 'amsl', got {datum!r}")
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
        transform = (a.c, a.a, a.b, a.f, a.d, a.e)
        if datum == "amsl":
            if geoid_undulation_m is not None:
                heights = heights + validate.finite_scalar("geoid_undulation_m", geoid_undulation_m)
            else:
                heights = heights + _cell_undulations_m(heights.shape, transform, crs)
        return cls(heights, transform, crs, sigma_m, fill_holes)

    def local(self) -> LocalDem:
        """The DEM resampled into the ENU frame of its centre, for fast ray casting
        (built on first use, ~0.3 s per million cells)."""
        if not self._local:
            self._local.append(LocalDem(self.heights_m, self.transform, self.crs))
        return self._local[0]

    def check_covers(self, lat_deg, lon_deg, what: str = "the flight") -> None:
        """Raise :class:`DataError` unless every point (WGS84) lies on the DEM's data."""
        h = self.height_at(lat_deg, lon_deg)
        if not np.all(np.isfinite(h)):
            lat = np.asarray(lat_deg, float).ravel()
            lon = np.asarray(lon_deg, float).ravel()
            k = int(np.flatnonzero(~np.isfinite(h.ravel()))[0])
            raise DataError(f"the DEM does not cover {what}: no height at lat {lat[k]:.6f}, lon {lon[k]:.6f} "
                            f"({int(np.sum(~np.isfinite(h)))} of {h.size} points off the DEM or in no-data)")

    @property
    def alt_m(self) -> float:
        """Median ellipsoidal height of the DEM, metres (a starting guess for ray casting)."""
        return self._median_m

    def sigma_at(self, lat_deg, lon_deg) -> np.ndarray:
        """1-sigma height error (m) at the given points: ``sigma_m``, growing by
        :data:`FILL_SIGMA_PER_M` per metre into a filled no-data hole (interpolated
        across it, a slope's curvature is unknown)."""
        lat = validate.latitude("lat_deg", lat_deg)
        lon = validate.longitude("lon_deg", lon_deg)
        base = np.full(np.broadcast(lat, lon).shape, self.sigma_m)
        if self._fill_dist_m is None:
            return base
        x, y = self._to_grid.transform(lon, lat)
        x0, dx, _, y0, _, dy = self.transform
        h, w = self.heights_m.shape
        col = np.clip(((np.asarray(x) - x0) / dx).astype(int), 0, w - 1)
        row = np.clip(((np.asarray(y) - y0) / dy).astype(int), 0, h - 1)
        return base + FILL_SIGMA_PER_M * self._fill_dist_m[row, col]

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

#: Growth of a filled DEM cell's height sigma with its distance to real data, m per m
#: (a 30 m hole in a 30-degree slope: linear interpolation misses its curvature by ~1 m).
FILL_SIGMA_PER_M = 0.05


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
              frame: LocalFrame) -> tuple[np.ndarray, np.ndarray]:
    """Ground points ``(N, 3)`` ENU in ``frame`` and their ellipsoidal heights ``(N,)``.

    Flat ground: one exact ray/ellipsoid-height intersection (the foundation's
    :func:`ground_intersection`). DEM: first hit on the DEM, all rays at once
    (:class:`~skyfix.thermal.demcast.LocalDem`, to a centimetre); raises
    :class:`GeometryError` when a ray points above the horizon, leaves the DEM or meets
    a no-data hole that was not filled.
    """
    if isinstance(ground, FlatGround):
        pts = ground_intersection(camera, pose, uv, ground.alt_m, frame)
        return pts, np.full(pts.shape[0], ground.alt_m)
    pts = ground_points(camera, pose, uv, ground, frame)
    return pts, np.asarray(frame.to_geodetic(pts[:, 0], pts[:, 1], pts[:, 2])[2], float)


def ground_points(camera: Camera, pose: CameraPose, uv: np.ndarray, ground: FlatGround | DemGround,
                  frame: LocalFrame) -> np.ndarray:
    """The points of :func:`intersect` without their heights (``(N, 3)`` ENU in ``frame``)."""
    if isinstance(ground, FlatGround):
        return ground_intersection(camera, pose, uv, ground.alt_m, frame)
    cam, r_frame_from_cam = pose.in_frame(frame)
    return dem_hits(ground, frame, cam, camera.pixel_to_ray(validate.points("uv", uv, 2)) @ r_frame_from_cam.T)


def dem_hits(dem: DemGround, frame: LocalFrame, cam_m: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """First hits ``(N, 3)`` on ``dem`` of unit ``rays`` ``(N, 3)`` from ``cam_m`` ``(3,)``,
    all ENU in ``frame``. The rays are cast in the DEM's own frame; frame to frame is a
    rigid motion (:func:`frame_motion`), which keeps the distance along each ray."""
    local = dem.local()
    r, t = frame_motion(frame, local.frame)
    dist_m = local.cast(r @ cam_m + t, rays @ r.T)
    return cam_m + dist_m[:, None] * rays


@functools.lru_cache(maxsize=64)
def frame_motion(src: LocalFrame, dst: LocalFrame) -> tuple[np.ndarray, np.ndarray]:
    """``(R, t)`` with ``p_dst = R @ p_src + t`` for ENU points (m) of ``src`` in ``dst``.

    Exact: both frames are rotations and translations of ECEF (pyproj's topocentric), so
    one frame's points are a rigid motion of the other's: R turns ``src``'s axes into
    ``dst``'s, t is ``src``'s origin in ``dst``. Read-only arrays.
    """
    t = np.array([float(x) for x in dst.to_enu(src.lat0_deg, src.lon0_deg, src.alt0_m)])
    r = dst.enu_rotation_at(src.lat0_deg, src.lon0_deg)
    for a in (r, t):
        a.setflags(write=False)
    return r, t


def _fill(heights_m: np.ndarray, holes: np.ndarray) -> np.ndarray:
    """No-data cells filled by linear interpolation (Delaunay, scipy) from the valid cells
    around them; cells outside their hull (a hole on the edge) take the nearest value."""
    from scipy.interpolate import griddata
    from scipy.ndimage import binary_dilation

    ring = binary_dilation(holes, iterations=2) & ~holes
    src = np.argwhere(ring)
    dst = np.argwhere(holes)
    out = heights_m.copy()
    if src.shape[0] == 0:
        raise InputError("DemGround.heights_m: no-data everywhere around the holes")
    vals = griddata(src, heights_m[ring], dst, method="linear")
    near = griddata(src, heights_m[ring], dst, method="nearest")
    out[holes] = np.where(np.isfinite(vals), vals, near)
    return out


def _cell_undulations_m(shape: tuple[int, int], transform: tuple, crs: str) -> np.ndarray:
    """EGM96 undulation (m) at every cell centre of a grid; the geoid varies over tens of
    kilometres, so it is evaluated on a coarse lattice and interpolated."""
    from skyfix.geoid import geoid_undulation_m

    x0, dx, _, y0, _, dy = transform
    h, w = shape
    rows = np.linspace(0, h - 1, min(h, 17))
    cols = np.linspace(0, w - 1, min(w, 17))
    cc, rr = np.meshgrid(cols, rows)
    lon, lat = pyproj.Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(
        x0 + (cc + 0.5) * dx, y0 + (rr + 0.5) * dy)
    coarse = geoid_undulation_m(lat, lon)
    from scipy.interpolate import RegularGridInterpolator

    interp = RegularGridInterpolator((rows, cols), coarse)
    r_all, c_all = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    return interp(np.stack((r_all.ravel(), c_all.ravel()), axis=1)).reshape(h, w)
