"""GPS-loss recovery inside ``skyfix serve``: the help agent on the service's loop, its decisions flown.

:class:`HelpLoop` runs :class:`skyfix.crps.help_agent.HelpAgent` from the service's main loop
(every accepted envelope in, one step per tick with fusion's GNSS health and estimate of this
drone) and acts on its decisions through :mod:`skyfix.drivers`:

- as the requester (its own GNSS lost or rejected): the service injects the fused position
  (GPS_INPUT) for as long as the recovery lasts; the autopilot holds (BRAKE on ArduPilot, AUTO.LOITER
  on PX4), then flies the fault response once helpers position it (RTL by default, the mission,
  or LAND), lands when no helper fix comes; normal again once fusion finds GNSS healthy and consistent (the
  autopilot keeps the mode it is in: a return home is finished, not undone);
- as a helper: it flies to the vantage point with guided setpoints (kept >= 10 m from every
  drone by :func:`skyfix.crps.vantage.vantage_point`), aims the gimbal at the requester's
  newest fix, and its :class:`skyfix.crps.helper_eye.HelperEye` turns camera frames into
  relative observations that are signed and published here; on release it resumes the mode
  it left (its mission) once the leg there keeps clear of the others (:mod:`skyfix.crps.rejoin`).

Autopilot commands block for their acknowledgement, so they run on one worker thread; the
wanted mode is re-commanded until the autopilot reports it (a lost command, a link drop).
Times: the service's clock, s. Positions: WGS84, ellipsoidal heights.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from skyfix import geo
from skyfix.crps import messages as M
from skyfix.crps.help_agent import HelpAgent
from skyfix.crps.help_protocol import HelpConfig, HelperStatus
from skyfix.crps.helper_eye import EyeConfig, HelperEye
from skyfix.crps.node import held_velocity_cov_m2
from skyfix.crps.rejoin import Rejoin, RejoinConfig
from skyfix.crps.return_speed import ReturnSpeed
from skyfix.crps.roles import FaultResponse, HelperDecision, Mode, RequesterConfig
from skyfix.crps.vantage import VantageConfig
from skyfix.drivers.modes import role_mode
from skyfix.errors import SkyfixError
from skyfix.fusion.health import HealthState
from skyfix.types import GeoFix

log = logging.getLogger(__name__)

RECOMMAND_WALL_S = 2.0  # a wanted mode not reported by the autopilot after this long is commanded again
# the companion's backstop for a landing the autopilot's own land detector misses: in its LAND mode, at most this high
# above home and still (vertical speed under LANDED_STILL_MPS) for LANDED_FOR_S of the clock, the drone is on the
# ground (LAND descends until it touches), and it is disarmed (forced: ArduPilot refuses a GCS disarm before its
# land detector fires). Loaded SITL runs touched down, the position controller wound up to 20-30 deg of demanded
# tilt against the ground after the touchdown's jolt, the throttle mix never reached its minimum and the copter
# stood armed for 45 s
LANDED_MAX_ALT_M = 1.0
LANDED_STILL_MPS = 0.1
LANDED_FOR_S = 5.0
GOTO_MOVE_M = 2.0       # a vantage point that moved this far is sent again
# a peer's newest estimate is moved on with its velocity for at most this long (s): estimates come at 10 Hz, so an
# older one means they stopped (20 % loss rarely hides more than a few in a row) while the peer's heartbeats may go
# on; held for minutes, a 5 m/s velocity would put the peer hundreds of metres from its last estimate
PEER_MOVE_MAX_S = 3.0
_ROLE_OF = {Mode.HOLD: "hold", Mode.RETURN_HOME: "rtl", Mode.LAND: "land", Mode.CONTINUE: "mission"}


@dataclass(frozen=True)
class HelpSetup:
    """How a service takes part in GPS-loss recovery (``ServiceConfig.help``). ``camera``: the gimbal
    camera used to help (None: this drone asks for help but never offers it)."""

    fault_response: str = "return_home"
    camera: object | None = None
    eye: EyeConfig = field(default_factory=EyeConfig)
    requester: RequesterConfig | None = None
    protocol: HelpConfig | None = None
    vantage: VantageConfig | None = None
    # a vantage point is never lower than this above the helper's home (take-off ground, taken as level around
    # the target's home): low enough that a target landing at its home stays above the helpers' horizon, sky
    # behind it, down to ~2 m (the eye looks 1.5 deg above its horizon: 0.5-0.9 m at 20-35 m)
    min_alt_rel_m: float = 1.5
    on_frame: object | None = None    # HelperEye's on_frame (a harness scoring the camera), else None
    # the requester returns no faster than its helpers fly (VantageConfig.helper_speed_mps): ArduPilot's RTL_SPEED
    # for the recovery (crps/return_speed.py); None: the autopilot's own return speed
    return_speed_mps: float | None = 5.0

    def build(self, service) -> HelpLoop:
        return HelpLoop(service, self)


class _Actions:
    """One worker thread for blocking autopilot commands; a newer command of a kind replaces a waiting one."""

    def __init__(self, name: str) -> None:
        self._pending: dict[str, tuple[str, object]] = {}
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self.busy = False
        self._last_failure: dict[str, str] = {}  # what -> the text of its last failure (logged once at warning level)
        self._thread = threading.Thread(target=self._run, daemon=True, name=name)
        self._thread.start()

    def submit(self, kind: str, what: str, fn) -> None:
        with self._lock:
            self._pending[kind] = (what, fn)
        self._wake.set()

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=5.0)

    def _run(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(0.5)
            self._wake.clear()
            while not self._stop.is_set():
                with self._lock:
                    if not self._pending:
                        break
                    what, fn = self._pending.pop(next(iter(self._pending)))
                    self.busy = True
                try:
                    fn()
                except SkyfixError as exc:  # refused, timed out, link down: the loop asks again later
                    # the same refusal once as a warning (e.g. ArduPilot refusing BRAKE while its EKF has no position
                    # after a hold's injection ended: retried every RECOMMAND_WALL_S until it has one again)
                    level = logging.DEBUG if self._last_failure.get(what) == str(exc) else logging.WARNING
                    self._last_failure[what] = str(exc)
                    log.log(level, "%s failed: %s", what, exc)
                else:
                    self._last_failure.pop(what, None)
                finally:
                    self.busy = False


class HelpLoop:
    """The help roles of ``service`` (a :class:`skyfix.crps.service.Service` with a node and a vehicle)."""

    def __init__(self, service, setup: HelpSetup) -> None:
        self.svc, self.setup = service, setup
        self.id = service.cfg.drone_id
        home = service.vehicle.state.home
        self.home = (home.lat_deg, home.lon_deg, home.alt_ellipsoid_m)
        rcfg = setup.requester or RequesterConfig(fault_response=FaultResponse.parse(setup.fault_response))
        self.agent = HelpAgent(service.codec, service.transport, service.peers, self.home, service.node.frame,
                               requester_cfg=rcfg, help_cfg=setup.protocol, vantage_cfg=setup.vantage)
        self.eye = HelperEye(setup.camera, self.id, lambda t: service.node.fix(self.id, t), service.clock,
                             setup.eye, on_frame=setup.on_frame) if setup.camera is not None else None
        self.events: list[tuple[float, str]] = []  # the timeline: (clock s, what happened)
        self.mode = Mode.NORMAL
        self.helping: str | None = None
        self.helpers: tuple[str, ...] = ()
        self._status = HelperStatus(*self.home, 1.0, localised=False, available=False)
        self._peer_fix: dict[str, tuple[GeoFix, np.ndarray]] = {}
        self._want: str | None = None
        self._want_sent_wall_s = -math.inf
        self._resume: str | None = None
        self._goto_enu: np.ndarray | None = None
        self._height: tuple[float, float] | None = None  # (autopilot's height above home m, own fused ENU up m)
        self._still_since_s: float | None = None  # landing: on the ground and still since (clock s)
        self._actions = _Actions(f"skyfix-help-{self.id}")
        self._speed = ReturnSpeed(setup.return_speed_mps, self._actions.submit)
        sep_m = (setup.vantage or VantageConfig()).min_separation_m
        self._rejoin = Rejoin(self._actions.submit, RejoinConfig(separation_m=sep_m))
        self._others: dict[str, tuple[np.ndarray, np.ndarray | None]] = {}  # ENU now, velocity (fresh) or None
        self._team: tuple[str, ...] = ()  # the helpers of the request this one helps (itself included)

    @property
    def recovering(self) -> bool:
        """True while this drone flies without its own GNSS (hold, fault response, landing)."""
        return self.mode is not Mode.NORMAL

    @property
    def landing_low(self) -> bool:
        """Landing at or below the requester's ``land_below_m`` (:meth:`RequesterRole.landing_low`)."""
        return self.agent.requester.landing_low(self.svc.node.latest.get(self.id),
                                                None if self._height is None else self._height[0])

    def close(self) -> None:
        if self.eye is not None:
            self.eye.close()
        self._actions.close()
        try:  # the worker has stopped: written back here, the autopilot keeps what it stores
            self._speed.restore(self.svc.vehicle, now=True)
        except SkyfixError as exc:
            log.warning("%s: RTL_SPEED not restored: %s", self.id, exc)

    # -- service hooks ---------------------------------------------------------------------------
    def receive(self, env: M.Envelope, now_s: float) -> None:
        """Every accepted envelope (main loop)."""
        body = env.body
        if isinstance(body, M.FusedEstimate):
            try:
                self._peer_fix[env.sender] = (M.estimate_fix(body, env.sender), np.asarray(body.vel_enu_mps, float))
            except (SkyfixError, ValueError):
                pass  # counted by the service's own handling of the same message
        self.agent.receive(env, now_s, self._status)

    def step(self, now_s: float, state) -> None:
        """One tick after fusion: decide, act, publish the camera's observations."""
        node = self.svc.node
        fused = node.latest.get(self.id)
        gnss = node.engine.health(self.id).get("gnss") if self.id in node.engine.drone_ids else None
        self._status = self._my_status(now_s, state, gnss)
        peers = {p.drone_id: (p.lat_deg, p.lon_deg, p.alt_m) for p in self.svc.peers.snapshot()
                 if not p.lost and math.isfinite(p.lat_deg) and math.isfinite(p.alt_m)}
        # a peer's newest fix moved on to now with its velocity: a drone flying home at 5 m/s is metres past its
        # last estimate, and where it goes decides which vantage points stay clear of it
        velocities = {}
        for pid in peers:
            known = self._peer_fix.get(pid)
            if known is not None and np.all(np.isfinite(known[1])):
                now_fix, vel = _peer_now(known[0], known[1], now_s)
                peers[pid] = (now_fix.lat_deg, now_fix.lon_deg, now_fix.alt_m)
                if vel is not None:
                    velocities[pid] = vel
        # where the others are now (ENU, velocity when fresh): a released helper's way back is checked against it,
        # from the tick of its release on (kept every tick: a few peers)
        frame = self.svc.node.frame
        self._others = {pid: (np.asarray(frame.to_enu(*p), float), velocities.get(pid)) for pid, p in peers.items()
                        if pid != self.id}
        self._height = _height(self.svc.node, self.id, now_s, state)
        floor_up_m = -math.inf if self._height is None else self._height[1] - self._height[0] + self.setup.min_alt_rel_m
        decisions = self.agent.step(now_s, gnss, fused, self._status, peers, floor_up_m=floor_up_m,
                                    alt_rel_m=None if self._height is None else self._height[0],
                                    peer_velocities=velocities)
        if self.recovering and state is not None and state.position is not None and not state.armed \
                and self.agent.requester.protocol.active:
            self.agent.stand_down(now_s, "landed")  # on the ground: nothing left to help with
            self._event(now_s, "landed: helpers released")
            self._speed.restore(self.svc.vehicle)
        self._as_requester(now_s, decisions.requester)
        self._landed_backstop(now_s, state)
        self._as_helper(now_s, decisions.helper)
        if self.eye is not None:
            for obs in self.eye.take():
                self.svc._publish(M.relative_message(obs))
        self._command_mode(state)

    # -- decisions -> autopilot ------------------------------------------------------------------
    def _my_status(self, now_s: float, state, gnss) -> HelperStatus:
        fix = self.svc.node.fix(self.id, now_s, frame=True)  # placed against the others: the shared error left out
        battery = state.battery.remaining_pct / 100.0 if state is not None and state.battery is not None \
            and math.isfinite(state.battery.remaining_pct) else 0.0
        if fix is None:
            return HelperStatus(*self.home, battery, localised=False, available=False)
        # flying: above half the helpers' floor (a helper looking at a landing target flies at the floor; at
        # 2 m, the bound before the floor came down to 1.5 m, it withdrew as "recalled" in the target's descent)
        airborne = state is not None and state.armed and state.position is not None \
            and state.position.alt_rel_m > 0.5 * self.setup.min_alt_rel_m
        # localised while its GNSS is fused: DEGRADED is a fused fix with a quality flag or one innovation outlier
        # dropped (a helper braking hard at its vantage point). Withdrawing on it (then barred for exclude_s) cost
        # the demo flight both helpers for 10 s each; the requester, too, holds only on LOST or REJECTED
        localised = gnss is not None and gnss.state in (HealthState.OK, HealthState.DEGRADED) \
            and fix.sigma_horizontal_m <= 3.0
        return HelperStatus(fix.lat_deg, fix.lon_deg, fix.alt_m, battery, localised=localised,
                            available=self.eye is not None and airborne)

    def note(self, now_s: float, text: str) -> None:
        """A help event from the service (timeline, log, the /help/event channel)."""
        self._event(now_s, text)

    def _event(self, now_s: float, text: str) -> None:
        self.events.append((now_s, text))
        log.info("%s: %s", self.id, text)
        self.svc.outputs.json("/help/event", {"time_s": now_s, "drone": self.id, "event": text}, now_s)

    def _as_requester(self, now_s: float, dec) -> None:
        note = self._speed.take_note()
        if note is not None:
            self._event(now_s, note)
        if dec.mode is not self.mode:
            self._event(now_s, f"{dec.mode.value} ({dec.reason})")
            if self.mode is Mode.NORMAL:
                self._speed.limit(self.svc.vehicle, self._flavour())
            elif dec.mode is Mode.NORMAL:
                self._speed.restore(self.svc.vehicle)
            self.mode = dec.mode
            role = _ROLE_OF.get(dec.mode)
            self._want = None if role is None else _requester_mode(self._flavour(), role)
            self._want_sent_wall_s = -math.inf
        if dec.helpers != self.helpers:
            gone = [h for h in self.helpers if h not in dec.helpers]
            why = {h: w for _, w, h in self.agent.requester.protocol.events if h in gone}  # the newest per helper
            left = "; ".join(f"{h} {why.get(h, 'released')}" for h in gone)
            self.helpers = dec.helpers
            self._event(now_s, f"helpers assigned: {', '.join(dec.helpers) or 'none'}" + (f" ({left})" if left else ""))

    def _landed_backstop(self, now_s: float, state) -> None:
        """Disarm a drone its autopilot has landed in LAND but not disarmed (LANDED_* above)."""
        vehicle = self.svc.vehicle
        pos, vel = (state.position, state.velocity) if state is not None else (None, None)
        landing = self.mode is Mode.LAND and state is not None and state.armed and state.mode == self._land_mode()
        still = landing and pos is not None and vel is not None and math.isfinite(pos.alt_rel_m) \
            and pos.alt_rel_m <= LANDED_MAX_ALT_M and abs(vel.down_mps) < LANDED_STILL_MPS
        if not still:
            self._still_since_s = None
            return
        if self._still_since_s is None:
            self._still_since_s = now_s
        if now_s - self._still_since_s >= LANDED_FOR_S and vehicle is not None and not self._actions.busy:
            self._still_since_s = None  # once per LANDED_FOR_S: the next try waits as long
            self._event(now_s, f"still on the ground {LANDED_FOR_S:.0f} s in {state.mode}, autopilot armed: disarming")
            self._actions.submit("disarm", f"{self.id} disarm (landed)", lambda: vehicle.disarm(force=True))

    def _land_mode(self) -> str:
        return _requester_mode(self._flavour(), _ROLE_OF[Mode.LAND])

    def _as_helper(self, now_s: float, dec: HelperDecision) -> None:
        vehicle = self.svc.vehicle
        if dec.helping != self.helping:
            if dec.helping is not None:
                self._event(now_s, f"helping {dec.helping}")
                if self.helping is None and vehicle is not None and not self._rejoin.active:
                    # a resume commanded but not yet reported by the autopilot is still the mode to go back to
                    self._resume = self._want or vehicle.state.mode
                self._rejoin.cancel()
                self._want = None
            else:
                why = next((w for _, w, _ in reversed(self.agent.helper.protocol.events) if w.startswith("released")),
                           "released")
                self._event(now_s, f"{why.replace('released', 'released by ' + str(self.helping), 1)}, back to "
                                   f"{self._resume or 'its mission'} once its way there is clear")
                if vehicle is not None:
                    self._rejoin.start(vehicle, self._resume, now_s, self._team, self.id)
                else:
                    self._want, self._want_sent_wall_s = self._resume, -math.inf
                self._goto_enu = None
            self.helping = dec.helping
            if self.eye is not None and dec.helping is None:
                self.eye.set_target(None)
        if dec.helping is None and vehicle is not None:
            self._way_back(now_s, vehicle)
        if dec.helping is None or vehicle is None:
            return
        self._team = self.agent.helper.protocol.team  # kept for the release, which clears it
        if dec.vantage is not None:
            v = dec.vantage.enu_m
            if self._goto_enu is None or float(np.linalg.norm(v - self._goto_enu)) > GOTO_MOVE_M:
                self._goto_enu = v.copy()
                lat, lon, alt = (float(c) for c in self.svc.node.frame.to_geodetic(*v))
                # heights above home from the autopilot's own (barometric) height: home's altitude from HOME_POSITION
                # (AMSL + the geoid) and the fused GNSS altitudes need not share a datum (ArduPilot SITL: no geoid)
                alt_rel = alt - self.home[2] if self._height is None else self._height[0] + float(v[2]) - self._height[1]
                alt_rel = max(alt_rel, self.setup.min_alt_rel_m)
                self._actions.submit("move", f"{self.id} goto vantage",
                                     lambda: vehicle.goto(lat, lon, alt_rel))
        elif self._goto_enu is not None and self._height is not None:
            # no vantage clear of the others: stop where it is rather than fly on to a point chosen when the target
            # was elsewhere (a moving target may be heading for it)
            own = self.svc.node.fix(self.id, now_s)
            if own is not None:
                self._goto_enu = None
                alt_rel = max(self._height[0], self.setup.min_alt_rel_m)
                self._event(now_s, "no vantage clear of the others: holding")
                self._actions.submit("move", f"{self.id} hold",
                                     lambda: vehicle.goto(own.lat_deg, own.lon_deg, alt_rel))
        self._aim(now_s, dec.helping, dec.target)

    def _way_back(self, now_s: float, vehicle) -> None:
        """Released: back to the mode it left once the leg there keeps clear of the others (crps/rejoin.py)."""
        if not self._rejoin.active:
            return
        if self.recovering:  # its own GNSS lost meanwhile: the requester's modes rule
            self._rejoin.cancel()
            return
        own = self.svc.node.fix(self.id, now_s)
        frame = self.svc.node.frame
        own_enu = None if own is None else np.asarray(frame.to_enu(own.lat_deg, own.lon_deg, own.alt_m), float)
        home = vehicle.state.home  # only its horizontal position is used (an RTL leg is flown at the helper's height)
        home_enu = None if home is None else np.asarray(frame.to_enu(home.lat_deg, home.lon_deg, 0.0), float)
        verdict = self._rejoin.step(vehicle, now_s, own_enu, None if self._height is None else self._height[0],
                                    self._others, lambda lat, lon: np.asarray(frame.to_enu(lat, lon, 0.0))[:2],
                                    home_enu)
        for note in self._rejoin.take_notes():
            self._event(now_s, note)
        if verdict == "resume":
            self._want, self._want_sent_wall_s = self._resume, -math.inf
        elif verdict in ("hold", "climb") and own is not None and self._height is not None:
            up_m = self._height[0] if verdict == "hold" else self._height[0] + float(self._rejoin.goto_enu_m[2]
                                                                                     - own_enu[2])
            alt_rel = max(up_m, self.setup.min_alt_rel_m)
            self._actions.submit("move", f"{self.id} {verdict} (way back blocked)",
                                 lambda: vehicle.goto(own.lat_deg, own.lon_deg, alt_rel))

    def _aim(self, now_s: float, target_id: str, target_pos) -> None:
        """Gimbal at where this helper's own eye last saw the target (fresh), else at the target's newest fix,
        moved to now with the target's velocity; the eye searches around that fix (its prior gate)."""
        if self.eye is None:
            return
        own = self.svc.node.fix(self.id, now_s)
        known = self._peer_fix.get(target_id)
        vel = None
        if known is not None:
            prior, vel = _peer_now(known[0], known[1], now_s)
        elif target_pos is not None:
            prior = GeoFix(*target_pos, np.diag([25.0, 25.0, 9.0]), now_s, f"request:{target_id}")
        else:
            return
        # a fix a few metres off at 30 m puts the target at the frame's edge and the next fix further off:
        # the camera follows what it sees, while the search window stays the requester's fix
        seen = self.eye.sighting(target_id, now_s)
        aim = prior if seen is None else _moved(seen, np.zeros(3) if vel is None else vel, now_s)
        if own is not None:
            az_deg, dist_m = geo.inverse(own.lat_deg, own.lon_deg, aim.lat_deg, aim.lon_deg)
            pitch_deg = math.degrees(math.atan2(aim.alt_m - own.alt_m, max(float(dist_m), 1e-3)))
            self.eye.point(float(az_deg), pitch_deg)
        self.eye.set_target(target_id, prior)

    def _command_mode(self, state) -> None:
        """Command the wanted mode until the autopilot reports it."""
        vehicle = self.svc.vehicle
        want = self._want
        if want is not None and getattr(self.svc, "injection_withheld", False):
            # no position is injected (a hover nothing measured past its bound, or the wind-up guard): the autopilot's
            # own position is no better than dead reckoning, so it lands, as its GPS-loss failsafe would (SITL: after
            # the failsafe cleared for a second, BRAKE commanded again flew a wound-up controller on for 12 s)
            want = self._land_mode()
        if want is None or vehicle is None or state is None or not state.link_ok:
            return
        if state.mode == want:
            if not self.recovering:
                self._want = None  # back on its mission: the mission's own mode changes are its business
            return
        if time.monotonic() - self._want_sent_wall_s < RECOMMAND_WALL_S or self._actions.busy:
            return
        self._want_sent_wall_s = time.monotonic()
        self._actions.submit("mode", f"{self.id} mode {want}", lambda: vehicle.set_mode(want))

    def _flavour(self) -> str:
        vehicle = self.svc.vehicle
        return vehicle.autopilot if vehicle is not None and vehicle.autopilot in ("ardupilot", "px4") else "ardupilot"


