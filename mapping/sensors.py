"""Sensor widths of common survey cameras, for photos whose EXIF lacks the focal-plane
resolution (DJI writes none). Width in millimetres of the full sensor; a frame cropped to
16:9 from it keeps that width, so ``focal_px = focal_mm * image_width / width_mm``.

Values are the manufacturers' published sensor sizes (1-inch type 13.2 x 8.8 mm,
1/2.3-inch type 6.17 x 4.55 mm, Four Thirds 17.3 x 13.0 mm).
"""

from __future__ import annotations

__all__ = ["sensor_width_mm"]

_ONE_INCH_MM = 13.2
_ONE_OVER_2_3_MM = 6.17
_FOUR_THIRDS_MM = 17.3

#: (make, model) lower-case -> sensor width in millimetres.
SENSOR_WIDTH_MM: dict[tuple[str, str], float] = {
    ("dji", "fc6310"): _ONE_INCH_MM,       # Phantom 4 Pro
    ("dji", "fc6310s"): _ONE_INCH_MM,      # Phantom 4 Pro V2.0
    ("dji", "fc6310r"): _ONE_INCH_MM,      # Phantom 4 RTK
    ("hasselblad", "l1d-20c"): _ONE_INCH_MM,  # Mavic 2 Pro
    ("dji", "fc330"): _ONE_OVER_2_3_MM,    # Phantom 4
    ("dji", "fc300x"): _ONE_OVER_2_3_MM,   # Phantom 3 Professional
    ("dji", "fc300s"): _ONE_OVER_2_3_MM,   # Phantom 3 Advanced
    ("dji", "fc220"): _ONE_OVER_2_3_MM,    # Mavic Pro
    ("dji", "fc6520"): _FOUR_THIRDS_MM,    # Zenmuse X5S
    ("canon", "canon powershot elph 300 hs"): _ONE_OVER_2_3_MM,
}


def sensor_width_mm(make: str | None, model: str | None) -> float | None:
    """Sensor width (mm) of a known camera, or None."""
    if not make or not model:
        return None
    return SENSOR_WIDTH_MM.get((make.strip().lower(), model.strip().lower()))
