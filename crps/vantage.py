"""Where a helper should fly to look at a drone that lost GNSS.

All positions are ENU metres in one caller's :class:`skyfix.geo.LocalFrame`. Candidates lie
on a grid of azimuths (every ``azimuth_step_deg``) and slant ranges (``range_min_m`` to
``range_max_m``, where monocular ranging is accurate, see the crps README) around the
target, ``below_target_m`` lower so the target is seen against the sky, but never below ``floor_up_m``
(the helper's lowest safe height: a landing target ends up below it). A candidate is
feasible when it keeps ``min_separation_m`` from every other drone (plus three sigma of the
target's horizontal uncertainty from the target) and from the other helpers' vantage points,
and the straight leg from the helper to it keeps that from the target and the other drones;
the chosen one minimises a weighted sum of: distance from the preferred range, time to fly there (as metres at
the helper's speed), ``1 - geometry_quality`` of the lines of sight of all helpers seen from the target, and the
shortfall of the target's elevation above the candidate's horizon under ``want_elevation_deg``: a target
low over the ground (landing) is kept against the sky from a closer, lower point while one exists.

A moving target (``target_vel_enu_mps``: a lost drone flying home at 5 m/s) is judged in its own frame:
- the candidates are offsets from it; a helper at ``helper_speed_mps`` reaches one in the time that velocity
  allows (never one ahead of a target as fast as itself; when none can be reached, a target flying away, it
  follows towards the nearest offset in the target's frame);
- the way there is a straight line *relative to the target* that keeps the separation from it;
- an offset stays clear of the target's track for ``stop_horizon_s`` (an autopilot brakes at every goal it is
  sent, so a helper trailing its goal must not be left in the target's way);
- the point to fly to is where the offset will be on arrival (led at most ``lead_max_s``).
Judged as if it stood still, a helper chose points ahead of a target flying home, flew with it without ever
arriving, and was caught up from behind: 4.1 m in one benchmark seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from skyfix.crps.help_protocol import geometry_quality


@dataclass(frozen=True)
class VantageConfig:
    """Vantage-point search (lengths m, angles deg)."""

    range_min_m: float = 20.0
    range_max_m: float = 60.0
    range_preferred_m: float = 35.0
    n_ranges: int = 9
    azimuth_step_deg: float = 5.0
    below_target_m: float = 5.0      # helper flies lower: the target against the sky, not terrain
    min_separation_m: float = 10.0   # from every drone, at the vantage point
    w_range: float = 1.0             # cost of the range error, per (range span)^2
    w_travel: float = 0.5            # cost per preferred-range of distance to fly
    w_geometry: float = 2.0          # cost of collinear lines of sight
    want_elevation_deg: float = 6.0  # the target this far above the helper's horizon (sky behind it) ...
    w_elevation: float = 2.0         # ... else this cost per want_elevation_deg short of it
    # the helper's own horizontal transit speed, m/s: ArduPilot's WPNAV_SPEED default was 500 cm/s (1000 in
    # Copter 4.x); planning with less than the helper flies only makes points ahead of a moving target look harder
    helper_speed_mps: float = 5.0
    lead_max_s: float = 5.0          # a moving target is led by at most this much of its motion
    stop_horizon_s: float = 10.0     # a helper stopped at its offset is clear of the target's track this long


@dataclass(frozen=True)
class Vantage:
    """A vantage point (ENU m), the heading that faces the target (deg clockwise from north), the
    camera pitch (deg, positive up), the slant range to the target (m) and the geometry quality (0-1)."""

    enu_m: np.ndarray
    yaw_deg: float
    pitch_deg: float
    range_m: float
    geometry_quality: float


def _candidates(target_enu_m: np.ndarray, floor_up_m: float, cfg: VantageConfig) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) candidate positions (never below ``floor_up_m``) and their (N,) slant ranges."""
    az = np.radians(np.arange(0.0, 360.0, cfg.azimuth_step_deg))
    slant = np.linspace(cfg.range_min_m, cfg.range_max_m, cfg.n_ranges)
    az_g, slant_g = np.meshgrid(az, slant, indexing="ij")
    below_m = min(cfg.below_target_m, target_enu_m[2] - floor_up_m)  # negative: the target below the floor
    horiz = np.sqrt(np.maximum(slant_g**2 - below_m**2, 0.0))
    pts = np.stack([target_enu_m[0] + horiz * np.sin(az_g), target_enu_m[1] + horiz * np.cos(az_g),
                    np.full_like(horiz, target_enu_m[2] - below_m)], axis=-1)
    return pts.reshape(-1, 3), slant_g.ravel()


