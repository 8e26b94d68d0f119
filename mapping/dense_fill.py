"""Filters and hole filling for the dense DSM (:mod:`skyfix.mapping.dense`): spikes and
isolated cells out, holes of a fine surface filled from a coarser pass where that pass is
trustworthy (smooth ground next to the fine surface, at its height), and a pyramid fill for
the orthophoto's surface. Heights in metres on the DSM grid; NaN: no height."""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["fill_from", "fill_holes", "local_range_m", "without_spikes"]


def fill_holes(surface_m: np.ndarray) -> np.ndarray:
    """NaN cells filled from ever coarser block means (a pyramid), finite cells kept."""
    if np.isfinite(surface_m).all() or not np.isfinite(surface_m).any():
        return surface_m.copy()
    h, w = surface_m.shape
    padded = np.pad(surface_m, ((0, h % 2), (0, w % 2)), constant_values=np.nan)
    blocks = padded.reshape(padded.shape[0] // 2, 2, padded.shape[1] // 2, 2)
    with np.errstate(invalid="ignore"):
        finite = np.isfinite(blocks)
        coarse = np.where(finite, blocks, 0.0).sum(axis=(1, 3)) / finite.sum(axis=(1, 3))
    coarse = fill_holes(coarse)
    up = np.repeat(np.repeat(coarse, 2, axis=0), 2, axis=1)[:h, :w]
    return np.where(np.isfinite(surface_m), surface_m, up)


def without_spikes(surface: np.ndarray, spike_m: float) -> np.ndarray:
    """``surface`` less spikes (cells more than ``spike_m`` off their 5x5 median) and isolated
    cells (fewer than 6 measured in their 5x5 neighbourhood: stray matches)."""
    from scipy.ndimage import median_filter

    surface = surface.copy()
    spikes = np.abs(surface - median_filter(fill_holes(surface), size=5, mode="nearest")) > spike_m
    surface[spikes] = np.nan
    neighbours_seen = cv2.boxFilter(np.isfinite(surface).astype(np.float32), -1, (5, 5), normalize=False)
    surface[neighbours_seen < 6] = np.nan
    return surface


def local_range_m(surface: np.ndarray, size: int) -> np.ndarray:
    """(H, W) highest minus lowest measured height within ``size`` x ``size`` cells (NaN ignored)."""
    from scipy.ndimage import maximum_filter, minimum_filter

    finite = np.isfinite(surface)
    high = maximum_filter(np.where(finite, surface, -np.inf), size=size, mode="nearest")
    low = minimum_filter(np.where(finite, surface, np.inf), size=size, mode="nearest")
    return high - low


def _fill_once(surface: np.ndarray, filler: np.ndarray, spike_m: float, max_range_m: float) -> tuple[np.ndarray, dict]:
    """``surface`` with its empty cells taken from a coarser pass's ``filler`` where that is
    trustworthy (see :func:`skyfix.mapping.dense.dense_dsm`), and the pass's statistics: cells added, cells both
    measured and their median / 90th-percentile absolute difference (m)."""
    added = ~np.isfinite(surface) & np.isfinite(filler)
    merged = np.where(added, filler, surface)
    # Not a spike on the merged surface, and on smooth ground: a coarse pass smears roofs
    # and crowns into the ground around them (on the rendered survey, metres off).
    merged[added & ~np.isfinite(without_spikes(merged, spike_m))] = np.nan
    merged[added & (local_range_m(merged, 5) > max_range_m)] = np.nan
    merged[added & (local_range_m(surface, 11) > 2 * max_range_m)] = np.nan
    # Next to the finer surface and at its height: holes are filled from their rims.
    near = cv2.boxFilter(np.isfinite(surface).astype(np.float32), -1, (7, 7), normalize=False) >= 6
    off = np.abs(merged - fill_holes(surface)) > max_range_m
    merged[added & (~near | off)] = np.nan
    both = np.abs(filler - surface)[np.isfinite(filler) & np.isfinite(surface)]
    stats = {"cells_added": int((np.isfinite(merged) & ~np.isfinite(surface)).sum()), "cells_both": int(both.size),
             "median_abs_diff_m": float(np.median(both)) if both.size else float("nan"),
             "p90_abs_diff_m": float(np.percentile(both, 90)) if both.size else float("nan")}
    return merged, stats


def fill_from(surface: np.ndarray, filler: np.ndarray, spike_m: float, max_range_m: float,
              max_rounds: int = 100) -> tuple[np.ndarray, dict]:
    """``surface`` with its empty cells taken from ``filler`` (a coarser or mirrored pass) by
    :func:`_fill_once`, repeated while it adds cells (at most ``max_rounds``): each round
    accepts the cells next to the surface grown so far, so a hole wider than the 7x7 rim
    window fills inward from its rim, every cell judged against its measured neighbours.
    Statistics as :func:`_fill_once`'s, with ``cells_added`` summed over the rounds and
    ``rounds`` the rounds that added cells."""
    merged, stats = _fill_once(surface, filler, spike_m, max_range_m)
    rounds, added = 1, stats["cells_added"]
    while added and rounds < max_rounds:
        merged, more = _fill_once(merged, filler, spike_m, max_range_m)
        added = more["cells_added"]
        stats["cells_added"] += added
        rounds += 1 if added else 0
    return merged, {**stats, "rounds": rounds}
