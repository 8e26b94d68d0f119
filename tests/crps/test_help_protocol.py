"""The help protocol over the in-process bus with an injected clock: offers, assignment, retries,
replacement, release, forged messages."""

import math

import numpy as np
import pytest
from helpnet import KEY, Net, at, last_fix

from skyfix.crps.help_protocol import HelpConfig, Offer, geometry_quality, select_helpers
from skyfix.crps.messages import HelpAssign, HelpRelease, HelpRequest, HelpResponse, SwarmCodec


def test_geometry_quality_known_values():
    assert geometry_quality([0.0, 90.0]) == pytest.approx(1.0)
    assert geometry_quality([10.0, 190.0]) == pytest.approx(0.0, abs=1e-12)  # opposite: one line
    assert geometry_quality([0.0, 45.0]) == pytest.approx(1 - math.cos(math.radians(45)))  # eigen 1 -/+ cos
    assert geometry_quality([0.0, 120.0, 240.0]) == pytest.approx(1.0)
    assert geometry_quality([30.0]) == 0.0
    batch = np.random.default_rng(0).uniform(0, 360, (50, 3))  # batched = one at a time
    np.testing.assert_allclose(geometry_quality(batch), [geometry_quality(list(b)) for b in batch], atol=1e-12)


def test_selection_prefers_spread_bearings_over_a_slightly_closer_collinear_helper():
    cfg = HelpConfig()
    lat0, lon0, _ = at(0, 0)
    def offer(h, e, n, battery=0.9):
        lat, lon, alt = at(e, n)
        d = math.hypot(e, n)
        return Offer(h, 0.0, lat, lon, alt, battery, d, d / cfg.cruise_mps)
    offers = [offer("east", 30, 0), offer("east2", 35, 0), offer("north", 0, 60), offer("flat", 0, -20, 0.2)]
    # costs: east 0.225, east2 0.246, north 0.35; {east, east2} collinear (+1), {east, north} at 90 deg (+0)
    assert select_helpers(offers, lat0, lon0, 2, cfg) == ("east", "north")
    # with 'east' already kept, one more: north (90 deg) beats east2 (0 deg)
    assert select_helpers(offers, lat0, lon0, 1, cfg, kept=(offers[0],)) == ("north",)
    # without the geometry term the two nearest win
    flat_cfg = HelpConfig(w_geometry=0.0)
    assert select_helpers(offers, lat0, lon0, 2, flat_cfg) == ("east", "east2")


def test_three_drones_request_offers_assignment():
    net = Net()
    lost = net.add("lost", 0, 0)
    net.add("h1", 40, 0)
    net.add("h2", 0, -80, battery_frac=0.6)
    net.run(1.0)  # everyone hears everyone
    t0 = net.clock.t
    lost.send(lost.requester.start(t0, last_fix(net.clock)))
    net.run(5.0, until=lambda: len(lost.requester.helpers()) == 2)
    assert lost.requester.helpers() == ("h1", "h2")
    offers = lost.requester.offers
    assert offers["h1"].distance_m == pytest.approx(40.0, abs=0.1)
    assert offers["h2"].distance_m == pytest.approx(80.0, abs=0.1)
    assert offers["h2"].eta_s == pytest.approx(80.0 / net.cfg.cruise_mps, rel=1e-3)
    assert offers["h2"].battery_frac == 0.6
    # assigned right after the offer window; both acknowledged on the next step
    assert net.clock.t - t0 == pytest.approx(net.cfg.offer_window_s + 0.1, abs=0.11)
    for h in ("h1", "h2"):
        r = net.drones[h].responder
        assert r.requester_id == "lost" and r.epoch == 1
        assert r.request.lat_deg == pytest.approx(at(0, 0)[0]) and r.request.sigma_h_m == pytest.approx(1.5)
        assert np.reshape(r.request.cov_enu_m2, (3, 3))[2, 2] == 4.0


