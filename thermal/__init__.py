"""skyfix.thermal: fire hotspots in thermal frames, where they are on the ground, and
how they evolve over a flight.

- :func:`detect_hotspots` — 8-bit (white/black-hot, colour palettes), 16-bit
  radiometric counts or float deg C frames -> :class:`Hotspot` list.
- :func:`geolocate` / :func:`geolocate_many` — hotspot + camera + pose + ground ->
  :class:`~skyfix.types.GeoFix` with a covariance from :class:`PoseUncertainty`.
- :class:`FlatGround` / :class:`DemGround` — the ground, with its datum explicit.
- :func:`camera_pose` — a pose with altitude datum and gimbal-yaw reference named.
- :class:`FireTracker` — frames over time -> fused :class:`Fire` list.
- :func:`associate` + :func:`locate_jointly` — a whole flight's sightings and its
  :class:`PoseLog` -> fires, boresight and camera clock offset, with the pose errors
  drones have (:class:`PoseErrorPrior`: correlated GNSS, attitude drift).
"""

from skyfix.thermal.detect import (
    DEFAULT_KELVIN_PER_COUNT,
    DEFAULT_THRESHOLD_C,
    Hotspot,
    RelativeTemperatureWarning,
    detect_hotspots,
)
from skyfix.thermal.geolocate import geolocate, geolocate_many, locate_in_frame
from skyfix.thermal.ground import DemGround, FlatGround
from skyfix.thermal.joint import JointSolution, PoseErrorPrior, locate_jointly
from skyfix.thermal.palettes import PALETTES, apply_palette, palette_to_intensity
from skyfix.thermal.pose import PoseUncertainty, camera_pose
from skyfix.thermal.poselog import PoseLog
from skyfix.thermal.sightings import Sightings, associate
from skyfix.thermal.tracker import Fire, FireTracker, TrackerSettings

__all__ = [
    "DEFAULT_KELVIN_PER_COUNT", "DEFAULT_THRESHOLD_C", "PALETTES", "DemGround", "Fire",
    "FireTracker", "FlatGround", "Hotspot", "JointSolution", "PoseErrorPrior", "PoseLog",
    "PoseUncertainty", "RelativeTemperatureWarning", "Sightings", "TrackerSettings", "apply_palette",
    "associate", "camera_pose", "detect_hotspots", "geolocate", "geolocate_many", "locate_in_frame",
    "locate_jointly", "palette_to_intensity",
]
