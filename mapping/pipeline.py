"""Photo-to-model pipeline: geotagged photos -> orthophoto, DSM, point cloud, report.

Stages run in order over one project folder (``out_dir``); each writes its outputs and
a marker ``work/stages/<stage>.json`` (with its time). On a new run a stage whose marker
exists is skipped unless it is forced or an earlier stage ran again, so a run resumes
after a crash or Ctrl-C. Feature extraction and matching keep the pycolmap database
(``work/database.db``) and are never redone once their markers exist (force them with
``force=("features",)``); pycolmap also skips images already in the database.

Stages: ``photos`` (EXIF, rejections, GPS overlap), ``correct`` (optional barrel lens
correction), ``features``, ``matches``, ``mapping`` (pycolmap), ``georef`` (similarity to
GPS in a local ENU frame), ``dsm``, ``ortho``, ``export`` (PLY, GeoJSON, report).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path

from skyfix import validate
from skyfix.camera import Camera
from skyfix.distortion import Barrel
from skyfix.errors import ConfigurationError, InputError, SkyfixError
from skyfix.mapping.export_stage import export_run
from skyfix.mapping.georef_stage import georef_load, georef_run
from skyfix.mapping.photo_stages import correct_load, correct_run, photos_run
from skyfix.mapping.project import STAGES, Project, RunState, stage_options
from skyfix.mapping.report import Report, peak_memory_mib
from skyfix.mapping.sfm_stages import (
    features_run,
    mapping_load,
    mapping_run,
    matches_load,
    matches_run,
)
from skyfix.mapping.surface_stages import dsm_load, dsm_run, ortho_load, ortho_run

__all__ = ["STAGES", "PipelineConfig", "run_pipeline", "stage_options"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PipelineConfig:
    """Everything a run needs; defaults suit 1-12 Mpx survey photos on a laptop."""

    photos_dir: str | os.PathLike
    out_dir: str | os.PathLike
    barrel: Barrel | None = None          # ImageMagick barrel model: photos are corrected first
    calibration: Camera | None = None     # pre-calibrated lens, passed to pycolmap (held fixed)
    shared_lens: tuple | None = ()        # another model's lens per camera group (sfm.model_lenses), held fixed in mapping;
                                          # None: not known yet (scale_out: the lens submodel's task supplies it)
    resolution_cm: float | None = None    # orthophoto pixel; None: the photos' median GSD
    dsm_resolution_m: float | None = None  # DSM cell; None: dense_cell_px matched pixels (sparse: 2x point spacing)
    max_ortho_mpx: float | None = None    # only if asked: raise the pixel size if the orthophoto would be larger
    max_image_size_px: int = 1600         # photos are downscaled to this for features
    max_features: int = 4000              # SIFT features per photo
    exhaustive_max_photos: int = 40       # more photos than this: spatial (GPS neighbour) matching
    spatial_neighbours: int = 12          # GPS neighbours matched per photo in spatial matching
    max_agl_m: float = 120.0              # upper bound of height above ground for the overlap check
    georef_max_error_m: float = 10.0      # RANSAC inlier distance camera centre <-> GPS
    two_view_max_offset_m: float = 5.0    # a photo placed by a two-view model: this close to its GPS horizontally
    two_view_max_vertical_m: float = 12.0  # ... and vertically within 3x the GPS vertical sigma (no priors: host RMS), at most this
    ortho_seams: bool = True              # one photo per pixel, graph-cut seams, gains (False: feathered mean)
    seam_band_px: float = 6.0             # blending band across a seam, orthophoto pixels
    blend_power: float = 2.0              # feathered mean only: exponent of the edge-distance weight
    estimate_gps_lag: bool = True         # estimate the GPS time lag from the model and remove it (reported)
    refine_focal: bool = False            # let bundle adjustment move the focal length (see sfm.reconstruct)
    gps_sigma_m: tuple[float, float] = (2.0, 4.0)  # GPS pose prior std dev (horizontal, vertical); () = no priors
    seed: int = 0                         # pycolmap's random seed: the same photos give the same model
    dense: bool = True                    # DSM from dense stereo matching (False: from the sparse points)
    dense_scale: float = 0.5              # photos are matched at this fraction of their size
    dense_fill_scales: tuple[float, ...] = (0.4, 0.3, 0.2)  # coarser SGBM passes: only cells finer ones left empty
    dense_cell_px: float = 2.0            # DSM cell = this many matched pixels on the ground
    dense_local_norm_px: int = 15         # pixels SGBM leaves empty matched again on locally normalised photos (0: off)
    max_dense_points: int = 5_000_000     # points.ply holds at most this many dense points (stated in the report)
    dsm_fill_max_m2: float = 4.0          # dense DSM: enclosed holes up to this area interpolated, in dsm_interpolated.tif
    threads: int = -1                     # -1: all cores
    sfm_threads: int = 1                  # structure from motion's registration and adjustment threads: 1 repeats exactly
    match_threads: int = 1                # feature matching threads: 1 repeats exactly
    force: tuple[str, ...] = ()           # stages to re-run even when their outputs exist
    stop_after: str | None = None         # end the run after this stage (a later run resumes from its marker)

    def __post_init__(self) -> None:
        if self.barrel is not None and self.calibration is not None:
            raise ConfigurationError("give either barrel= (correct photos) or calibration= (pass the lens "
                                     "model to pycolmap), not both")
        if self.calibration is not None and self.shared_lens:
            raise ConfigurationError("give either calibration= or shared_lens=, not both")
        unknown = set(self.force) - set(STAGES)
        if unknown:
            raise ConfigurationError(f"force names unknown stage(s) {sorted(unknown)}; stages are {list(STAGES)}")
        if self.stop_after is not None and self.stop_after not in STAGES:
            raise ConfigurationError(f"stop_after names unknown stage {self.stop_after!r}; stages are {list(STAGES)}")
        if not 0.05 <= self.dense_scale <= 1.0:
            raise InputError(f"dense_scale must be in [0.05, 1], got {self.dense_scale!r}")
        if any(not 0.05 <= f < self.dense_scale for f in self.dense_fill_scales):
            raise InputError(f"dense_fill_scales must each be in [0.05, dense_scale), got {self.dense_fill_scales!r}")
        if not (self.dense_local_norm_px == 0 or 3 <= self.dense_local_norm_px <= 255):
            raise InputError(f"dense_local_norm_px must be 0 (off) or in [3, 255] px, got {self.dense_local_norm_px!r}")
        for name in ("threads", "sfm_threads", "match_threads"):  # COLMAP aborts the process on 0 or below -1
            if getattr(self, name) == 0 or getattr(self, name) < -1:
                raise InputError(f"{name} must be -1 (all cores) or at least 1, got {getattr(self, name)!r}")
        for name in ("resolution_cm", "dsm_resolution_m", "max_ortho_mpx"):
            v = getattr(self, name)
            if v is not None:
                validate.positive_scalar(name, v)


def run_pipeline(config: PipelineConfig) -> Report:
    """Run (or resume) the pipeline; returns the :class:`Report` also saved as ``report.json``.

    Raises :class:`InputError` for a missing/empty photo folder and :class:`DataError` when
    no photo is usable or nothing reconstructs; the report written so far says why.
    """
    import cv2

    start = time.perf_counter()
    out = Path(config.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    project = Project(out)
    report = Report(str(config.photos_dir), str(out))
    if config.threads > 0:
        cv2.setNumThreads(config.threads)
    state = RunState()
    dirty = False
    try:
        for stage in STAGES:
            marker = project.marker(stage)
            options = stage_options(config, stage)
            changed = marker is not None and marker.get("options") != options
            if changed:
                log.info("stage %s runs again: its options changed since the last run (%s)", stage,
                         ", ".join(k for k in options if (marker.get("options") or {}).get(k) != options[k]))
            rerun = stage in config.force or marker is None or changed or \
                (dirty and stage not in ("features", "matches"))
            if stage == "photos":
                rerun = True  # cheap, and later stages need the photo list
            if not rerun:
                report.stage_seconds[stage] = marker.get("seconds", 0.0)
                report.resumed_stages.append(stage)
                _STAGE_LOAD[stage](config, project, state, report, marker)
                if stage == config.stop_after:
                    break
                continue
            t0 = time.perf_counter()
            log.info("stage %s", stage)
            if marker is not None and stage in ("features", "matches"):
                project.reset_database(stage)
            data = _STAGE_RUN[stage](config, project, state, report) or {}
            data["seconds"] = time.perf_counter() - t0
            data["options"] = options
            if stage != "photos":
                dirty = True
            elif marker is not None and marker.get("names") != data.get("names"):
                log.info("the photo set changed since the last run: every stage runs again")
                project.clear_from("correct")
                config = dataclasses.replace(config, force=STAGES)
            project.mark(stage, data)
            report.stage_seconds[stage] = data["seconds"]
            if stage == config.stop_after:
                break
    except SkyfixError as exc:
        report.error = str(exc)
        raise
    finally:
        report.total_seconds = time.perf_counter() - start
        report.peak_memory_mib = peak_memory_mib()
        report.save_json(project.report_json)
    return report


def _noop_load(config, project, state, report, marker) -> None:
    return None


# One module per stage family, each stage's entry points: run (returns marker data) and load.
_STAGE_RUN = {"photos": photos_run, "correct": correct_run, "features": features_run,
              "matches": matches_run, "mapping": mapping_run, "georef": georef_run, "dsm": dsm_run,
              "ortho": ortho_run, "export": export_run}
_STAGE_LOAD = {"photos": _noop_load, "correct": correct_load, "features": _noop_load,
               "matches": matches_load, "mapping": mapping_load, "georef": georef_load, "dsm": dsm_load,
               "ortho": ortho_load, "export": _noop_load}
