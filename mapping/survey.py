"""Survey (coverage) planning for one drone or several.

All geometry is planned in the local ENU plane (metres, :class:`skyfix.geo.LocalFrame`
about the first corner / the area's first vertex); waypoints convert to WGS84 only when
exported. Two kinds of plan:

- ``"stations"`` (the source platform's grid): from three corners A, B, C the area is the
  parallelogram spanned by v = B - A and w = C - A; waypoints lie on a grid of
  ``step_m`` along v and w, visited row by row in boustrophedon order; the drone holds
  at each (a sensor reading per waypoint).
- ``"lines"`` (photogrammetry): from a polygon, a camera, an altitude and forward/side
  overlaps; line spacing and camera trigger distance follow from the ground footprint
  of the nadir camera; each line is extended by a turn-around margin so the drone is on
  the line before the first photo. ``trigger_on[k]`` says whether the camera triggers
  (every ``trigger_distance_m``) along the segment from waypoint k to k + 1.

:func:`extend_survey` re-centres a plan on an alarm point and grows it by 50 % per
joining drone keeping shape and step; splitting a plan among drones and handing a
failing drone's path over are in :mod:`skyfix.mapping.split`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from skyfix import validate
from skyfix.camera import Camera
from skyfix.errors import GeometryError, InputError
from skyfix.geo import LocalFrame

__all__ = ["MAX_WAYPOINTS", "SurveyPart", "SurveyPlan", "extend_survey", "plan_polygon", "plan_survey",
           "plan_three_corners"]


@dataclass(frozen=True, eq=False)
class SurveyPlan:
    """A coverage path in the local ENU plane of ``frame``.

    ``waypoints_en_m`` ``(N, 2)`` east/north metres, in flying order. ``altitude_m``: flight
    height above the take-off point (the MAVLink relative-altitude frame).
    ``trigger_on`` ``(N-1,)`` bool: camera triggers along segment k (lines plans).
    ``area_en_m`` ``(M, 2)``: the requested area's boundary. ``step_m``: station spacing
    (stations) or line spacing (lines). ``v_en_m``/``w_en_m``: the shape vectors the
    plan was built from (stations), kept so the plan can be extended.
    """

    frame: LocalFrame
    kind: str
    waypoints_en_m: np.ndarray
    altitude_m: float
    area_en_m: np.ndarray
    step_m: float
    trigger_on: np.ndarray
    trigger_distance_m: float | None = None
    hold_s: float = 0.0
    v_en_m: np.ndarray | None = None
    w_en_m: np.ndarray | None = None
    heading_deg: float | None = None
    turnaround_m: float = 0.0
    camera: Camera | None = None
    forward_overlap: float | None = None
    side_overlap: float | None = None
    notes: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.kind not in ("stations", "lines"):
            raise InputError(f"SurveyPlan.kind must be 'stations' or 'lines', got {self.kind!r}")
        for name in ("waypoints_en_m", "area_en_m", "trigger_on", "v_en_m", "w_en_m"):
            arr = getattr(self, name)
            if arr is not None:
                arr = np.array(arr, dtype=bool if name == "trigger_on" else np.float64)
                arr.setflags(write=False)
                object.__setattr__(self, name, arr)
        if self.trigger_on.shape != (max(len(self.waypoints_en_m) - 1, 0),):
            raise InputError("trigger_on must have one flag per segment (N - 1)")

    @property
    def n_waypoints(self) -> int:
        return len(self.waypoints_en_m)

    @property
    def path_length_m(self) -> float:
        """Length of the path through all waypoints, metres."""
        return _path_length(self.waypoints_en_m)

    def waypoints_latlon(self) -> np.ndarray:
        """``(N, 2)`` WGS84 (lat_deg, lon_deg) of the waypoints."""
        return _en_to_latlon(self.frame, self.waypoints_en_m)

    def photo_positions_en_m(self) -> tuple[np.ndarray, np.ndarray]:
        """Planned photo positions ``(P, 2)`` and camera headings ``(P,)`` in degrees from north.

        Along each run of triggering segments photos fall every ``trigger_distance_m``
        from the run's start (trigger on arrival, then by distance), as an autopilot
        executing ``DO_SET_CAM_TRIGG_DIST`` does.
        """
        if self.trigger_distance_m is None or not self.trigger_on.any():
            return np.zeros((0, 2)), np.zeros(0)
        pts, headings = [], []
        wp, t = self.waypoints_en_m, self.trigger_distance_m
        carry = 0.0  # distance already travelled since the last photo within a run
        for k in range(len(wp) - 1):
            if not self.trigger_on[k]:
                carry = 0.0
                continue
            seg = wp[k + 1] - wp[k]
            length = float(np.hypot(*seg))
            if length == 0:
                continue
            heading = math.degrees(math.atan2(seg[0], seg[1])) % 360.0
            # A run starts with a photo; across a waypoint inside a run the distance counter
            # carries on, so the next photo comes t after the previous one (never twice).
            first = 0.0 if (k == 0 or not self.trigger_on[k - 1]) else t - carry
            s = np.arange(first, length + 1e-6, t)
            pts.extend(wp[k] + seg * (s[:, None] / length))
            headings.extend([heading] * len(s))
            carry = (length - s[-1]) if len(s) else carry + length
        return np.array(pts).reshape(-1, 2), np.array(headings)


@dataclass(frozen=True, eq=False)
class SurveyPart:
    """One drone's contiguous share of a plan.

    ``plan`` holds the part's own waypoints (same frame, altitude and camera settings);
    ``drone_id`` the drone it is assigned to; ``first_index`` the index in the parent
    plan's path where the part starts (cut points inserted mid-segment count as the
    following waypoint); ``approach_m`` the straight distance from the drone to the part's
    first waypoint.
    """

    drone_id: str
    plan: SurveyPlan
    first_index: int
    approach_m: float

    @property
    def length_m(self) -> float:
        return self.plan.path_length_m


def _path_length(wp: np.ndarray) -> float:
    return float(np.sum(np.hypot(*np.diff(wp, axis=0).T))) if len(wp) > 1 else 0.0


def _en_to_latlon(frame: LocalFrame, en: np.ndarray) -> np.ndarray:
    if len(en) == 0:
        return np.zeros((0, 2))
    lat, lon, _ = frame.to_geodetic(en[:, 0], en[:, 1], np.zeros(len(en)))
    return np.stack((lat, lon), axis=1)


def _latlon_points(name: str, value, min_rows: int) -> np.ndarray:
    pts = validate.points(name, value, 2)
    validate.latitude(f"{name} latitude", pts[:, 0])
    validate.longitude(f"{name} longitude", pts[:, 1])
    if len(pts) < min_rows:
        raise InputError(f"{name} needs at least {min_rows} (lat, lon) points, got {len(pts)}")
    return pts


def _frame_at(latlon: np.ndarray, ground_alt_m: float) -> LocalFrame:
    return LocalFrame(float(latlon[0, 0]), float(latlon[0, 1]), ground_alt_m)


def _to_en(frame: LocalFrame, latlon: np.ndarray) -> np.ndarray:
    e, n, _ = frame.to_enu(latlon[:, 0], latlon[:, 1], np.full(len(latlon), frame.alt0_m))
    return np.stack((e, n), axis=1)


# --------------------------------------------------------------------------- stations


_STEP_SLACK = 0.02

#: Most waypoints in one plan. A MAVLink mission numbers its items with a uint16 (at most
#: 65 535) and a photo line adds up to two camera commands per four waypoints, plus home,
#: take-off, speed and return: 40 000 waypoints always fit. Checked before any allocation.
MAX_WAYPOINTS = 40_000


def _check_waypoint_count(count: int, what: str) -> None:
    if count > MAX_WAYPOINTS:
        raise InputError(f"{what} gives {count:,} waypoints; at most {MAX_WAYPOINTS:,} fit in one MAVLink mission")


def _grid(origin: np.ndarray, v: np.ndarray, w: np.ndarray, step_m: float) -> np.ndarray:
    """Boustrophedon grid: rows along v (alternating direction), stepping along w.

    A side within 2 % of a step of a whole number of steps counts as that whole number,
    so corners typed with 6-decimal coordinates (~0.1 m) still give the intended grid.
    """
    n_v = int(math.floor(np.hypot(*v) / step_m + _STEP_SLACK)) + 1
    n_w = int(math.floor(np.hypot(*w) / step_m + _STEP_SLACK)) + 1
    _check_waypoint_count(n_v * n_w, f"step_m={step_m:g} over {np.hypot(*v):.0f} x {np.hypot(*w):.0f} m")
    v_hat, w_hat = v / np.hypot(*v), w / np.hypot(*w)
    rows = []
    for j in range(n_w):
        i = np.arange(n_v) if j % 2 == 0 else np.arange(n_v)[::-1]
        rows.append(origin + (i[:, None] * step_m) * v_hat + (j * step_m) * w_hat)
    return np.concatenate(rows)


def _stations_plan(frame: LocalFrame, origin: np.ndarray, v: np.ndarray, w: np.ndarray, step_m: float,
                   altitude_m: float, hold_s: float) -> SurveyPlan:
    lv, lw = float(np.hypot(*v)), float(np.hypot(*w))
    if min(lv, lw) < 1e-6:
        raise GeometryError("survey corners coincide: B - A and C - A must both be non-zero")
    sin_angle = abs(v[0] * w[1] - v[1] * w[0]) / (lv * lw)
    if sin_angle < math.sin(math.radians(5.0)):
        raise GeometryError(f"survey corners are (nearly) collinear: the angle between B - A and C - A is "
                            f"{math.degrees(math.asin(min(sin_angle, 1.0))):.2f} deg; at least 5 deg expected")
    if step_m > min(lv, lw) * (1.0 + _STEP_SLACK):
        raise GeometryError(f"step_m={step_m} is longer than a side of the area ({lv:.2f} m, {lw:.2f} m)")
    wp = _grid(origin, v, w, step_m)
    area = np.array([origin, origin + v, origin + v + w, origin + w])
    return SurveyPlan(frame, "stations", wp, altitude_m, area, step_m, np.zeros(len(wp) - 1, bool),
                      hold_s=hold_s, v_en_m=v, w_en_m=w)



def plan_three_corners(corner_a, corner_b, corner_c, step_m: float, altitude_m: float, *,
                       hold_s: float = 0.0, ground_alt_m: float = 0.0) -> SurveyPlan:
    """Station grid from three corners given as (lat_deg, lon_deg), as the source platform did.

    v = B - A and w = C - A (local ENU metres at A) span the area; waypoints every
    ``step_m`` along v and w; ``hold_s`` seconds at each. Raises :class:`GeometryError`
    for coincident or collinear corners or a step longer than a side.

    Example:
        A 28 m x 35 m field, stations every 7 m: 5 x 6 stations, flown as a lawnmower:

        >>> from skyfix.geo import destination
        >>> a = (40.6303, -8.6575)
        >>> b, c = (tuple(float(x) for x in destination(*a, bearing, d)) for bearing, d in ((90.0, 28.0), (0.0, 35.0)))
        >>> plan = plan_three_corners(a, b, c, 7.0, 10.0)
        >>> plan.kind, len(plan.waypoints_en_m), plan.waypoints_en_m[:6].round(1).tolist()
        ('stations', 30, [[0.0, 0.0], [7.0, -0.0], [14.0, -0.0], [21.0, -0.0], [28.0, -0.0], [28.0, 7.0]])
    """
    corners = _latlon_points("corners", [corner_a, corner_b, corner_c], 3)
    step = validate.positive_scalar("step_m", step_m)
    alt = validate.positive_scalar("altitude_m", altitude_m)
    hold = validate.nonnegative_scalar("hold_s", hold_s)
    frame = _frame_at(corners, validate.finite_scalar("ground_alt_m", ground_alt_m))
    en = _to_en(frame, corners)
    return _stations_plan(frame, en[0], en[1] - en[0], en[2] - en[0], step, alt, hold)


# --------------------------------------------------------------------------- lines


def _rot(heading_deg: float) -> np.ndarray:
    """Rotation taking (along, across) line coordinates to (east, north) for a heading from north."""
    h = math.radians(heading_deg)
    along = np.array([math.sin(h), math.cos(h)])
    across = np.array([math.cos(h), -math.sin(h)])  # to the right of the flight direction
    return np.stack((along, across), axis=1)


def footprint_m(camera: Camera, altitude_m: float) -> tuple[float, float]:
    """(across-track, along-track) ground footprint of a nadir camera at ``altitude_m`` above flat ground.

    The image's u axis (width) is across track, v (height) along track, as for a camera
    with its top edge towards the flight direction.
    """
    return camera.width * altitude_m / camera.fx, camera.height * altitude_m / camera.fy


def _default_heading(area: np.ndarray) -> float:
    from shapely.geometry import Polygon

    rect = np.asarray(Polygon(area).minimum_rotated_rectangle.exterior.coords)[:4]
    edges = np.diff(np.vstack((rect, rect[:1])), axis=0)
    longest = edges[int(np.argmax(np.hypot(*edges.T)))]
    return math.degrees(math.atan2(longest[0], longest[1])) % 180.0


def _lines(area: np.ndarray, heading_deg: float, spacing_m: float, trigger_m: float,
           turnaround_m: float, from_left: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Waypoints and trigger flags of parallel lines covering ``area`` (see module docstring):
    the first line flown along ``heading_deg`` at the area's right-hand edge (``from_left``:
    at its left-hand edge), the next one back, and so on."""
    from shapely.geometry import Polygon, box

    rot = _rot(heading_deg)
    local = area @ rot  # (along, across)
    poly = Polygon(local)
    x_min, y_min, x_max, y_max = poly.bounds
    height = y_max - y_min
    n_lines = max(1, math.ceil(height / spacing_m - 1e-9))
    _check_waypoint_count(4 * n_lines, f"a line spacing of {spacing_m:.3g} m over {height:.0f} m")
    centres = y_min + height / 2.0 + (np.arange(n_lines) - (n_lines - 1) / 2.0) * spacing_m
    wps, flags = [], []
    order = np.arange(n_lines)[::-1] if from_left else np.arange(n_lines)
    for k, g in enumerate(order):  # k: flying order, g: position across the area
        y = centres[g]
        lo = y_min - 1.0 if g == 0 else y - spacing_m / 2.0
        hi = y_max + 1.0 if g == n_lines - 1 else y + spacing_m / 2.0
        piece = poly.intersection(box(x_min - 1.0, lo, x_max + 1.0, hi))
        if piece.is_empty:
            continue
        x0, _, x1, _ = piece.bounds
        n_photos = max(1, math.ceil((x1 - x0) / trigger_m - 1e-9) + 1)
        span = (n_photos - 1) * trigger_m
        start = (x0 + x1) / 2.0 - span / 2.0
        xs = [start - turnaround_m, start, start + span, start + span + turnaround_m]
        if k % 2 == 1:
            xs = xs[::-1]
        line = np.array([[x, y] for x in xs])
        if wps:
            flags.append(False)  # the turn from the previous line
        wps.append(line)
        flags.extend([False, True, False])
    if not wps:
        raise GeometryError("the survey polygon has no area to cover")
    pts = np.concatenate(wps) @ rot.T
    # Drop zero-length margins (turnaround_m = 0) and single-photo lines' repeated points.
    keep = np.ones(len(pts), bool)
    flags_arr = np.array(flags, bool)
    seg = np.hypot(*np.diff(pts, axis=0).T)
    for k in np.flatnonzero(seg < 1e-9):
        keep[k + 1] = False
    if not keep.all():
        new_flags = []
        idx = np.flatnonzero(keep)
        for a, b in zip(idx[:-1], idx[1:], strict=True):
            new_flags.append(bool(flags_arr[a:b].any()))
        pts, flags_arr = pts[keep], np.array(new_flags, bool)
    return pts, flags_arr


