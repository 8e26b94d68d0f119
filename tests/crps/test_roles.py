"""Requester and helper roles: GNSS loss from the real fusion engine's health, hold, help request,
fault response once helpers position the drone, normal again when GNSS is back; helper vantage."""

import numpy as np
import pytest
from helpnet import ALT0, LAT0, LON0, Net, at, last_fix

from skyfix.crps.help_protocol import HelperStatus
from skyfix.crps.messages import HelpRelease, HelpRequest
from skyfix.crps.roles import FaultResponse, HelperRole, Mode, RequesterConfig, RequesterRole
from skyfix.errors import InputError
from skyfix.fusion.engine import FusionEngine
from skyfix.geo import LocalFrame
from skyfix.types import RelativeObservation

FRAME = LocalFrame(LAT0, LON0, ALT0)
POS = {"a": np.array([0.0, 0.0, 50.0]), "h1": np.array([30.0, 0.0, 45.0]), "h2": np.array([0.0, 30.0, 45.0])}
GNSS_SIGMA_M = 1.0       # GNSS error: Gauss-Markov, 1 m 1-sigma, 60 s correlation time (as receivers drift)
GNSS_TAU_S = 60.0
RANGE_SIGMA_REL = 0.02   # 2 % of range, 1-sigma (crps ranging on tracks)
BEARING_SIGMA_RAD = 2e-3


def fly(role, rng, t_loss, t_back, t_end, observe_from_s, dt=0.2, back_off_m=(0.0, 0.0, 0.0),
        gnss_sigma_m=GNSS_SIGMA_M, shared_sigma_m=0.0, config=None, estimates=None, gnss_tau_s=GNSS_TAU_S):
    """Three hovering drones in a real FusionEngine (``config``); 'a' has no GNSS fix in [t_loss, t_back); the
    helpers observe it (noisy range and bearing) from ``observe_from_s`` while it asks for help; its
    GNSS comes back ``back_off_m`` (ENU) off. Each receiver's error: ``gnss_sigma_m`` per axis, of which
    ``shared_sigma_m`` is one error all three share (held over the run: the atmosphere's tens of minutes), the
    rest each receiver's own, wandering with ``gnss_tau_s``.
    Decisions and messages by time; 'a''s estimates appended to ``estimates`` if given."""
    eng = FusionEngine((LAT0, LON0, ALT0), lag_s=2.0, config=config)
    log = []
    own_sigma_m = np.sqrt(gnss_sigma_m**2 - shared_sigma_m**2)
    common = rng.normal(0, 1.0, 3) * shared_sigma_m
    bias = {d: rng.normal(0, own_sigma_m, 3) for d in POS}
    keep = np.exp(-dt / gnss_tau_s)
    for t in np.arange(0.0, t_end, dt):
        t = round(float(t), 6)
        for d, p in POS.items():
            bias[d] = keep * bias[d] + rng.normal(0, own_sigma_m * np.sqrt(1 - keep**2), 3)
            eng.add_velocity(d, t, rng.normal(0, 0.05, 3), 0.1)
            fix_type = 0 if d == "a" and t_loss <= t < t_back else 3
            off = np.asarray(back_off_m) if d == "a" and t >= t_back else 0.0
            lat, lon, alt = FRAME.to_geodetic(*(p + common + bias[d] + off + rng.normal(0, 0.1, 3)))
            eng.add_gnss(d, t, float(lat), float(lon), float(alt), h_sigma_m=gnss_sigma_m,
                         v_sigma_m=gnss_sigma_m, fix_type=fix_type)
        if t >= observe_from_s and role.protocol.active:
            for h in ("h1", "h2"):
                los = POS["a"] - POS[h]
                r = float(np.linalg.norm(los))
                u = los / r + rng.normal(0, BEARING_SIGMA_RAD, 3)
                s2 = (RANGE_SIGMA_REL * r) ** 2
                cov = np.eye(3) * (BEARING_SIGMA_RAD * r) ** 2 + np.outer(los, los) / r**2 * s2
                lat, lon, alt = FRAME.to_geodetic(*POS[h])
                eng.add_relative(RelativeObservation(h, "a", t, u / np.linalg.norm(u), r * (1 + rng.normal(0, 0.02)),
                                                     cov, float(lat), float(lon), float(alt)))
        eng.update()
        est = eng.estimate("a")
        if estimates is not None:
            estimates.append(est)
        decision, out = role.step(t, eng.health("a").get("gnss"), est, ["h1", "h2"])
        log.append((t, decision, out))
    return log


