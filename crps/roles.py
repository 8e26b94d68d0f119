"""What a drone does about GNSS loss, its own or a neighbour's: decisions as data.

:class:`RequesterRole` watches its own GNSS health as fusion reports it
(:meth:`skyfix.fusion.FusionEngine.health`): on loss or rejection it holds and asks for help
(:class:`skyfix.crps.help_protocol.HelpRequester`); once its fused position rests on helpers'
observations and is tight enough it flies the configured fault response (return home by
default, continue, or land); without such a fix for ``hold_timeout_s`` it lands; GNSS healthy
for ``gnss_ok_for_s`` (fusion readmits it only when consistent) ends it all. :class:`HelperRole`
answers requests (:class:`skyfix.crps.help_protocol.HelpResponder`) and, while helping, gives
the vantage point to fly to and the camera pointing (:func:`skyfix.crps.vantage.vantage_point`).
Nothing here talks to an autopilot: the service or the simulator acts on the decisions.
Times are seconds on the swarm's clock; geodetic positions WGS84 with ellipsoidal heights.
"""

from __future__ import annotations

import enum
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import numpy as np

from skyfix import geo
from skyfix.crps.help_protocol import HelpConfig, HelperStatus, HelpRequester, HelpResponder
from skyfix.crps.messages import Body, Envelope
from skyfix.crps.vantage import Vantage, VantageConfig, vantage_point
from skyfix.errors import InputError
from skyfix.fusion.estimate import Estimate
from skyfix.fusion.health import HealthState, SourceHealth
from skyfix.geo import LocalFrame
from skyfix.types import GeoFix


class FaultResponse(str, enum.Enum):
    """What the requester does once it is positioned by its helpers."""

    RETURN_HOME = "return_home"
    CONTINUE = "continue"
    LAND = "land"

    @classmethod
    def parse(cls, value: str) -> FaultResponse:
        try:
            return cls(str(value))
        except ValueError:
            raise InputError(f"fault response must be one of {[m.value for m in cls]}, got {value!r}") from None


class Mode(str, enum.Enum):
    NORMAL = "normal"            # own GNSS healthy: the mission as planned
    HOLD = "hold"                # GNSS lost, no helper-based fix yet: hold position, ask for help
    RETURN_HOME = "return_home"
    CONTINUE = "continue"
    LAND = "land"


@dataclass(frozen=True)
class RequesterConfig:
    """Requester decisions (times s, lengths m)."""

    fault_response: FaultResponse = FaultResponse.RETURN_HOME
    gnss_ok_for_s: float = 3.0       # GNSS healthy this long before normal operation again
    fused_sigma_h_max_m: float = 3.0  # a helper-based fix this tight (1-sigma) is good enough to fly on
    # ... and, once flown on, until it is looser than this: a fix whose sigma wanders about the entry bound
    # (between two helpers' frames) would otherwise switch hold / fault response at every estimate
    fused_sigma_h_keep_m: float = 4.0
    fix_max_age_s: float = 2.0       # an older fused estimate does not count
    hold_timeout_s: float = 90.0     # no usable fix for this long while holding: land
    # returning home when the helper fix goes, the drone lands where it is if it is low (the helpers lose a
    # landing drone under their horizon: nothing better comes) and this close to home (fused, horizontal), or
    # high and sure of home (the fix's land_sigma_k-sigma circle inside land_sure_within_m: where it lands then
    # is where it is, so no further from home than a landing that counts as home); else it holds for the helpers,
    # who see it again at height (benchmarks/recovery.py seed 8 on 14cd873: the helpers lost it for 4 s at 15 m on
    # its way in at 5 m/s, 5 m from home by a 1.1 m-sigma fix, and under the 6 m radius it landed there, 5.24 m off)
    land_near_home_m: float = 6.0
    land_sure_within_m: float = 3.0
    # "low", m above home: the helpers (never under 1.5 m) keep a landing drone above their horizon down to
    # ~2-3 m; holding unobserved drifts (an autopilot flying on a held injected position: up to 2 m/s on SITL)
    land_below_m: float = 5.0
    land_sigma_k: float = 2.0


@dataclass(frozen=True)
class Decision:
    """The requester's mode since ``since_s`` and why; ``setpoint`` (lat_deg, lon_deg, alt_m) to fly to
    (hold: the last good fix; return home: home; land: the present fused position; else None)."""

    mode: Mode
    reason: str
    since_s: float
    setpoint: tuple[float, float, float] | None
    helpers: tuple[str, ...]


def _helper_based(est: Estimate | None, now_s: float, cfg: RequesterConfig, flying_on_it: bool = False) -> bool:
    """A fused estimate that rests on helpers' observations and is tight and fresh enough to fly on
    (``flying_on_it``: to keep flying on, the looser bound ``fused_sigma_h_keep_m``). Its sigma in the swarm's
    GNSS frame counts: home and the helpers carry the receivers' shared error too, so that error, however large
    the receivers' stated accuracy makes it, never keeps a drone from flying home on its helpers."""
    sigma_max_m = cfg.fused_sigma_h_keep_m if flying_on_it else cfg.fused_sigma_h_max_m
    return (est is not None and now_s - est.time_s <= cfg.fix_max_age_s
            and any(s.startswith("relative:") for s in est.sources)
            and est.sigma_frame_horizontal_m <= sigma_max_m)


