"""Three help agents on the in-process bus, as the service's main loop would drive them."""

import numpy as np
from helpnet import ALT0, DT_S, KEY, LAT0, LON0, Clock, at

from skyfix.crps.help_agent import HelpAgent
from skyfix.crps.help_protocol import HelperStatus
from skyfix.crps.messages import Heartbeat, SwarmCodec
from skyfix.crps.roles import Mode
from skyfix.crps.swarm import PeerTable
from skyfix.crps.transport import InProcessBus
from skyfix.fusion.estimate import Estimate
from skyfix.fusion.health import HealthState, SourceHealth
from skyfix.geo import LocalFrame

FRAME = LocalFrame(LAT0, LON0, ALT0)
ENU = {"a": (0.0, 0.0, 50.0), "h1": (40.0, 0.0, 50.0), "h2": (0.0, -40.0, 50.0)}


def estimate(drone, t, sigma_m, sources):
    lat, lon, alt = (float(c) for c in FRAME.to_geodetic(*ENU[drone]))
    return Estimate(drone, t, lat, lon, alt, np.array(ENU[drone]), np.eye(3) * sigma_m**2, np.zeros(3),
                    np.eye(3) * 0.01, sources)


def test_agents_recover_a_drone_and_release_the_helpers():
    clock, bus = Clock(), InProcessBus()
    agents, inbox = {}, {}
    for d in ENU:
        codec, link = SwarmCodec(d, KEY, clock=clock), bus.attach("skyfix", d)
        inbox[d] = []
        link.subscribe(lambda _k, data, d=d: inbox[d].append(data))
        agents[d] = HelpAgent(codec, link, PeerTable(), at(100, 100), FRAME)
    positions = {d: tuple(float(c) for c in FRAME.to_geodetic(*p)) for d, p in ENU.items()}
    status = {d: HelperStatus(*positions[d], 0.8) for d in ENU}
    log = []

    def loop(seconds, gnss_state, a_estimate):
        for _ in range(int(round(seconds / DT_S))):
            clock.t = round(clock.t + DT_S, 6)
            t = clock.t
            for d, agent in agents.items():
                for data in inbox[d]:
                    env = agent.codec.decode(data)
                    if env is not None:
                        agent.peers.heard(env, t)
                        agent.receive(env, t, status[d])
                inbox[d].clear()
                agent.peers.check(t)
                if round(t / DT_S) % 5 == 0:
                    agent.transport.publish("heartbeat", agent.codec.encode(Heartbeat("ok", "gnss", 1.0, True)))
                healthy = d != "a" or gnss_state is HealthState.OK
                gnss = SourceHealth(HealthState.OK if healthy else gnss_state, "test", 0.0)
                fused = a_estimate(t) if d == "a" else estimate(d, t, 1.0, ("gnss",))
                others = {p: pos for p, pos in positions.items() if p != d}
                log.append((t, d, agent.step(t, gnss, fused, status[d], others)))

    loop(2.0, HealthState.OK, lambda t: estimate("a", t, 1.0, ("gnss", "velocity")))
    t_loss = clock.t
    loop(3.0, HealthState.LOST, lambda t: estimate("a", t, 4.0, ("velocity",)))  # dead reckoning: no fix to fly on
    a_now = log[-3][2].requester
    assert a_now.mode is Mode.HOLD and a_now.helpers == ("h1", "h2")
    assert a_now.since_s == t_loss + DT_S
    for h in ("h1", "h2"):
        dec = next(e[2].helper for e in reversed(log) if e[1] == h)
        assert dec.helping == "a" and 20.0 <= dec.vantage.range_m <= 60.0
        assert dec.target == positions["a"]  # the requester's broadcast position (the peer table's)
    assert log[-3][2].helper.helping is None  # the drone asking for help helps nobody
    loop(1.0, HealthState.LOST, lambda t: estimate("a", t, 1.2, ("relative:h1", "relative:h2", "velocity")))
    a_now = log[-3][2].requester
    assert a_now.mode is Mode.RETURN_HOME and a_now.setpoint == at(100, 100)
    loop(3.5, HealthState.OK, lambda t: estimate("a", t, 1.0, ("gnss", "velocity")))
    assert log[-3][2].requester.mode is Mode.NORMAL
    assert all(e[2].helper.helping is None for e in log[-3:])  # helpers back on their missions
    assert all(a.codec.dropped.total() == 0 for a in agents.values())
