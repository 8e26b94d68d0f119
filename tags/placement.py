"""Placement optimiser: assign tag values to grid positions so that adjacent tags
(diagonals included) differ as much as possible in colour, each value used once.

Simulated annealing over swaps (two positions exchange values) and replacements (a
position takes an unused value). The energy is a soft minimum of the adjacent tag
distances, sum(exp(-d / tau)), so the optimiser pushes up the worst pairs first.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from skyfix import validate
from skyfix.errors import InputError
from skyfix.tags.codec import TileCodec
from skyfix.tags.palette import palette_delta_e

_MATRIX_LIMIT = 4096  # precompute the value x value distance table up to this capacity


@dataclass(frozen=True)
class PlacementReport:
    """Adjacent-tag colour distances (CIE76 units) of the result and of random placement.

    ``random_min``/``random_mean`` are medians over ``random_trials`` random placements.
    """

    min_distance: float
    mean_distance: float
    random_min: float
    random_mean: float
    random_trials: int
    iterations: int
    elapsed_s: float


def king_edges(rows: int, cols: int) -> np.ndarray:
    """Undirected 8-neighbour edges ``(E, 2)`` of a rows x cols grid (flat row-major indices)."""
    idx = np.arange(rows * cols).reshape(rows, cols)
    pairs = [np.stack((idx[:, :-1].ravel(), idx[:, 1:].ravel()), 1),
             np.stack((idx[:-1, :].ravel(), idx[1:, :].ravel()), 1),
             np.stack((idx[:-1, :-1].ravel(), idx[1:, 1:].ravel()), 1),
             np.stack((idx[:-1, 1:].ravel(), idx[1:, :-1].ravel()), 1)]
    return np.concatenate(pairs, axis=0)


class _Distance:
    """Tag-to-tag colour distance by value, from a table when the capacity is small."""

    def __init__(self, codec: TileCodec) -> None:
        self.codec = codec
        self.de2 = palette_delta_e(codec.palette_rgb) ** 2
        self.table = None
        if codec.capacity <= _MATRIX_LIMIT:
            digits = codec.encode(np.arange(codec.capacity))
            d2 = np.zeros((codec.capacity, codec.capacity), np.float32)
            for i in range(codec.tiles):
                d2 += self.de2[digits[:, i][:, None], digits[:, i][None, :]]
            self.table = np.sqrt(d2)

    def __call__(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        if self.table is not None:
            return self.table[a, b]
        da, db = self.codec.encode(np.ravel(a)), self.codec.encode(np.ravel(b))
        return np.sqrt(self.de2[da, db].sum(axis=1)).reshape(np.shape(a))


def optimise_placement(codec: TileCodec, rows: int, cols: int, *, time_limit_s: float = 5.0,
                       max_iterations: int = 400_000, random_trials: int = 20,
                       seed: int = 0, on_progress=None) -> tuple[np.ndarray, PlacementReport]:
    """Values ``(rows, cols)`` (row 0 south) maximising adjacent colour distance, and a report.

    Stops after ``time_limit_s`` seconds or ``max_iterations`` moves, whichever is first.
    ``on_progress(fraction)``, when given, is called as the search advances (0 to 1).
    """
    rows, cols = validate.integer_in("rows", rows, 1), validate.integer_in("cols", cols, 1)
    n_pos = rows * cols
    if n_pos > codec.capacity:
        raise InputError(f"a {rows} x {cols} field needs {n_pos} distinct values but c={codec.colors}, "
                         f"n={codec.tiles} tags only have {codec.capacity}")
    validate.positive_scalar("time_limit_s", time_limit_s)
    rng = np.random.default_rng(seed)
    dist = _Distance(codec)
    edges = king_edges(rows, cols)

    def stats(values: np.ndarray) -> tuple[float, float]:
        if len(edges) == 0:
            return math.inf, math.inf
        d = dist(values[edges[:, 0]], values[edges[:, 1]])
        return float(d.min()), float(d.mean())

    rand = [stats(rng.permutation(codec.capacity)[:n_pos]) for _ in range(random_trials)]
    start = time.perf_counter()
    pool = rng.permutation(codec.capacity)
    values, unused = pool[:n_pos].copy(), pool[n_pos:].copy()
    neighbours = [[] for _ in range(n_pos)]
    for a, b in edges:
        neighbours[a].append(b)
        neighbours[b].append(a)
    neighbours = [np.array(nb, dtype=int) for nb in neighbours]

    de = palette_delta_e(codec.palette_rgb)
    tau = 0.15 * float(de[de > 0].min())
    # Temperatures on the scale of one closest-pair edge's energy.
    temp0 = 0.5 * math.exp(-float(de[de > 0].min()) / tau)
    temp1 = 1e-3 * temp0
    iteration = 0
    frac = 0.0
    for iteration in range(1, max_iterations + 1):
        if iteration % 256 == 0:
            frac = max(iteration / max_iterations, (time.perf_counter() - start) / time_limit_s)
            if on_progress is not None:
                on_progress(min(frac, 1.0))
            if frac >= 1.0:
                break
        temp = temp0 * (temp1 / temp0) ** frac
        a = int(rng.integers(n_pos))
        nb_a = neighbours[a]
        if unused.size and rng.random() < 0.3:
            j = int(rng.integers(unused.size))
            old, new = values[a], unused[j]
            nbv = values[nb_a]
            delta = float(np.exp(-dist(np.full(nbv.shape, new), nbv) / tau).sum()
                          - np.exp(-dist(np.full(nbv.shape, old), nbv) / tau).sum())
            if delta < 0 or rng.random() < math.exp(-delta / temp):
                values[a], unused[j] = new, old
            continue
        b = int(rng.integers(n_pos))
        if a == b:
            continue
        nb_b = neighbours[b]
        nb_a, nb_b = nb_a[nb_a != b], nb_b[nb_b != a]
        va, vb = values[a], values[b]
        na, nb = values[nb_a], values[nb_b]
        before = (np.exp(-dist(np.full(na.shape, va), na) / tau).sum()
                  + np.exp(-dist(np.full(nb.shape, vb), nb) / tau).sum())
        after = (np.exp(-dist(np.full(na.shape, vb), na) / tau).sum()
                 + np.exp(-dist(np.full(nb.shape, va), nb) / tau).sum())
        delta = float(after - before)
        if delta < 0 or rng.random() < math.exp(-delta / temp):
            values[a], values[b] = vb, va
    elapsed = time.perf_counter() - start
    best_min, best_mean = stats(values)
    report = PlacementReport(best_min, best_mean, float(np.median([r[0] for r in rand])),
                             float(np.median([r[1] for r in rand])), random_trials, iteration, elapsed)
    return values.reshape(rows, cols), report
