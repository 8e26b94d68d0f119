"""skyfix.mapping: lens models and correction, camera calibration, survey planning.

Public names are loaded on first use (so ``skyfix --help`` does not import OpenCV or
shapely through this package):

- lens models: :data:`BarrelModel` (ImageMagick ``-distort barrel``), ``BrownConrady``,
  ``Fisheye``, :func:`barrel_to_opencv`, :func:`opencv_to_barrel` (module ``lens``);
- correction: :class:`Undistortion` (``correct``), :func:`correct_photos` and
  :class:`CorrectionSpec` (``batch``), EXIF in ``exif``, a torch/kornia backend in
  ``remap_torch``;
- calibration: :func:`calibrate`, :class:`BoardSpec` (``calibrate``, ``board``);
- surveys: :func:`plan_survey`, :func:`plan_three_corners`, :func:`plan_polygon`,
  :func:`extend_survey` (``survey``), :func:`split_survey`, :func:`handoff` (``split``),
  :func:`verify_coverage` (``coverage``), :func:`mission_items` (of the foundation's :class:`~skyfix.mission.MissionItem`)
  (``mission``), file writers in ``export``;
- photo-to-model pipeline: :func:`run_pipeline`, :class:`PipelineConfig`, :class:`Report`
  (``pipeline``, ``report``; the project folder's files in ``project``; the stages in
  ``photo_stages``, ``sfm_stages``, ``georef_stage``, ``surface_stages``, ``export_stage`` over
  ``photos``, ``sfm``, ``georef``, ``dsm``, ``ortho``, ``grid``, ``geotiff``, ``model_files``);
- camera files: :func:`load_camera`, :func:`save_camera` (the foundation's
  :mod:`skyfix.camera_io`, re-exported here).
"""

from __future__ import annotations

from skyfix.lazy import lazy_exports

_EXPORTS = {
    "BarrelModel": "lens", "BrownConrady": "lens", "Fisheye": "lens", "barrel_camera": "lens",
    "barrel_to_opencv": "lens", "opencv_to_barrel": "lens", "parse_barrel": "lens",
    "Undistortion": "correct", "CorrectionSpec": "batch", "correct_photos": "batch",
    "read_metadata": "exif", "BoardSpec": "board", "Calibration": "calibrate", "calibrate": "calibrate",
    "SurveyPlan": "survey", "SurveyPart": "survey", "plan_survey": "survey", "plan_three_corners": "survey",
    "plan_polygon": "survey", "extend_survey": "survey", "split_survey": "split", "handoff": "split",
    "verify_coverage": "coverage", "MissionItem": "skyfix.mission", "mission_items": "mission",
    "load_camera": "skyfix.camera_io", "save_camera": "skyfix.camera_io",
    "PipelineConfig": "pipeline", "run_pipeline": "pipeline", "Report": "report", "load_photos": "photos",
}

__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)
