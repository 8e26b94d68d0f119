"""Write survey plans as files people open: GeoJSON, KML, a QGC mission file and a PNG.

Every writer takes the parts of a plan (one :class:`SurveyPart` per drone, or the
whole plan as a single part) so one file shows the whole collaborative mission.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from skyfix.mapping.mission import mission_items
from skyfix.mapping.survey import SurveyPart, SurveyPlan
from skyfix.mission import MissionItem, mavlink

__all__ = ["write_geojson", "write_kml", "write_png", "write_qgc_mission", "plan_geojson"]


def _parts(plan_or_parts: SurveyPlan | Sequence[SurveyPart]) -> tuple[SurveyPlan, list[SurveyPart]]:
    if isinstance(plan_or_parts, SurveyPlan):
        return plan_or_parts, [SurveyPart("drone", plan_or_parts, 0, 0.0)]
    parts = list(plan_or_parts)
    return parts[0].plan, parts


def _lonlat(plan: SurveyPlan, en: np.ndarray) -> list[list[float]]:
    lat, lon, _ = plan.frame.to_geodetic(en[:, 0], en[:, 1], np.zeros(len(en)))
    return [[float(a), float(b)] for a, b in zip(lon, lat, strict=True)]


def plan_geojson(plan_or_parts: SurveyPlan | Sequence[SurveyPart]) -> dict:
    """GeoJSON FeatureCollection (WGS84 lon/lat): area polygon, one path per drone, waypoints, photos."""
    plan, parts = _parts(plan_or_parts)
    ring = _lonlat(plan, plan.area_en_m)
    features = [{"type": "Feature", "geometry": {"type": "Polygon", "coordinates": [ring + ring[:1]]},
                 "properties": {"role": "area", "kind": plan.kind, "altitude_m": plan.altitude_m,
                                "step_m": plan.step_m, "trigger_distance_m": plan.trigger_distance_m}}]
    for part in parts:
        p = part.plan
        coords = _lonlat(p, p.waypoints_en_m)
        features.append({"type": "Feature", "geometry": {"type": "LineString", "coordinates": coords},
                         "properties": {"role": "path", "drone_id": part.drone_id, "length_m": p.path_length_m,
                                        "n_waypoints": p.n_waypoints, "first_index": part.first_index}})
        for k, c in enumerate(coords):
            features.append({"type": "Feature", "geometry": {"type": "Point", "coordinates": c},
                             "properties": {"role": "waypoint", "drone_id": part.drone_id, "index": k}})
        photos, headings = p.photo_positions_en_m()
        for c, h in zip(_lonlat(p, photos), headings, strict=True):
            features.append({"type": "Feature", "geometry": {"type": "Point", "coordinates": c},
                             "properties": {"role": "photo", "drone_id": part.drone_id, "heading_deg": float(h)}})
    return {"type": "FeatureCollection", "features": features}


def write_geojson(path: str | os.PathLike, plan_or_parts) -> None:
    """Write :func:`plan_geojson` to ``path``."""
    Path(path).write_text(json.dumps(plan_geojson(plan_or_parts), indent=1) + "\n")


def write_kml(path: str | os.PathLike, plan_or_parts) -> None:
    """KML (Google Earth): area, one path per drone (altitude relative to ground), waypoints."""
    import simplekml

    plan, parts = _parts(plan_or_parts)
    kml = simplekml.Kml()
    ring = _lonlat(plan, plan.area_en_m)
    area = kml.newpolygon(name="survey area", outerboundaryis=[tuple(c) for c in ring + ring[:1]])
    area.style.polystyle.color = simplekml.Color.changealphaint(60, simplekml.Color.yellow)
    colours = [simplekml.Color.red, simplekml.Color.blue, simplekml.Color.green, simplekml.Color.orange,
               simplekml.Color.purple, simplekml.Color.cyan]
    for i, part in enumerate(parts):
        coords = [(c[0], c[1], part.plan.altitude_m) for c in _lonlat(part.plan, part.plan.waypoints_en_m)]
        line = kml.newlinestring(name=f"drone {part.drone_id}", coords=coords)
        line.altitudemode = simplekml.AltitudeMode.relativetoground
        line.style.linestyle.color = colours[i % len(colours)]
        line.style.linestyle.width = 3
        folder = kml.newfolder(name=f"drone {part.drone_id} waypoints")
        for k, c in enumerate(coords):
            pt = folder.newpoint(name=str(k), coords=[c])
            pt.altitudemode = simplekml.AltitudeMode.relativetoground
    kml.save(str(path))


#: The file holds degrees, not 1e7 integers: *_INT frames are written as their float twins.
_WPL_FRAME = {mavlink.MAV_FRAME_GLOBAL_INT: mavlink.MAV_FRAME_GLOBAL,
              mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT: mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT}


def write_qgc_mission(path: str | os.PathLike, items: Sequence[MissionItem]) -> None:
    """Mission file in the ``QGC WPL 110`` text format (QGroundControl, Mission Planner, MAVProxy);
    item 0 is home there, marked current as Mission Planner writes it."""
    lines = ["QGC WPL 110"]
    for seq, it in enumerate(items):
        params = ["0" if math.isnan(p) else f"{p:.8g}" for p in (it.param1, it.param2, it.param3, it.param4)]
        lines.append("\t".join([str(seq), str(int(seq == 0)), str(_WPL_FRAME.get(it.frame, it.frame)), str(it.command),
                                *params, f"{it.lat_deg:.7f}", f"{it.lon_deg:.7f}", f"{it.alt_m:.3f}",
                                str(int(it.autocontinue))]))
    Path(path).write_text("\n".join(lines) + "\n")


def write_png(path: str | os.PathLike, plan_or_parts, *, footprints: bool = True, title: str | None = None) -> None:
    """Top view of the plan over a metric grid: area, each drone's path, start points, photo footprints."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plan, parts = _parts(plan_or_parts)
    fig, ax = plt.subplots(figsize=(8, 8), dpi=110)
    ring = np.vstack((plan.area_en_m, plan.area_en_m[:1]))
    ax.fill(ring[:, 0], ring[:, 1], color="gold", alpha=0.25, label="requested area")
    ax.plot(ring[:, 0], ring[:, 1], color="goldenrod", lw=1.5)
    cmap = plt.get_cmap("tab10")
    for i, part in enumerate(parts):
        p, colour = part.plan, cmap(i % 10)
        if footprints and p.camera is not None:
            from skyfix.mapping.coverage import footprints as feet

            for foot in feet(p, samples_per_edge=1):
                xy = np.asarray(foot.exterior.coords)
                ax.plot(xy[:, 0], xy[:, 1], color=colour, lw=0.4, alpha=0.35)
        wp = p.waypoints_en_m
        ax.plot(wp[:, 0], wp[:, 1], "-", color=colour, lw=1.8,
                label=f"drone {part.drone_id}: {p.n_waypoints} wp, {p.path_length_m:.0f} m")
        ax.plot(wp[:, 0], wp[:, 1], ".", color=colour, ms=5)
        ax.plot(wp[0, 0], wp[0, 1], "o", color=colour, ms=10, mfc="white", mew=2)
        photos, _ = p.photo_positions_en_m()
        if len(photos):
            ax.plot(photos[:, 0], photos[:, 1], "x", color=colour, ms=3)
    ax.set_aspect("equal")
    ax.grid(True, lw=0.5, alpha=0.6)
    ax.set_xlabel(f"east of {plan.frame.lat0_deg:.6f}, {plan.frame.lon0_deg:.6f} (m)")
    ax.set_ylabel("north (m)")
    ax.set_title(title or f"{plan.kind} survey at {plan.altitude_m:.0f} m, step {plan.step_m:.1f} m")
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def write_all(out_dir: str | os.PathLike, plan_or_parts, *, home_latlon_alt=None, speed_mps: float | None = None,
              stem: str = "plan") -> dict[str, str]:
    """GeoJSON, KML, PNG and one QGC mission file per drone in ``out_dir``; returns {kind: path}.

    Every mission file starts with home as item 0 (ArduPilot, Mission Planner and QGC WPL
    files treat item 0 as home, so a take-off there would be lost): ``home_latlon_alt``
    (lat_deg, lon_deg, alt_m AMSL) for all drones, or {drone_id: (lat, lon, alt)}; a
    drone without one gets its part's first waypoint at altitude 0 (the autopilot sets
    its real home when it arms).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    _, parts = _parts(plan_or_parts)
    written = {"geojson": out / f"{stem}.geojson", "kml": out / f"{stem}.kml", "png": out / f"{stem}.png"}
    write_geojson(written["geojson"], plan_or_parts)
    write_kml(written["kml"], plan_or_parts)
    write_png(written["png"], plan_or_parts)
    for part in parts:
        home = home_latlon_alt.get(part.drone_id) if isinstance(home_latlon_alt, dict) else home_latlon_alt
        if home is None:
            home = (*part.plan.waypoints_latlon()[0], 0.0)
        path = out / f"{stem}_{part.drone_id}.waypoints"
        write_qgc_mission(path, mission_items(part, home_latlon_alt=home, speed_mps=speed_mps))
        written[f"mission_{part.drone_id}"] = path
    return {k: str(v) for k, v in written.items()}
