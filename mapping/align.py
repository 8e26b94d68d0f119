"""Align georeferenced submodels to each other and to the photos' GPS, all at once.

Every submodel is already georeferenced to its own photos' GPS, so they agree to within the GPS fit; what
remains between two of them (a shift of centimetres to decimetres, a scale or tilt of a few thousandths)
would show as a height step or an image shift where they meet. Fitting each submodel onto one reference
through the photos they share removes the step, but a tilt fixed on a narrow shared band is extrapolated
across the whole submodel (a rendered survey split in 4: ground 0.45 m low at the far side of a submodel
tied to the reference by 14 photos at its edge). So every submodel k gets a small similarity T_k (rotation
w_k, scale 1 + d_k, shift t_k about the survey's centre p0, linearised: they are corrections of
thousandths), solved jointly by weighted least squares over
- every photo two submodels share: T_i(c_i) = T_j(c_j), to a sigma estimated from the fit itself (the RMS
  per axis of the kept shared photos' differences, at least ``SHARED_SIGMA_M``): models that differ in
  shape by decimetres (Seneca) must not be held to centimetres, or shrinking every submodel about the
  centre shortens their differences more than it costs (a 10 % shrink, cameras moved 10 m, on Seneca split
  in 3 at a fixed 2 cm), and
- every camera where its own submodel's georeference put it: T_k(c_k) = c_k, to the GPS sigmas
  (horizontal, vertical). Each submodel was fitted to its photos' GPS by least squares (after removing
  their time lag, :mod:`skyfix.mapping.gps_lag`), so near that fit its GPS residuals are orthogonal to any
  small similarity: moving it away from its own cameras costs what moving it away from its GPS costs, without
  the GPS noise and lag. (Raw GPS here, tried first, pulled both Seneca submodels to a 3 % smaller scale:
  a 1-2 s lag shifts the tags along alternating lines.)
leaving out, after each solve, a shared photo the two submodels still place more than ``SHARED_OUTLIER_M``
(and 3x the median) apart: a photo placed by another model inside one submodel (Seneca: three photos 5 m
off) would otherwise be worth shrinking both submodels by 2 % (a Huber weight still lets a 5 m residual
at a 2 cm sigma pull hard). The overlaps then agree as tightly as the models allow, and each submodel moves no further from its
own georeference than that takes, the larger ones least.
Coordinates: UTM metres minus a common origin (E, N, height AMSL); transforms 3x4 ``[sR | t]``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

__all__ = ["Alignment", "align_submodels", "apply"]

log = logging.getLogger(__name__)

SHARED_SIGMA_M = 0.02  # one photo's centre in two submodels: at best (then re-estimated from the fit)
SHARED_OUTLIER_M = 0.5  # a shared photo the submodels place further apart than this after the fit is left out
IRLS_ROUNDS = 5


@dataclass
class Alignment:
    """How one submodel was placed: ``matrix`` (3x4, local metres); ``shared`` photos it shares with other
    submodels, the RMS of their centres' differences before and after (m; after: over those kept),
    ``left_out`` the shared photos left out as placed too far apart; ``moved_rms_m`` how far its cameras
    moved; ``scale`` and ``tilt_deg`` of the correction."""

    index: int
    matrix: np.ndarray = field(default_factory=lambda: np.hstack((np.eye(3), np.zeros((3, 1)))))
    shared: int = 0
    rms_before_m: float = float("nan")
    rms_after_m: float = float("nan")
    moved_rms_m: float = float("nan")
    scale: float = 1.0
    tilt_deg: float = 0.0
    left_out: list = field(default_factory=list)

    def to_dict(self) -> dict:
        return {"index": self.index, "shared_photos": self.shared,
                "rms_before_m": self.rms_before_m, "rms_after_m": self.rms_after_m, "moved_rms_m": self.moved_rms_m,
                "scale": self.scale, "tilt_deg": self.tilt_deg, "left_out": list(self.left_out),
                "translation_m": [float(v) for v in self.matrix[:, 3]],
                "matrix": [[float(v) for v in row] for row in self.matrix]}


def apply(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``(N, 3)`` points mapped by a 3x4 transform."""
    return np.asarray(points, float) @ matrix[:, :3].T + matrix[:, 3]


def _jacobian(d: np.ndarray) -> np.ndarray:
    """(N, 3, 7) derivative of T(p) = p + w x d + s d + t (d = p - p0) by (w, s, t)."""
    n = len(d)
    jac = np.zeros((n, 3, 7))
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    # w x d = -[d]x w
    jac[:, 0, 1], jac[:, 0, 2] = z, -y
    jac[:, 1, 0], jac[:, 1, 2] = -z, x
    jac[:, 2, 0], jac[:, 2, 1] = y, -x
    jac[:, :, 3] = d
    jac[:, :, 4:] = np.eye(3)
    return jac


def _matrix(params: np.ndarray, p0: np.ndarray) -> np.ndarray:
    """The 3x4 similarity of (w, s, t) about ``p0`` (rotation by Rodrigues: exact for any w)."""
    import cv2

    rot, _ = cv2.Rodrigues(params[:3].reshape(3, 1))
    a = (1.0 + params[3]) * rot
    return np.hstack((a, (p0 - a @ p0 + params[4:])[:, None]))


