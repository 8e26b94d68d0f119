"""A camera observer's pointing error in a relative observation: the part its frames share.

An observation's offset (target minus observer, frame ENU, m) is the camera's ray scaled by its range. A
pointing error of (yaw, pitch) rad moves it across the line of sight by ``J @ (yaw, pitch, 0)``, with

    J = [r_h e_h, r e_v, 0],   e_h = up x u / |up x u| (horizontal, across),  e_v = u x e_h (up-ish, across)

``u`` the unit ray, ``r`` the range and ``r_h`` its horizontal part (a yaw turns the ray about the vertical).
The heading reference's error is the same in every frame of a flight, so it is a state of the observer that
its observations share (:meth:`skyfix.fusion.chains.StateChains.ensure_pointing`); what each frame adds on its
own is the observation's stated covariance less that shared part, across the line of sight, never less than a
floor (centroid and gimbal noise).
"""

from __future__ import annotations

import numpy as np

_UP = np.array([0.0, 0.0, 1.0])


def _basis(offset_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
    """Unit ray u, horizontal across e_h, vertical across e_v, range r and horizontal range r_h."""
    r = float(np.linalg.norm(offset_m))
    u = offset_m / max(r, 1e-9)
    across = np.cross(_UP, u)
    n = float(np.linalg.norm(across))
    e_h = across / n if n > 1e-6 else np.array([1.0, 0.0, 0.0])  # looking straight up or down: east
    e_v = np.cross(u, e_h)
    return u, e_h, e_v, r, float(np.hypot(offset_m[0], offset_m[1]))


def pointing_jacobian(offset_m: np.ndarray) -> np.ndarray:
    """(3, 3) change of the offset per rad of (yaw counter-clockwise, pitch up, -) pointing error.

    Example:
        >>> (pointing_jacobian(np.array([0.0, 30.0, 0.0])).round(6) + 0.0).tolist()  # 30 m north, level
        [[-30.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 30.0, 0.0]]
    """
    _, e_h, e_v, r, r_h = _basis(np.asarray(offset_m, float))
    return np.column_stack([r_h * e_h, r * e_v, np.zeros(3)])


def white_part(cov_m2: np.ndarray, offset_m: np.ndarray, shared_sigma_rad: float, floor_rad: float) -> np.ndarray:
    """``cov_m2`` (3, 3) less the shared pointing part (``shared_sigma_rad`` on both axes) across the line of sight,
    each across-axis variance kept >= (range x ``floor_rad``)^2; along the ray as stated.

    Example (2 deg stated, 2 deg shared, 0.2 deg floor, 30 m: 0.105 m across):
        >>> c = np.diag([0.5**2, (30 * np.radians(2.0))**2, (30 * np.radians(2.0))**2])
        >>> np.sqrt(np.diag(white_part(c, np.array([30.0, 0.0, 0.0]), np.radians(2.0), np.radians(0.2)))).round(3)
        array([0.5  , 0.105, 0.105])
    """
    u, e_h, e_v, r, r_h = _basis(np.asarray(offset_m, float))
    basis = np.column_stack([u, e_h, e_v])
    local = basis.T @ cov_m2 @ basis
    local[1, 1] -= (r_h * shared_sigma_rad) ** 2
    local[2, 2] -= (r * shared_sigma_rad) ** 2
    floor2 = (r * floor_rad) ** 2
    for i in (1, 2):
        if local[i, i] < floor2:  # nothing of its own left across this axis: the floor, uncorrelated
            local[i, :] = local[:, i] = 0.0
            local[i, i] = floor2
    vals, vecs = np.linalg.eigh(0.5 * (local + local.T))
    local = (vecs * np.maximum(vals, floor2 * 1e-3)) @ vecs.T
    return basis @ local @ basis.T
