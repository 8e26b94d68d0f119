"""Digital surface model on a UTM grid from georeferenced 3-D points.

Each cell takes the median height of the points that fall in it; isolated spikes are
removed by comparing each cell with the median of its 5x5 neighbourhood; empty cells
inside the points' convex hull are filled by linear interpolation (Delaunay), cells
outside it by the nearest value (``filled``) and left as NaN in ``surface_m``.
Heights are in the datum of the input points (AMSL for the photo pipeline).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np

from skyfix import validate
from skyfix.errors import DataError
from skyfix.mapping.grid import Grid

__all__ = ["Dsm", "auto_dsm_resolution_m", "build_dsm", "cell_median", "cell_medians", "enclosed_holes"]


@dataclass(frozen=True)
class Dsm:
    """``surface_m`` (H, W) float32 heights with NaN outside the points' hull;
    ``filled_m`` the same with every cell filled; ``observed`` (H, W) bool cells with points."""

    grid: Grid
    surface_m: np.ndarray
    filled_m: np.ndarray
    observed: np.ndarray


def auto_dsm_resolution_m(points_utm_m: np.ndarray, min_m: float = 0.5, max_m: float = 20.0) -> float:
    """A cell size giving about one point per 4 cells' area (twice the mean point spacing)."""
    pts = validate.points("points_utm_m", points_utm_m, 3)
    span = np.ptp(pts[:, :2], axis=0)
    area_m2 = max(float(span[0] * span[1]), 1.0)
    return float(np.clip(2.0 * math.sqrt(area_m2 / max(len(pts), 1)), min_m, max_m))


def cell_medians(cells: np.ndarray, heights_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(sorted distinct cell indices, median height of each, number of heights in each), vectorised."""
    if len(cells) == 0:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0, np.int64)
    order = np.lexsort((heights_m, cells))
    cells, heights_m = cells[order], heights_m[order]
    starts = np.flatnonzero(np.r_[True, cells[1:] != cells[:-1]])
    counts = np.diff(np.r_[starts, len(cells)])
    return cells[starts], 0.5 * (heights_m[starts + (counts - 1) // 2] + heights_m[starts + counts // 2]), counts


def cell_median(cells: np.ndarray, heights_m: np.ndarray, n_cells: int) -> np.ndarray:
    """Median height per cell index (``n_cells`` long, NaN where no point falls), vectorised."""
    index, median, _ = cell_medians(cells, heights_m)
    out = np.full(n_cells, np.nan)
    out[index] = median
    return out


def build_dsm(points_utm_m: np.ndarray, grid: Grid, spike_m: float = 5.0) -> Dsm:
    """DSM of ``(N, 3)`` points (easting_m, northing_m, height_m) in ``grid``'s zone.

    ``spike_m``: a cell further than this from its neighbourhood median is dropped before
    filling (sparse SfM points include a few mis-triangulated ones).
    """
    from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator
    from scipy.ndimage import generic_filter

    pts = validate.points("points_utm_m", points_utm_m, 3)
    col, row = grid.to_pixel(pts[:, 0], pts[:, 1])
    col_i, row_i = np.round(col).astype(np.int64), np.round(row).astype(np.int64)
    inside = (col_i >= 0) & (col_i < grid.width) & (row_i >= 0) & (row_i < grid.height)
    if inside.sum() < 3:
        raise DataError(f"only {int(inside.sum())} 3-D point(s) fall inside the DSM grid; at least 3 are needed")
    surface = cell_median(row_i[inside] * grid.width + col_i[inside], pts[inside, 2],
                          grid.height * grid.width).reshape(grid.height, grid.width)
    with warnings.catch_warnings():  # all-NaN neighbourhoods give NaN, as wanted
        warnings.simplefilter("ignore", RuntimeWarning)
        local = generic_filter(surface, np.nanmedian, size=5, mode="constant", cval=np.nan)
    spikes = np.isfinite(surface) & (np.abs(surface - local) > spike_m)
    surface[spikes] = np.nan
    observed = np.isfinite(surface)
    rr, cc = np.nonzero(observed)
    known = np.stack((cc, rr), axis=1).astype(np.float64)
    values = surface[observed]
    all_r, all_c = np.mgrid[0:grid.height, 0:grid.width]
    query = np.stack((all_c.ravel(), all_r.ravel()), axis=1).astype(np.float64)
    try:
        linear = LinearNDInterpolator(known, values)(query).reshape(surface.shape)
    except Exception:  # qhull fails on collinear cells; nearest filling below still works
        linear = np.full(surface.shape, np.nan)
    nearest = NearestNDInterpolator(known, values)(query).reshape(surface.shape)
    hull = np.where(observed, surface, linear)
    filled = np.where(np.isfinite(hull), hull, nearest)
    return Dsm(grid, hull.astype(np.float32), filled.astype(np.float32), observed)


def enclosed_holes(observed: np.ndarray, max_cells: int) -> np.ndarray:
    """(H, W) bool: the unmeasured cells of holes that measured cells enclose on every side
    (4-connected, not touching the grid's edge) and that hold at most ``max_cells`` cells:
    the holes small enough to interpolate honestly; larger or open ones stay empty."""
    import cv2

    holes = (~np.asarray(observed, bool)).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(holes, connectivity=4)
    h, w = holes.shape
    x, y, bw, bh, area = (stats[:, i] for i in range(5))
    inside = (x > 0) & (y > 0) & (x + bw < w) & (y + bh < h)
    keep = inside & (area <= max_cells)
    keep[0] = False  # label 0: the measured cells
    return keep[labels] & holes.astype(bool)

