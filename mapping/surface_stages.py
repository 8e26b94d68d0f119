"""The pipeline's surface stages (see :mod:`skyfix.mapping.pipeline`): ``dsm`` (dense or
sparse surface model on a UTM grid, flying-height check) and ``ortho`` (orthomosaic at the
photos' GSD). Each ``*_run(config, project, state, report)`` returns its marker data and
each ``*_load(..., marker)`` restores the state and report from it; files by the
:class:`~skyfix.mapping.project.Project`'s names only.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from skyfix.errors import DataError

if TYPE_CHECKING:
    from skyfix.mapping.pipeline import PipelineConfig
    from skyfix.mapping.project import Project, RunState
    from skyfix.mapping.report import Report

__all__ = ["dsm_load", "dsm_run", "median_gsd_m", "ortho_load", "ortho_run", "points", "valid_share"]


def points(models: list, max_error_px: float = 2.0, min_track: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) xyz and (N, 3) uint8 colours of well-measured points of ``models``."""
    xyz, rgb = [], []
    for rec in models:
        for p in rec.points3D.values():
            if p.error <= max_error_px and p.track.length() >= min_track:
                xyz.append(p.xyz)
                rgb.append(p.color)
    if not xyz:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    return np.array(xyz, dtype=np.float64), np.array(rgb, dtype=np.uint8)


def dsm_run(config: PipelineConfig, project: Project, state: RunState, report: Report) -> dict:
    from skyfix.mapping.dsm import auto_dsm_resolution_m, build_dsm, enclosed_holes
    from skyfix.mapping.geotiff import write_dsm_tif, write_mask_tif
    from skyfix.mapping.grid import Grid, enu_to_utm, utm_epsg

    if not state.referenced:
        report.warnings.append("no georeferenced model: DSM and orthophoto skipped")
        state.dsm = None
        return {"skipped": True}
    frame = state.frame
    xyz, _ = points(state.referenced)
    if len(xyz) < 3:
        raise DataError(f"only {len(xyz)} well-measured 3-D points; a DSM needs more")
    epsg = utm_epsg(frame.lat0_deg, frame.lon0_deg)
    utm = enu_to_utm(frame, xyz, epsg)
    lo, hi = utm[:, :2].min(axis=0), utm[:, :2].max(axis=0)
    extra = {}
    if config.dense:
        dsm, extra = _dense(config, project, state, xyz, epsg)
        grid = dsm.grid
    else:
        res_m = config.dsm_resolution_m or auto_dsm_resolution_m(utm)
        grid = Grid.covering(epsg, lo[0], lo[1], hi[0], hi[1], res_m)
        dsm = build_dsm(utm, grid)
    written, area = dsm.surface_m, extra.pop("stereo_area", None)
    if config.dense:  # small enclosed holes interpolated in the file, and marked
        holes = enclosed_holes(dsm.observed, int(config.dsm_fill_max_m2 / grid.resolution_m ** 2))
        written = np.where(holes, dsm.filled_m, dsm.surface_m)
        write_mask_tif(project.dsm_interpolated_tif, holes, grid,
                       f"1: height interpolated in an enclosed hole of at most {config.dsm_fill_max_m2:g} m2")
        extra["interpolated_share"] = valid_share(holes, area)
    write_dsm_tif(project.dsm_tif, written, grid)
    np.save(project.dsm_filled, dsm.filled_m)
    np.save(project.dsm_surface, dsm.surface_m)
    from skyfix.mapping.height_check import flying_height

    check = flying_height(state.referenced, state.photos, frame, dsm)
    data = {"grid": grid.to_dict(), "points": len(xyz), "flying_height": check.to_dict(),
            "flying_height_suspicious": check.suspicious(), "valid_share": valid_share(dsm.observed, area), **extra}
    dsm_load(config, project, state, report, data)
    return data


def valid_share(observed: np.ndarray, area: np.ndarray | None = None) -> float:
    """Share of the cells inside the surveyed ``area`` (default: the convex hull of the
    measured cells) that hold a measured height (not interpolated)."""
    import cv2

    if area is not None:
        return float(observed[area].mean()) if area.any() else 0.0
    rows, cols = np.nonzero(observed)
    if len(rows) < 3:
        return 0.0
    hull = cv2.convexHull(np.stack((cols, rows), axis=1).astype(np.int32))
    area = np.zeros(observed.shape, np.uint8)
    cv2.fillConvexPoly(area, hull, 1)
    return float(observed[area > 0].mean())


