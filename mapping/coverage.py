"""Check a photo survey by footprint geometry: is the area covered, at what overlaps?

Each planned photo's footprint is found by casting the image border through the camera
(:func:`skyfix.camera.ground_intersection`, exact on the ellipsoid) from a nadir pose at
the photo position, heading along its line. Overlaps are measured on the footprints, not
taken from the planning formulas.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from skyfix.camera import CameraPose, ground_intersection
from skyfix.errors import InputError
from skyfix.mapping.survey import SurveyPlan

__all__ = ["CoverageReport", "footprints", "verify_coverage"]


@dataclass(frozen=True)
class CoverageReport:
    """Coverage of a photo survey, measured on footprints (areas in m^2, overlaps as fractions).

    ``uncovered_m2``: area of the requested polygon seen by no photo. ``forward_overlap_min``:
    smallest overlap (intersection / footprint area) of consecutive photos on a line.
    ``side_overlap_min``: smallest across-track overlap width of adjacent lines divided by
    the footprint width.
    """

    area_m2: float
    uncovered_m2: float
    n_photos: int
    forward_overlap_min: float
    side_overlap_min: float


def footprints(plan: SurveyPlan, samples_per_edge: int = 8) -> list:
    """Shapely polygons (local ENU metres) of every planned photo's ground footprint."""
    from shapely.geometry import Polygon

    if plan.camera is None:
        raise InputError("plan has no camera (only photo surveys have footprints)")
    cam = plan.camera
    t = np.linspace(0.0, 1.0, samples_per_edge, endpoint=False)
    w, h = cam.width - 0.5, cam.height - 0.5
    border = np.concatenate([
        np.stack((-0.5 + t * (w + 0.5), np.full_like(t, -0.5)), axis=1),
        np.stack((np.full_like(t, w), -0.5 + t * (h + 0.5)), axis=1),
        np.stack((w - t * (w + 0.5), np.full_like(t, h)), axis=1),
        np.stack((np.full_like(t, -0.5), h - t * (h + 0.5)), axis=1),
    ])
    positions, headings = plan.photo_positions_en_m()
    frame = plan.frame
    lat, lon, _ = frame.to_geodetic(positions[:, 0], positions[:, 1], np.zeros(len(positions)))
    out = []
    for la, lo, yaw in zip(lat, lon, headings, strict=True):
        pose = CameraPose(float(la), float(lo), frame.alt0_m + plan.altitude_m, yaw_deg=float(yaw))
        ground = ground_intersection(cam, pose, border, frame.alt0_m, frame)
        out.append(Polygon(ground[:, :2]))
    return out


def _runs(plan: SurveyPlan) -> list[np.ndarray]:
    """Photo indices grouped by line (consecutive photos with the same heading)."""
    _, headings = plan.photo_positions_en_m()
    if len(headings) == 0:
        return []
    breaks = np.flatnonzero(np.abs(np.diff(headings)) > 1e-6) + 1
    return np.split(np.arange(len(headings)), breaks)


def verify_coverage(plan: SurveyPlan) -> CoverageReport:
    """Measure coverage and overlaps of a ``lines`` plan (see :class:`CoverageReport`).

    Example:
        The footprints of a plan for 70 % forward and 60 % side overlap cover its polygon
        and overlap as planned:

        >>> from skyfix.camera import Camera
        >>> from skyfix.geo import LocalFrame
        >>> from skyfix.mapping.survey import plan_polygon
        >>> en_m = np.array([[0.0, 0.0, 0.0], [150.0, 0.0, 0.0], [150.0, 100.0, 0.0], [0.0, 100.0, 0.0]])
        >>> field = LocalFrame(40.6303, -8.6575, 0.0).to_geodetic_points(en_m)[:, :2]  # 150 m x 100 m
        >>> report = verify_coverage(plan_polygon(field, Camera.from_fov(1200, 900, 60.0), 60.0, 0.7, 0.6))
        >>> report.uncovered_m2, round(report.forward_overlap_min, 3), round(report.side_overlap_min, 3)
        (0.0, 0.7, 0.6)
    """
    from shapely import union_all
    from shapely.geometry import Polygon

    feet = footprints(plan)
    if not feet:
        raise InputError("plan triggers no photos")
    area = Polygon(plan.area_en_m)
    uncovered = area.difference(union_all(feet)).area
    forward = [feet[i].intersection(feet[i + 1]).area / feet[i].area
               for run in _runs(plan) for i in run[:-1]]
    # Side overlap: across-track width of the overlap of adjacent line strips.
    h = np.radians(plan.heading_deg or 0.0)
    across = np.array([np.cos(h), -np.sin(h)])
    strips = [union_all([feet[i] for i in run]) for run in _runs(plan)]
    side = []
    for a, b in zip(strips[:-1], strips[1:], strict=True):
        overlap = a.intersection(b)
        if overlap.is_empty:
            side.append(0.0)
            continue
        pts_o = np.asarray(overlap.convex_hull.exterior.coords) @ across
        pts_a = np.asarray(feet[0].exterior.coords) @ across
        side.append((pts_o.max() - pts_o.min()) / (pts_a.max() - pts_a.min()))
    return CoverageReport(float(area.area), float(uncovered), len(feet),
                          float(min(forward)) if forward else 1.0, float(min(side)) if side else 1.0)