def test_best_two_of_four_and_a_low_battery_drone_declines():
    net = Net()
    lost = net.add("lost", 0, 0)
    net.add("east", 30, 0)
    net.add("east2", 35, 0)
    net.add("north", 0, 60)
    net.add("flat", 0, -20, battery_frac=0.2)
    net.run(1.0)
    lost.send(lost.requester.start(net.clock.t, last_fix(net.clock)))
    net.run(4.0)
    assert lost.requester.helpers() == ("east", "north")
    assert "flat" not in lost.requester.offers  # it declined (battery below 30 %)
    assert net.drones["east2"].responder.requester_id is None  # not taken from its mission


def test_a_helper_that_goes_quiet_is_replaced_within_the_timeout():
    net = Net()
    lost = net.add("lost", 0, 0)
    net.add("h1", 30, 0)
    net.add("h2", 0, 40)
    spare = net.add("h3", -60, -60)
    net.run(1.0)
    lost.send(lost.requester.start(net.clock.t, last_fix(net.clock)))
    net.run(3.0)
    assert lost.requester.helpers() == ("h1", "h2")
    net.drones["h1"].quiet = True
    t_quiet = net.clock.t
    took = net.run(10.0, until=lambda: lost.requester.helpers() == ("h2", "h3"))
    assert lost.requester.helpers() == ("h2", "h3")
    # lost after 1.5 s of silence (peer table), then the fresh offer window and one acknowledgement
    assert took <= net.cfg.quiet_after_s + 0.5 + net.cfg.retry_s + 0.3
    assert spare.responder.requester_id == "lost"
    dropped = [e for e in lost.requester.events if e[1].startswith("dropped")]
    assert dropped == [(pytest.approx(t_quiet + 1.6, abs=0.11), "dropped (went quiet)", "h1")]


@pytest.mark.parametrize("seed", range(5))
def test_twenty_percent_message_loss_still_ends_assigned(seed):
    net = Net(seed=seed)
    lost = net.add("lost", 0, 0, loss=0.2)
    for h, (e, n) in {"h1": (30, 0), "h2": (0, 40)}.items():
        net.add(h, e, n, loss=0.2)
    net.run(1.0)
    lost.send(lost.requester.start(net.clock.t, last_fix(net.clock)))
    took = net.run(15.0, until=lambda: len(lost.requester.helpers()) == 2)
    assert lost.requester.helpers() == ("h1", "h2")
    assert took <= 6.0  # each exchange is repeated every 0.5 s: a few retries at 20 % loss
    assert all(net.drones[h].responder.requester_id == "lost" for h in ("h1", "h2"))


def test_forged_or_unsigned_help_messages_are_dropped():
    net = Net()
    lost = net.add("lost", 0, 0)
    victim = net.add("h1", 30, 0)
    net.run(1.0)
    mallory = SwarmCodec("mallory", b"not-the-swarm-key-at-all-32byte", clock=net.clock)
    bus_link = net.bus.attach("skyfix", "mallory")
    # a forged assignment would pull h1 off its mission; a forged offer would steal a slot
    bus_link.publish("help", mallory.encode(HelpAssign(("h1",), 1)))
    bus_link.publish("help", mallory.encode(HelpResponse("lost", True, 1.0, *at(5, 5), 1.0, 7.0, 1)))
    unsigned = SwarmCodec("mallory", KEY, clock=net.clock).encode(HelpRelease(("h1",), 1))[:-32] + bytes(32)
    lost.send(lost.requester.start(net.clock.t, last_fix(net.clock)))
    bus_link.publish("help", unsigned)
    net.run(3.0)
    assert victim.codec.dropped["forged"] == 3 and lost.codec.dropped["forged"] == 3  # 2 wrong key, 1 no tag
    assert lost.requester.helpers() == ("h1",) and "mallory" not in lost.requester.offers
    assert victim.responder.requester_id == "lost"


