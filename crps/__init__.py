"""skyfix.crps: collaborative relative positioning (drone-to-drone monocular ranging).

Pipeline: a detector (:class:`SilhouetteDetector` for a drone against sky or smooth
ground, :class:`MarkerDetector` for a marker on the drone, :class:`BoxDetector` for a
user's own model) finds the target in pixels; :class:`Tracker` follows it with a region
of interest; :func:`observe` turns a detection into a :class:`skyfix.types.RelativeObservation`
(bearing in ENU, range, covariance) and :func:`locate` fuses several helpers' observations
into a :class:`skyfix.types.GeoFix`.
"""

from skyfix.crps.detection import BoxDetector, Detection, Detector, to_gray
from skyfix.crps.marker import MarkerDetector
from skyfix.crps.model import DroneModel, ShapeTable, shape_table
from skyfix.crps.observe import angular_jacobian, locate, observe
from skyfix.crps.ranging import range_from_reference, range_from_size
from skyfix.crps.silhouette import SilhouetteConfig, SilhouetteDetector, estimate_noise_sigma
from skyfix.crps.track import Tracker, TrackerConfig

__all__ = ["BoxDetector", "Detection", "Detector", "DroneModel", "MarkerDetector", "ShapeTable",
           "SilhouetteConfig", "SilhouetteDetector", "Tracker", "TrackerConfig", "angular_jacobian",
           "estimate_noise_sigma", "locate", "observe", "range_from_reference", "range_from_size",
           "shape_table", "to_gray"]
