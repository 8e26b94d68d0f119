"""Reference mapping: keep only tags whose decoded value agrees with the known layout.

Each decoded tag says where it is on the floor. A tag whose value was misread claims a
place that does not fit its neighbours. Every tag proposes the plane-to-image homography
of its own tiles; the proposal that explains the most other tags' image positions wins
(a RANSAC over tags); a least-squares homography over the winners then checks every
tile of every tag, which also catches tags read in the wrong orientation.
"""

from __future__ import annotations

import functools

import numpy as np


def _apply(h: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Homographies ``(..., 3, 3)`` applied to points ``(..., N, 2)`` -> ``(..., N, 2)``."""
    p = xy @ np.swapaxes(h[..., :2, :2], -1, -2) + h[..., None, :2, 2]
    w = xy @ h[..., 2, :2][..., :, None] + h[..., 2, 2][..., None, None]
    return p / w


def homographies_4pt(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Batched exact homographies ``(T, 3, 3)`` mapping 4 points ``(T, 4, 2)`` src -> dst."""
    t = len(src)
    a = np.zeros((t, 8, 8))
    x, y = src[..., 0], src[..., 1]
    u, v = dst[..., 0], dst[..., 1]
    a[:, 0::2, 0], a[:, 0::2, 1], a[:, 0::2, 2] = x, y, 1.0
    a[:, 1::2, 3], a[:, 1::2, 4], a[:, 1::2, 5] = x, y, 1.0
    a[:, 0::2, 6], a[:, 0::2, 7] = -u * x, -u * y
    a[:, 1::2, 6], a[:, 1::2, 7] = -v * x, -v * y
    b = dst.reshape(t, 8)                  # (u0, v0, u1, v1, ...): the rows' order
    sol = np.ones((t, 9))
    try:
        sol[:, :8] = np.linalg.solve(a, b[..., None])[..., 0]
    except np.linalg.LinAlgError:   # a degenerate (collinear) tag somewhere: solve one by one
        for i in range(t):
            sol[i, :8] = np.linalg.lstsq(a[i], b[i], rcond=None)[0]
    return sol.reshape(t, 3, 3)


def homography_lsq(src: np.ndarray, dst: np.ndarray) -> np.ndarray | None:
    """Least-squares homography ``(3, 3)`` src -> dst from ``(N, 2)`` points (normalised DLT)."""
    def norm(p):
        c = p.mean(axis=0)
        s = np.sqrt(2.0) / max(float(np.linalg.norm(p - c, axis=1).mean()), 1e-12)
        return np.array([[s, 0.0, -s * c[0]], [0.0, s, -s * c[1]], [0.0, 0.0, 1.0]])

    ts, td = norm(src), norm(dst)
    a = src @ ts[:2, :2].T + ts[:2, 2]
    b = dst @ td[:2, :2].T + td[:2, 2]
    n = len(a)
    m = np.zeros((2 * n, 9))
    m[0::2, 0:2], m[0::2, 2] = a, 1.0
    m[1::2, 3:5], m[1::2, 5] = a, 1.0
    m[0::2, 6:8] = -b[:, 0:1] * a
    m[0::2, 8] = -b[:, 0]
    m[1::2, 6:8] = -b[:, 1:2] * a
    m[1::2, 8] = -b[:, 1]
    # Null vector of m = eigenvector of m^T m with the smallest eigenvalue (9x9: cheap).
    ev, vec = np.linalg.eigh(m.T @ m)
    if ev[1] < 1e-12 * ev[-1]:
        return None
    h = np.linalg.inv(td) @ vec[:, 0].reshape(3, 3) @ ts
    return h / h[2, 2]


def consistent_tags(ground_xy: np.ndarray, image_uv: np.ndarray, spacing_m: float, pitch_m: float,
                    *, min_support: int = 2, max_hypotheses: int = 10, check_tiles: bool = True) -> np.ndarray:
    """Mask ``(T,)`` of tags consistent with the layout.

    ``ground_xy`` ``(T, n, 2)`` field positions of each tag's tiles (metres) implied by
    its decoded value; ``image_uv`` ``(T, n, 2)`` the tiles' ideal (undistorted) pixels.
    A proposal must explain at least ``min_support`` tags (itself included). With
    ``check_tiles`` a least-squares homography over the voters then checks every tile (a
    caller that fits a pose next can do that check on the pose residuals instead).
    """
    t = len(ground_xy)
    keep = np.zeros(t, bool)
    if t < min_support or t == 0:
        return keep
    # Proposals from at most max_hypotheses tags spread over the list: one sound tag among
    # them is enough, and the vote costs hypotheses x tags.
    hyp = _spread(t, min(t, max_hypotheses))
    hs = homographies_4pt(ground_xy[hyp, :4], image_uv[hyp, :4])
    n = ground_xy.shape[1]
    g_c = ground_xy.sum(axis=1) / n
    u_c = image_uv.sum(axis=1) / n
    # Local image scale of each tag, px per metre, from its own tiles.
    du, dg = image_uv - u_c[:, None], ground_xy - g_c[:, None]
    px_per_m = (np.sqrt(np.einsum("tnk,tnk->tn", du, du)).sum(axis=1)
                / np.sqrt(np.einsum("tnk,tnk->tn", dg, dg)).sum(axis=1))
    with np.errstate(invalid="ignore", divide="ignore"):
        p = hs[:, :, :2] @ g_c.T + hs[:, :, 2:]                           # (hyp, 3, tag)
        ex, ey = p[:, 0] / p[:, 2] - u_c[:, 0], p[:, 1] / p[:, 2] - u_c[:, 1]
        err = np.sqrt(ex * ex + ey * ey)                                   # (hyp, tag)
        inlier = err < 0.4 * spacing_m * px_per_m
    support = inlier.sum(axis=1)
    # Ties go to the smaller total error (a point behind the camera counts 1e9 px).
    best = int(np.argmax(support - 1e-6 * np.where(np.isnan(err), 1e9, err).sum(axis=1)))
    keep = inlier[best]
    for _ in range(2 if check_tiles else 0):
        before = keep
        if keep.sum() < min_support:
            return np.zeros(t, bool)
        h = homography_lsq(ground_xy[keep].reshape(-1, 2), image_uv[keep].reshape(-1, 2))
        if h is None:
            return np.zeros(t, bool)
        resid = np.linalg.norm(_apply(h, ground_xy) - image_uv, axis=2).max(axis=1)
        keep = resid < 0.25 * pitch_m * px_per_m
        if np.array_equal(keep, before):
            break
    return keep if keep.sum() >= min_support else np.zeros(t, bool)


@functools.lru_cache(maxsize=256)
def _spread(t: int, k: int) -> np.ndarray:
    """``k`` indices spread evenly over ``range(t)`` (first and last included)."""
    idx = np.linspace(0, t - 1, k).round().astype(int)
    idx.setflags(write=False)
    return idx
