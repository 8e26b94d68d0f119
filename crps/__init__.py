"""skyfix.crps: collaborative relative positioning (drone-to-drone monocular ranging).

Pipeline: a detector (:class:`SilhouetteDetector` for a drone against sky or smooth
ground, :class:`MarkerDetector` for a marker on the drone, :class:`BoxDetector` for a
user's own model) finds the target in pixels; :class:`Tracker` follows it with a region
of interest; :class:`SilhouetteFit` re-measures small silhouettes by fitting the drone
model to the pixels; :func:`prior_window`/:func:`prior_gate` restrict a directed search to
where the help request puts the target; :class:`GroundMotionFilter` drops detections that
move with the ground over a sequence (terrain backgrounds); :func:`observe` turns a detection into a :class:`skyfix.types.RelativeObservation`
(bearing in ENU, range, covariance) and :func:`locate` fuses several helpers' observations
into a :class:`skyfix.types.GeoFix`.

Names are imported on first use so that ``skyfix --help`` does not load OpenCV.
"""

from __future__ import annotations

from skyfix.lazy import lazy_exports

_EXPORTS = {
    "BoxDetector": "detection", "Detection": "detection", "Detector": "detection", "to_gray": "detection",
    "GroundCheck": "ground", "GroundMotionConfig": "ground", "GroundMotionFilter": "ground",
    "FitState": "fit", "SilhouetteFit": "fit", "SilhouetteFitConfig": "fit",
    "PriorWindow": "prior", "prior_gate": "prior", "prior_window": "prior",
    "MarkerDetector": "marker",
    "DroneModel": "model", "ShapeTable": "model", "shape_table": "model",
    "angular_jacobian": "observation", "locate": "observation", "observe": "observation", "shape_consistent": "observation",
    "range_from_reference": "ranging", "range_from_size": "ranging",
    "SilhouetteConfig": "silhouette", "SilhouetteDetector": "silhouette", "estimate_noise_sigma": "silhouette",
    "Tracker": "track", "TrackerConfig": "track",
}

__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)
