"""Fast, first-hit ray casting onto a DEM, vectorised over a frame's rays.

A DEM is given in its own CRS (UTM, a national grid, geographic degrees) with heights
above the ellipsoid; a ray lives in a local ENU frame. Converting every ray sample
through pyproj costs milliseconds per hotspot, so the DEM is resampled once into the
ENU frame of its own centre (:class:`LocalDem`: the surface's exact ``up`` coordinate on
a regular east/north grid at the DEM's resolution, curvature of the earth included).
A ray is then marched in steps of half a cell from where it passes the highest summit
until it is below the surface (so a ridge in front is never skipped), and the crossing
is refined by regula falsi to a centimetre. Only the hit points go back through pyproj.
"""

from __future__ import annotations

import cv2
import numpy as np
import pyproj

from skyfix.errors import GeometryError
from skyfix.geo import LocalFrame

#: Refinement stops when the ray is this close to the surface, metres (DEMs are good to decimetres at best).
HIT_TOL_M = 0.01
_BLOCK = 16


class LocalDem:
    """The surface ``up_m`` ``(H, W)`` (NaN: no data) on an east/north grid of ``step_m``
    centred on ``frame``'s origin; ``max_up_m``/``min_up_m`` its highest and lowest points."""

    def __init__(self, heights_m: np.ndarray, transform: tuple, crs: str) -> None:
        x0, dx, _, y0, _, dy = transform
        h, w = heights_m.shape
        to_geo = pyproj.Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
        lon_c, lat_c = to_geo.transform(x0 + dx * w / 2.0, y0 + dy * h / 2.0)
        corners_x = x0 + dx * np.array([0, w, 0, w])
        corners_y = y0 + dy * np.array([0, 0, h, h])
        lon, lat = to_geo.transform(corners_x, corners_y)
        h_mid = float(np.nanmedian(heights_m))
        self.frame = LocalFrame(float(lat_c), float(lon_c), h_mid)
        e, n, _ = self.frame.to_enu(lat, lon, np.full(4, h_mid))
        # The resampled grid's cell: the DEM's, measured on the ground at its centre.
        lon_1, lat_1 = to_geo.transform(x0 + dx * (w / 2 + 1), y0 + dy * (h / 2 + 1))
        ce, cn, _ = self.frame.to_enu(lat_1, lon_1, h_mid)
        self.step_m = float(min(abs(ce), abs(cn)))
        half = float(min(np.max(np.abs(e)), np.max(np.abs(n))))
        n_cells = int(half / self.step_m)
        axis = np.arange(-n_cells, n_cells + 1) * self.step_m
        ee, nn = np.meshgrid(axis, axis[::-1])
        up = self._resample(ee, nn, heights_m, transform, crs, h_mid)
        self.up_m = up.astype(np.float32)
        self.half_m = n_cells * self.step_m
        self.max_up_m = float(np.nanmax(up))
        self.min_up_m = float(np.nanmin(up))
        # Highest point of each block of _BLOCK x _BLOCK cells (and its border), so a ray
        # can skip the air above the terrain in block-sized steps.
        grown = cv2.dilate(np.where(np.isfinite(up), up, self.max_up_m).astype(np.float32), np.ones((3, 3), np.uint8))
        nb = -(-grown.shape[0] // _BLOCK)
        pad = np.full((nb * _BLOCK, nb * _BLOCK), self.max_up_m, np.float32)
        pad[:grown.shape[0], :grown.shape[1]] = grown
        self.block_max_m = pad.reshape(nb, _BLOCK, nb, _BLOCK).max(axis=(1, 3))
        # The same in a ring of +inf: no ray is ever in free air off the grid.
        self._block_top_m = np.pad(self.block_max_m, 1, constant_values=np.inf)
        self._window = 0.5 * self.step_m * np.arange(4 * _BLOCK + 1)  # a march's samples along a ray, m

    def _resample(self, ee, nn, heights_m, transform, crs, h_mid) -> np.ndarray:
        x0, dx, _, y0, _, dy = transform
        to_crs = pyproj.Transformer.from_crs("EPSG:4326", crs, always_xy=True)
        up = np.zeros(ee.shape)
        for _ in range(2):  # the node's geodetic position depends (slightly) on its height
            lat, lon, h = self.frame.to_geodetic(ee, nn, np.nan_to_num(up))  # NaN: off the DEM
            x, y = to_crs.transform(lon, lat)
            col = ((np.asarray(x) - x0) / dx - 0.5).astype(np.float32)
            row = ((np.asarray(y) - y0) / dy - 0.5).astype(np.float32)
            z = bilinear(heights_m.astype(np.float32), col, row).reshape(ee.shape)
            up = np.nan_to_num(up) + (z - h)
        return up

    def sample(self, east_m: np.ndarray, north_m: np.ndarray) -> np.ndarray:
        """Surface ``up`` (m) at frame (east, north) (any shape); NaN off the grid or in holes."""
        col = ((east_m + self.half_m) / self.step_m).ravel()
        row = ((self.half_m - north_m) / self.step_m).ravel()
        out = bilinear(self.up_m, col.astype(np.float32), row.astype(np.float32))
        out[(np.minimum(col, row) < 0) | (np.maximum(col, row) > self.up_m.shape[0] - 1)] = np.nan
        return out.reshape(np.shape(east_m))

    def cast(self, origin_m: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """First-hit ray parameters ``(N,)`` (m along unit ``dirs`` ``(N, 3)`` from
        ``origin_m`` ``(3,)``, this DEM's frame); raises :class:`GeometryError` naming the
        first ray that points above the horizon, leaves the DEM or meets a hole."""
        d_up = dirs[:, 2]
        if np.any(d_up >= -1e-6):
            raise GeometryError(f"ray {int(np.argmax(d_up >= -1e-6))} points at or above the horizon")
        t_end = (origin_m[2] - self.min_up_m) / -d_up  # below the lowest ground from here on
        t = self._skip_air(origin_m, dirs, np.maximum((origin_m[2] - self.max_up_m) / -d_up, 0.0))
        out = np.full(dirs.shape[0], np.nan)
        todo = np.arange(dirs.shape[0])
        window = self._window
        for _ in range(10_000):
            d = dirs if todo.size == dirs.shape[0] else dirs[todo]
            ts = t[todo, None] + window[None, :]
            # origin + ts * d per axis: the same sums as on (n, k, 3) arrays, without them
            gap = (origin_m[2] + ts * d[:, 2:3]) - self.sample(origin_m[0] + ts * d[:, 0:1], origin_m[1] + ts * d[:, 1:2])
            below = ~(gap > 0)  # NaN (off the grid, a hole) stops the march too
            k = np.argmax(below, axis=1)
            rows = np.arange(todo.size)
            hit = below[rows, k]
            if np.any(hit & ((k == 0) | ~np.isfinite(gap[rows, k]))):
                raise GeometryError("a ray leaves the DEM or meets a no-data hole before the ground")
            if hit.any():
                h = rows[hit]
                out[todo[hit]] = self._refine(origin_m, d[hit], ts[h, k[h] - 1], gap[h, k[h] - 1],
                                              ts[h, k[h]], gap[h, k[h]])
            todo = todo[~hit]
            if todo.size == 0:
                return out
            if np.any(t[todo] + window[-1] > t_end[todo]):
                raise GeometryError("a ray leaves the DEM before it meets the ground")
            t[todo] = self._skip_air(origin_m, dirs[todo], t[todo] + window[-1])
        raise GeometryError("ray marching did not finish")

    def _skip_air(self, o: np.ndarray, d: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Advance each ray in half-block steps while it stays above the highest point of
        the blocks under both ends of the step (it cannot meet the ground there)."""
        block_m = _BLOCK * self.step_m
        nb = self.block_max_m.shape[0]
        span = float(np.max((o[2] - self.min_up_m) / -d[:, 2] - t))
        ts = t[:, None] + 0.5 * block_m * np.arange(max(int(span / (0.5 * block_m)) + 2, 2))[None, :]
        i = np.minimum(np.maximum(np.floor((self.half_m - (o[1] + ts * d[:, 1:2])) / block_m), -1), nb).astype(int) + 1
        j = np.minimum(np.maximum(np.floor(((o[0] + ts * d[:, 0:1]) + self.half_m) / block_m), -1), nb).astype(int) + 1
        clear = (o[2] + ts * d[:, 2:3]) > self._block_top_m[i, j]
        free = np.zeros(clear.shape, bool)  # step k (from sample k to k + 1) is in free air; the last never
        np.logical_and(clear[:, :-1], clear[:, 1:], out=free[:, :-1])
        return ts[np.arange(t.size), np.argmin(free, axis=1)]

    def _refine(self, o, d, ta, fa, tb, fb) -> np.ndarray:
        """Regula falsi between an above (fa > 0) and a below (fb <= 0) point; the kept
        end's value is halved (Illinois) so one-sided convergence cannot stall."""
        tc = tb
        for _ in range(60):
            tc = tb - fb * (tb - ta) / (fb - fa)
            p = o + tc[:, None] * d
            fc = p[:, 2] - self.sample(p[:, 0], p[:, 1])
            if np.all(np.abs(fc) < HIT_TOL_M):
                break
            above = fc > 0
            ta, fa, tb, fb = (np.where(above, tc, ta), np.where(above, fc, 0.5 * fa),
                              np.where(above, tb, tc), np.where(above, 0.5 * fb, fc))
        return tc


def bilinear(grid: np.ndarray, col: np.ndarray, row: np.ndarray) -> np.ndarray:
    """Bilinear samples of float32 ``grid`` at float32 (col, row) ``(M,)``, NaN outside
    (cv2.remap wants maps under 32767 pixels a side: up to that, one row; beyond, the
    points are laid out 1024 to a row)."""
    m = col.size
    if m == 0:
        return np.zeros(0)
    if m < 32767:
        maps = np.ravel(col).reshape(1, m), np.ravel(row).reshape(1, m)
    else:
        rows = -(-m // 1024)
        pad = np.full((2, rows * 1024), -10.0, np.float32)
        pad[0, :m], pad[1, :m] = np.ravel(col), np.ravel(row)
        maps = pad[0].reshape(rows, 1024), pad[1].reshape(rows, 1024)
    out = cv2.remap(grid, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
    return out.ravel()[:m].astype(np.float64)
