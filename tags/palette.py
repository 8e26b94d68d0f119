"""Tile colours: sRGB <-> CIELAB and a palette chosen far apart in CIELAB.

Colours are sRGB in [0, 1] (what is printed and what a camera records after its
tone curve). Distances are CIE76 Delta-E (Euclidean in CIELAB, D65 white).
"""

from __future__ import annotations

import itertools

import numpy as np

from skyfix import validate
from skyfix.errors import InputError

_M_XYZ_FROM_RGB = np.array([[0.4124564, 0.3575761, 0.1804375],
                            [0.2126729, 0.7151522, 0.0721750],
                            [0.0193339, 0.1191920, 0.9503041]])
_WHITE_XYZ = _M_XYZ_FROM_RGB.sum(axis=1)
#: Largest min-channel of a tile colour: tiles must stay well below white paper in every
#: channel so one "darker than paper in some channel" threshold segments them.
MAX_INK_CHANNEL = 0.25


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """sRGB tone curve removed, elementwise, from values already clipped to [0, 1]."""
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _xyz_to_lab(xyz: np.ndarray) -> np.ndarray:
    """White-normalised XYZ ``(..., 3)`` -> CIELAB ``(..., 3)``."""
    f = np.where(xyz > (6 / 29) ** 3, np.cbrt(xyz), xyz / (3 * (6 / 29) ** 2) + 4 / 29)
    return np.stack((116 * f[..., 1] - 16, 500 * (f[..., 0] - f[..., 1]),
                     200 * (f[..., 1] - f[..., 2])), axis=-1)


def srgb_to_lab(rgb: np.ndarray) -> np.ndarray:
    """sRGB in [0, 1] ``(..., 3)`` -> CIELAB ``(..., 3)`` (L in [0, 100], D65)."""
    lin = _srgb_to_linear(np.clip(np.asarray(rgb, dtype=np.float64), 0.0, 1.0))
    return _xyz_to_lab(lin @ _M_XYZ_FROM_RGB.T / _WHITE_XYZ)


def srgb_grid_to_lab(levels: np.ndarray) -> np.ndarray:
    """CIELAB ``(L, L, L, 3)`` of every sRGB colour whose channels (r, g, b index order)
    take the ``L`` given levels in [0, 1]. The tone curve is applied to the ``L`` levels
    only and XYZ mixed by broadcasting: the same values as :func:`srgb_to_lab` on the
    full grid (to rounding) at a fraction of the cost."""
    lin = _srgb_to_linear(np.clip(np.asarray(levels, dtype=np.float64).ravel(), 0.0, 1.0))
    m = _M_XYZ_FROM_RGB / _WHITE_XYZ[:, None]          # row i: channel weights of X, Y or Z
    xyz = (lin[:, None, None, None] * m[:, 0] + lin[None, :, None, None] * m[:, 1]
           + lin[None, None, :, None] * m[:, 2])
    return _xyz_to_lab(xyz)


def delta_e(lab_a: np.ndarray, lab_b: np.ndarray) -> np.ndarray:
    """CIE76 colour difference between broadcastable ``(..., 3)`` CIELAB arrays."""
    return np.linalg.norm(np.asarray(lab_a) - np.asarray(lab_b), axis=-1)


def choose_palette(colors: int, levels: int = 5) -> np.ndarray:
    """``colors`` sRGB colours ``(c, 3)`` far apart in CIELAB and far from white paper.

    Greedy farthest-point selection over an sRGB grid of ``levels`` steps per channel,
    restricted to ink colours (min channel <= MAX_INK_CHANNEL), with the paper white
    counted as already chosen so every tile also stands out from the background.
    Deterministic: the same ``colors`` always gives the same palette.
    """
    colors = validate.integer_in("colors", colors, 2, 12)
    grid = np.linspace(0.0, 1.0, levels)
    cand = np.array(list(itertools.product(grid, repeat=3)))
    cand = cand[cand.min(axis=1) <= MAX_INK_CHANNEL + 1e-9]
    lab = srgb_to_lab(cand)
    nearest = delta_e(lab, srgb_to_lab(np.ones(3)))
    chosen: list[int] = []
    for _ in range(int(colors)):
        pick = int(np.argmax(nearest))
        chosen.append(pick)
        nearest = np.minimum(nearest, delta_e(lab, lab[pick]))
    return cand[chosen]


def palette_delta_e(palette_rgb: np.ndarray) -> np.ndarray:
    """Pairwise CIE76 distances ``(c, c)`` of a palette given as sRGB ``(c, 3)``."""
    pal = validate.finite_array("palette_rgb", palette_rgb)
    if pal.ndim != 2 or pal.shape[1] != 3:
        raise InputError(f"palette_rgb must have shape (c, 3), got {pal.shape}")
    lab = srgb_to_lab(pal)
    return delta_e(lab[:, None, :], lab[None, :, :])
