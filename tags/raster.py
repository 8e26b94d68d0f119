"""Exact area-coverage rasterisation of axis-aligned rectangles (for print and texture).

Image convention: row 0 is the north edge, column 0 the west edge; pixel (col, row)
covers [col, col+1) x [row, row+1) in pixel-edge coordinates.
"""

from __future__ import annotations

import numpy as np


def _overlap(lo: float, hi: float, n: int) -> tuple[int, np.ndarray]:
    """First pixel index and per-pixel covered fraction of the interval [lo, hi)."""
    i0 = max(0, int(np.floor(lo)))
    i1 = min(n, int(np.ceil(hi)))
    if i1 <= i0:
        return i0, np.zeros(0)
    edges = np.arange(i0, i1, dtype=float)
    return i0, np.clip(np.minimum(hi, edges + 1.0) - np.maximum(lo, edges), 0.0, 1.0)


def fill_rects(image: np.ndarray, rects_px: np.ndarray, colours: np.ndarray) -> None:
    """Paint rectangles into ``image`` (H, W, C) float in place, blending by exact coverage.

    ``rects_px`` ``(N, 4)`` = (x0, y0, x1, y1) in pixel-edge coordinates; ``colours``
    ``(N, C)``. The caller owns ``image`` (this is a drawing primitive).
    """
    h, w = image.shape[:2]
    for (x0, y0, x1, y1), colour in zip(rects_px, colours, strict=True):
        c0, fx = _overlap(x0, x1, w)
        r0, fy = _overlap(y0, y1, h)
        if fx.size == 0 or fy.size == 0:
            continue
        alpha = (fy[:, None] * fx[None, :])[..., None]
        patch = image[r0:r0 + fy.size, c0:c0 + fx.size]
        patch *= 1.0 - alpha
        patch += alpha * colour
