"""A released helper's way back to its mission, kept clear of the other drones.

On release a helper resumes the mode it left. In its mission mode the autopilot flies a straight
leg from where the helper is to the mission's current item (ArduPilot with MIS_RESTART 1: its
first), and that leg knows nothing of the drone it helped (flying home, or hovering) nor of the
other helpers. :class:`Rejoin` reads the mission back from the autopilot, finds the leg the
autopilot will fly (that item, or the next one with a position after DO_ commands; home for RTL)
and resumes only while the leg keeps ``separation_m + margin_m`` from every other drone: where
each is now and where its velocity takes it within ``horizon_s`` (a drone flying home at 5 m/s
sweeps 100 m in 20 s). Otherwise the helper holds where it is and tries again every tick; what it
waits for goes in the timeline.

Positions: ENU metres in the caller's :class:`skyfix.geo.LocalFrame`; heights of mission items
above home (the autopilot's own height, so the fused and the autopilot's datums need not agree).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from skyfix.crps.vantage import path_clearance
from skyfix.drivers.mav import mavlink as M
from skyfix.drivers.modes import role_mode
from skyfix.errors import SkyfixError
from skyfix.mission import MissionItem

log = logging.getLogger(__name__)

# commands the autopilot flies to a position (lat/lon 0, 0: where the vehicle is)
_NAV_TO = (M.MAV_CMD_NAV_WAYPOINT, M.MAV_CMD_NAV_SPLINE_WAYPOINT, M.MAV_CMD_NAV_LOITER_UNLIM,
           M.MAV_CMD_NAV_LOITER_TURNS, M.MAV_CMD_NAV_LOITER_TIME, M.MAV_CMD_NAV_LOITER_TO_ALT,
           M.MAV_CMD_NAV_LAND, M.MAV_CMD_NAV_TAKEOFF)
_RELATIVE_FRAMES = (M.MAV_FRAME_GLOBAL_RELATIVE_ALT, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT)
_SWEEP_STEP_M = 0.5  # a moving drone's sweep is sampled this finely (the clearance is off by at most half of it)


@dataclass(frozen=True)
class RejoinConfig:
    """When a leg back to the mission is clear (lengths m, times s)."""

    separation_m: float = 10.0   # the helpers' separation from every drone (VantageConfig.min_separation_m)
    # on top: the others' fixes and this one's against the swarm's GNSS frame (~1 m each in the benchmark's
    # world) and the autopilot's tracking of a straight leg in wind
    margin_m: float = 2.0
    horizon_s: float = 20.0      # a drone's velocity counts this far ahead
    climb_max_m: float = 40.0    # a blocked leg may start with a climb straight up of at most this much
    # the mission read-back blocks the help loop's command worker this long at most (a few hundred items over a
    # lossy telemetry radio fit; a dead link must not hold up the commands of a new assignment for a minute)
    read_timeout_s: float = 30.0
    stagger_s: float = 3.0       # helpers released together check their legs this far apart (id order)


@dataclass(frozen=True)
class Leg:
    """The straight leg the autopilot will fly on resuming: to ``goal_enu_m`` (None: none, it stays)."""

    goal_enu_m: np.ndarray | None
    what: str  # for the timeline: "waypoint 4", "home", "the mission's end"


def leg_clearance_m(start_enu_m, goal_enu_m, others_enu_m, others_vel_enu_mps=None, horizon_s: float = 20.0
                    ) -> np.ndarray:
    """(N,) how close the straight leg ``start`` -> ``goal`` (3,) comes to each of ``others_enu_m`` (N, 3): to
    where each is now and anywhere its velocity (N, 3; rows of NaN or None: standing still) takes it within
    ``horizon_s``. Whatever the two speeds, so a leg that crosses another drone's track is never clear.

    Example:
        >>> leg_clearance_m([0, 0, 30], [100, 0, 30], [[50, 20, 30], [50, 20, 30]],
        ...                 [[0, 0, 0], [0, -5, 0]]).round(1).tolist()
        [20.0, 0.0]
    """
    start = np.asarray(start_enu_m, dtype=float).reshape(3)
    goal = np.asarray(goal_enu_m, dtype=float).reshape(1, 3)
    pos = np.asarray(others_enu_m, dtype=float).reshape(-1, 3)
    if not len(pos):
        return np.zeros(0)
    vel = np.zeros_like(pos) if others_vel_enu_mps is None else \
        np.nan_to_num(np.asarray(others_vel_enu_mps, dtype=float).reshape(-1, 3), nan=0.0)
    sweep_m = np.linalg.norm(vel, axis=1) * horizon_s
    n = int(max(1, math.ceil(float(sweep_m.max()) / _SWEEP_STEP_M))) + 1
    frac = np.linspace(0.0, 1.0, n)
    samples = pos[:, None, :] + frac[None, :, None] * (vel * horizon_s)[:, None, :]   # (N, n, 3)
    return path_clearance(start, goal, samples.reshape(-1, 3))[0].reshape(len(pos), n).min(axis=1)


def leg_of(items: Sequence[MissionItem], seq: int, autopilot: str, to_enu: Callable[[float, float], np.ndarray],
           own_enu_m: np.ndarray, own_alt_rel_m: float, home_enu_m: np.ndarray | None) -> Leg:
    """The leg the mission mode flies from ``own_enu_m`` with the vehicle's current item ``seq`` (MISSION_CURRENT;
    on ArduPilot its seq counts home as item 0, which :meth:`Vehicle.download_mission` drops). ``to_enu(lat,
    lon)``: horizontal ENU (2,) of a WGS84 point; item heights above home are taken against ``own_alt_rel_m``."""
    own = np.asarray(own_enu_m, dtype=float).reshape(3)
    index = seq - 1 if autopilot == "ardupilot" else seq
    for k in range(max(index, 0), len(items)):
        item = items[k]
        label = f"waypoint {k + 1 if autopilot == 'ardupilot' else k}"
        if item.command == M.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            return Leg(None if home_enu_m is None else np.array([*np.asarray(home_enu_m)[:2], own[2]]), "home")
        if item.command not in _NAV_TO:
            continue  # DO_ and condition commands: run on the way, the autopilot flies on to the next
        here = item.lat_deg == 0.0 and item.lon_deg == 0.0
        xy = own[:2] if here else np.asarray(to_enu(item.lat_deg, item.lon_deg), dtype=float)[:2]
        if item.command == M.MAV_CMD_NAV_LAND:
            up = own[2] - own_alt_rel_m  # down to the take-off ground's height
        elif item.frame in _RELATIVE_FRAMES and math.isfinite(item.alt_m):
            up = own[2] + item.alt_m - own_alt_rel_m
        else:  # AMSL or terrain heights: taken as level with the helper (the horizontal leg decides)
            up = own[2]
        return Leg(np.array([*xy, up]), label)
    return Leg(None, "the mission's end")


class Rejoin:
    """One helper's return to the mode it left, once the way there is clear (see the module doc).

    ``submit(kind, what, fn)`` runs ``fn`` on the help loop's command worker (the mission download blocks
    for its transfer). Call :meth:`start` on release, :meth:`step` every tick until it returns ``"resume"``;
    :meth:`cancel` when the helper is assigned again."""

    def __init__(self, submit: Callable[[str, str, Callable[[], None]], None], cfg: RejoinConfig | None = None
                 ) -> None:
        self.cfg = cfg or RejoinConfig()
        self._submit = submit
        self.active = False
        self._mode: str | None = None
        self._items: list[MissionItem] | None = None
        self._read_failed: str | None = None
        self._seq = -1
        self._flavour = "ardupilot"
        self._check_from_s = -math.inf
        self._blocked_by: str | None = None
        self._notes: list[str] = []
        self.goto_enu_m: np.ndarray | None = None  # with "climb": where to go first (ENU m)

    def start(self, vehicle, resume_mode: str | None, now_s: float = 0.0, team: tuple[str, ...] = (),
              drone_id: str = "") -> None:
        """Released at ``now_s``: the way back to ``resume_mode`` (the mode the helper left) is to be checked.
        ``team``: the helpers of the same request, this one (``drone_id``) included. Released together, each
        first checks its leg :attr:`RejoinConfig.stagger_s` after the one before it (in id order): a helper that
        has just set off shows no velocity yet, so two crossing legs checked at one instant both look clear."""
        self.active, self._mode, self._blocked_by = True, resume_mode, None
        rank = sorted(team).index(drone_id) if drone_id in team else 0
        self._check_from_s = now_s + rank * self.cfg.stagger_s
        self._items, self._read_failed = None, None
        self._flavour = flavour = vehicle.autopilot if vehicle.autopilot == "px4" else "ardupilot"
        if resume_mode == role_mode(flavour, "mission"):
            self._seq = vehicle.state.mission_seq

            def read() -> None:
                try:
                    if flavour == "ardupilot" and vehicle.get_param("MIS_RESTART") == 1:
                        self._seq = 1  # AUTO starts the mission over (AP_Mission::start_or_resume), not resumes
                    self._items = vehicle.download_mission(timeout_s=self.cfg.read_timeout_s)
                except SkyfixError as exc:
                    self._read_failed = str(exc)

            self._submit("mission", "read the mission back", read)

    def cancel(self) -> None:
        self.active = False

    def take_notes(self) -> list[str]:
        notes, self._notes = self._notes, []
        return notes

    def step(self, vehicle, now_s: float, own_enu_m, own_alt_rel_m: float | None,
             others: dict[str, tuple[np.ndarray, object]], to_enu: Callable[[float, float], np.ndarray],
             home_enu_m: np.ndarray | None) -> str | None:
        """``"resume"`` when the helper may go back to its mode now; ``"hold"`` when it must stop where it is,
        ``"climb"`` when it is to climb straight up to :attr:`goto_enu_m` first (each once, when the way is first
        found blocked); else None (waiting: for the mission, or still blocked, or climbing).
        ``others``: id -> (ENU position now (3,), ENU velocity (3,) or None) of every other drone."""
        if not self.active or now_s < self._check_from_s:
            return None
        flavour = self._flavour
        if self._mode == role_mode(flavour, "mission"):
            if self._read_failed is not None:
                return self._go(f"the mission was not read back ({self._read_failed}): back to it unchecked")
            if self._items is None:
                return None
            if own_enu_m is None or own_alt_rel_m is None:
                return None
            leg = leg_of(self._items, self._seq, flavour, to_enu, own_enu_m, own_alt_rel_m, home_enu_m)
        elif self._mode == role_mode(flavour, "rtl"):
            if own_enu_m is None or home_enu_m is None:
                return None
            leg = Leg(np.array([*np.asarray(home_enu_m)[:2], np.asarray(own_enu_m)[2]]), "home")
        else:  # a mode that stays where it is (LOITER, GUIDED, ...)
            return self._go("")
        if leg.goal_enu_m is None or not others:
            return self._go(f"nothing in the way to {leg.what}")
        own = np.asarray(own_enu_m, dtype=float).reshape(3)
        ids = list(others)
        pos = np.array([np.asarray(others[i][0], float).reshape(3) for i in ids])
        vel = np.array([np.full(3, np.nan) if others[i][1] is None else np.asarray(others[i][1], float).reshape(3)
                        for i in ids])
        clear, need = self._clearance(own, leg.goal_enu_m, pos, vel)
        worst = int(np.argmin(clear - need))
        if clear[worst] >= need[worst]:
            return self._go(f"the leg to {leg.what} keeps {float(clear.min()):.0f} m from the others")
        # a helper low beside a landed drone, its leg climbing over it: straight up first, where that is clear
        bound = self.cfg.separation_m + self.cfg.margin_m
        up = max(float(leg.goal_enu_m[2]), float(pos[worst, 2]) + bound)
        climb = np.array([own[0], own[1], up])
        if up > own[2] + 1.0 and up - own[2] <= self.cfg.climb_max_m \
                and all(bool(np.all(c >= n)) for c, n in (self._clearance(own, climb, pos, vel),
                                                          self._clearance(climb, leg.goal_enu_m, pos, vel))):
            self.goto_enu_m = climb
            if self._blocked_by != "climb":
                self._blocked_by = "climb"
                self._notes.append(f"the leg to {leg.what} passes {float(clear[worst]):.1f} m from {ids[worst]}: "
                                   f"climbing {up - own[2]:.0f} m first")
                return "climb"
            return None
        if self._blocked_by != ids[worst]:
            first = self._blocked_by in (None, "climb")  # a climb no longer clear stops too
            self._blocked_by = ids[worst]
            self._notes.append(f"the leg to {leg.what} passes {float(clear[worst]):.1f} m from {ids[worst]}'s "
                               f"track: holding until it is clear")
            return "hold" if first else None
        return None

    def _clearance(self, start: np.ndarray, goal: np.ndarray, pos: np.ndarray, vel: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
        """(N,) the leg's clearance from each other drone and what it needs: the bound, or for a drone closer
        than that at the start (a helper watching a landing) not closing in."""
        clear = leg_clearance_m(start, goal, pos, vel, self.cfg.horizon_s)
        need = np.minimum(self.cfg.separation_m + self.cfg.margin_m, np.linalg.norm(pos - start, axis=1) - 0.5)
        return clear, need

    def _go(self, why: str) -> str:
        self.active = False
        if why:
            self._notes.append(why)
        return "resume"