def first(log, pred):
    return next(entry for entry in log if pred(entry))


def test_gnss_loss_hold_request_return_home_and_back_to_normal():
    home = at(100.0, -50.0)
    role = RequesterRole("a", home)
    log = fly(role, np.random.default_rng(1), t_loss=6.0, t_back=20.0, t_end=30.0, observe_from_s=9.0)
    t_hold, d_hold, out = first(log, lambda e: e[1].mode is Mode.HOLD)
    assert t_hold == 6.0  # the receiver reports no fix: fusion calls GNSS lost at once
    req = next(b for b in out if isinstance(b, HelpRequest))
    assert req.active and req.epoch == 1
    # the request carries the last good fused fix: where 'a' hovers, its 1-sigma near GNSS's
    e, n, _ = FRAME.to_enu(req.lat_deg, req.lon_deg, req.alt_m)
    assert np.hypot(e, n) < 3 * GNSS_SIGMA_M and 0.2 < req.sigma_h_m < 2 * GNSS_SIGMA_M
    assert d_hold.setpoint == pytest.approx((req.lat_deg, req.lon_deg, req.alt_m))
    t_rth, d_rth, _ = first(log, lambda e: e[1].mode is Mode.RETURN_HOME)
    assert 9.0 <= t_rth <= 12.0 and d_rth.setpoint == home and d_rth.reason == "positioned by helpers"
    # never back to hold while observed; normal once GNSS has been healthy (readmitted) for 3 s
    t_ok = first(log, lambda e: e[1].mode is Mode.NORMAL and e[0] > 20.0)[0]
    assert all(d.mode is Mode.RETURN_HOME for t, d, _ in log if t_rth <= t < t_ok)
    t_ok, d_ok, out_ok = first(log, lambda e: e[1].mode is Mode.NORMAL and e[0] > 20.0)
    assert 20.0 + 3.0 <= t_ok <= 20.0 + 5.0 + 3.0 + 1.0  # readmission (<= 5 s) + 3 s healthy
    assert d_ok.setpoint is None
    cancel = next(b for b in out_ok if isinstance(b, HelpRequest))
    assert not cancel.active and cancel.epoch == 1


def test_a_large_error_the_receivers_share_does_not_keep_the_drone_from_flying_home_on_its_helpers():
    """Receivers of 3.5 m per axis (the engine told so), 90 % of the variance shared by all three drones: the
    helped drone's absolute sigma stays above the 3 m fly-on bound (the shared error alone is 3.3 m, and no
    helper can see it), yet against home and its helpers, which carry that error too, it is placed to well
    under a metre: it flies home on them (before: held until its 90 s ran out, then landed where it was)."""
    from skyfix.fusion import FusionConfig

    cfg = FusionConfig(gnss_gm_h_sigma_m=3.5, gnss_gm_v_sigma_m=3.5, gnss_common_share=0.9)
    role, estimates = RequesterRole("a", at(100.0, -50.0)), []
    log = fly(role, np.random.default_rng(3), t_loss=6.0, t_back=1e9, t_end=16.0, observe_from_s=9.0,
              gnss_sigma_m=3.6, shared_sigma_m=np.sqrt(0.9) * 3.5, config=cfg, estimates=estimates,
              gnss_tau_s=20.0)  # a flying antenna's multipath (datasets.gnss_error), not the engine's 60 s
    t_rth, d_rth, _ = first(log, lambda e: e[1].mode is Mode.RETURN_HOME)
    assert 9.0 <= t_rth <= 12.0 and d_rth.reason == "positioned by helpers"
    assert all(d.mode is Mode.RETURN_HOME for t, d, _ in log if t >= t_rth)
    helped = [e for (t, _, _), e in zip(log, estimates, strict=True) if t >= t_rth]
    assert all(e.sigma_horizontal_m > 3.0 for e in helped)  # honest: the shared error is in it
    # the helpers' own errors (sqrt(0.1) x 3.5 m per axis, two of them) and the ranging: ~0.9 m
    assert all(e.sigma_frame_horizontal_m < 1.5 for e in helped)