def test_cancel_releases_every_helper_and_a_release_returns_one():
    net = Net()
    lost = net.add("lost", 0, 0)
    for h, (e, n) in {"h1": (30, 0), "h2": (0, 40)}.items():
        net.add(h, e, n)
    net.run(1.0)
    lost.send(lost.requester.start(net.clock.t, last_fix(net.clock)))
    net.run(3.0)
    assert lost.requester.helpers() == ("h1", "h2")
    lost.send(lost.requester.cancel(net.clock.t, "gnss back"))
    net.run(0.2)
    assert lost.requester.helpers() == () and not lost.requester.active
    for h in ("h1", "h2"):
        r = net.drones[h].responder
        assert r.requester_id is None and r.events[-1][1] == "released (gnss back)"
    # a new request starts a new epoch, and the helpers come again
    lost.send(lost.requester.start(net.clock.t, last_fix(net.clock)))
    net.run(3.0)
    assert lost.requester.epoch == 2 and lost.requester.helpers() == ("h1", "h2")
    assert net.drones["h1"].responder.epoch == 2


def test_a_helper_abandons_a_requester_that_fell_silent():
    net = Net()
    lost = net.add("lost", 0, 0)
    net.add("h1", 30, 0)
    net.run(1.0)
    lost.send(lost.requester.start(net.clock.t, last_fix(net.clock)))
    net.run(2.0)
    assert net.drones["h1"].responder.requester_id == "lost"
    lost.quiet = True
    t_quiet = net.clock.t
    net.run(net.cfg.abandon_after_s + 1.0, until=lambda: net.drones["h1"].responder.requester_id is None)
    assert net.drones["h1"].responder.requester_id is None
    assert net.clock.t - t_quiet == pytest.approx(net.cfg.abandon_after_s, abs=0.25)


def test_a_helper_that_loses_its_own_gnss_withdraws_and_a_busy_helper_declines():
    net = Net()
    a = net.add("a", 0, 0)
    b = net.add("b", 50, 0)
    net.add("h1", 0, 30)
    net.run(1.0)
    a.send(a.requester.start(net.clock.t, last_fix(net.clock)))
    net.run(2.0)
    assert a.requester.helpers() == ("b", "h1")
    # b loses its own GNSS: it leaves a (a decline), then asks for help itself
    b.send(b.responder.withdraw(net.clock.t, "own gnss lost"))
    b.send(b.requester.start(net.clock.t, last_fix(net.clock, 50, 0)))
    net.run(3.0)
    assert a.requester.helpers() == ("h1",) and b.requester.helpers() == ()
    assert ("dropped (declined)", "b") in [(e[1], e[2]) for e in a.requester.events]
    assert net.drones["h1"].responder.requester_id == "a"  # busy: it declined b
    assert b.responder.requester_id is None
    assert HelpRequest in {type(x) for x in b.requester.tick(net.clock.t + 1.0, ["a", "h1"])}  # still asking


def test_help_messages_stay_compatible_with_the_first_release_both_ways():
    import msgspec

    class OldHelpRequest(msgspec.Struct, tag="HelpRequest", array_like=True):  # as released with wire version 1
        active: bool
        last_good_time_s: float
        lat_deg: float
        lon_deg: float
        alt_m: float
        sigma_h_m: float

    old = OldHelpRequest(True, 1.7e9, 46.5, 6.6, 500.0, 1.5)
    new = msgspec.msgpack.decode(msgspec.msgpack.encode(old), type=HelpRequest)
    assert new == HelpRequest(True, 1.7e9, 46.5, 6.6, 500.0, 1.5, (), 0)
    back = msgspec.msgpack.decode(msgspec.msgpack.encode(HelpRequest(True, 1.7e9, 46.5, 6.6, 500.0, 1.5,
                                                                     tuple(range(9)), 3)), type=OldHelpRequest)
    assert back == old
    assert math.isnan(HelpResponse("a", True).battery_frac) and not HelpResponse("a", True).assigned