def _min_distance(pts: np.ndarray, others: np.ndarray) -> np.ndarray:
    """(N,) distance from each point to the nearest of ``others`` (inf when there are none)."""
    if others.size == 0:
        return np.full(len(pts), np.inf)
    return np.linalg.norm(pts[:, None, :] - others[None, :, :], axis=-1).min(axis=1)


def path_clearance(start: np.ndarray, ends: np.ndarray, obstacles: np.ndarray) -> np.ndarray:
    """(N, M) closest approach to each of ``obstacles`` (M, 3) along the straight legs from ``start`` (3,)
    to each of ``ends`` (N, 3)."""
    leg = ends - start                                               # (N, 3)
    rel = obstacles - start                                          # (M, 3)
    len2 = np.maximum((leg * leg).sum(axis=1), 1e-12)[:, None]
    frac = np.clip(leg @ rel.T / len2, 0.0, 1.0)                     # (N, M)
    closest = start + frac[..., None] * leg[:, None, :]              # (N, M, 3)
    return np.linalg.norm(closest - obstacles[None, :, :], axis=-1)


def _arrival_s(rel_m: np.ndarray, target_vel_mps: np.ndarray, speed_mps: float) -> np.ndarray:
    """(N,) smallest time (s) in which a helper at ``speed_mps`` moves ``rel_m`` (N, 3) relative to a target moving
    at ``target_vel_mps`` (3,): |rel/T + v| = speed; inf where it cannot (a target as fast, heading away)."""
    a = (rel_m * rel_m).sum(axis=1)
    b = rel_m @ target_vel_mps
    c = float(target_vel_mps @ target_vel_mps) - speed_mps**2
    disc = b * b - a * c
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_t = (-b + np.sqrt(np.maximum(disc, 0.0))) / a          # 1 / T, the larger root
        t = np.where((disc >= 0.0) & (inv_t > 0.0), 1.0 / inv_t, np.inf)
    return np.where(a < 1e-12, 0.0, t)


def _track_clearance(offsets_m: np.ndarray, target_vel_mps: np.ndarray, horizon_s: float) -> np.ndarray:
    """(N,) closest approach of a target moving at ``target_vel_mps`` for ``horizon_s`` to points standing still
    at ``offsets_m`` (N, 3) from it now."""
    seg = -target_vel_mps * horizon_s                               # the points' path in the target's frame
    len2 = max(float(seg @ seg), 1e-12)
    frac = np.clip(-(offsets_m @ seg) / len2, 0.0, 1.0)
    return np.linalg.norm(offsets_m + frac[:, None] * seg, axis=1)


