"""Tile-tag codec and geometry.

A tag is a k x k grid of square coloured tiles (n = k^2 tiles, c colours). Its value is
written in base c, most significant digit first, read clockwise (as seen from above,
north up) starting from the lower-right tile and spiralling inwards. The lower-right
tile is displaced diagonally outwards so the reading start is found in any orientation.

Tag frame: x east, y north, metres, origin at the centre of the undisplaced tile grid.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from skyfix import validate
from skyfix.errors import InputError
from skyfix.tags.palette import choose_palette, palette_delta_e, srgb_to_lab

SUPPORTED_TILES = (4, 9, 16)


def spiral_order(k: int) -> np.ndarray:
    """Grid cells ``(k*k, 2)`` as (col, row) with row 0 at the bottom (south), in reading
    order: clockwise from the lower-right cell, spiralling inwards."""
    cells: list[tuple[int, int]] = []
    lo, hi = 0, k - 1
    while lo <= hi:
        if lo == hi:
            cells.append((lo, lo))
            break
        cells += [(c, lo) for c in range(hi, lo, -1)]      # bottom row, right -> left
        cells += [(lo, r) for r in range(lo, hi)]          # left column, bottom -> top
        cells += [(c, hi) for c in range(lo, hi)]          # top row, left -> right
        cells += [(hi, r) for r in range(hi, lo, -1)]      # right column, top -> bottom
        lo, hi = lo + 1, hi - 1
    return np.array(cells, dtype=int)


@dataclass(frozen=True)
class TileCodec:
    """Value <-> tile colours for tags of ``tiles`` tiles in ``colors`` colours.

    ``palette_rgb`` ``(colors, 3)`` sRGB in [0, 1]; by default chosen far apart in CIELAB
    (:func:`~skyfix.tags.palette.choose_palette`).
    """

    colors: int = 6
    tiles: int = 4
    palette_rgb: np.ndarray | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "colors", validate.integer_in("colors", self.colors, 2, 12))
        if self.tiles not in SUPPORTED_TILES:
            raise InputError(f"tiles must be one of {SUPPORTED_TILES} (a k x k grid), got {self.tiles!r}")
        object.__setattr__(self, "tiles", int(self.tiles))
        pal = choose_palette(self.colors) if self.palette_rgb is None else validate.finite_array(
            "palette_rgb", self.palette_rgb).copy()
        if pal.shape != (self.colors, 3) or pal.min() < 0 or pal.max() > 1:
            raise InputError(f"palette_rgb must be ({self.colors}, 3) sRGB in [0, 1], got shape {pal.shape}")
        pal.setflags(write=False)
        object.__setattr__(self, "palette_rgb", pal)
        lab = srgb_to_lab(pal)
        lab.setflags(write=False)
        object.__setattr__(self, "_palette_lab", lab)

    @property
    def palette_lab(self) -> np.ndarray:
        """The palette in CIELAB ``(colors, 3)``."""
        return self._palette_lab

    @property
    def capacity(self) -> int:
        """Number of distinct values, ``colors ** tiles``."""
        return self.colors ** self.tiles

    @property
    def k(self) -> int:
        """Tiles per side."""
        return int(round(self.tiles ** 0.5))

    def encode(self, values) -> np.ndarray:
        """Values ``(N,)`` (or a scalar) -> colour indices ``(N, tiles)`` in reading order."""
        v = np.atleast_1d(np.asarray(values))
        if not np.issubdtype(v.dtype, np.integer) or v.ndim != 1:
            raise InputError(f"values must be integers (N,), got dtype {v.dtype} shape {v.shape}")
        if np.any((v < 0) | (v >= self.capacity)):
            raise InputError(f"values must be in [0, {self.capacity - 1}] for c={self.colors}, n={self.tiles}")
        powers = self.colors ** np.arange(self.tiles - 1, -1, -1, dtype=np.int64)
        return (v.astype(np.int64)[:, None] // powers[None, :]) % self.colors

    def decode(self, digits) -> np.ndarray:
        """Colour indices ``(N, tiles)`` in reading order -> values ``(N,)``."""
        d = np.asarray(digits)
        if d.ndim == 1:
            d = d[None, :]
        if d.ndim != 2 or d.shape[1] != self.tiles or not np.issubdtype(d.dtype, np.integer):
            raise InputError(f"digits must be integers of shape (N, {self.tiles}), got {d.dtype} {d.shape}")
        if np.any((d < 0) | (d >= self.colors)):
            raise InputError(f"digits must be in [0, {self.colors - 1}]")
        powers = self.colors ** np.arange(self.tiles - 1, -1, -1, dtype=np.int64)
        return d.astype(np.int64) @ powers

    def colours_rgb(self, values) -> np.ndarray:
        """Values ``(N,)`` -> tile colours ``(N, tiles, 3)`` sRGB in reading order."""
        return self.palette_rgb[self.encode(values)]

    def tag_distance(self, values_a, values_b) -> np.ndarray:
        """Colour distance between tags (broadcast ``(N,)`` x ``(N,)``): the Euclidean norm of
        per-tile CIE76 differences, i.e. a tag seen as an n-vector in colour space."""
        de = palette_delta_e(self.palette_rgb)
        da, db = self.encode(values_a), self.encode(values_b)
        return np.sqrt((de[da, db] ** 2).sum(axis=-1))


@dataclass(frozen=True)
class TagGeometry:
    """Tile sizes of a tag, metres: ``tile_m`` side, ``gap_m`` between tiles, ``offset_m``
    diagonal displacement (along east and along south) of the lower-right tile."""

    tiles: int = 4
    tile_m: float = 0.05
    gap_m: float = 0.01
    offset_m: float = 0.025

    def __post_init__(self) -> None:
        if self.tiles not in SUPPORTED_TILES:
            raise InputError(f"tiles must be one of {SUPPORTED_TILES}, got {self.tiles!r}")
        object.__setattr__(self, "tile_m", validate.positive_scalar("tile_m", self.tile_m))
        for name in ("gap_m", "offset_m"):
            object.__setattr__(self, name, validate.nonnegative_scalar(name, getattr(self, name)))
        if self.offset_m < 0.2 * self.tile_m:
            raise InputError(f"offset_m={self.offset_m} is too small to mark orientation; use >= 0.2 * tile_m")

    @property
    def k(self) -> int:
        return int(round(self.tiles ** 0.5))

    @property
    def pitch_m(self) -> float:
        """Centre-to-centre distance of adjacent tiles, metres."""
        return self.tile_m + self.gap_m

    @property
    def size_m(self) -> float:
        """Outer side of the tag including the displacement, metres."""
        return self.k * self.tile_m + (self.k - 1) * self.gap_m + self.offset_m

    def tile_centres_m(self) -> np.ndarray:
        """Tile centres ``(tiles, 2)`` (x east, y north) in the tag frame, reading order."""
        return _tile_centres(self).copy()


@functools.lru_cache(maxsize=32)
def _tile_centres(geometry: TagGeometry) -> np.ndarray:
    cells = spiral_order(geometry.k).astype(float)
    xy = (cells - (geometry.k - 1) / 2.0) * geometry.pitch_m
    xy[0] += (geometry.offset_m, -geometry.offset_m)
    return xy
