"""skyfix.tags: fiducial floor tags for localising a drone with a downward camera.

Coloured-tile tags (FlyZone-style): :class:`TileCodec` (value <-> tile colours, base c,
clockwise from the displaced lower-right tile), :func:`dimension` (tag size, spacing and
the (c, n) Pareto front for a site), :class:`TagField` (placement optimiser, save/load,
PNG/SVG print), :func:`locate_tiles` (detect, decode, reference-map, pose with the IMU's
roll/pitch as a prior) -> :class:`TagFix`.

AprilTag/ArUco boards through ``cv2.aruco``: :class:`ArucoField` and :func:`locate_aruco`,
returning the same :class:`TagFix` (IPPE with both planar solutions scored).

Heavy imports (cv2, scipy) load with the submodules that need them.
"""

from skyfix.tags.codec import TagGeometry, TileCodec
from skyfix.tags.dimensioning import Dimensioning, dimension
from skyfix.tags.field import TagField
from skyfix.tags.placement import PlacementReport, optimise_placement
from skyfix.tags.pose import AttitudePrior, TagFix

__all__ = ["ArucoField", "AttitudePrior", "Dimensioning", "PlacementReport", "TagField", "TagFix",
           "TagGeometry", "TileCodec", "dimension", "locate_aruco", "locate_tiles", "optimise_placement"]


def __getattr__(name: str):
    # cv2-backed entry points import on first use so `import skyfix.tags` stays light.
    if name == "locate_tiles":
        from skyfix.tags.locate import locate_tiles
        return locate_tiles
    if name in ("ArucoField", "locate_aruco"):
        from skyfix.tags import aruco
        return getattr(aruco, name)
    raise AttributeError(f"module 'skyfix.tags' has no attribute {name!r}")
