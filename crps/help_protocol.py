"""The help protocol: a drone without GNSS asks its neighbours to come and look at it.

Two pure state machines over the signed swarm messages (:mod:`skyfix.crps.messages`), with the
clock injected (every method takes ``now_s``, seconds on the swarm's shared clock) and no I/O:
each returns the message bodies to publish on the ``help`` topic.

- :class:`HelpRequester` (the drone that lost GNSS): broadcasts a :class:`HelpRequest` with its
  last good fix, collects offers for ``offer_window_s``, assigns the best ``helpers_wanted``
  (:func:`select_helpers`: distance/ETA, battery and the spread of their bearings seen from the
  last fix), repeats request and assignment every ``retry_s`` until answered (a lossy link still
  ends assigned), replaces a helper that declines, does not acknowledge within ``ack_timeout_s``,
  goes quiet (the peer table's lost signal) or sends no observation of it (none by its ETA +
  ``obs_grace_s``, or none for ``obs_timeout_s``: the target left its view), and releases
  everyone on cancel. It fuses the
  helpers' observations itself, so there is no leader: :meth:`HelpRequester.helpers` is the
  roster of observers to trust.
- :class:`HelpResponder` (every other drone): offers or declines, acknowledges an assignment,
  and is released by a release, a cancel, or a requester silent for ``abandon_after_s``.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from skyfix import geo
from skyfix.crps.messages import (
    Body,
    Envelope,
    HelpAssign,
    HelpRelease,
    HelpRequest,
    HelpResponse,
    RelativeObs,
)
from skyfix.crps.swarm import LOST_AFTER_S
from skyfix.types import GeoFix

log = logging.getLogger(__name__)

MAX_CANDIDATES = 8  # offers ranked by their own cost before the combinatorial geometry search


@dataclass(frozen=True)
class HelpConfig:
    """Protocol timing and helper-selection weights (times in s)."""

    helpers_wanted: int = 2
    offer_window_s: float = 1.0     # offers collected this long after a new request before assigning
    retry_s: float = 0.5            # request / assignment repeated this often while unanswered
    ack_timeout_s: float = 2.5      # an assigned helper silent about its assignment this long is replaced
    offer_max_age_s: float = 5.0    # an older offer is not used (the helper has moved on)
    exclude_s: float = 10.0         # a replaced helper is not assigned again for this long
    quiet_after_s: float = LOST_AFTER_S  # what the peer table calls lost
    obs_grace_s: float = 10.0       # after its ETA, a helper with no observation of the requester is replaced
    obs_timeout_s: float = 5.0      # ... and one whose observations stopped for this long (target out of view)
    abandon_after_s: float = 10.0   # a helper goes back to its mission when its requester is silent this long
    min_battery_frac: float = 0.3   # below this share a drone declines (and offers from it are ignored)
    eta_ref_s: float = 30.0         # an ETA of this many seconds costs 1
    w_battery: float = 1.0          # cost of an empty battery (1 - share)
    w_geometry: float = 1.0         # cost of collinear helpers (1 - geometry_quality)
    cruise_mps: float = 8.0         # helper's transit speed for its ETA, m/s


@dataclass(frozen=True)
class Offer:
    """One helper's offer: its position (WGS84, ellipsoidal m), battery share 0-1, distance to the
    requester's last fix, m, and ETA, s, received at ``time_s``."""

    helper_id: str
    time_s: float
    lat_deg: float
    lon_deg: float
    alt_m: float
    battery_frac: float
    distance_m: float
    eta_s: float


def geometry_quality(bearings_deg) -> float | np.ndarray:
    """How well horizontal bearings (deg from north) spread, 0 (collinear) to 1 (evenly spread);
    ``(..., k)`` bearings give ``(...)`` qualities (a float for one set).

    Each line of sight constrains the target across it (information ``I - u u^T``); the
    quality is the weakest direction's information over the best possible, ``k/2``."""
    az = np.radians(np.asarray(list(bearings_deg) if not isinstance(bearings_deg, np.ndarray) else bearings_deg,
                               dtype=float))
    k = az.shape[-1] if az.ndim else 1
    if k < 2:
        return 0.0 if az.ndim <= 1 else np.zeros(az.shape[:-1])
    e, n = np.sin(az), np.cos(az)
    a, b, c = k - (e * e).sum(-1), -(e * n).sum(-1), k - (n * n).sum(-1)  # info = [[a, b], [b, c]]
    lam_min = 0.5 * (a + c) - np.sqrt(0.25 * (a - c) ** 2 + b * b)
    q = np.clip(lam_min / (k / 2.0), 0.0, 1.0)
    return float(q) if az.ndim == 1 else q


