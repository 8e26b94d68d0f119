"""Thermal display palettes and their inverse (colour -> relative intensity).

A palette maps an 8-bit intensity (0 = coldest shown, 255 = hottest shown) to an RGB
colour. ``white-hot`` and ``black-hot`` are grey ramps; ``ironbow`` and ``arctic``
are colour ramps defined here by control points (close to, not byte-identical with,
any vendor's table). Inversion is nearest-colour lookup through a 64x64x64 table, so
a frame stored in a palette can be turned back into relative intensity; the absolute
temperature scale is lost either way.
"""

from __future__ import annotations

import functools

import numpy as np
from scipy.spatial import cKDTree

from skyfix.errors import InputError

GREY_PALETTES = ("white-hot", "black-hot")
COLOUR_PALETTES = ("ironbow", "arctic")
PALETTES = GREY_PALETTES + COLOUR_PALETTES

# (intensity in [0, 1], (R, G, B)) control points, linearly interpolated.
_CONTROL_POINTS: dict[str, list[tuple[float, tuple[int, int, int]]]] = {
    "ironbow": [(0.0, (0, 0, 16)), (0.18, (40, 0, 110)), (0.38, (150, 10, 140)),
                (0.55, (215, 50, 60)), (0.72, (245, 130, 0)), (0.88, (255, 210, 40)),
                (1.0, (255, 255, 235))],
    "arctic": [(0.0, (5, 10, 60)), (0.25, (20, 60, 160)), (0.45, (30, 150, 220)),
               (0.6, (140, 215, 235)), (0.75, (230, 190, 90)), (0.9, (250, 120, 30)),
               (1.0, (255, 240, 200))],
}

_LUT_BITS = 6


def check_palette(name: str) -> str:
    """Return ``name`` if it is a known palette, else raise :class:`InputError`."""
    if name not in PALETTES:
        raise InputError(f"palette must be one of {PALETTES}, got {name!r}")
    return name


@functools.lru_cache(maxsize=8)
def palette_table(name: str) -> np.ndarray:
    """``(256, 3)`` uint8 RGB colour of each intensity level for palette ``name``."""
    check_palette(name)
    levels = np.arange(256) / 255.0
    if name == "white-hot":
        grey = np.arange(256)
        table = np.stack((grey, grey, grey), axis=1)
    elif name == "black-hot":
        grey = 255 - np.arange(256)
        table = np.stack((grey, grey, grey), axis=1)
    else:
        pts = _CONTROL_POINTS[name]
        x = np.array([p[0] for p in pts])
        rgb = np.array([p[1] for p in pts], dtype=float)
        table = np.stack([np.interp(levels, x, rgb[:, c]) for c in range(3)], axis=1)
    out = np.round(table).astype(np.uint8)
    out.setflags(write=False)
    return out


def apply_palette(intensity_u8: np.ndarray, name: str) -> np.ndarray:
    """8-bit intensity ``(H, W)`` -> ``(H, W, 3)`` uint8 RGB in palette ``name``."""
    arr = np.asarray(intensity_u8)
    if arr.dtype != np.uint8 or arr.ndim != 2:
        raise InputError(f"intensity_u8 must be a (H, W) uint8 array, got {arr.dtype} {arr.shape}")
    return palette_table(name)[arr]


@functools.lru_cache(maxsize=8)
def _inverse_table(name: str) -> tuple[np.ndarray, np.ndarray]:
    """(level, colour distance) for every 6-bit-per-channel RGB cell, shape (64, 64, 64)."""
    table = palette_table(name).astype(float)
    n = 1 << _LUT_BITS
    step = 256 // n
    centres = np.arange(n) * step + (step - 1) / 2.0
    r, g, b = np.meshgrid(centres, centres, centres, indexing="ij")
    dist, idx = cKDTree(table).query(np.stack((r.ravel(), g.ravel(), b.ravel()), axis=1))
    return idx.astype(np.uint8).reshape(n, n, n), dist.astype(np.float32).reshape(n, n, n)


def palette_to_intensity(rgb: np.ndarray, name: str, *, max_mismatch_fraction: float = 0.05
                         ) -> np.ndarray:
    """``(H, W, 3)`` uint8 RGB image in palette ``name`` -> ``(H, W)`` uint8 relative intensity.

    Raises :class:`InputError` when more than ``max_mismatch_fraction`` of the pixels
    are far (> 24 RGB units) from every palette colour: the frame is probably in
    another palette or in BGR order.
    """
    arr = np.asarray(rgb)
    if arr.dtype != np.uint8 or arr.ndim != 3 or arr.shape[2] != 3:
        raise InputError(f"palette frame must be (H, W, 3) uint8 RGB, got {arr.dtype} {arr.shape}")
    check_palette(name)
    shift = 8 - _LUT_BITS
    r, g, b = (arr[..., c] >> shift for c in range(3))
    level_lut, dist_lut = _inverse_table(name)
    far = float(np.mean(dist_lut[r, g, b] > 24.0))
    if far > max_mismatch_fraction:
        raise InputError(f"frame does not look like palette {name!r}: {100 * far:.0f} % of pixels "
                         "match no palette colour (wrong palette, or BGR instead of RGB?)")
    return level_lut[r, g, b]
