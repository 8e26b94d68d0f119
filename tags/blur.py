"""Motion-blur length from the anisotropy of the image gradients.

Square tags have as much edge along one axis as along the other, so the structure
tensor of a sharp frame is nearly isotropic whatever the yaw. A linear streak of
length L along a direction spreads the edges facing that direction over ~L pixels and
cuts their gradient energy by ~w0 / (w0 + L), w0 being the sharp edge width; the
eigenvalue ratio of the tensor therefore gives L ~ w0 * (lambda_max / lambda_min - 1).
"""

from __future__ import annotations

import cv2
import numpy as np

#: Effective sharp-edge width, half-resolution pixels (calibrated on rendered frames:
#: an 8 px streak along a tag edge reads 7-8 px; streaks diagonal to the edges read low).
SHARP_EDGE_PX = 2.5


def motion_blur_px(grey: np.ndarray) -> float:
    """Estimated streak length in pixels of a uint8 greyscale image ``(H, W)`` (0 if sharp)."""
    return motion_blur_half_res(cv2.resize(grey, (grey.shape[1] // 2, grey.shape[0] // 2),
                                           interpolation=cv2.INTER_AREA))


def motion_blur_half_res(grey_half: np.ndarray) -> float:
    """:func:`motion_blur_px` of an image already reduced 2x (2x2 box); result in
    full-resolution pixels."""
    # Sobel derivatives (int16) and the structure tensor from exact integer sums of squares
    # (cv2.norm accumulates in double): 2 fx.fy = |fx + fy|^2 - |fx|^2 - |fy|^2. No float
    # copies of the gradient images.
    dx, dy = cv2.spatialGradient(np.ascontiguousarray(grey_half, dtype=np.uint8))
    n = max(dx.size, 1)
    sxx, syy = cv2.norm(dx, cv2.NORM_L2SQR), cv2.norm(dy, cv2.NORM_L2SQR)
    sxy = 0.5 * (cv2.norm(cv2.add(dx, dy, dtype=cv2.CV_32S), cv2.NORM_L2SQR) - sxx - syy)
    jxx, jyy, jxy = sxx / n, syy / n, sxy / n
    tr, det = jxx + jyy, jxx * jyy - jxy * jxy
    disc = max(tr * tr / 4.0 - det, 0.0) ** 0.5
    lmax, lmin = tr / 2.0 + disc, tr / 2.0 - disc
    if lmax < 1.0:       # no edges at all
        return 0.0
    # Half-resolution length -> full-resolution pixels.
    return float(2.0 * SHARP_EDGE_PX * (lmax / max(lmin, 1e-6) - 1.0))
