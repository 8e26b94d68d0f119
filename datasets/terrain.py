"""A synthetic mountain: the true terrain of a rendered world, and the DEMs users have of it.

The terrain is a height field ``up_m = f(east_m, north_m)`` in the ENU axes of a
:class:`~skyfix.geo.LocalFrame` (origin on the valley floor), tabulated on a fine grid
(1 m by default) and interpolated bilinearly: ridges and peaks of a few hundred metres
(slopes of 20-40 degrees) plus metre-scale roughness (rocks, tree stands). Rays are cast
onto it exactly by sphere tracing and Newton polish, so every rendered pixel's ground
point is known.

A DEM of it (:meth:`Terrain.dem`) is what a user gets from a mapping agency: a north-up
grid in a projected CRS (UTM by default) or geographic degrees, cells of 5-30 m that
average the roughness away, heights above the ellipsoid or above the EGM96 geoid,
optionally with no-data holes; :meth:`Terrain.write_dem` writes it as a GeoTIFF.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pyproj

from skyfix import validate
from skyfix.datasets.thermal_scene import forest_texture
from skyfix.errors import GeometryError, InputError
from skyfix.geo import LocalFrame
from skyfix.thermal.demcast import bilinear
from skyfix.thermal.ground import DemGround

#: Ray-terrain intersections stop when the ray is this close above the surface, metres.
TOL_M = 0.005


def utm_crs(lat_deg: float, lon_deg: float) -> str:
    """The WGS84 UTM zone CRS ("EPSG:326zz"/"EPSG:327zz") containing the point."""
    zone = int((float(lon_deg) + 180.0) // 6.0) % 60 + 1
    return f"EPSG:{32600 + zone if lat_deg >= 0 else 32700 + zone}"


class Terrain:
    """True terrain heights ``up_m`` ``(H, W)`` on a north-up grid of ``metres_per_px``
    centred on the origin of ``frame`` (row 0 at the north edge). Build a random
    mountain with :meth:`mountain`."""

    def __init__(self, frame: LocalFrame, up_m: np.ndarray, metres_per_px: float) -> None:
        if not isinstance(frame, LocalFrame):
            raise InputError(f"frame must be a LocalFrame, got {type(frame).__name__}")
        up = validate.finite_array("up_m", up_m)
        if up.ndim != 2 or min(up.shape) < 4:
            raise InputError(f"up_m must be (H, W) with H, W >= 4, got {up.shape}")
        self.frame = frame
        self.metres_per_px = validate.positive_scalar("metres_per_px", metres_per_px)
        self.up_m = up.astype(np.float32)
        gn, ge = np.gradient(up, self.metres_per_px)
        self._grad = (ge.astype(np.float32), (-gn).astype(np.float32))  # d up / d east, d up / d north
        self.max_slope = float(np.hypot(ge, gn).max())
        self.max_up_m = float(up.max())

    @classmethod
    def mountain(cls, frame: LocalFrame, *, seed: int = 0, size_m: float = 2000.0, metres_per_px: float = 1.0,
                 relief_m: float = 320.0, roughness_m: float = 0.4) -> Terrain:
        """A random ridge with two summits and a side spur crossing the middle of the area,
        ``relief_m`` high, plus ``roughness_m`` (1-sigma) of 2-40 m scale roughness."""
        rng = np.random.default_rng(seed)
        n = int(round(validate.positive_scalar("size_m", size_m) / metres_per_px)) | 1
        half = (n - 1) / 2.0 * metres_per_px
        east = np.linspace(-half, half, n)
        ee, nn = np.meshgrid(east, -east)
        up = np.zeros((n, n))
        heading = rng.uniform(0, math.pi)
        # Ridge line through a point near the middle, two summits along it and a spur.
        along = np.array([math.sin(heading), math.cos(heading)])
        across = np.array([along[1], -along[0]])
        c = rng.uniform(-150, 150, 2) + 350.0 * across
        d_along = (ee - c[0]) * along[0] + (nn - c[1]) * along[1]
        d_across = (ee - c[0]) * across[0] + (nn - c[1]) * across[1]
        up += 0.6 * relief_m * np.exp(-0.5 * (d_across / 330.0) ** 2)
        for s_along, h, w in ((rng.uniform(-500, -200), 0.45, 220.0), (rng.uniform(200, 500), 0.35, 260.0)):
            up += h * relief_m * np.exp(-0.5 * ((d_along - s_along) ** 2 + d_across ** 2) / w ** 2)
        spur = rng.uniform(-300, 300)
        up += 0.2 * relief_m * np.exp(-0.5 * ((d_along - spur) / 90.0) ** 2) / (1.0 + np.exp(d_across / 150.0))
        if roughness_m > 0:
            up += roughness_m * forest_texture(n, metres_per_px, seed + 101).astype(np.float64)
        return cls(frame, up, metres_per_px)

    @property
    def half_size_m(self) -> float:
        """Distance from the centre to the grid's edge cell centres, metres."""
        return (self.up_m.shape[1] - 1) / 2.0 * self.metres_per_px

    def _colrow(self, east_m: np.ndarray, north_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        h, w = self.up_m.shape
        return (east_m / self.metres_per_px + (w - 1) / 2.0, (h - 1) / 2.0 - north_m / self.metres_per_px)

    def _sample(self, grid: np.ndarray, col: np.ndarray, row: np.ndarray) -> np.ndarray:
        """Bilinear samples of ``grid`` at (col, row) float arrays (any shape), NaN outside."""
        return bilinear(grid, col.ravel().astype(np.float32), row.ravel().astype(np.float32)).reshape(col.shape)

    def up_at(self, east_m, north_m) -> np.ndarray:
        """Terrain ``up`` (m, in the frame) at frame (east, north) metres; NaN off the grid."""
        e, n = np.broadcast_arrays(np.asarray(east_m, float), np.asarray(north_m, float))
        return self._sample(self.up_m, *self._colrow(e, n))

    def cast(self, origin_enu_m: np.ndarray, dirs: np.ndarray, *, t_start: np.ndarray | None = None,
             max_iter: int = 300, newton_below_m: float = 1.0) -> np.ndarray:
        """Ray parameters ``t`` ``(M,)`` (metres along unit ``dirs`` ``(M, 3)`` from
        ``origin_enu_m`` ``(3,)``) of the first terrain hit; NaN for rays that leave the grid
        or point up. Sphere tracing (steps that cannot cross the surface given its
        steepest slope) from ``t_start`` (default: where the ray passes the highest
        summit) until the ray is ``newton_below_m`` above the surface, then Newton steps
        on the local tangent plane."""
        o = validate.finite_array("origin_enu_m", origin_enu_m).reshape(3)
        d = validate.points("dirs", dirs, 3)
        h0 = float(self.up_at(o[0], o[1]))
        if not np.isfinite(h0) or o[2] <= h0:
            raise GeometryError(f"ray origin {o.round(2).tolist()} is off the terrain grid or below the ground")
        t = np.full(d.shape[0], np.nan)
        down = d[:, 2] < -1e-6
        t[down] = np.maximum((o[2] - self.max_up_m) / -d[down, 2], 0.0)
        if t_start is not None:
            t = np.where(np.isfinite(t_start) & down, np.maximum(t_start, np.nan_to_num(t)), t)
        rate = -d[:, 2] + 1.02 * self.max_slope * np.hypot(d[:, 0], d[:, 1])
        idx = np.flatnonzero(down)
        # Work on compacted copies of the rays still marching (indexing the full arrays
        # every step costs more than the terrain look-ups).
        t_a, d_a, r_a = t[idx], d[idx], rate[idx]
        for _ in range(max_iter):
            p = o + t_a[:, None] * d_a
            gap = p[:, 2] - self._sample(self.up_m, *self._colrow(p[:, 0], p[:, 1]))
            settled = ~(gap > newton_below_m)
            if settled.any():
                t[idx[settled]] = np.where(np.isfinite(gap[settled]), t_a[settled], np.nan)
                go = ~settled
                idx, t_a, d_a, r_a, gap = idx[go], t_a[go], d_a[go], r_a[go], gap[go]
            if idx.size == 0:
                break
            t_a += gap / r_a
        t[idx] = np.nan  # not converged: grazing ray
        ok = np.flatnonzero(np.isfinite(t))
        for _ in range(6):
            p = o + t[ok, None] * d[ok]
            col, row = self._colrow(p[:, 0], p[:, 1])
            gap = p[:, 2] - self._sample(self.up_m, col, row)
            slope = d[ok, 2] - (self._sample(self._grad[0], col, row) * d[ok, 0]
                                + self._sample(self._grad[1], col, row) * d[ok, 1])
            good = np.isfinite(gap) & (slope < -1e-3)
            t[ok[~good]] = np.nan
            ok, gap, slope = ok[good], gap[good], slope[good]
            t[ok] -= gap / slope
            ok = ok[np.abs(gap) > TOL_M]
        t[ok] = np.nan  # Newton did not settle
        return t

    def cast_image(self, origin_enu_m: np.ndarray, dirs: np.ndarray, *, stride: int = 8) -> np.ndarray:
        """:meth:`cast` for an image of rays ``(H, W, 3)`` -> ``t`` ``(H, W)``: rays on a
        ``stride`` grid are traced from the top; the others start just before the
        nearest hit among their coarse neighbours, so a ridge in front is never skipped."""
        h, w = dirs.shape[:2]
        coarse = self.cast(origin_enu_m, dirs[::stride, ::stride].reshape(-1, 3))
        coarse = coarse.reshape(dirs[::stride, ::stride].shape[:2])
        near = cv2.erode(np.where(np.isfinite(coarse), coarse, np.inf).astype(np.float32),
                         np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE)
        start = np.repeat(np.repeat(near, stride, 0), stride, 1)[:h, :w].astype(np.float64) * 0.995
        start[~np.isfinite(start)] = np.nan
        return self.cast(origin_enu_m, dirs.reshape(-1, 3), t_start=start.ravel()).reshape(h, w)

    def dem(self, *, metres_per_px: float = 10.0, crs: str | None = None, datum: str = "ellipsoid",
            half_size_m: float | None = None, holes: int = 0, seed: int = 0) -> tuple[np.ndarray, tuple, str]:
        """A DEM of this terrain as a user has it: (heights ``(H, W)``, GDAL affine transform,
        CRS). Each cell holds the mean true height over its footprint (the roughness is
        averaged, as a photogrammetric or lidar DEM product does), in metres above the
        ellipsoid (``datum="ellipsoid"``) or the EGM96 geoid (``"amsl"``). ``crs``: a
        projected CRS (default: the UTM zone) or "EPSG:4326" (cell size then in degrees,
        ``metres_per_px`` converted at the origin). ``holes``: no-data (NaN) discs."""
        from skyfix.geoid import geoid_undulation_m

        if datum not in ("ellipsoid", "amsl"):
            raise InputError(f"datum must be 'ellipsoid' or 'amsl', got {datum!r}")
        fr = self.frame
        crs = crs or utm_crs(fr.lat0_deg, fr.lon0_deg)
        half = min(half_size_m or self.half_size_m, self.half_size_m) - metres_per_px
        to_crs = pyproj.Transformer.from_crs("EPSG:4326", crs, always_xy=True)
        x0, y0 = to_crs.transform(fr.lon0_deg, fr.lat0_deg)
        step = validate.positive_scalar("metres_per_px", metres_per_px)
        if pyproj.CRS(crs).is_geographic:
            step_x = step / (111_320.0 * math.cos(math.radians(fr.lat0_deg)))
            step_y = step / 110_574.0
            n_x, n_y = int(2 * half / step), int(2 * half / step)
        else:
            step_x = step_y = step
            n_x = n_y = int(2 * half / step)
        left, top = x0 - n_x / 2 * step_x, y0 + n_y / 2 * step_y
        xs = left + (np.arange(n_x) + 0.5) * step_x
        ys = top - (np.arange(n_y) + 0.5) * step_y
        xx, yy = np.meshgrid(xs, ys)
        lon, lat = to_crs.transform(xx, yy, direction=pyproj.enums.TransformDirection.INVERSE)
        e, n, _ = fr.to_enu(lat, lon, np.full(lat.shape, fr.alt0_m))
        # Cell mean of the true surface: average a 4x4 sub-sample of the cell.
        sub = (np.arange(4) + 0.5) / 4 - 0.5
        up = np.zeros(e.shape)
        for a in sub:
            for b in sub:
                up += self.up_at(e + a * step, n + b * step)
        up /= 16.0
        _, _, h = fr.to_geodetic(e, n, up)  # ellipsoidal height of the surface point
        heights = np.asarray(h, float)
        if datum == "amsl":
            heights = heights - geoid_undulation_m(lat, lon)
        rng = np.random.default_rng(seed)
        for _ in range(int(holes)):
            r, c = rng.integers(0, n_y), rng.integers(0, n_x)
            rad = rng.uniform(2, 6)
            rr, cc = np.mgrid[0:n_y, 0:n_x]
            heights[(rr - r) ** 2 + (cc - c) ** 2 <= rad * rad] = np.nan
        return heights, (left, step_x, 0.0, top, 0.0, -step_y), crs

    def dem_ground(self, *, sigma_m: float = 1.0, **kwargs) -> DemGround:
        """:meth:`dem` (ellipsoidal) as a :class:`DemGround` with 1-sigma ``sigma_m``."""
        heights, transform, crs = self.dem(**kwargs)
        return DemGround(heights, transform, crs, sigma_m)

    def write_dem(self, path: str | Path, *, nodata: float = -9999.0, **kwargs) -> Path:
        """:meth:`dem` written as a float32 GeoTIFF (NaN cells as ``nodata``)."""
        import rasterio
        from rasterio.transform import Affine

        heights, (x0, dx, _, y0, _, dy), crs = self.dem(**kwargs)
        path = Path(path)
        with rasterio.open(path, "w", driver="GTiff", height=heights.shape[0], width=heights.shape[1], count=1,
                           dtype="float32", crs=crs, transform=Affine(dx, 0.0, x0, 0.0, dy, y0),
                           nodata=nodata) as dst:
            dst.write(np.where(np.isfinite(heights), heights, nodata).astype(np.float32), 1)
        return path