def _height(node, drone_id: str, now_s: float, state) -> tuple[float, float] | None:
    """(the autopilot's height above home m, the drone's fused ENU up m in ``node``'s frame) now, or None."""
    pos = state.position if state is not None else None
    fix = node.fix(drone_id, now_s)
    if pos is None or fix is None or not math.isfinite(pos.alt_rel_m):
        return None
    return float(pos.alt_rel_m), float(node.frame.to_enu(fix.lat_deg, fix.lon_deg, fix.alt_m)[2])


def _moved(fix: GeoFix, vel_enu_mps: np.ndarray, now_s: float) -> GeoFix:
    """``fix`` moved on to ``now_s`` at ``vel_enu_mps`` (ENU m/s; never back in time)."""
    frame = geo.LocalFrame(fix.lat_deg, fix.lon_deg, fix.alt_m)
    lat, lon, alt = (float(c) for c in frame.to_geodetic(*(vel_enu_mps * max(0.0, now_s - fix.time_s))))
    return GeoFix(lat, lon, alt, fix.cov_enu_m2, now_s, fix.source_id)


def _peer_now(fix: GeoFix, vel_enu_mps: np.ndarray, now_s: float) -> tuple[GeoFix, np.ndarray | None]:
    """A peer's newest estimate moved to ``now_s`` at its velocity (ENU m/s), and the velocity to plan with.

    An estimate older than :data:`PEER_MOVE_MAX_S` is moved that far and no further, and its velocity is not
    passed on (None): nothing says the peer still flies it. The covariance grows with the estimate's age as
    :meth:`skyfix.crps.node.Node.fix`'s does (a drone braking or turning at its autopilot's acceleration)."""
    age_s = max(0.0, now_s - fix.time_s)
    moved = _moved(fix, vel_enu_mps, min(now_s, fix.time_s + PEER_MOVE_MAX_S))
    out = GeoFix(moved.lat_deg, moved.lon_deg, moved.alt_m, moved.cov_enu_m2 + held_velocity_cov_m2(age_s), now_s,
                 fix.source_id)
    return out, (vel_enu_mps if age_s <= PEER_MOVE_MAX_S else None)


def _requester_mode(flavour: str, role: str) -> str:
    """The autopilot mode the requester flies for ``role``. Hold on ArduPilot is BRAKE, not LOITER: ArduCopter's
    LOITER climbs or sinks on the pilot's throttle stick wherever it rests (SITL's simulated stick at 1000 sank
    the lost drone at 2.5 m/s to the ground), BRAKE holds the position whatever the sticks say."""
    if role == "hold" and flavour == "ardupilot":
        return "BRAKE"
    return role_mode(flavour, role)