@pytest.mark.parametrize(("response", "setpoint"), [(FaultResponse.CONTINUE, None), (FaultResponse.LAND, "here")])
def test_configured_fault_responses(response, setpoint):
    role = RequesterRole("a", at(100.0, 0.0), RequesterConfig(fault_response=response))
    log = fly(role, np.random.default_rng(2), t_loss=5.0, t_back=99.0, t_end=12.0, observe_from_s=7.0)
    t, d, _ = first(log, lambda e: e[1].mode is Mode(response.value))
    assert 7.0 <= t <= 10.0
    if setpoint is None:
        assert d.setpoint is None
    else:  # land where it is: the fused position, within a few metres of the hover point
        e, n, _ = FRAME.to_enu(*d.setpoint)
        assert np.hypot(e, n) < 3.0


def test_no_helpers_holds_then_lands_after_the_timeout():
    role = RequesterRole("a", at(100.0, 0.0), RequesterConfig(hold_timeout_s=6.0))
    log = fly(role, np.random.default_rng(3), t_loss=3.0, t_back=99.0, t_end=12.0, observe_from_s=99.0)
    t_hold = first(log, lambda e: e[1].mode is Mode.HOLD)[0]
    t_land, d_land, _ = first(log, lambda e: e[1].mode is Mode.LAND)
    assert t_land - t_hold == pytest.approx(6.0, abs=0.21) and d_land.reason == "no helper fix for 6 s"
    assert FaultResponse.parse("land") is FaultResponse.LAND
    with pytest.raises(InputError, match="fault response"):
        FaultResponse.parse("panic")


def test_helper_role_flies_to_a_vantage_and_back_to_its_mission():
    net = Net()
    lost = net.add("lost", 0, 0)
    net.add("h1", 40, 0)
    net.add("h2", 0, -40)
    net.run(1.0)
    lost.send(lost.requester.start(net.clock.t, last_fix(net.clock)))
    net.run(3.0)
    roles = {h: HelperRole(h, FRAME) for h in ("h1", "h2")}
    for h, r in roles.items():
        r.protocol = net.drones[h].responder  # the role around the protocol state that the net drove
    peers = {"lost": at(0, 0), "h1": at(40, 0), "h2": at(0, -40)}
    d1, _ = roles["h1"].step(net.clock.t, HelperStatus(*peers["h1"], 0.9), peers, list(peers))
    mates = {"h1": d1.vantage.enu_m}
    d2, _ = roles["h2"].step(net.clock.t, HelperStatus(*peers["h2"], 0.9), peers, list(peers), mates)
    assert d1.helping == d2.helping == "lost" and roles["h2"].protocol.team == ("h1", "h2")
    target = np.array([float(c) for c in FRAME.to_enu(*peers["lost"])])
    for d in (d1, d2):
        assert 20.0 <= d.vantage.range_m <= 60.0
        assert np.linalg.norm(d.vantage.enu_m - target) >= 10.0
    assert np.linalg.norm(d1.vantage.enu_m - d2.vantage.enu_m) >= 10.0
    assert d2.vantage.geometry_quality > 0.95
    # own GNSS lost while helping: it withdraws (a decline) and is back on its own
    d, out = roles["h1"].step(net.clock.t, HelperStatus(*peers["h1"], 0.9, localised=False), peers, list(peers))
    assert d.helping is None and out and not out[0].accept and out[0].requester_id == "lost"
    # a release sends h2 back to its mission
    lost.send([HelpRelease(("h2",), lost.requester.epoch, "done")])
    net.run(0.2)
    d, _ = roles["h2"].step(net.clock.t, HelperStatus(*peers["h2"], 0.9), peers, list(peers))
    assert d.helping is None and d.vantage is None


def test_gnss_back_30_m_off_is_not_trusted_and_recovery_goes_on():
    role = RequesterRole("a", at(100.0, 0.0))
    log = fly(role, np.random.default_rng(4), t_loss=4.0, t_back=10.0, t_end=22.0, observe_from_s=6.0,
              back_off_m=(30.0, 0.0, 0.0))
    t_rth = first(log, lambda e: e[1].mode is Mode.RETURN_HOME)[0]
    assert t_rth <= 9.0
    assert all(d.mode is Mode.RETURN_HOME for t, d, _ in log if t >= t_rth)  # 12 s of offset GNSS: never normal
    assert role.protocol.active and role.protocol.helpers() == ()  # (no bus here: nobody was assigned)