@dataclass
class RequesterRole:
    """The requester behaviour of drone ``drone_id`` with ``home`` (lat_deg, lon_deg, alt_m)."""

    drone_id: str
    home: tuple[float, float, float]
    cfg: RequesterConfig = field(default_factory=RequesterConfig)
    help_cfg: HelpConfig = field(default_factory=HelpConfig)
    mode: Mode = Mode.NORMAL
    reason: str = "start"
    since_s: float = 0.0
    last_good: GeoFix | None = None
    _gnss_ok_since_s: float | None = None
    _fix_since_s: float | None = None

    def __post_init__(self) -> None:
        self.protocol = HelpRequester(self.drone_id, self.help_cfg)

    def on_message(self, env: Envelope, now_s: float) -> list[Body]:
        return self.protocol.on_message(env, now_s)

    def step(self, now_s: float, gnss: SourceHealth | None, fused: Estimate | None,
             live_peers: Iterable[str], alt_rel_m: float | None = None) -> tuple[Decision, list[Body]]:
        """One decision from fusion's GNSS health and fused estimate of this drone; the help messages to send.
        ``alt_rel_m``: its height above home as its autopilot measures it (barometer), else None (the fused
        altitude less home's is used)."""
        out: list[Body] = []
        healthy = gnss is not None and gnss.state is HealthState.OK
        if self.mode is Mode.NORMAL:
            if healthy and fused is not None:
                self.last_good = GeoFix(fused.lat_deg, fused.lon_deg, fused.alt_m, fused.cov_enu_m2, fused.time_s,
                                        "skyfix.fusion")
            elif gnss is not None and gnss.state in (HealthState.LOST, HealthState.REJECTED) \
                    and self.last_good is not None:
                self._set(Mode.HOLD, f"gnss {gnss.state}: {gnss.reason}", now_s)
                self._gnss_ok_since_s = self._fix_since_s = None
                out += self.protocol.start(now_s, self.last_good)
        else:
            self._gnss_ok_since_s = (self._gnss_ok_since_s or now_s) if healthy else None
            if self._gnss_ok_since_s is not None and now_s - self._gnss_ok_since_s >= self.cfg.gnss_ok_for_s:
                self._set(Mode.NORMAL, "gnss healthy again", now_s)
                out += self.protocol.cancel(now_s, "gnss back")
            else:
                self._recover(now_s, fused, alt_rel_m)
        out += self.protocol.tick(now_s, live_peers, recruit=not self.landing_low(fused, alt_rel_m))
        return Decision(self.mode, self.reason, self.since_s, self._setpoint(fused), self.protocol.helpers()), out

    def _recover(self, now_s: float, fused: Estimate | None, alt_rel_m: float | None) -> None:
        """Hold until helpers position us, then the fault response; back to hold when that fix goes."""
        good = _helper_based(fused, now_s, self.cfg, flying_on_it=self.mode in (Mode.RETURN_HOME, Mode.CONTINUE))
        if self.mode is Mode.HOLD:
            if good:
                self._set(Mode(self.cfg.fault_response.value), "positioned by helpers", now_s)
            elif now_s - self.since_s >= self.cfg.hold_timeout_s:
                self._set(Mode.LAND, f"no helper fix for {self.cfg.hold_timeout_s:.0f} s", now_s)
        elif self.mode in (Mode.RETURN_HOME, Mode.CONTINUE) and not good:
            if self.mode is Mode.RETURN_HOME and self._near_home(fused, alt_rel_m, now_s):
                # over home and low, the helpers lose it against the ground: finish the landing
                self._set(Mode.LAND, "helper fix lost over home", now_s)
            else:
                self._set(Mode.HOLD, "helper fix lost", now_s)

    def landing_low(self, fused: Estimate | None, alt_rel_m: float | None) -> bool:
        """Landing at or below ``land_below_m`` (``alt_rel_m`` the autopilot's height above home, else the fused
        altitude less home's): helpers that lose it are not replaced (new ones would lose it against the ground
        too, and a landed drone's fix moved by their late sightings kept SITL from disarming), and the service
        holds its injected fix at once (:meth:`skyfix.crps.inject_policy.InjectionPolicy.fix`)."""
        if self.mode is not Mode.LAND:
            return False
        height_m = self._height_m(fused, alt_rel_m)
        return height_m is not None and height_m <= self.cfg.land_below_m

    def _height_m(self, fused: Estimate | None, alt_rel_m: float | None) -> float | None:
        """Height above home (m): the autopilot's where known, else the fused altitude less home's; else None."""
        if alt_rel_m is not None and np.isfinite(alt_rel_m):
            return float(alt_rel_m)
        return None if fused is None else fused.alt_m - self.home[2]

    def _near_home(self, fused: Estimate | None, alt_rel_m: float | None, now_s: float) -> bool:
        """Whether a drone returning home that lost its helper fix should land where ``fused`` puts it: near
        home and low, or high and within ``land_sure_within_m`` of home counting the fix's sigma in the swarm's
        GNSS frame, where home is (a fix that
        grew loose in a link drop, 4-6 m off, or a fast drone still metres out is not landed on at height: the
        helpers see it again)."""
        if fused is None:
            return False
        _, dist_m = geo.inverse(fused.lat_deg, fused.lon_deg, self.home[0], self.home[1])
        cfg = self.cfg
        if self._height_m(fused, alt_rel_m) <= cfg.land_below_m:
            return float(dist_m) <= cfg.land_near_home_m
        # a stale estimate's sigma is not its present uncertainty (a MAVLink drop stops the estimates): not sure
        fresh = now_s - fused.time_s <= cfg.fix_max_age_s
        return fresh and float(dist_m) + cfg.land_sigma_k * fused.sigma_frame_horizontal_m <= cfg.land_sure_within_m

    def _setpoint(self, fused: Estimate | None) -> tuple[float, float, float] | None:
        if self.mode is Mode.HOLD and self.last_good is not None:
            return (self.last_good.lat_deg, self.last_good.lon_deg, self.last_good.alt_m)
        if self.mode is Mode.RETURN_HOME:
            return self.home
        if self.mode is Mode.LAND:
            src = fused if fused is not None else self.last_good
            return None if src is None else (src.lat_deg, src.lon_deg, src.alt_m)
        return None

    def _set(self, mode: Mode, reason: str, now_s: float) -> None:
        self.mode, self.reason, self.since_s = mode, reason, now_s