def plan_polygon(polygon_latlon, camera: Camera, altitude_m: float, forward_overlap: float,
                 side_overlap: float, *, heading_deg: float | None = None, turnaround_m: float | None = None,
                 ground_alt_m: float = 0.0) -> SurveyPlan:
    """Photogrammetry lines over a polygon of (lat_deg, lon_deg) vertices.

    ``camera``: the (corrected, pinhole) camera, nadir, image top towards the flight
    direction; ``altitude_m`` above flat ground. Overlaps are fractions in [0, 1).
    Line spacing = across-track footprint x (1 - side_overlap); trigger distance =
    along-track footprint x (1 - forward_overlap). ``heading_deg`` (from north) of the
    lines defaults to the long side of the polygon's minimum rotated rectangle;
    ``turnaround_m`` (default: half the along-track footprint) extends every line
    before the first and after the last photo.

    Example:
        A 60-degree, 1200 x 900 camera (focal 1039 px) 60 m up sees 69.3 m across and
        52.0 m along track: lines 27.7 m apart for 60 % side overlap, a photo every 15.6 m
        for 70 % forward overlap:

        >>> from skyfix.geo import destination
        >>> a = (40.6303, -8.6575)
        >>> corners = [a] + [tuple(float(x) for x in destination(*a, bearing, d))
        ...                  for bearing, d in ((90.0, 200.0), (45.0, 200.0), (0.0, 150.0))]
        >>> plan = plan_polygon(corners, Camera.from_fov(1200, 900, 60.0), 60.0, 0.7, 0.6)
        >>> plan.kind, round(plan.step_m, 1), round(plan.trigger_distance_m, 1)
        ('lines', 27.7, 15.6)
    """
    poly = _latlon_points("polygon", polygon_latlon, 3)
    if not isinstance(camera, Camera):
        raise InputError(f"camera must be a skyfix.camera.Camera, got {type(camera).__name__}")
    alt = validate.positive_scalar("altitude_m", altitude_m)
    for name, value in (("forward_overlap", forward_overlap), ("side_overlap", side_overlap)):
        v = validate.finite_scalar(name, value)
        if not 0.0 <= v < 1.0:
            raise InputError(f"{name} must be a fraction in [0, 1), got {v}")
    frame = _frame_at(poly, validate.finite_scalar("ground_alt_m", ground_alt_m))
    area = _to_en(frame, poly)
    from shapely.geometry import Polygon

    shape = Polygon(area)
    if not shape.is_valid or shape.area < 1e-6:
        raise GeometryError("polygon must be a simple (non-self-intersecting) polygon with non-zero area")
    across, along = footprint_m(camera, alt)
    heading = _default_heading(area) if heading_deg is None else validate.finite_scalar("heading_deg", heading_deg)
    margin = along / 2.0 if turnaround_m is None else validate.nonnegative_scalar("turnaround_m", turnaround_m)
    spacing = across * (1.0 - float(side_overlap))
    trigger = along * (1.0 - float(forward_overlap))
    wp, flags = _lines(area, heading, spacing, trigger, margin)
    return SurveyPlan(frame, "lines", wp, alt, area, spacing, flags, trigger_distance_m=trigger,
                      heading_deg=heading, turnaround_m=margin, camera=camera,
                      forward_overlap=float(forward_overlap), side_overlap=float(side_overlap))