def vantage_point(target_enu_m, own_enu_m, other_drones_enu_m=(), helper_vantages_enu_m=(), *,
                  target_sigma_h_m: float = 0.0, floor_up_m: float = -math.inf,
                  target_vel_enu_mps=None, cfg: VantageConfig | None = None) -> Vantage | None:
    """The best vantage point for a helper at ``own_enu_m`` looking at ``target_enu_m`` (3,).

    ``other_drones_enu_m`` (N, 3): every other drone now (not the target, not this one);
    ``helper_vantages_enu_m`` (M, 3): where the other helpers are going; ``floor_up_m`` the lowest the
    helper may fly (ENU up; e.g. 1.5 m above its take-off ground, taken as level about the target);
    ``target_vel_enu_mps`` (3,) the target's velocity (None: standing still); the point returned is where to fly
    (for a moving target: where the chosen offset from it will be on arrival). None when no candidate is feasible
    (crowded sky: hold where you are)."""
    cfg = cfg or VantageConfig()
    target = np.asarray(target_enu_m, dtype=float).reshape(3)
    own = np.asarray(own_enu_m, dtype=float).reshape(3)
    vel = np.zeros(3) if target_vel_enu_mps is None else np.asarray(target_vel_enu_mps, dtype=float).reshape(3)
    drones = np.asarray(other_drones_enu_m, dtype=float).reshape(-1, 3)
    mates = np.asarray(helper_vantages_enu_m, dtype=float).reshape(-1, 3)
    pts, slant = _candidates(target, float(floor_up_m), cfg)
    offsets, start = pts - target, own - target                   # in the target's frame
    arrival_s = _arrival_s(offsets - start, vel, cfg.helper_speed_mps)
    reachable = np.isfinite(arrival_s)
    goals = pts + vel * np.minimum(arrival_s, cfg.lead_max_s)[:, None]
    ok = _track_clearance(offsets, vel, cfg.stop_horizon_s) >= cfg.min_separation_m + 3.0 * target_sigma_h_m
    ok &= _min_distance(goals, np.vstack([drones, mates])) >= cfg.min_separation_m
    # the way there keeps the separation too (or, from a drone already closer, does not close in): from the
    # target in its frame, from the other drones in the world
    need_target = min(cfg.min_separation_m + 3.0 * target_sigma_h_m, float(np.linalg.norm(start)) - 1e-6)
    ok &= path_clearance(start, offsets, np.zeros((1, 3)))[:, 0] >= need_target
    if len(drones):
        need = np.minimum(cfg.min_separation_m, np.linalg.norm(drones - own, axis=1) - 1e-6)
        ok &= (path_clearance(own, goals, drones) >= need).all(axis=1)
    if (ok & reachable).any():
        ok &= reachable
    elif ok.any():
        # a target flying away as fast as the helper: follow it, ranked by how far each offset is in its frame
        arrival_s = np.linalg.norm(offsets - start, axis=1) / cfg.helper_speed_mps
    else:
        return None
    pts, slant, goals, arrival_s = pts[ok], slant[ok], goals[ok], arrival_s[ok]
    span = cfg.range_max_m - cfg.range_min_m
    cost = cfg.w_range * ((slant - cfg.range_preferred_m) / span) ** 2
    cost += cfg.w_travel * cfg.helper_speed_mps * arrival_s / cfg.range_preferred_m
    mate_az = np.degrees(np.arctan2(mates[:, 0] - target[0], mates[:, 1] - target[1]))
    cand_az = np.degrees(np.arctan2(pts[:, 0] - target[0], pts[:, 1] - target[1]))
    if len(mates):
        quality = geometry_quality(np.column_stack([np.broadcast_to(mate_az, (len(pts), len(mates))), cand_az]))
    else:
        quality = np.ones(len(pts))
    cost += cfg.w_geometry * (1.0 - quality)
    elevation_deg = np.degrees(np.arctan2(target[2] - pts[:, 2], np.hypot(*(target[:2] - pts[:, :2]).T)))
    cost += cfg.w_elevation * np.maximum(cfg.want_elevation_deg - elevation_deg, 0.0) / cfg.want_elevation_deg
    best = int(np.argmin(cost))
    d = target - pts[best]
    return Vantage(goals[best], float(np.degrees(np.arctan2(d[0], d[1])) % 360.0),
                   float(np.degrees(math.atan2(d[2], math.hypot(d[0], d[1])))), float(slant[best]),
                   float(quality[best]))
