"""Dimensioning: tag size, spacing and the admissible (colours, tiles) range for a site.

Rules (all from the pinhole model, straight-down camera tilted by up to ``tilt_deg``):
- tiles stay decodable at the highest flight: a tile spans >= ``min_tile_px`` pixels at
  ``max_height_m`` seen along the optical axis at the largest tilt (range ``h / cos(tilt)``);
- several tags are always in view at the lowest flight: the ground footprint's short
  side, shrunk by the tilt, holds >= ``tags_across`` spacings;
- tags stay separable: spacing >= ``separation`` x tag size;
- the field needs rows x cols distinct values: c^n >= rows * cols.
More tiles (n) make a tag larger and tiles fewer pixels; more colours (c) make colours
closer together. The Pareto front over (c, n) keeps, for each feasible n, the smallest
c (and drops any pair another beats on both).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from skyfix import validate
from skyfix.camera import Camera
from skyfix.errors import InputError
from skyfix.tags.codec import SUPPORTED_TILES


@dataclass(frozen=True)
class Dimensioning:
    """Chosen sizes (metres), grid, admissible pairs and the Pareto front of (c, n)."""

    tile_m: float
    gap_m: float
    offset_m: float
    spacing_m: float
    rows: int
    cols: int
    admissible: tuple[tuple[int, int], ...]
    pareto: tuple[tuple[int, int], ...]
    chosen: tuple[int, int]
    tile_px_at_max_height: float
    tags_in_view_at_min_height: float


def dimension(area_x_m: float, area_y_m: float, camera: Camera, min_height_m: float,
              max_height_m: float, *, tilt_deg: float = 15.0, min_tile_px: float = 8.0,
              tags_across: float = 2.5, separation: float = 1.4, max_colors: int = 6,
              gap_ratio: float = 0.4, offset_ratio: float = 0.5) -> Dimensioning:
    """Size a tile-tag field for an ``area_x_m`` x ``area_y_m`` site (see module doc)."""
    ax, ay = validate.positive_scalar("area_x_m", area_x_m), validate.positive_scalar("area_y_m", area_y_m)
    h0, h1 = validate.positive_scalar("min_height_m", min_height_m), validate.positive_scalar("max_height_m", max_height_m)
    if h1 < h0:
        raise InputError(f"max_height_m={h1} must be >= min_height_m={h0}")
    tilt = math.radians(validate.finite_scalar("tilt_deg", tilt_deg))
    f = min(camera.fx, camera.fy)
    slant = h1 / math.cos(tilt)
    tile_m = min_tile_px * slant / f
    # Ground footprint short side at the lowest flight, tilted the worst way.
    short_half = math.atan(min(camera.width, camera.height) / 2.0 / f)
    footprint = h0 * (math.tan(short_half - tilt) + math.tan(short_half)) if short_half > tilt else 0.0
    spacing = footprint / tags_across
    admissible, tag_sizes = [], {}
    for n in SUPPORTED_TILES:
        k = int(round(n ** 0.5))
        size = k * tile_m + (k - 1) * gap_ratio * tile_m + offset_ratio * tile_m
        tag_sizes[n] = size
        if spacing < separation * size:
            continue
        cols, rows = math.floor(ax / spacing) + 1, math.floor(ay / spacing) + 1
        c_min = max(2, math.ceil((rows * cols) ** (1.0 / n) - 1e-9))
        while c_min ** n < rows * cols:
            c_min += 1
        admissible += [(c, n) for c in range(c_min, max_colors + 1)]
    if not admissible:
        fits = [n for n in SUPPORTED_TILES if spacing >= separation * tag_sizes[n]]
        n_tags = (math.floor(ax / spacing) + 1) * (math.floor(ay / spacing) + 1)
        raise InputError(f"no (colours, tiles) pair works: tiles of {tile_m:.3f} m (>= {min_tile_px} px at "
                         f"{h1} m) at {spacing:.3f} m spacing ({tags_across} tags across at {h0} m) allow "
                         f"n in {fits} but the area needs {n_tags} distinct tags with <= {max_colors} "
                         "colours; split the area, raise max_colors (CLI: --max-colors) or narrow the height range")
    front = []
    for c, n in sorted(admissible, key=lambda p: (p[1], p[0])):
        if not any(c2 <= c and n2 <= n and (c2, n2) != (c, n) for c2, n2 in admissible):
            front.append((c, n))
    # The smallest tag (fewest tiles -> biggest tiles per tag area) among the front.
    chosen = min(front, key=lambda p: (p[1], p[0]))
    cols, rows = math.floor(ax / spacing) + 1, math.floor(ay / spacing) + 1
    return Dimensioning(tile_m, gap_ratio * tile_m, offset_ratio * tile_m, spacing, rows, cols,
                        tuple(admissible), tuple(front), chosen, min_tile_px,
                        (footprint / spacing) ** 2 if spacing > 0 else 0.0)