def _dense(config: PipelineConfig, project: Project, state: RunState, sparse_enu: np.ndarray, epsg: int) -> tuple:
    """Dense DSM (mapping.dense) on a grid of ``dense_cell_px`` matched pixels; saves the cloud."""
    from skyfix.mapping.dense import dense_dsm, stereo_area
    from skyfix.mapping.grid import EnuToUtm, Grid
    from skyfix.mapping.ortho import load_views

    views = load_views(state.referenced, state.image_dir)
    up = (float(np.percentile(sparse_enu[:, 2], 1)) - 20.0, float(np.percentile(sparse_enu[:, 2], 99)) + 20.0)
    lo, hi = sparse_enu[:, :2].min(axis=0), sparse_enu[:, :2].max(axis=0)
    to_utm = EnuToUtm(state.frame, epsg, (lo[0], lo[1], hi[0], hi[1]), up)
    gsd_m = median_gsd_m(state.referenced, state.frame, None, float(np.median(sparse_enu[:, 2])))
    res_m = config.dsm_resolution_m or gsd_m / config.dense_scale * config.dense_cell_px
    utm = to_utm(sparse_enu)
    grid = Grid.covering(epsg, *utm[:, :2].min(axis=0), *utm[:, :2].max(axis=0), res_m)
    dsm, cloud = dense_dsm(views, {v.name: v.path for v in views}, sparse_enu, to_utm, grid,
                           scale=config.dense_scale, fill_scales=tuple(config.dense_fill_scales),
                           local_norm_px=config.dense_local_norm_px,
                           max_points=config.max_dense_points, seed=config.seed)
    np.savez(project.dense_points, xyz=cloud.xyz_utm_m, rgb=cloud.rgb)
    ground_up_m = float(np.median(sparse_enu[:, 2]))
    area = stereo_area(views, grid, to_utm, ground_up_m)
    # What the measure can reach: cells both photos of a tried pair see (ground seen only by
    # photos of different models, or with too short/long a baseline, has no pair).
    matchable = stereo_area(views, grid, to_utm, ground_up_m, pairs=list(cloud.candidates)) & area
    return dsm, {"stereo_area": area, "valid_area": "cells inside the footprints of two or more photos",
                 "matchable_share": valid_share(matchable, area),
                 "valid_share_of_matchable": valid_share(dsm.observed, matchable),
                 "dense_points": len(cloud.xyz_utm_m), "dense_pairs": cloud.pairs, "dense_scale": cloud.scale,
                 "dense_pairs_dropped": list(cloud.dropped), "dense_fills": list(cloud.fills),
                 "enu_to_utm_max_residual_m": to_utm.max_residual_m}


def dsm_load(config: PipelineConfig, project: Project, state: RunState, report: Report, marker: dict) -> None:
    from skyfix.mapping.dsm import Dsm
    from skyfix.mapping.grid import Grid

    if marker.get("skipped"):
        state.dsm = None
        return
    grid = Grid(**marker["grid"])
    surface = np.load(project.dsm_surface)
    state.dsm = Dsm(grid, surface, np.load(project.dsm_filled), np.isfinite(surface))
    report.crs_epsg = grid.epsg
    report.dsm_resolution_m = grid.resolution_m
    report.flying_height = marker.get("flying_height", {})
    report.dsm_valid_share = marker.get("valid_share", math.nan)
    report.dsm_interpolated_share = marker.get("interpolated_share", 0.0)
    report.dsm_matchable_share = marker.get("matchable_share", math.nan)
    if marker.get("interpolated_share"):
        report.outputs["dsm_interpolated"] = str(project.dsm_interpolated_tif)
    report.dense_points = marker.get("dense_points", 0)
    report.dense_pairs = marker.get("dense_pairs", 0)
    if marker.get("dense_pairs_dropped"):
        report.warnings.append("dense pairs left out of the DSM, their heights off the other pairs' (wrong relative "
                               "pose or a repetitive-texture false match): " + ", ".join(marker["dense_pairs_dropped"]))
    if marker.get("flying_height_suspicious"):
        report.warnings.append(report.flying_height["line"] + ": the model's heights are probably wrong (focal "
                               "length?) unless the take-off point was that far above or below the ground surveyed")
    report.outputs["dsm"] = str(project.dsm_tif)