def test_signed_but_non_physical_help_messages_are_dropped_and_the_protocol_goes_on():
    net = Net()
    lost = net.add("lost", 0, 0)
    h1 = net.add("h1", 30, 0)
    net.run(1.0)
    buggy = SwarmCodec("buggy", KEY, clock=net.clock)  # holds the key, sends nonsense
    link = net.bus.attach("skyfix", "buggy")
    link.publish("help", buggy.encode(HelpRequest(True, net.clock.t, 123.0, 6.6, 500.0, 1.0)))  # latitude 123
    lost.send(lost.requester.start(net.clock.t, last_fix(net.clock)))
    for offer in (HelpResponse("lost", True, -4.0, *at(0, 30), 0.9, 30.0, 1),  # negative ETA: would rank first
                  HelpResponse("lost", True, 4.0, math.nan, 6.6, 500.0, 0.9, 30.0, 1)):
        link.publish("help", buggy.encode(offer))
    net.run(1.2)
    assert lost.requester.helpers() == ("h1",) and "buggy" not in lost.requester.offers
    assert "buggy" not in h1.responder.requests and h1.responder.requester_id == "lost"


def _three_observing_helpers():
    """A requester that asked for help 8 s ago, three helpers that observe it while helping (h1, h2 chosen)."""
    net = Net()
    lost = net.add("lost", 0, 0)
    for h, (e, n) in {"h1": (30, 0), "h2": (0, 40), "h3": (-60, -60)}.items():
        net.add(h, e, n).observes = True
    net.run(1.0)
    lost.send(lost.requester.start(net.clock.t, last_fix(net.clock)))
    net.run(8.0)
    return net, lost


def test_a_helper_whose_observations_stop_is_replaced():
    net, lost = _three_observing_helpers()
    assert lost.requester.helpers() == ("h1", "h2")  # observing: kept well past ETA + grace
    net.drones["h1"].observes = False  # the target left h1's view; h1 is still flying and talking
    t_blind = net.clock.t
    took = net.run(10.0, until=lambda: lost.requester.helpers() == ("h2", "h3"))
    # 5 s without an observation, then a fresh request -> offer -> assignment -> acknowledgement (3 steps)
    assert took == pytest.approx(net.cfg.obs_timeout_s + 0.3, abs=0.25)
    assert ("dropped (no observations)", "h1") in [(e[1], e[2]) for e in lost.requester.events]
    assert net.drones["h1"].responder.requester_id is None  # released back to its mission
    assert lost.requester.excluded_until_s["h1"] == pytest.approx(t_blind + 5.1 + net.cfg.exclude_s, abs=0.15)


def test_a_requester_that_stops_recruiting_releases_a_blind_helper_and_takes_no_other():
    """Landing under its helpers' horizon: a helper that loses it is released as before, but no spare is
    assigned and no request repeated (the spare would lose it against the ground too)."""
    net, lost = _three_observing_helpers()
    assert lost.requester.helpers() == ("h1", "h2")
    lost.recruit = False
    net.drones["h1"].observes = False
    t_blind = net.clock.t
    net.run(net.cfg.obs_timeout_s + 3.0 * net.cfg.retry_s + 2.0)
    assert lost.requester.helpers() == ("h2",)  # h1 released, nobody in its place
    assert net.drones["h1"].responder.requester_id is None
    assert net.drones["h3"].responder.requester_id is None
    assert not any(e[1] == "assigned" and e[0] > t_blind for e in lost.requester.events)
    lost.recruit = True  # e.g. it climbed again: recruiting resumes
    net.run(10.0, until=lambda: lost.requester.helpers() == ("h2", "h3"))
    assert lost.requester.helpers() == ("h2", "h3")


def test_a_helper_that_never_observes_is_replaced_after_its_eta_and_grace():
    net = Net(HelpConfig(obs_grace_s=2.0))
    lost = net.add("lost", 0, 0)
    net.add("h1", 40, 0).observes = True
    net.add("h2", 0, 80)          # never sees the target; ETA 10 s
    net.add("h3", -70, -70).observes = True
    net.run(1.0)
    t0 = net.clock.t
    lost.send(lost.requester.start(t0, last_fix(net.clock)))
    net.run(20.0, until=lambda: lost.requester.helpers() == ("h1", "h3"))
    t_drop = next(e[0] for e in lost.requester.events if e[1] == "dropped (no observations)")
    t_assigned = next(e[0] for e in lost.requester.events if e[1:] == ("assigned", "h2"))
    assert t_drop - t_assigned == pytest.approx(80.0 / net.cfg.cruise_mps + 2.0, abs=0.15)
