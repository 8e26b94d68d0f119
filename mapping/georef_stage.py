"""The pipeline's ``georef`` stage (see :mod:`skyfix.mapping.pipeline`): each model's
similarity to GPS in a local ENU frame, GPS lag, two-view models attached to their hosts.
"""

from __future__ import annotations

import math
import shutil
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from skyfix.mapping.pipeline import PipelineConfig
    from skyfix.mapping.project import Project, RunState
    from skyfix.mapping.report import Report

__all__ = ['georef_load', 'georef_run']


def georef_run(config: PipelineConfig, project: Project, state: RunState, report: Report) -> dict:
    from skyfix.mapping.georef import georeference, survey_frame

    if project.georef.exists():
        shutil.rmtree(project.georef)
    from skyfix.mapping.gps_lag import gps_velocities

    models = state.models
    frame = survey_frame(state.photos)
    velocities = gps_velocities(state.photos, frame) if frame is not None and config.estimate_gps_lag else {}
    state.velocities = velocities
    results = []
    for i, rec in enumerate(models):
        if frame is None:
            from skyfix.mapping.georef import ModelGeoref

            results.append(ModelGeoref(i, rec.num_reg_images(), False, "no photo has GPS; model left unreferenced"))
        else:
            results.append(georeference(rec, state.photos, frame, i, max_error_m=config.georef_max_error_m,
                                        velocities=velocities))
        rec.write(str(project.georef_model(i)))
    state.frame = frame
    rejected = _attach_pairs(config, project, state, results)
    data = {"frame": None if frame is None else [frame.lat0_deg, frame.lon0_deg, frame.alt0_m],
            "models": [r.to_dict() for r in results], "two_view_rejected": rejected}
    georef_load(config, project, state, report, data)
    return data


def _attach_pairs(config: PipelineConfig, project: Project, state: RunState, results: list) -> list[str]:
    """Two-view models anchored on georeferenced main models; accepted ones are appended to
    ``results`` and written as further models, rejected ones only return their reason."""
    from skyfix.mapping.georef import attach_pair

    models, frame, rejected = state.models, state.frame, []
    for pair_rec, pair in state.pairs:
        host = next((i for i, rec in enumerate(models[:len(results)]) if results[i].georeferenced
                     and any(im.name == pair.partner and im.has_pose for im in rec.images.values())), None)
        if frame is None or host is None:
            rejected.append(f"{pair.photo}: partner {pair.partner} is in no georeferenced model; not placed")
            continue
        lag = results[host].gps_lag
        shift = {n: lag["lag_s"] * v for n, v in state.velocities.items()} if lag.get("applied") else None
        found = attach_pair(pair_rec, models[host], results[host], pair, state.photos, frame, len(results),
                            max_offset_m=config.two_view_max_offset_m,
                            max_vertical_m=config.two_view_max_vertical_m, gps_shift_enu=shift,
                            prior_sigma_vertical_m=config.gps_sigma_m[1] if _priors_used(config, state) else None)
        if not found.georeferenced:
            rejected.append(found.reason)
            continue
        results.append(found)
        pair_rec.write(str(project.georef_model(found.model_index)))
    return rejected


def _priors_used(config: PipelineConfig, state: RunState) -> bool:
    """Whether mapping adjusted with GPS pose priors (the condition of sfm_stages.mapping_run)."""
    return bool(config.gps_sigma_m) and sum(p.has_gps for p in state.photos) >= 3


def georef_load(config: PipelineConfig, project: Project, state: RunState, report: Report, marker: dict) -> None:
    from skyfix.geo import LocalFrame
    from skyfix.mapping import sfm

    state.models = sfm.load_models(project.georef)
    state.frame = None if marker["frame"] is None else LocalFrame(*marker["frame"])
    _summarise_models(state, report)
    report.models = marker["models"]
    report.registered_two_view = [m["two_view"] for m in marker["models"] if m.get("two_view")]
    report.warnings.extend(marker.get("two_view_rejected", []))
    referenced = [m for m in marker["models"] if m["georeferenced"]]
    report.georeferenced = bool(referenced)
    report.gps_lag = next((m["gps_lag"] for m in referenced if m.get("gps_lag")), {})
    for m in marker["models"]:
        if not m["georeferenced"]:
            report.warnings.append(f"model {m['model']} ({m['registered']} photos) not georeferenced: {m['reason']}")
    mapped = [m for m in marker["models"] if not m.get("two_view")]
    if len(mapped) > 1:
        report.warnings.append(f"mapping produced {len(mapped)} models; georeferenced ones are merged in the outputs")
    if referenced:
        res = np.array([r for m in referenced for r in m["residuals_enu_m"].values()])
        report.georef_rms_m = float(np.sqrt((res ** 2).sum(axis=1).mean()))
        report.georef_rms_horizontal_m = float(np.sqrt((res[:, :2] ** 2).sum(axis=1).mean()))
    state.referenced = [state.models[m["model"]] for m in referenced]
    state.unreferenced = [state.models[m["model"]] for m in marker["models"] if not m["georeferenced"]]


def _summarise_models(state: RunState, report: Report) -> None:
    models = state.models
    registered = sorted({im.name for rec in models for im in rec.images.values() if im.has_pose})
    report.registered = registered
    report.unregistered = sorted(set(report.photos_used) - set(registered))
    errors = [rec.compute_mean_reprojection_error() for rec in models]
    weights = [rec.compute_num_observations() for rec in models]
    report.mean_reprojection_error_px = float(np.average(errors, weights=weights)) if sum(weights) else math.nan
    report.points = int(sum(rec.num_points3D() for rec in models))
