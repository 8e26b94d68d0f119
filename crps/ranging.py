"""Range from apparent size: the pinhole relation and the reference-image form.

An object of size ``S`` metres at range ``D`` spans ``s = f * S / D`` pixels on the
optical axis of a camera with focal length ``f`` pixels, so ``D = f * S / s``. With a
reference image in which the same object spans ``s0`` pixels at known range ``d0``,
``D1 = d0 * s0 / s1`` (the UAV-framework source prints ``d0 * s1 / s0``, which is
inverted: a target that looks bigger is nearer). First-order error propagation gives
``sigma_D = D * sigma_s / s``.
"""

from __future__ import annotations

import numpy as np

from skyfix import validate

__all__ = ["range_from_reference", "range_from_size"]


def range_from_size(size_px, object_size_m, focal_px, size_sigma_px=0.0) -> tuple[np.ndarray, np.ndarray]:
    """Range and its 1-sigma from apparent size; all arguments broadcast.

    ``size_px`` apparent size in pixels (on-axis equivalent), ``object_size_m`` true
    size in metres, ``focal_px`` focal length in pixels, ``size_sigma_px`` 1-sigma of
    ``size_px``. Returns ``(range_m, range_sigma_m)`` arrays of the broadcast shape.

    Example:
        A 0.5 m drone 20 px wide through a 1000 px lens is 25 m away; 0.4 px of size noise
        is 2 % of the size, so 0.5 m of range:

        >>> range_m, sigma_m = range_from_size(20.0, 0.5, 1000.0, size_sigma_px=0.4)
        >>> float(range_m), round(float(sigma_m), 3)
        (25.0, 0.5)
    """
    s = validate.positive_array("size_px", size_px)
    size_m = validate.positive_array("object_size_m", object_size_m)
    f = validate.positive_array("focal_px", focal_px)
    sigma = validate.nonnegative_array("size_sigma_px", size_sigma_px)
    range_m = f * size_m / s
    return range_m, range_m * sigma / s


def range_from_reference(d0_m, s0_px, s1_px, s1_sigma_px=0.0) -> tuple[np.ndarray, np.ndarray]:
    """Range ``d0 * s0 / s1`` from a reference image, and its 1-sigma; arguments broadcast.

    ``d0_m`` range of the reference image, ``s0_px`` apparent size there, ``s1_px``
    apparent size now (same camera and zoom), ``s1_sigma_px`` 1-sigma of ``s1_px``.

    Example:
        Half as wide as on the reference taken at 20 m: twice as far.

        >>> [float(x) for x in range_from_reference(20.0, 40.0, 20.0)]
        [40.0, 0.0]
    """
    d0 = validate.positive_array("d0_m", d0_m)
    s0 = validate.positive_array("s0_px", s0_px)
    s1 = validate.positive_array("s1_px", s1_px)
    sigma = validate.nonnegative_array("s1_sigma_px", s1_sigma_px)
    range_m = d0 * s0 / s1
    return range_m, range_m * sigma / s1
