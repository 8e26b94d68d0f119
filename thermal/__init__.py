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

from __future__ import annotations

from skyfix.lazy import lazy_exports

_EXPORTS = {
    "DEFAULT_KELVIN_PER_COUNT": "detect", "DEFAULT_THRESHOLD_C": "detect", "Hotspot": "detect",
    "RelativeTemperatureWarning": "detect", "detect_hotspots": "detect",
    "geolocate": "geolocate", "geolocate_many": "geolocate", "locate_in_frame": "geolocate",
    "DemGround": "ground", "FlatGround": "ground",
    "JointSolution": "joint", "PoseErrorPrior": "joint", "locate_jointly": "joint",
    "PALETTES": "palettes", "apply_palette": "palettes", "palette_to_intensity": "palettes",
    "PoseUncertainty": "pose", "camera_pose": "pose",
    "PoseLog": "poselog",
    "Sightings": "sightings", "associate": "sightings",
    "Fire": "tracker", "FireTracker": "tracker", "TrackerSettings": "tracker",
}

__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)