def align_submodels(centres: dict[int, dict[str, np.ndarray]],
                    gps_sigma_m: tuple[float, float] = (2.0, 4.0)) -> dict[int, Alignment]:
    """Place every submodel (see the module docs). ``centres``: submodel index -> photo name -> camera centre
    (3,) in local metres, as the submodel's own georeference put it; ``gps_sigma_m``: the GPS sigmas
    (horizontal, vertical) that georeference was fitted with."""
    ids = sorted(centres)
    if not ids:
        return {}
    col = {k: 7 * i for i, k in enumerate(ids)}
    every = np.array([c for k in ids for c in centres[k].values()])
    p0 = every.mean(axis=0)
    shared_rows, gps_rows = [], []  # (k, name) pairs
    names_by = {k: set(centres[k]) for k in ids}
    pairs = [(i, j, sorted(names_by[i] & names_by[j])) for a, i in enumerate(ids) for j in ids[a + 1:]]
    pairs = [(i, j, names) for i, j, names in pairs if names]
    for k in ids:
        gps_rows += [(k, n) for n in sorted(centres[k])]
    shared_rows = [(i, j, n) for i, j, names in pairs for n in names]
    sig_gps = np.array([gps_sigma_m[0], gps_sigma_m[0], gps_sigma_m[1]], float)
    n_rows = 3 * (len(shared_rows) + len(gps_rows))
    a_mat = np.zeros((n_rows, 7 * len(ids)))
    b_vec = np.zeros(n_rows)
    sig = np.zeros(n_rows)
    r = 0
    for i, j, n in shared_rows:
        ci, cj = centres[i][n], centres[j][n]
        a_mat[r:r + 3, col[i]:col[i] + 7] = _jacobian((ci - p0)[None])[0]
        a_mat[r:r + 3, col[j]:col[j] + 7] = -_jacobian((cj - p0)[None])[0]
        b_vec[r:r + 3] = cj - ci
        sig[r:r + 3] = SHARED_SIGMA_M
        r += 3
    for k, n in gps_rows:
        c = centres[k][n]
        a_mat[r:r + 3, col[k]:col[k] + 7] = _jacobian((c - p0)[None])[0]
        b_vec[r:r + 3] = 0.0  # stay where the submodel's own GPS fit put it
        sig[r:r + 3] = sig_gps
        r += 3
    weights = np.ones(n_rows)
    x = np.zeros(7 * len(ids))
    n_shared = 3 * len(shared_rows)
    for _ in range(IRLS_ROUNDS):
        w = np.sqrt(weights) / sig
        x, *_ = np.linalg.lstsq(a_mat * w[:, None], b_vec * w, rcond=None)
        if not n_shared:
            break
        apart = np.linalg.norm((a_mat[:n_shared] @ x - b_vec[:n_shared]).reshape(-1, 3), axis=1)
        keep = apart <= max(SHARED_OUTLIER_M, 3.0 * float(np.median(apart)))
        new = np.concatenate((np.repeat(keep.astype(float), 3), np.ones(n_rows - n_shared)))
        sigma = max(SHARED_SIGMA_M, float(np.sqrt(np.mean(apart[keep] ** 2) / 3.0))) if keep.any() else SHARED_SIGMA_M
        if np.array_equal(new, weights) and abs(sigma - sig[0]) <= 0.05 * sig[0]:
            break
        weights, sig[:n_shared] = new, sigma
    out = {}
    kept = weights[:n_shared:3] > 0
    for k in ids:
        m = _matrix(x[col[k]:col[k] + 7], p0)
        mine = [(i, j, n, ok) for (i, j, n), ok in zip(shared_rows, kept, strict=True) if k in (i, j)]
        before = [centres[i][n] - centres[j][n] for i, j, n, _ in mine]
        after = [apply(_matrix(x[col[i]:col[i] + 7], p0), centres[i][n][None])[0]
                 - apply(_matrix(x[col[j]:col[j] + 7], p0), centres[j][n][None])[0] for i, j, n, ok in mine if ok]
        own = np.array(list(centres[k].values()))
        w = x[col[k]:col[k] + 3]
        tilt = float(np.degrees(np.hypot(w[0], w[1])))
        out[k] = Alignment(k, m, len({n for _, _, n, _ in mine}), _rms(before), _rms(after),
                           _rms(apply(m, own) - own), float(1.0 + x[col[k] + 3]), tilt,
                           sorted({n for _, _, n, ok in mine if not ok}))
        log.info("submodel %d: %d shared photos RMS %.3f -> %.3f m, cameras moved %.3f m, scale %+.4f %%, "
                 "tilt %.3f deg", k, out[k].shared, out[k].rms_before_m, out[k].rms_after_m, out[k].moved_rms_m,
                 100 * x[col[k] + 3], tilt)
    return out


def _rms(diffs) -> float:
    d = np.asarray(diffs, float)
    return float(np.sqrt(np.mean(np.sum(d.reshape(-1, 3) ** 2, axis=1)))) if d.size else float("nan")