def own_cost(offer: Offer, cfg: HelpConfig) -> float:
    """A helper's cost on its own: ETA over ``eta_ref_s`` plus the battery it lacks."""
    return offer.eta_s / cfg.eta_ref_s + cfg.w_battery * (1.0 - offer.battery_frac)


def select_helpers(offers: list[Offer], fix_lat_deg: float, fix_lon_deg: float, need: int,
                   cfg: HelpConfig, kept: tuple[Offer, ...] = ()) -> tuple[str, ...]:
    """The ``need`` helper ids of ``offers`` (best first) that, with the ``kept`` helpers, minimise the
    mean own cost plus ``w_geometry * (1 - geometry_quality)`` of the bearings from the fix."""
    usable = [o for o in offers if o.battery_frac >= cfg.min_battery_frac and math.isfinite(o.eta_s)]
    usable = sorted(usable, key=lambda o: own_cost(o, cfg))[:MAX_CANDIDATES]
    need = min(need, len(usable))
    if need <= 0:
        return ()
    everyone = list(kept) + usable
    az, _ = geo.inverse(np.full(len(everyone), fix_lat_deg), np.full(len(everyone), fix_lon_deg),
                        [o.lat_deg for o in everyone], [o.lon_deg for o in everyone])
    az_of = {o.helper_id: float(a) for o, a in zip(everyone, np.atleast_1d(az), strict=True)}
    best, best_cost = (), math.inf
    for combo in itertools.combinations(usable, need):
        team = list(kept) + list(combo)
        cost = (float(np.mean([own_cost(o, cfg) for o in team]))
                + cfg.w_geometry * (1.0 - geometry_quality(az_of[o.helper_id] for o in team)))
        if cost < best_cost - 1e-12:
            best, best_cost = combo, cost
    return tuple(sorted((o.helper_id for o in best), key=lambda h: own_cost(_by_id(best, h), cfg)))


def _by_id(offers: Iterable[Offer], helper_id: str) -> Offer:
    return next(o for o in offers if o.helper_id == helper_id)


@dataclass
class _Assignment:
    offer: Offer
    since_s: float
    acked: bool = False
    observed_s: float = -math.inf  # newest observation of the requester by this helper

    def blind(self, now_s: float, cfg: HelpConfig) -> bool:
        """No observation by the time it should be there (ETA + grace), or none for ``obs_timeout_s`` since."""
        if self.observed_s == -math.inf:
            return now_s - self.since_s > self.offer.eta_s + cfg.obs_grace_s
        return now_s - self.observed_s > cfg.obs_timeout_s