@dataclass(frozen=True)
class HelperDecision:
    """``helping`` whom (None: on its own mission) and, while helping, the vantage to fly to
    (None: no feasible one, hold) and the target's position used (lat_deg, lon_deg, alt_m)."""

    helping: str | None
    vantage: Vantage | None
    target: tuple[float, float, float] | None


@dataclass
class HelperRole:
    """The helper behaviour of drone ``drone_id``; positions in ENU of ``frame``."""

    drone_id: str
    frame: LocalFrame
    vantage_cfg: VantageConfig = field(default_factory=VantageConfig)
    help_cfg: HelpConfig = field(default_factory=HelpConfig)

    def __post_init__(self) -> None:
        self.protocol = HelpResponder(self.drone_id, self.help_cfg)

    def on_message(self, env: Envelope, now_s: float, me: HelperStatus) -> list[Body]:
        return self.protocol.on_message(env, now_s, me)

    def step(self, now_s: float, me: HelperStatus, peers: Mapping[str, tuple[float, float, float]],
             live_peers: Iterable[str], mates_vantage: Mapping[str, np.ndarray] | None = None,
             floor_up_m: float = -np.inf,
             velocities: Mapping[str, np.ndarray] | None = None) -> tuple[HelperDecision, list[Body]]:
        """The helper decision; ``peers`` every other drone's latest position (lat, lon, alt), the
        requester's included when known (else its request's last fix is used); ``mates_vantage`` the
        other helpers' vantage points (ENU) where known, else their present positions are used; ``floor_up_m``
        the lowest this helper may fly (ENU up); ``velocities`` the drones' ENU velocities (m/s) where known:
        a moving requester is judged in its own frame (:func:`skyfix.crps.vantage.vantage_point`)."""
        out: list[Body] = []
        if self.protocol.requester_id is not None and not (me.localised and me.available):
            out += self.protocol.withdraw(now_s, "own position lost" if not me.localised else "recalled")
        self.protocol.tick(now_s, live_peers)
        req_id, req = self.protocol.requester_id, self.protocol.request
        if req_id is None:
            return HelperDecision(None, None, None), out
        target = peers.get(req_id) or (None if req is None else (req.lat_deg, req.lon_deg, req.alt_m))
        if target is None:
            return HelperDecision(req_id, None, None), out
        sigma_h = req.sigma_h_m if req is not None else 0.0
        def enu(p: tuple[float, float, float]) -> np.ndarray:
            return np.array([float(c) for c in self.frame.to_enu(*p)])

        mates = {h: (mates_vantage or {}).get(h) for h in self.protocol.team if h != self.drone_id}
        mates = {h: v if v is not None else enu(peers[h]) for h, v in mates.items() if v is not None or h in peers}
        others = [enu(p) for h, p in peers.items() if h != req_id and h not in mates]
        target_vel = (velocities or {}).get(req_id) if req_id in peers else None
        v = vantage_point(enu(target), enu((me.lat_deg, me.lon_deg, me.alt_m)), others, list(mates.values()),
                          target_sigma_h_m=sigma_h, floor_up_m=floor_up_m, target_vel_enu_mps=target_vel,
                          cfg=self.vantage_cfg)
        return HelperDecision(req_id, v, tuple(target)), out
