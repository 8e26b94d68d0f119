"""Survey plans as JSON (``plan.json``), so ``skyfix plan extend/split/handoff`` can reload them.

Positions are stored in the plan's local ENU metres together with the frame origin
(WGS84 lat/lon, ellipsoidal height) and, for reading by other tools, as lat/lon too.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from skyfix.camera_io import camera_from_dict, camera_to_dict
from skyfix.errors import DataError, InputError
from skyfix.geo import LocalFrame
from skyfix.jsonfile import read_json
from skyfix.mapping.survey import SurveyPlan

__all__ = ["load_plan", "plan_from_dict", "plan_to_dict", "save_plan"]


def plan_to_dict(plan: SurveyPlan) -> dict:
    """JSON-ready description of ``plan``."""
    def arr(a):
        return None if a is None else np.asarray(a).tolist()

    return {"format": "skyfix-survey-plan/1", "kind": plan.kind,
            "origin": {"lat_deg": plan.frame.lat0_deg, "lon_deg": plan.frame.lon0_deg,
                       "alt_m": plan.frame.alt0_m},
            "altitude_m": plan.altitude_m, "step_m": plan.step_m, "hold_s": plan.hold_s,
            "trigger_distance_m": plan.trigger_distance_m, "heading_deg": plan.heading_deg,
            "turnaround_m": plan.turnaround_m, "forward_overlap": plan.forward_overlap,
            "side_overlap": plan.side_overlap,
            "camera": camera_to_dict(plan.camera) if plan.camera is not None else None,
            "v_en_m": arr(plan.v_en_m), "w_en_m": arr(plan.w_en_m),
            "area_en_m": arr(plan.area_en_m), "waypoints_en_m": arr(plan.waypoints_en_m),
            "trigger_on": arr(plan.trigger_on), "waypoints_latlon": arr(plan.waypoints_latlon())}


def plan_from_dict(data: dict, source: str = "plan") -> SurveyPlan:
    """Inverse of :func:`plan_to_dict`; DataError naming ``source`` when malformed."""
    try:
        if data.get("format") != "skyfix-survey-plan/1":
            raise DataError(f"{source}: not a skyfix survey plan (format {data.get('format')!r})")
        o = data["origin"]
        cam = data.get("camera")
        return SurveyPlan(LocalFrame(o["lat_deg"], o["lon_deg"], o["alt_m"]), data["kind"],
                          np.array(data["waypoints_en_m"], float), data["altitude_m"],
                          np.array(data["area_en_m"], float), data["step_m"], np.array(data["trigger_on"], bool),
                          trigger_distance_m=data.get("trigger_distance_m"), hold_s=data.get("hold_s", 0.0),
                          v_en_m=data.get("v_en_m"), w_en_m=data.get("w_en_m"), heading_deg=data.get("heading_deg"),
                          turnaround_m=data.get("turnaround_m", 0.0),
                          camera=camera_from_dict(cam, source) if cam else None,
                          forward_overlap=data.get("forward_overlap"), side_overlap=data.get("side_overlap"))
    except (KeyError, TypeError, ValueError) as exc:
        if isinstance(exc, InputError):
            raise DataError(f"{source}: invalid plan ({exc})") from exc
        raise DataError(f"{source}: malformed plan file ({exc!r})") from exc


def save_plan(path: str | os.PathLike, plan: SurveyPlan) -> None:
    Path(path).write_text(json.dumps(plan_to_dict(plan), indent=1) + "\n")


def load_plan(path: str | os.PathLike) -> SurveyPlan:
    p = Path(path)
    return plan_from_dict(read_json(p, "plan file", missing=InputError), str(p))