@dataclass
class HelpRequester:
    """The requesting side for drone ``drone_id`` (see the module docstring)."""

    drone_id: str
    cfg: HelpConfig = field(default_factory=HelpConfig)
    epoch: int = 0
    active: bool = False
    fix: GeoFix | None = None
    offers: dict[str, Offer] = field(default_factory=dict)
    assigned: dict[str, _Assignment] = field(default_factory=dict)
    excluded_until_s: dict[str, float] = field(default_factory=dict)
    events: list[tuple[float, str, str]] = field(default_factory=list)  # (time_s, what, helper id)
    _started_s: float = 0.0
    _last_request_s: float = -math.inf
    _last_assign_s: float = -math.inf

    def helpers(self) -> tuple[str, ...]:
        """Ids of the assigned helpers that acknowledged: the observers to trust."""
        return tuple(sorted(h for h, a in self.assigned.items() if a.acked))

    def start(self, now_s: float, last_fix: GeoFix) -> list[Body]:
        """Ask for help with ``last_fix`` (the last good fused position); a new epoch."""
        self.epoch += 1
        self.active, self.fix, self._started_s = True, last_fix, now_s
        self.offers.clear()
        self.assigned.clear()
        self._last_assign_s = -math.inf
        return [self._request(now_s)]

    def cancel(self, now_s: float, reason: str = "gnss back") -> list[Body]:
        """Stop asking; every assigned helper is released."""
        if not self.active:
            return []
        self.active = False
        out: list[Body] = []
        if self.assigned:  # the release first: it carries the reason
            out.append(HelpRelease(tuple(sorted(self.assigned)), self.epoch, reason))
            for h in self.assigned:
                self.events.append((now_s, "released", h))
        out.append(HelpRequest(False, self.fix.time_s, self.fix.lat_deg, self.fix.lon_deg,
                               self.fix.alt_m, self.fix.sigma_horizontal_m, epoch=self.epoch))
        self.assigned.clear()
        self.offers.clear()
        return out

    def on_message(self, env: Envelope, now_s: float) -> list[Body]:
        """Account for one accepted envelope (offers, declines, acknowledgements of this epoch)."""
        body, h = env.body, env.sender
        if isinstance(body, RelativeObs) and body.target_id == self.drone_id and h in self.assigned:
            self.assigned[h].observed_s = now_s
            return []
        if not (self.active and isinstance(body, HelpResponse) and body.requester_id == self.drone_id
                and body.epoch == self.epoch):
            return []
        if not body.accept:
            self.offers.pop(h, None)
            if self.assigned.pop(h, None) is not None:
                self._replace(now_s, h, "declined")
            return []
        if body.assigned:
            if h in self.assigned:
                self.assigned[h].acked = True
            else:  # it believes it is assigned, we do not (an assignment that was replaced): release it
                return [HelpRelease((h,), self.epoch, "not assigned")]
            return []
        if not _plausible(body.lat_deg, body.lon_deg, body.alt_m) or not body.eta_s >= 0.0:
            log.warning("help offer from %r dropped: position (%r, %r, %r) or ETA %r not physical", h,
                        body.lat_deg, body.lon_deg, body.alt_m, body.eta_s)
            return []
        battery = body.battery_frac if 0.0 <= body.battery_frac <= 1.0 else 0.0  # unknown: ranked last
        self.offers[h] = Offer(h, now_s, body.lat_deg, body.lon_deg, body.alt_m, battery, body.distance_m, body.eta_s)
        return []

    def tick(self, now_s: float, live_peers: Iterable[str], recruit: bool = True) -> list[Body]:
        """Periodic work (call at a few Hz): replace lost or silent helpers, assign, repeat. ``recruit`` False:
        lost or silent helpers are still released, but none is assigned in their place and no request repeated
        (a drone landing under its helpers' horizon: new helpers would only lose it against the ground too)."""
        if not self.active:
            return []
        live = set(live_peers)
        out: list[Body] = []
        for h, a in list(self.assigned.items()):
            why = ("went quiet" if h not in live else
                   "did not acknowledge" if not a.acked and now_s - a.since_s > self.cfg.ack_timeout_s else
                   "no observations" if a.acked and a.blind(now_s, self.cfg) else None)
            if why is not None:
                del self.assigned[h]
                out.append(HelpRelease((h,), self.epoch, why))
                self._replace(now_s, h, why)
        self.offers = {h: o for h, o in self.offers.items()
                       if h in live and now_s - o.time_s <= self.cfg.offer_max_age_s}
        need = self.cfg.helpers_wanted - len(self.assigned) if recruit else 0
        fresh = False
        if need > 0 and now_s - self._started_s >= self.cfg.offer_window_s:
            free = [o for h, o in self.offers.items()
                    if h not in self.assigned and self.excluded_until_s.get(h, -math.inf) <= now_s]
            kept = tuple(a.offer for a in self.assigned.values())
            for h in select_helpers(free, self.fix.lat_deg, self.fix.lon_deg, need, self.cfg, kept):
                self.assigned[h] = _Assignment(self.offers[h], now_s)
                self.events.append((now_s, "assigned", h))
                fresh = True
            need = self.cfg.helpers_wanted - len(self.assigned)
        if need > 0 and now_s - self._last_request_s >= self.cfg.retry_s:
            out.append(self._request(now_s))
        unacked = any(not a.acked for a in self.assigned.values())
        if self.assigned and (fresh or (unacked and now_s - self._last_assign_s >= self.cfg.retry_s)):
            self._last_assign_s = now_s
            out.append(HelpAssign(tuple(sorted(self.assigned)), self.epoch))
        return out

    def _replace(self, now_s: float, helper_id: str, why: str) -> None:
        self.offers.pop(helper_id, None)
        self.excluded_until_s[helper_id] = now_s + self.cfg.exclude_s
        self.events.append((now_s, f"dropped ({why})", helper_id))

    def _request(self, now_s: float) -> HelpRequest:
        self._last_request_s = now_s
        f = self.fix
        return HelpRequest(True, f.time_s, f.lat_deg, f.lon_deg, f.alt_m, f.sigma_horizontal_m,
                           tuple(float(x) for x in np.asarray(f.cov_enu_m2, dtype=float).reshape(9)), self.epoch)


def _plausible(lat_deg: float, lon_deg: float, alt_m: float) -> bool:
    """A position a drone can be at (a key holder's bug must not stop the protocol with an exception)."""
    return -90.0 <= lat_deg <= 90.0 and -180.0 <= lon_deg <= 180.0 and -1000.0 < alt_m < 20000.0


@dataclass(frozen=True)
class HelperStatus:
    """What a possible helper knows of itself: fused position (WGS84, ellipsoidal m), battery share 0-1,
    whether its own position is good enough to help (``localised``), and whether it may leave its mission."""

    lat_deg: float
    lon_deg: float
    alt_m: float
    battery_frac: float
    localised: bool = True
    available: bool = True