def median_gsd_m(models: list, frame, dsm, ground_up: float | None = None) -> float:
    """Median ground sample distance: height above the median DSM height (or ``ground_up``,
    ENU metres) / focal length."""
    if ground_up is None:  # measured cells only: filled ones are interpolations
        ground_up = float(np.nanmedian(dsm.surface_m)) - frame.alt0_m
    gsd = []
    for rec in models:
        for image in rec.images.values():
            if image.has_pose:
                cam = rec.cameras[image.camera_id]
                gsd.append((image.projection_center()[2] - ground_up) / cam.mean_focal_length())
    return float(np.median(gsd))


def ortho_run(config: PipelineConfig, project: Project, state: RunState, report: Report) -> dict:
    from skyfix.mapping.geotiff import write_orthophoto_tif
    from skyfix.mapping.grid import Grid, UtmToEnu, enu_to_utm
    from skyfix.mapping.model_files import write_preview_png
    from skyfix.mapping.ortho import load_views, orthomosaic

    dsm = state.dsm
    if dsm is None:
        return {"skipped": True}
    frame, models = state.frame, state.referenced
    gsd_m = median_gsd_m(models, frame, dsm)
    res_m = config.resolution_cm / 100.0 if config.resolution_cm else gsd_m
    # Ortho extent: the camera footprints bounded by the DSM box grown by a footprint's half-size.
    centres = np.array([im.projection_center() for rec in models for im in rec.images.values() if im.has_pose])
    centres_utm = enu_to_utm(frame, centres, dsm.grid.epsg)
    west, south, east, north = dsm.grid.bounds_m
    margin = 0.5 * gsd_m * max(max(c.width, c.height) for rec in models for c in rec.cameras.values())
    west, south = min(west, centres_utm[:, 0].min() - margin), min(south, centres_utm[:, 1].min() - margin)
    east, north = max(east, centres_utm[:, 0].max() + margin), max(north, centres_utm[:, 1].max() + margin)
    area = (east - west) * (north - south)
    if config.max_ortho_mpx is not None and area / res_m ** 2 > config.max_ortho_mpx * 1e6:
        res_m = math.sqrt(area / (config.max_ortho_mpx * 1e6))
        report.warnings.append(f"orthophoto pixel raised to {res_m * 100:.1f} cm (GSD {gsd_m * 100:.1f} cm) "
                               f"because max_ortho_mpx={config.max_ortho_mpx:g} was asked for")
    grid = Grid.covering(dsm.grid.epsg, west, south, east, north, res_m)
    to_enu = UtmToEnu(frame, grid.epsg, grid.bounds_m)
    views = load_views(models, state.image_dir)
    if config.ortho_seams:
        from skyfix.mapping.mosaic import seamed_mosaic

        mosaic = seamed_mosaic(views, grid, dsm, to_enu, band_px=config.seam_band_px)
    else:
        mosaic = orthomosaic(views, grid, dsm, to_enu, blend_power=config.blend_power)
    # Crop to the covered part.
    alpha = mosaic.rgba[..., 3] > 0
    rows, cols = np.flatnonzero(alpha.any(axis=1)), np.flatnonzero(alpha.any(axis=0))
    r0, r1, c0, c1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    west_c, north_c = grid.centres_m(r0, c0)
    crop = Grid(grid.epsg, float(west_c) - res_m / 2, float(north_c) + res_m / 2, res_m, int(c1 - c0), int(r1 - r0))
    rgba = mosaic.rgba[r0:r1, c0:c1]
    write_orthophoto_tif(project.orthophoto_tif, rgba, crop)
    write_preview_png(project.orthophoto_png, rgba)
    data = {"grid": crop.to_dict(), "gsd_m": gsd_m, "covered_m2": float(alpha.sum() * res_m ** 2),
            "photos": mosaic.photos_used, "utm_to_enu_max_residual_m": to_enu.max_residual_m}
    ortho_load(config, project, state, report, data)
    return data


def ortho_load(config: PipelineConfig, project: Project, state: RunState, report: Report, marker: dict) -> None:
    if marker.get("skipped"):
        return
    report.gsd_cm = marker["gsd_m"] * 100.0
    report.resolution_cm = marker["grid"]["resolution_m"] * 100.0
    report.covered_area_m2 = marker["covered_m2"]
    report.outputs["orthophoto"] = str(project.orthophoto_tif)
    report.outputs["preview"] = str(project.orthophoto_png)
    state.ortho_grid = marker["grid"]
