"""The pipeline's structure-from-motion stages (see :mod:`skyfix.mapping.pipeline`):
``features``, ``matches`` and ``mapping`` over pycolmap (:mod:`skyfix.mapping.sfm`).
Each ``*_run`` returns its marker data; ``*_load`` restores the state from a marker.
"""

from __future__ import annotations

import dataclasses
import shutil
from typing import TYPE_CHECKING

from skyfix.errors import DataError

if TYPE_CHECKING:
    from skyfix.mapping.pipeline import PipelineConfig
    from skyfix.mapping.project import Project, RunState
    from skyfix.mapping.report import Report

__all__ = ['features_run', 'mapping_load', 'mapping_run', 'matches_load', 'matches_run']


def features_run(config: PipelineConfig, project: Project, state: RunState, report: Report) -> dict:
    from skyfix.mapping import sfm

    sfm.extract(project.database, state.image_dir, state.photos, calibration=config.calibration,
                max_image_size_px=config.max_image_size_px, max_features=config.max_features,
                threads=config.threads)
    return {"database": str(project.database)}


def matches_run(config: PipelineConfig, project: Project, state: RunState, report: Report) -> dict:
    from skyfix.mapping import sfm

    report.matching = sfm.match(project.database, state.photos, exhaustive_max_photos=config.exhaustive_max_photos,
                                neighbours=config.spatial_neighbours, seed=config.seed, threads=config.match_threads)
    return {"method": report.matching}


def matches_load(config: PipelineConfig, project: Project, state: RunState, report: Report, marker: dict) -> None:
    report.matching = marker.get("method", "")


def mapping_run(config: PipelineConfig, project: Project, state: RunState, report: Report) -> dict:
    from skyfix.mapping import sfm

    if project.sparse.exists():
        shutil.rmtree(project.sparse)
    from skyfix.mapping.georef import survey_frame

    frame = survey_frame(state.photos)
    priors = 0
    if frame is not None and config.gps_sigma_m:
        priors = sfm.set_pose_priors(project.database, state.photos, frame, config.gps_sigma_m)
    if config.shared_lens:  # split-merge: every submodel with one lens, or their overlaps disagree
        sfm.set_lenses(project.database, state.photos, config.shared_lens)
    models = sfm.reconstruct(project.database, state.image_dir, project.sparse,
                             calibrated=config.calibration is not None or bool(config.shared_lens),
                             refine_focal=config.refine_focal,
                             pose_priors=priors >= 3, seed=config.seed, sfm_threads=config.sfm_threads)
    if not models:
        raise DataError("structure from motion reconstructed nothing: the photos share too few features "
                        "(do they overlap? are they sharp?)")
    registered = {im.name for rec in models for im in rec.images.values() if im.has_pose}
    unregistered = {p.name for p in state.photos if p.has_gps} - registered
    state.models = models
    state.pairs = sfm.pair_models(project.database, state.image_dir, project.pairs, unregistered,
                                     models, seed=config.seed, sfm_threads=config.sfm_threads) if unregistered else []
    return {"models": len(models), "pairs": [dataclasses.asdict(pair) for _, pair in state.pairs]}


def mapping_load(config: PipelineConfig, project: Project, state: RunState, report: Report, marker: dict) -> None:
    from skyfix.mapping import sfm

    state.models = sfm.load_models(project.sparse)
    pair_recs = sfm.load_models(project.pairs)
    state.pairs = [(rec, sfm.PairModel(**d)) for rec, d in zip(pair_recs, marker.get("pairs", []), strict=True)]