def plan_survey(*, corners=None, step_m: float | None = None, polygon=None, camera: Camera | None = None,
                altitude_m: float, forward_overlap: float | None = None, side_overlap: float | None = None,
                **options) -> SurveyPlan:
    """Plan from (a) ``corners`` (three (lat, lon)) + ``step_m`` or (b) ``polygon`` + ``camera`` + overlaps.

    Thin dispatcher over :func:`plan_three_corners` and :func:`plan_polygon`; ``options``
    go to the chosen one.
    """
    if (corners is None) == (polygon is None):
        raise InputError("plan_survey needs exactly one of corners= (with step_m) or polygon= (with camera)")
    if corners is not None:
        if step_m is None or len(corners) != 3:
            raise InputError("corners= needs exactly three (lat, lon) corners and step_m")
        return plan_three_corners(*corners, step_m, altitude_m, **options)
    if camera is None or forward_overlap is None or side_overlap is None:
        raise InputError("polygon= needs camera=, forward_overlap= and side_overlap=")
    return plan_polygon(polygon, camera, altitude_m, forward_overlap, side_overlap, **options)


# --------------------------------------------------------------------------- extend


def extend_survey(plan: SurveyPlan, alarm_latlon, joining_drones: int, *,
                  growth_per_drone: float = 0.5) -> SurveyPlan:
    """Re-centre ``plan`` on an alarm point and grow its area by ``growth_per_drone`` per joining drone.

    Shape and step stay: station grids scale both sides by sqrt(1 + growth x drones),
    each rounded to the nearest whole number of steps (the source platform's rule: 28 x 35 m
    at 7 m grown for two drones becomes 42 x 49 m, 56 waypoints); photo surveys scale
    the polygon about its centroid and re-plan the lines with the same camera settings.
    """
    alarm = _latlon_points("alarm_latlon", alarm_latlon, 1)
    joining = validate.integer_in("joining_drones", joining_drones, 0)
    growth = 1.0 + validate.finite_scalar("growth_per_drone", growth_per_drone) * joining
    if growth <= 0:
        raise InputError(f"area growth factor must be > 0, got {growth}")
    scale = math.sqrt(growth)
    centre = _to_en(plan.frame, alarm)[0]
    if plan.kind == "stations":
        sides = []
        for vec in (plan.v_en_m, plan.w_en_m):
            length = float(np.hypot(*vec))
            n_steps = max(1, round(length * scale / plan.step_m))
            sides.append(vec / length * n_steps * plan.step_m)
        v, w = sides
        origin = centre - (v + w) / 2.0
        return _stations_plan(plan.frame, origin, v, w, plan.step_m, plan.altitude_m, plan.hold_s)
    from shapely.geometry import Polygon

    centroid = np.asarray(Polygon(plan.area_en_m).centroid.coords[0])
    area = centre + (plan.area_en_m - centroid) * scale
    wp, flags = _lines(area, plan.heading_deg, plan.step_m, plan.trigger_distance_m, plan.turnaround_m)
    return replace(plan, waypoints_en_m=wp, trigger_on=flags, area_en_m=area)
