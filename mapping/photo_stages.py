"""The pipeline's photo stages (see :mod:`skyfix.mapping.pipeline`): ``photos`` (EXIF,
rejections, camera groups, GPS overlap) and ``correct`` (optional barrel lens correction).
Each ``*_run`` returns its marker data; ``*_load`` restores the state from a marker.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING

from skyfix.errors import DataError
from skyfix.mapping.photos import Photo, camera_groups, check_gps_overlap, load_photos

if TYPE_CHECKING:
    from skyfix.mapping.pipeline import PipelineConfig
    from skyfix.mapping.project import Project, RunState
    from skyfix.mapping.report import Report

__all__ = ['correct_load', 'correct_run', 'photos_run']


def photos_run(config: PipelineConfig, project: Project, state: RunState, report: Report) -> dict:
    photos, rejected = load_photos(config.photos_dir)
    report.photos_found = len(photos) + len(rejected)
    report.rejected = [{"photo": r.name, "reason": r.reason} for r in rejected]
    report.warnings += [f"rejected {r.name}: {r.reason}" for r in rejected]
    if not photos:
        raise DataError(f"none of the {len(rejected)} photo(s) in {config.photos_dir} is usable: "
                        + "; ".join(f"{r.name}: {r.reason}" for r in rejected[:5]))
    groups = camera_groups(photos)
    report.camera_groups = [{"make": k[0], "model": k[1], "width": k[2], "height": k[3], "focal_px": k[4],
                             "focal_source": v[0].focal_source, "focal_refined": config.refine_focal,
                             "photos": len(v)} for k, v in groups.items()]
    for k, v in groups.items():
        if v[0].focal_source == "35mm-equivalent" and max(k[2], k[3]) / min(k[2], k[3]) > 1.6:
            report.warnings.append(f"{k[0]} {k[1]}: focal length from the 35 mm equivalent of a {k[2]}x{k[3]} "
                                   "frame; if it is cropped from the sensor this is 4-5 % short and every height "
                                   "above ground with it (give a lens calibration)")
    if len(groups) > 1:
        report.warnings.append(f"mixed cameras: {len(groups)} camera models, each with its own calibration")
    report.without_gps = [p.name for p in photos if not p.has_gps]
    if report.without_gps:
        report.warnings.append(f"{len(report.without_gps)} photo(s) without GPS in EXIF reconstruct but are not "
                               "used for georeferencing")
    overlap = check_gps_overlap(photos, config.max_agl_m)
    report.isolated_by_gps = overlap.isolated
    if overlap.isolated:
        report.warnings.append(f"{len(overlap.isolated)} photo(s) cannot overlap any other photo by GPS "
                               f"(even {config.max_agl_m:.0f} m above ground): {', '.join(overlap.isolated[:10])}")
    report.photos_used = [p.name for p in photos]
    state.photos = photos
    state.image_dir = Path(config.photos_dir)
    return {"names": report.photos_used, "photos": [dataclasses.asdict(p) for p in photos]}


def correct_run(config: PipelineConfig, project: Project, state: RunState, report: Report) -> dict:
    if config.barrel is None:
        state.image_dir = Path(config.photos_dir)
        return {"corrected": False}
    from skyfix.mapping.batch import CorrectionSpec, correct_photos

    result = correct_photos([p.path for p in state.photos], project.corrected,
                            CorrectionSpec(barrel=config.barrel), workers=None if config.threads < 1 else
                            config.threads, progress=False)
    focal = {Path(r.source).name: r.output_camera for r in result.written}
    kept = []
    for p in state.photos:
        cam = focal.get(p.name)
        if cam is None:
            reason = next(r.error for r in result.skipped if Path(r.source).name == p.name)
            report.rejected.append({"photo": p.name, "reason": f"lens correction failed: {reason}"})
            continue
        kept.append(dataclasses.replace(p, path=str(project.corrected / p.name), width=cam["width"],
                                        height=cam["height"], focal_px=cam["fx_px"] or p.focal_px))
    state.photos, state.image_dir = kept, project.corrected
    report.photos_used = [p.name for p in kept]
    return {"corrected": True, "photos": [dataclasses.asdict(p) for p in kept]}


def correct_load(config: PipelineConfig, project: Project, state: RunState, report: Report, marker: dict) -> None:
    if marker.get("corrected"):
        state.photos = [Photo(**d) for d in marker["photos"]]
        state.image_dir = project.corrected
        report.photos_used = [p.name for p in state.photos]
    else:
        state.image_dir = Path(config.photos_dir)
