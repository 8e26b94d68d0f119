"""Type aliases that carry a unit, for names whose conventional spelling has none.

A camera's ``fx, fy, cx, cy`` keep the names of the intrinsic matrix K that OpenCV,
COLMAP and the camera JSON use, and pixel arrays keep the name ``uv``; their
annotations say the unit instead. The unit is the ``typing.Annotated`` metadata, so
tools (and ``tests/foundation/test_unit_names.py``) can read it.

Example:
    >>> from typing import get_args
    >>> get_args(Pixels)[1], get_args(PixelArray)[1]
    ('px', 'px')
"""

from __future__ import annotations

from typing import Annotated, TypeAlias

import numpy as np

Pixels: TypeAlias = Annotated[float, "px"]
"""A length in pixels, or a pixel coordinate (OpenCV: centre of the top-left pixel is 0)."""

PixelArray: TypeAlias = Annotated[np.ndarray, "px"]
"""``(N, 2)`` pixel coordinates ``(u, v)``, OpenCV convention (u right, v down)."""

LatLonAltArray: TypeAlias = Annotated[np.ndarray, "deg, deg, m"]
"""``(N, 3)`` rows of (latitude deg, longitude deg, ellipsoidal height m), WGS84."""

UNIT_ALIASES = ("Pixels", "PixelArray", "LatLonAltArray")
"""The names above: an annotation that uses one of them states its unit."""
