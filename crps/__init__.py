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

import importlib
from typing import Any

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

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        value = getattr(importlib.import_module(f"skyfix.crps.{_EXPORTS[name]}"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'skyfix.crps' has no attribute {name!r}")


def __dir__() -> list[str]:
    return __all__
