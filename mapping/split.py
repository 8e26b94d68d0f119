"""Sharing a survey among drones: :func:`split_survey` cuts a plan's path into contiguous
parts of equal length and gives each to a drone; :func:`handoff` gives a failing drone's
remaining path to the nearest available drone. Positions in the plan's local ENU plane
(metres), drones as {id: (lat_deg, lon_deg)}.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from skyfix import validate
from skyfix.errors import InputError
from skyfix.geo import LocalFrame
from skyfix.mapping.survey import SurveyPart, SurveyPlan, _latlon_points, _lines, _to_en

__all__ = ["handoff", "split_survey"]


def _drone_positions(drones, frame: LocalFrame) -> tuple[list[str], np.ndarray]:
    if not isinstance(drones, dict) or not drones:
        raise InputError("drones must be a non-empty dict {drone_id: (lat_deg, lon_deg)}")
    ids = [str(k) for k in drones]
    pos = _latlon_points("drone positions", [drones[k] for k in drones], 1)
    return ids, _to_en(frame, pos)


def _cut(wp: np.ndarray, s_cut: float, cum: np.ndarray) -> tuple[int, np.ndarray]:
    """Segment index and point at arc length ``s_cut``."""
    k = int(np.clip(np.searchsorted(cum, s_cut, side="right") - 1, 0, len(wp) - 2))
    seg = cum[k + 1] - cum[k]
    frac = 0.0 if seg == 0 else (s_cut - cum[k]) / seg
    return k, wp[k] + frac * (wp[k + 1] - wp[k])


def _sub_plan(plan: SurveyPlan, wp: np.ndarray, flags: np.ndarray) -> SurveyPlan:
    return replace(plan, waypoints_en_m=wp, trigger_on=flags)


def _split_paths(plan: SurveyPlan, n: int) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """(first index, waypoints, flags) of ``n`` contiguous parts of equal length."""
    wp, flags = plan.waypoints_en_m, plan.trigger_on
    cum = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(wp, axis=0).T))))
    total = cum[-1]
    if plan.kind == "stations":
        # Cut between stations: part p gets stations [b_p, b_{p+1}); the hop between parts
        # is not flown by anyone, so balance the parts' own lengths.
        if n > len(wp):
            raise InputError(f"cannot split {len(wp)} waypoints among {n} drones")
        bounds = [0]
        for p in range(1, n):
            target = p * total / n
            b = int(np.argmin(np.abs(cum - target)))
            b = min(max(b, bounds[-1] + 1), len(wp) - (n - p))
            bounds.append(b)
        bounds.append(len(wp))
        return [(a, wp[a:b], flags[a:max(a, b - 1)]) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
    parts, prev_k, prev_pt = [], 0, wp[0]
    for p in range(1, n + 1):
        if p == n:
            k, pt = len(wp) - 2, wp[-1]
            pts = np.vstack((prev_pt[None], wp[prev_k + 1:]))
        else:
            k, pt = _cut(wp, p * total / n, cum)
            pts = np.vstack((prev_pt[None], wp[prev_k + 1:k + 1], pt[None]))
        seg_flags = np.concatenate(([flags[prev_k]], flags[prev_k + 1:k + 1])) if p < n else \
            np.concatenate(([flags[prev_k]], flags[prev_k + 1:]))
        keep = np.concatenate(([True], np.hypot(*np.diff(pts, axis=0).T) > 1e-9))
        idx = np.flatnonzero(keep)
        merged = [bool(seg_flags[a:b].any()) for a, b in zip(idx[:-1], idx[1:], strict=True)]
        parts.append((prev_k + (0 if p == 1 else 1), pts[keep], np.array(merged, bool)))
        prev_k, prev_pt = k, pt
    return parts


def _assign(plan: SurveyPlan, ids: list[str], pos: np.ndarray) -> tuple[float, list[SurveyPart]]:
    """Total approach (m) and the parts of ``plan`` given to the drones at ``pos`` (Hungarian)."""
    from scipy.optimize import linear_sum_assignment

    parts = _split_paths(plan, len(ids))
    starts = np.array([p[1][0] for p in parts])
    ends = np.array([p[1][-1] for p in parts])
    d_start = np.linalg.norm(pos[:, None, :] - starts[None], axis=2)
    d_end = np.linalg.norm(pos[:, None, :] - ends[None], axis=2)
    rows, cols = linear_sum_assignment(np.minimum(d_start, d_end))
    out = []
    for r, c in zip(rows, cols, strict=True):
        first, wp, flags = parts[c]
        if d_end[r, c] < d_start[r, c]:
            wp, flags = wp[::-1], flags[::-1]
        out.append(SurveyPart(ids[r], _sub_plan(plan, wp, flags), int(first), float(min(d_start[r, c], d_end[r, c]))))
    return sum(p.approach_m for p in out), sorted(out, key=lambda part: part.first_index)


def split_survey(plan: SurveyPlan, drones: dict) -> list[SurveyPart]:
    """Split ``plan`` among ``drones`` ({id: (lat_deg, lon_deg)}): contiguous parts, balanced length.

    Station plans are cut between stations (lengths then differ by at most one step);
    line plans are cut at exact fractions of the path length (a waypoint is inserted at
    the cut, the camera keeps triggering across it). Parts go to drones by least total
    approach distance (Hungarian assignment); a part is flown backwards when that starts
    it nearer its drone. A line plan may also be flown from any corner of the area (the
    same lines, the first one at the other edge and/or flown the other way): the layout
    needing the shortest total approach is used, so drones waiting at one edge do not all
    fly to the far one first.

    Example:
        A 1549 m line plan shared by a drone at its west corner and one 200 m east: two
        parts of 773 m, the eastern one starting where that drone waits:

        >>> from skyfix.camera import Camera
        >>> from skyfix.geo import destination
        >>> from skyfix.mapping.survey import plan_polygon
        >>> a = (40.6303, -8.6575)
        >>> corners = [a] + [tuple(float(x) for x in destination(*a, bearing, d))
        ...                  for bearing, d in ((90.0, 200.0), (45.0, 200.0), (0.0, 150.0))]
        >>> plan = plan_polygon(corners, Camera.from_fov(1200, 900, 60.0), 60.0, 0.7, 0.6)
        >>> parts = split_survey(plan, {"west": a, "east": corners[1]})
        >>> round(plan.path_length_m), [(p.drone_id, round(p.plan.path_length_m)) for p in parts]
        (1549, [('east', 773), ('west', 773)])
        >>> [p.first_index for p in parts], round(parts[0].approach_m)  # east starts at the path's start, 28 m off
        ([0, 10], 28)
    """
    ids, pos = _drone_positions(drones, plan.frame)
    layouts = [plan]
    if plan.kind == "lines" and plan.heading_deg is not None and plan.trigger_distance_m is not None:
        for heading, from_left in ((plan.heading_deg, True), ((plan.heading_deg + 180.0) % 360.0, False),
                                   ((plan.heading_deg + 180.0) % 360.0, True)):
            wp, flags = _lines(plan.area_en_m, heading, plan.step_m, plan.trigger_distance_m, plan.turnaround_m,
                               from_left)
            layouts.append(replace(plan, waypoints_en_m=wp, trigger_on=flags, heading_deg=heading))
    return min((_assign(layout, ids, pos) for layout in layouts), key=lambda found: found[0])[1]


def handoff(part: SurveyPart | SurveyPlan, next_index: int, available: dict, *,
            stopped_at_latlon=None) -> SurveyPart:
    """Give the rest of a failing drone's path to the nearest available drone.

    ``next_index``: index (in ``part``'s waypoints) of the first waypoint the failing drone
    had not reached. With ``stopped_at_latlon`` (its last position) the new path starts
    there, so a photo line is resumed where it was interrupted (the camera triggers on
    the resumed segment when it did on the interrupted one). ``available``:
    {id: (lat_deg, lon_deg)} of drones that can take over.
    """
    plan = part.plan if isinstance(part, SurveyPart) else part
    next_index = validate.integer_in("next_index", next_index, 0, plan.n_waypoints - 1)
    wp, flags = plan.waypoints_en_m[next_index:], plan.trigger_on[next_index:]
    if stopped_at_latlon is not None:
        stop = _to_en(plan.frame, _latlon_points("stopped_at_latlon", stopped_at_latlon, 1))[0]
        resumed = bool(plan.trigger_on[next_index - 1]) if next_index > 0 else False
        wp, flags = np.vstack((stop[None], wp)), np.concatenate(([resumed], flags))
    ids, pos = _drone_positions(available, plan.frame)
    dist = np.linalg.norm(pos - wp[0], axis=1)
    best = int(np.argmin(dist))
    offset = part.first_index if isinstance(part, SurveyPart) else 0
    return SurveyPart(ids[best], _sub_plan(plan, wp, flags), offset + int(next_index), float(dist[best]))