def _estimate(east_m, north_m, t, sources, sigma_m=1.0, up_m=10.0):
    from skyfix.fusion.estimate import Estimate

    enu = np.array([east_m, north_m, up_m])
    lat, lon, alt = (float(c) for c in FRAME.to_geodetic(*enu))
    return Estimate("a", t, lat, lon, alt, enu, np.eye(3) * sigma_m**2, np.zeros(3), np.eye(3) * 0.01, sources)


@pytest.mark.parametrize("east_m, up_m, sigma_m, expected", [
    (4.0, 2.0, 5.0, Mode.LAND),    # low over home: going under the helpers' horizon, holding would drift, land
    (20.0, 2.0, 1.0, Mode.HOLD),   # low but not over home: hold
    (1.0, 10.0, 0.9, Mode.LAND),   # high, over home and sure of it (1 m + 2 sigma <= 3 m)
    (1.0, 10.0, 2.0, Mode.HOLD),   # high, over home but not sure (1 m + 2 sigma > 3 m): hold for the helpers
    (4.0, 10.0, 1.5, Mode.HOLD),   # high, near home but not sure (4 m + 2 sigma > 3 m)
    (2.5, 10.0, 1.0, Mode.HOLD),   # high, on its way in: landing where it is would land it 2.5-4.5 m off
    (20.0, 10.0, 1.0, Mode.HOLD)])
def test_a_drone_returning_home_that_loses_its_helper_fix_lands_only_low_or_sure_over_home(east_m, up_m, sigma_m,
                                                                                            expected):
    from skyfix.fusion.health import HealthState, SourceHealth

    role = RequesterRole("a", at(0.0, 0.0, 0.0))
    ok, lost = SourceHealth(HealthState.OK, "", 0.0), SourceHealth(HealthState.LOST, "no fix", 1.0)
    role.step(0.0, ok, _estimate(east_m, 0.0, 0.0, ("gnss",), up_m=up_m), [])
    assert role.step(1.0, lost, _estimate(east_m, 0.0, 1.0, ("velocity",), up_m=up_m), [])[0].mode is Mode.HOLD
    helped = _estimate(east_m, 0.0, 2.0, ("relative:h1", "velocity"), up_m=up_m)
    assert role.step(2.0, lost, helped, [])[0].mode is Mode.RETURN_HOME
    # the helpers lose it (the estimate rests on velocity alone, its sigma as given)
    decision, _ = role.step(3.0, lost, _estimate(east_m, 0.0, 3.0, ("velocity",), sigma_m, up_m), [])
    assert decision.mode is expected


def test_a_fix_flown_on_is_kept_until_clearly_too_loose_not_dropped_at_the_entry_bound():
    """Hysteresis on the requester's 'positioned' bound: enter at sigma <= 3 m, keep flying on it up to 4 m."""
    from skyfix.fusion.health import HealthState, SourceHealth

    role = RequesterRole("a", at(0.0, 0.0, 0.0))
    cfg = role.cfg
    ok, lost = SourceHealth(HealthState.OK, "", 0.0), SourceHealth(HealthState.LOST, "no fix", 1.0)
    role.step(0.0, ok, _estimate(20.0, 0.0, 0.0, ("gnss",)), [])
    helped = ("relative:h1", "velocity")
    between = 0.5 * (cfg.fused_sigma_h_max_m + cfg.fused_sigma_h_keep_m)
    assert role.step(1.0, lost, _estimate(20.0, 0.0, 1.0, helped, sigma_m=between), [])[0].mode is Mode.HOLD
    assert role.step(2.0, lost, _estimate(20.0, 0.0, 2.0, helped, sigma_m=2.0), [])[0].mode is Mode.RETURN_HOME
    # its sigma wanders above the entry bound between two helpers' frames: it keeps going home
    assert role.step(2.5, lost, _estimate(20.0, 0.0, 2.5, helped, sigma_m=between), [])[0].mode is Mode.RETURN_HOME
    loose = cfg.fused_sigma_h_keep_m + 0.5
    assert role.step(3.0, lost, _estimate(20.0, 0.0, 3.0, helped, sigma_m=loose), [])[0].mode is Mode.HOLD


