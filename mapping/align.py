"""Align georeferenced submodels to each other through the photos they share.

Every submodel is already georeferenced to the photos' GPS on its own, so they agree to within the GPS
fit; what remains (a shift of a few centimetres to decimetres, a small scale or tilt) would show as a
height step or an image shift where two submodels meet. Each submodel is mapped onto the largest one by a
similarity fitted to the camera centres of the photos both reconstructed (LO-RANSAC, pycolmap
``estimate_sim3d_robust``, then least squares on the inliers), chained along the pairs that share the
most photos (a maximum spanning tree). Too few shared photos, or shared photos on one line (the roll about
it is then free), give a translation only (median of the differences). Coordinates are UTM metres minus a
common origin (E, N, height AMSL), transforms 3x4 ``[sR | t]`` acting on column vectors.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

__all__ = ["Alignment", "align_submodels", "apply"]

log = logging.getLogger(__name__)

MIN_SHARED = 3  # shared registered photos needed to tie two submodels
SIM3_MIN_SHARED = 4  # ... and to fit more than a translation
ALIGN_MAX_ERROR_M = 1.0  # RANSAC inlier distance between the two models' camera centres


@dataclass
class Alignment:
    """How one submodel was placed onto the reference: ``matrix`` (3x4, local metres), fitted to
    ``parent`` through ``shared`` photos by ``method`` ("reference", "sim3", "translation", "none");
    RMS of the shared camera centres' differences before and after (m)."""

    index: int
    matrix: np.ndarray = field(default_factory=lambda: np.hstack((np.eye(3), np.zeros((3, 1)))))
    parent: int | None = None
    method: str = "reference"
    shared: int = 0
    rms_before_m: float = float("nan")
    rms_after_m: float = float("nan")
    scale: float = 1.0

    def to_dict(self) -> dict:
        return {"index": self.index, "parent": self.parent, "method": self.method, "shared_photos": self.shared,
                "rms_before_m": self.rms_before_m, "rms_after_m": self.rms_after_m, "scale": self.scale,
                "translation_m": [float(v) for v in self.matrix[:, 3]],
                "matrix": [[float(v) for v in row] for row in self.matrix]}


def apply(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``(N, 3)`` points mapped by a 3x4 transform."""
    return np.asarray(points, float) @ matrix[:, :3].T + matrix[:, 3]


def _collinear(points: np.ndarray, ratio: float = 0.25) -> bool:
    sv = np.linalg.svd(points[:, :2] - points[:, :2].mean(axis=0), compute_uv=False)
    return sv[0] == 0 or sv[1] / sv[0] < ratio


def _fit(src: np.ndarray, tgt: np.ndarray) -> tuple[np.ndarray, str]:
    """Transform taking ``src`` centres onto ``tgt`` (both (N, 3))."""
    if len(src) >= SIM3_MIN_SHARED and not _collinear(tgt):
        import pycolmap

        ransac = pycolmap.RANSACOptions()
        ransac.max_error = ALIGN_MAX_ERROR_M
        ransac.random_seed = 0
        found = pycolmap.estimate_sim3d_robust(src, tgt, ransac)
        if found and found["num_inliers"] >= SIM3_MIN_SHARED:
            m = np.asarray(found["tgt_from_src"].matrix())
            inl = np.linalg.norm(apply(m, src) - tgt, axis=1) <= ALIGN_MAX_ERROR_M
            refined = pycolmap.estimate_sim3d(src[inl], tgt[inl]) if inl.sum() >= SIM3_MIN_SHARED else None
            return np.asarray((refined or found["tgt_from_src"]).matrix()), "sim3"
    shift = np.median(tgt - src, axis=0)
    return np.hstack((np.eye(3), shift[:, None])), "translation"


def align_submodels(centres: dict[int, dict[str, np.ndarray]]) -> dict[int, Alignment]:
    """Place every submodel onto the one with the most registered photos. ``centres``: submodel index ->
    photo name -> camera centre (3,) in local metres. A submodel sharing fewer than MIN_SHARED
    registered photos with every placed one keeps its own georeference (method "none")."""
    if not centres:
        return {}
    ref = max(centres, key=lambda i: (len(centres[i]), -i))
    placed = {ref: Alignment(ref)}
    while len(placed) < len(centres):
        best = None  # (shared count, -child, parent, child, names)
        for p in sorted(placed):
            for c in sorted(set(centres) - set(placed)):
                names = sorted(set(centres[p]) & set(centres[c]))
                key = (len(names), -c, -p)
                if len(names) >= MIN_SHARED and (best is None or key > best[0]):
                    best = (key, p, c, names)
        if best is None:
            for c in sorted(set(centres) - set(placed)):
                log.warning("submodel %d shares fewer than %d registered photos with the others: kept on its own "
                            "GPS georeference", c, MIN_SHARED)
                placed[c] = Alignment(c, method="none")
            break
        _, p, c, names = best
        src = np.array([centres[c][n] for n in names])
        tgt = apply(placed[p].matrix, np.array([centres[p][n] for n in names]))
        matrix, method = _fit(src, tgt)  # tgt is already in the reference frame
        before = float(np.sqrt(np.mean(np.sum((src - tgt) ** 2, axis=1))))
        after = float(np.sqrt(np.mean(np.sum((apply(matrix, src) - tgt) ** 2, axis=1))))
        scale = float(np.cbrt(np.linalg.det(matrix[:, :3])))
        placed[c] = Alignment(c, matrix, p, method, len(names), before, after, scale)
        log.info("submodel %d onto %d: %s through %d shared photos, RMS %.3f -> %.3f m", c, p, method, len(names),
                 before, after)
    return placed
