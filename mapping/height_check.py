"""Flying height above the reconstructed ground, next to the photos' own altitude data.

A model whose heights are wrong (a focal length off by a few percent scales every depth)
still fits its GPS camera positions, so the check compares two independent figures:
the model's height of each camera above the DSM cell below it, and the height the drone
itself recorded above its take-off point (DJI XMP ``RelativeAltitude``, barometric). They
agree when the ground below the cameras lies at the take-off height; a difference that
the terrain does not explain shows a height error at once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from skyfix.geo import LocalFrame
from skyfix.mapping.dsm import Dsm
from skyfix.mapping.grid import enu_to_utm
from skyfix.mapping.photos import Photo

__all__ = ["FlyingHeight", "flying_height"]


@dataclass(frozen=True)
class FlyingHeight:
    """Medians over registered photos, metres. ``relative_altitude_m`` is NaN when the
    photos carry none; ``photos`` counts photos with a DSM cell below them."""

    model_agl_m: float
    relative_altitude_m: float
    photos: int

    @property
    def difference_m(self) -> float:
        return self.model_agl_m - self.relative_altitude_m

    def suspicious(self, tolerance: float = 0.05, floor_m: float = 1.0) -> bool:
        """True when the two differ by more than ``tolerance`` of the height (and ``floor_m``)."""
        d = self.difference_m
        return math.isfinite(d) and abs(d) > max(floor_m, tolerance * abs(self.relative_altitude_m))

    def line(self) -> str:
        """The report line a user reads."""
        text = f"flying height above the reconstructed ground {self.model_agl_m:.1f} m (median of {self.photos})"
        if not math.isfinite(self.relative_altitude_m):
            return text + "; the photos record no height above take-off to compare with"
        return (text + f"; the photos' own relative altitude (above take-off) {self.relative_altitude_m:.1f} m, "
                f"difference {self.difference_m:+.1f} m")

    def to_dict(self) -> dict:
        return {"model_agl_m": self.model_agl_m, "relative_altitude_m": self.relative_altitude_m,
                "difference_m": self.difference_m, "photos": self.photos, "line": self.line()}


def flying_height(models: list, photos: list[Photo], frame: LocalFrame, dsm: Dsm, window_m: float = 3.0
                  ) -> FlyingHeight:
    """Compare camera heights above the DSM (median within ``window_m`` below each camera)
    with the photos' relative altitudes; ``models`` are georeferenced reconstructions."""
    by_name = {p.name: p for p in photos}
    names, centres = [], []
    for rec in models:
        for image in rec.images.values():
            if image.has_pose and image.name not in names:
                names.append(image.name)
                centres.append(image.projection_center())
    if not centres:
        return FlyingHeight(math.nan, math.nan, 0)
    utm = enu_to_utm(frame, np.array(centres), dsm.grid.epsg)
    col, row = dsm.grid.to_pixel(utm[:, 0], utm[:, 1])
    half = max(1, round(window_m / 2.0 / dsm.grid.resolution_m))
    agl, rel = [], []
    for name, c, r, height in zip(names, np.rint(col).astype(int), np.rint(row).astype(int), utm[:, 2], strict=True):
        patch = dsm.surface_m[max(r - half, 0):r + half + 1, max(c - half, 0):c + half + 1]
        if patch.size == 0 or not np.isfinite(patch).any():
            continue
        agl.append(height - float(np.nanmedian(patch)))
        photo = by_name.get(name)
        if photo is not None and photo.relative_alt_m is not None:
            rel.append(photo.relative_alt_m)
    return FlyingHeight(float(np.median(agl)) if agl else math.nan, float(np.median(rel)) if rel else math.nan,
                        len(agl))