@dataclass
class HelpResponder:
    """The helping side for drone ``drone_id``: ``requester_id`` is whom it helps (None: on its mission)."""

    drone_id: str
    cfg: HelpConfig = field(default_factory=HelpConfig)
    requester_id: str | None = None
    epoch: int = 0
    request: HelpRequest | None = None  # the request of the drone helped (its last good fix)
    team: tuple[str, ...] = ()  # every helper of that request, this one included (the newest assignment)
    requests: dict[str, HelpRequest] = field(default_factory=dict)  # newest active request per sender
    events: list[tuple[float, str, str]] = field(default_factory=list)  # (time_s, what, requester id)
    _requester_heard_s: float = -math.inf

    def on_message(self, env: Envelope, now_s: float, me: HelperStatus) -> list[Body]:
        """Answer one accepted envelope; ``me`` is this drone's present status."""
        body, sender = env.body, env.sender
        if sender == self.requester_id:
            self._requester_heard_s = now_s
        if isinstance(body, HelpRequest):
            return self._on_request(sender, body, now_s, me)
        if isinstance(body, HelpAssign):
            return self._on_assign(sender, body, now_s, me)
        if isinstance(body, HelpRelease) and sender == self.requester_id and self.drone_id in body.helper_ids:
            self._release(now_s, body.reason or "released")
        return []

    def tick(self, now_s: float, live_peers: Iterable[str]) -> None:
        """Back to the mission when the requester has been silent for ``abandon_after_s``."""
        if self.requester_id is None:
            return
        if self.requester_id in set(live_peers):
            self._requester_heard_s = max(self._requester_heard_s, now_s - self.cfg.quiet_after_s)
        if now_s - self._requester_heard_s > self.cfg.abandon_after_s:
            self._release(now_s, "requester silent")

    def withdraw(self, now_s: float, why: str) -> list[Body]:
        """Stop helping (e.g. this drone lost its own GNSS or must land): a decline tells the requester
        to replace it at once."""
        if self.requester_id is None:
            return []
        out: list[Body] = [HelpResponse(self.requester_id, False, epoch=self.epoch)]
        self._release(now_s, why)
        return out

    def _on_request(self, sender: str, req: HelpRequest, now_s: float, me: HelperStatus) -> list[Body]:
        if not req.active:
            self.requests.pop(sender, None)
            if sender == self.requester_id:
                self._release(now_s, "request cancelled")
            return []
        if not _plausible(req.lat_deg, req.lon_deg, req.alt_m):
            log.warning("help request from %r dropped: position (%r, %r, %r) not physical", sender,
                        req.lat_deg, req.lon_deg, req.alt_m)
            return []
        self.requests[sender] = req
        if sender == self.requester_id:
            self.request = req
            return []  # already helping it; the assignment messages carry the rest
        if self.requester_id is not None or not (me.available and me.localised) \
                or not me.battery_frac >= self.cfg.min_battery_frac:
            return [HelpResponse(sender, False, epoch=req.epoch)]
        _, dist = geo.inverse(me.lat_deg, me.lon_deg, req.lat_deg, req.lon_deg)
        dist_m = float(math.hypot(float(dist), me.alt_m - req.alt_m))
        # ETA: straight flight to the last fix at cruise speed, an upper bound of the time until it can observe
        return [HelpResponse(sender, True, dist_m / self.cfg.cruise_mps, me.lat_deg, me.lon_deg, me.alt_m,
                             me.battery_frac, dist_m, req.epoch)]

    def _on_assign(self, sender: str, msg: HelpAssign, now_s: float, me: HelperStatus) -> list[Body]:
        named = self.drone_id in msg.helper_ids
        if sender == self.requester_id:
            if not named and msg.epoch == self.epoch:
                self._release(now_s, "replaced")
            elif named:
                self.epoch, self.team = msg.epoch, msg.helper_ids
                return [self._ack(sender, msg.epoch)]  # a repeat: our acknowledgement was lost
            return []
        if not named:
            return []
        if self.requester_id is not None or not me.available or not me.battery_frac >= self.cfg.min_battery_frac:
            return [HelpResponse(sender, False, epoch=msg.epoch)]
        self.requester_id, self.epoch, self._requester_heard_s = sender, msg.epoch, now_s
        self.request, self.team = self.requests.get(sender), msg.helper_ids
        self.events.append((now_s, "helping", sender))
        return [self._ack(sender, msg.epoch)]

    def _ack(self, requester: str, epoch: int) -> HelpResponse:
        return HelpResponse(requester, True, epoch=epoch, assigned=True)

    def _release(self, now_s: float, why: str) -> None:
        self.events.append((now_s, f"released ({why})", self.requester_id or ""))
        self.requester_id, self.request, self.team = None, None, ()
