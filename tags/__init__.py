"""skyfix.tags: fiducial floor tags for localising a drone with a downward camera.

Coloured-tile tags (FlyZone-style): :class:`TileCodec` (value <-> tile colours, base c,
clockwise from the displaced lower-right tile), :func:`dimension` (tag size, spacing and
the (c, n) Pareto front for a site), :class:`TagField` (placement optimiser, save/load,
PNG/SVG print), :func:`locate_tiles` (detect, decode, reference-map, pose with the IMU's
roll/pitch as a prior) -> :class:`TagFix`.

AprilTag/ArUco boards through ``cv2.aruco``: :class:`ArucoField` and :func:`locate_aruco`,
returning the same :class:`TagFix` (IPPE with both planar solutions scored).

Every name loads its module (and OpenCV, scipy) on first use.
"""

from skyfix.lazy import lazy_exports

# Names are imported on first use, so `import skyfix.tags` (and `skyfix --help`) stays light.
__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "TagGeometry": "codec", "TileCodec": "codec", "Dimensioning": "dimensioning", "dimension": "dimensioning",
    "TagField": "field", "PlacementReport": "placement", "optimise_placement": "placement",
    "AttitudePrior": "pose", "TagFix": "pose", "locate_tiles": "locate", "ArucoField": "aruco",
    "locate_aruco": "aruco",
})
