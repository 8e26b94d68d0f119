"""A swarm of help-protocol drones on the in-process bus with one injected clock (for the tests)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from skyfix import geo
from skyfix.crps.help_protocol import HelpConfig, HelperStatus, HelpRequester, HelpResponder
from skyfix.crps.messages import TOPIC_OF, Heartbeat, RelativeObs, SwarmCodec
from skyfix.crps.swarm import PeerTable
from skyfix.crps.transport import InProcessBus
from skyfix.types import GeoFix

KEY = b"help-protocol-test-key-32-bytes!"
LAT0, LON0, ALT0 = 46.5, 6.6, 500.0
DT_S = 0.1  # the service's main loop runs at 10 Hz


class Clock:
    def __init__(self, t: float = 1.7e9) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def at(east_m: float, north_m: float, up_m: float = 0.0) -> tuple[float, float, float]:
    """WGS84 position ``east_m``, ``north_m``, ``up_m`` from the test origin."""
    lat, lon, alt = geo.LocalFrame(LAT0, LON0, ALT0).to_geodetic(east_m, north_m, up_m)
    return float(lat), float(lon), float(alt)


class Drone:
    """One drone: codec, transport (optionally losing ``loss`` of its outgoing datagrams), peer table,
    both protocol roles. ``quiet`` True: it stops sending anything (a helper that went away)."""

    def __init__(self, net: Net, drone_id: str, east_m: float, north_m: float, battery_frac: float = 0.9,
                 loss: float = 0.0) -> None:
        self.net, self.id = net, drone_id
        self.codec = SwarmCodec(drone_id, KEY, clock=net.clock)
        self.link = net.bus.attach("skyfix", drone_id)
        self.link.subscribe(lambda _key, data: self.inbox.append(data))
        self.inbox: list[bytes] = []
        self.peers = PeerTable()
        self.status = HelperStatus(*at(east_m, north_m), battery_frac)
        self.requester = HelpRequester(drone_id, net.cfg)
        self.responder = HelpResponder(drone_id, net.cfg)
        self.loss, self.quiet = loss, False
        self.observes = False  # while helping, streams an observation of its requester every step
        self.recruit = True  # as requester: replaces helpers it loses (False: a drone landing under their horizon)

    def send(self, bodies) -> None:
        for body in bodies:
            if self.quiet or self.net.rng.random() < self.loss:
                continue
            self.link.publish(TOPIC_OF[type(body)], self.codec.encode(body))

    def step(self, now_s: float) -> None:
        inbox, self.inbox = self.inbox, []
        me = replace(self.status, localised=False) if self.requester.active else self.status  # asking: not helping
        for data in inbox:
            env = self.codec.decode(data)
            if env is None:
                continue
            self.peers.heard(env, now_s)
            self.send(self.requester.on_message(env, now_s))
            self.send(self.responder.on_message(env, now_s, me))
        self.peers.check(now_s)
        live = self.peers.live()
        self.send(self.requester.tick(now_s, live, self.recruit))
        self.responder.tick(now_s, live)
        req = self.responder.request
        if self.observes and self.responder.requester_id is not None and req is not None:
            self.send([self._observation(now_s, req)])
        if round(now_s / DT_S) % 5 == 0:  # heartbeat at 2 Hz keeps this drone live in the peer tables
            self.send([Heartbeat("ok", "gnss", 1.0, True, len(live))])


    def _observation(self, now_s: float, req) -> RelativeObs:
        """What this helper's camera pipeline would send: here aimed at the request's last fix (the
        protocol counts observations, their content is fusion's business)."""
        frame = geo.LocalFrame(self.status.lat_deg, self.status.lon_deg, self.status.alt_m)
        los = np.array([float(c) for c in frame.to_enu(req.lat_deg, req.lon_deg, req.alt_m)])
        r = float(np.linalg.norm(los))
        cov = tuple((np.eye(3) * (0.02 * r) ** 2).ravel().tolist())
        return RelativeObs(self.responder.requester_id, now_s, tuple((los / r).tolist()), r, cov,
                           self.status.lat_deg, self.status.lon_deg, self.status.alt_m)


class Net:
    def __init__(self, cfg: HelpConfig | None = None, seed: int = 0) -> None:
        self.clock, self.bus, self.cfg = Clock(), InProcessBus(), cfg or HelpConfig()
        self.rng = np.random.default_rng(seed)
        self.drones: dict[str, Drone] = {}

    def add(self, drone_id: str, east_m: float, north_m: float, **kw) -> Drone:
        self.drones[drone_id] = Drone(self, drone_id, east_m, north_m, **kw)
        return self.drones[drone_id]

    def run(self, seconds: float, until=None) -> float:
        """Step every drone at 10 Hz for ``seconds`` (or until ``until()``); the time spent, s."""
        start = self.clock.t
        for _ in range(int(round(seconds / DT_S))):
            self.clock.t = round(self.clock.t + DT_S, 6)
            for d in self.drones.values():
                d.step(self.clock.t)
            if until is not None and until():
                break
        return self.clock.t - start


def last_fix(clock: Clock, east_m: float = 0.0, north_m: float = 0.0, sigma_m: float = 1.5) -> GeoFix:
    return GeoFix(*at(east_m, north_m), np.diag([sigma_m**2, sigma_m**2, 4.0]), clock.t, "skyfix.fusion")