def test_low_over_home_is_judged_on_the_autopilots_height_when_given():
    """The autopilot's barometric height above home decides "low", not the fused altitude less home's (their
    datums can differ: ArduPilot SITL reports ellipsoidal = AMSL while its home converts through the geoid)."""
    from skyfix.fusion.health import HealthState, SourceHealth

    ok, lost = SourceHealth(HealthState.OK, "", 0.0), SourceHealth(HealthState.LOST, "no fix", 1.0)
    for alt_rel_m, expected in ((2.0, Mode.LAND), (12.0, Mode.HOLD)):
        role = RequesterRole("a", at(0.0, 0.0, 0.0))
        role.step(0.0, ok, _estimate(4.0, 0.0, 0.0, ("gnss",)), [])
        role.step(1.0, lost, _estimate(4.0, 0.0, 1.0, ("velocity",)), [], alt_rel_m)
        assert role.step(2.0, lost, _estimate(4.0, 0.0, 2.0, ("relative:h1",)), [], alt_rel_m)[0].mode is Mode.RETURN_HOME
        # fused altitude 10 m above home, sigma 1.5 m: 4 m + 2 sigma > 3 m, so only "low" can land it
        decision, _ = role.step(3.0, lost, _estimate(4.0, 0.0, 3.0, ("velocity",), 1.5), [], alt_rel_m)
        assert decision.mode is expected


def test_a_stale_fix_near_home_is_not_sure_enough_to_land_on_at_height():
    """High over home, a fix that went stale (no estimate for > fix_max_age_s: a MAVLink drop) holds, though its
    last sigma would have passed distance + 2 sigma <= 3 m; a fresh one with that sigma lands."""
    from skyfix.fusion.health import HealthState, SourceHealth

    ok, lost = SourceHealth(HealthState.OK, "", 0.0), SourceHealth(HealthState.LOST, "no fix", 1.0)
    for fix_t, expected in ((3.0, Mode.LAND), (0.5, Mode.HOLD)):
        role = RequesterRole("a", at(0.0, 0.0, 0.0))
        role.step(0.0, ok, _estimate(1.0, 0.0, 0.0, ("gnss",)), [])
        role.step(0.2, lost, _estimate(1.0, 0.0, 0.2, ("velocity",)), [], 12.0)
        assert role.step(0.5, lost, _estimate(1.0, 0.0, 0.5, ("relative:h1",)), [], 12.0)[0].mode is Mode.RETURN_HOME
        decision, _ = role.step(3.0, lost, _estimate(1.0, 0.0, fix_t, ("velocity",), 1.0), [], 12.0)
        assert decision.mode is expected


@pytest.mark.parametrize("alt_rel_m, recruits", [(2.0, False), (12.0, True)])
def test_a_drone_landing_low_takes_no_new_helpers(alt_rel_m, recruits):
    """Landing at or below ``land_below_m`` (the autopilot's height), the requester assigns no helper in place of
    one it lost and repeats no request: a loaded SITL run stood landed and armed while helpers came and went.
    Landing high (the hold time-out) it still recruits: helpers can position it there."""
    from skyfix.crps.help_protocol import Offer
    from skyfix.crps.messages import HelpAssign
    from skyfix.fusion.health import HealthState, SourceHealth

    ok, lost = SourceHealth(HealthState.OK, "", 0.0), SourceHealth(HealthState.LOST, "no fix", 1.0)
    role = RequesterRole("a", at(0.0, 0.0, 0.0), RequesterConfig(hold_timeout_s=5.0))
    role.step(0.0, ok, _estimate(1.0, 0.0, 0.0, ("gnss",)), [])
    role.step(1.0, lost, _estimate(1.0, 0.0, 1.0, ("velocity",)), [], alt_rel_m)
    decision, _ = role.step(7.0, lost, _estimate(1.0, 0.0, 7.0, ("velocity",), 5.0), [], alt_rel_m)
    assert decision.mode is Mode.LAND
    lat, lon, alt = at(30.0, 0.0, 10.0)
    role.protocol.offers["h3"] = Offer("h3", 7.0, lat, lon, alt, 0.9, 30.0, 6.0)
    _, out = role.step(7.2, lost, _estimate(1.0, 0.0, 7.2, ("velocity",), 5.0), ["h3"], alt_rel_m)
    assert any(isinstance(b, HelpAssign) for b in out) is recruits
    assert role.protocol.helpers() == ()  # not acknowledged either way
    assert ("h3" in role.protocol.assigned) is recruits
