"""The pipeline's ``export`` stage (see :mod:`skyfix.mapping.pipeline`): points.ply,
cameras.geojson and report.png from the georeferenced models.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from skyfix.mapping.report import peak_memory_mib
from skyfix.mapping.surface_stages import points

if TYPE_CHECKING:
    from skyfix.mapping.pipeline import PipelineConfig
    from skyfix.mapping.project import Project, RunState
    from skyfix.mapping.report import Report

__all__ = ['export_run']


def export_run(config: PipelineConfig, project: Project, state: RunState, report: Report) -> dict:
    from skyfix.mapping.grid import enu_to_utm
    from skyfix.mapping.model_files import write_cameras_geojson, write_ply

    frame = state.frame
    by_name = {p.name: p for p in state.photos}
    features, cams_utm, gps_utm = [], [], []
    residuals = {n: r for m in report.models for n, r in m["residuals_enu_m"].items()}
    if state.referenced and config.dense and project.dense_points.exists():
        with np.load(project.dense_points) as cloud:
            write_ply(project.points_ply, cloud["xyz"], cloud["rgb"])
    elif state.referenced:
        xyz, rgb = points(state.referenced, max_error_px=4.0, min_track=2)
        write_ply(project.points_ply, enu_to_utm(frame, xyz, report.crs_epsg) if len(xyz) else xyz, rgb)
    if state.referenced:
        emitted: set[str] = set()  # a photo shared by two models is listed once, from the first model
        for rec in state.referenced:
            for image in rec.images.values():
                if not image.has_pose or image.name in emitted:
                    continue
                emitted.add(image.name)
                lat, lon, alt = frame.to_geodetic_points(image.projection_center()[None, :])[0]
                p = by_name.get(image.name)
                features.append({"lat_deg": lat, "lon_deg": lon, "alt_m": alt, "properties": {
                    "photo": image.name, "alt_amsl_m": alt, "gps_lat_deg": p.gps_lat_deg if p else None,
                    "gps_lon_deg": p.gps_lon_deg if p else None, "gps_alt_amsl_m": p.gps_alt_amsl_m if p else None,
                    "residual_enu_m": residuals.get(image.name)}})
                if p is not None and p.has_gps:
                    cams_utm.append(image.projection_center())
                    gps_utm.append(frame.to_enu_points(np.array([[p.gps_lat_deg, p.gps_lon_deg,
                                                                  p.gps_alt_amsl_m]]))[0])
        write_cameras_geojson(project.cameras_geojson, features)
        report.outputs["cameras"] = str(project.cameras_geojson)
    elif state.unreferenced:
        xyz, rgb = points(state.unreferenced, max_error_px=4.0, min_track=2)
        write_ply(project.points_ply, xyz, rgb)
        report.warnings.append("points.ply is in the arbitrary model frame (no georeference)")
    report.outputs["points"] = str(project.points_ply)
    report.outputs["report"] = str(project.report_json)
    report.outputs["report_png"] = str(project.report_png)
    report.total_seconds = sum(report.stage_seconds.values())
    report.peak_memory_mib = peak_memory_mib()
    preview = extent = None
    if state.ortho_grid is not None:
        import cv2

        g = state.ortho_grid
        img = cv2.imread(str(project.orthophoto_png), cv2.IMREAD_UNCHANGED)
        preview = cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA)
        extent = (g["west_m"], g["west_m"] + g["width"] * g["resolution_m"],
                  g["north_m"] - g["height"] * g["resolution_m"], g["north_m"])
    cams = enu_to_utm(frame, np.array(cams_utm), report.crs_epsg) if cams_utm else None
    gps = enu_to_utm(frame, np.array(gps_utm), report.crs_epsg) if gps_utm else None
    report.save_png(project.report_png, preview, extent, cams, gps)
    return {}
