"""InjectionPolicy.fix (crps/inject_policy.py): what the requester injects while no camera sees it (an autopilot echoing the fix).

Holding, the position injected is the autopilot's own (GLOBAL_POSITION_INT) with the fused covariance, for at most
INJECT_HOLD_MAX_S, then none: the autopilot's own GPS-loss failsafe flies it. A constant position (the last measured
fix, still the fallback while no fresh telemetry position is there) made ArduPilot SITL's EKF believe it stood still
while its position controller's integrator wound up: 840 m away under load, 100 m in 20 s unloaded with the
helpers' cameras looking away (benchmarks/recovery_sitl_loaded.py --blind-s 40). Landing, the held fix also keeps the accuracy it
was held with: the position is a constant the drone comes down on, and on ArduPilot SITL a stated accuracy growing
on the ground let the EKF walk ~0.5 m/s, so the copter never reached LAND_COMPLETE and never disarmed. The node is
the real one, fed 10 s of GNSS and velocity, then nothing (the receiver lost, no observation).
"""

import time
from types import SimpleNamespace

import numpy as np
import pytest
from helpnet import ALT0, LAT0, LON0

from skyfix.crps.inject_policy import (
    INJECT_HOLD_AFTER_S,
    INJECT_HOLD_MAX_S,
    LANDING_HOLD_SIGMA_M,
    WINDUP_FOR_S,
    InjectionPolicy,
)
from skyfix.crps.node import Node
from skyfix.crps.service import fusion_config
from skyfix.drivers.state import Attitude, GnssFix, Position, VehicleState, Velocity
from skyfix.geo import LocalFrame

FRAME = LocalFrame(LAT0, LON0, ALT0)
LAG_S = 3.0


def _node() -> tuple[Node, float]:
    rng = np.random.default_rng(4)
    node = Node("a", (LAT0, LON0, ALT0), lag_s=LAG_S, config=fusion_config(("a",), LAG_S))
    for k in range(50):  # hovering, GNSS and velocity at 5 Hz
        t = round(0.2 * k, 6)
        lat, lon, alt = FRAME.to_geodetic(*(np.array([0.0, 0.0, 10.0]) + rng.normal(0, 0.3, 3)))
        gps = GnssFix(fix_type=3, satellites=12, h_acc_m=0.5, v_acc_m=0.8, hdop=0.9, vdop=1.2, lat_deg=float(lat),
                      lon_deg=float(lon), alt_amsl_m=float(alt), alt_ellipsoid_m=float(alt),
                      alt_ellipsoid_source="autopilot", time_s=t)
        node.add_telemetry("a", VehicleState(1, velocity=Velocity(0.0, 0.0, 0.0, t), gps=gps), lambda m: m.time_s)
        node.update(("a",))
    return node, node.latest["a"].time_s


def _service(node: Node, clock: list[float], mode_or_help) -> InjectionPolicy:
    """The injection policy of a service stand-in with the parts it reads, on ``node`` and the clock ``clock[0]``;
    ``mode_or_help`` a help mode ("hold", "land": landing low) or a help loop stand-in with ``mode`` and
    ``landing_low``."""
    help_loop = SimpleNamespace(mode=SimpleNamespace(value=mode_or_help), landing_low=mode_or_help == "land",
                                notes=[]) \
        if isinstance(mode_or_help, str) else mode_or_help
    help_loop.note = lambda t, text: help_loop.notes.append(text)
    svc = SimpleNamespace(clock=lambda: clock[0], node=node, help=help_loop, vehicle=None,
                          cfg=SimpleNamespace(drone_id="a", injected_velocity_sigma_mps=1.5))
    return InjectionPolicy(svc)


def _telemetry_at(service, east_m: float, north_m: float, age_s: float = 0.1, *, roll_deg: float = 0.0,
                  north_mps: float = 0.0) -> None:
    """The autopilot reports its own position ``east_m``, ``north_m`` (node frame, 10 m up), received ``age_s``
    ago, its attitude (``roll_deg``, level otherwise) and its velocity (``north_mps``)."""
    lat, lon, alt = FRAME.to_geodetic(east_m, north_m, 10.0)
    stamp = time.time() - age_s
    pos = Position(float(lat), float(lon), float(alt), 10.0, stamp)
    att = Attitude(roll_deg, 0.0, 0.0, stamp)
    service.svc.vehicle = SimpleNamespace(state=VehicleState(1, link_ok=True, position=pos, attitude=att,
                                                         velocity=Velocity(north_mps, 0.0, 0.0, stamp)))


def _injected(mode: str) -> list:
    """The fixes injected 3, 6 and 9 s after the last input, the drone in help mode ``mode``."""
    node, t_last = _node()
    clock = [t_last]
    service = _service(node, clock, mode)
    out = []
    for dt in (INJECT_HOLD_AFTER_S + 1.0, 6.0, 9.0):
        clock[0] = t_last + dt
        out.append(service.fix())
    node.close()
    return out


def test_held_fix_keeps_its_position_and_while_landing_its_accuracy():
    holding, landing = _injected("hold"), _injected("land")
    for fixes in (holding, landing):  # the position injected is held in both
        assert all(f.lat_deg == fixes[0].lat_deg and f.lon_deg == fixes[0].lon_deg for f in fixes)
    sigma_hold = [f.sigma_horizontal_m for f in holding]
    sigma_land = [f.sigma_horizontal_m for f in landing]
    assert sigma_hold[2] > sigma_hold[0] + 1.0  # holding: the stated accuracy grows with the fused covariance
    assert sigma_land[0] == sigma_land[1] == sigma_land[2] == pytest.approx(LANDING_HOLD_SIGMA_M)  # a constant
    assert (landing[0].lat_deg, landing[0].lon_deg) == (holding[0].lat_deg, holding[0].lon_deg)  # held where it was


@pytest.mark.parametrize("mode, stays", [("hold", False), ("land", True)])
def test_a_sighting_after_the_hold_releases_a_holding_fix_but_not_a_landing_one(mode, stays):
    """A camera observation after the hold began: a holding drone flies on the measured fix again; a landing
    one stays on the position it was held on down to the ground (a late or new sighting near touchdown would
    move it; a loaded SITL run stood landed and armed while helpers came and went)."""
    node, t_last = _node()
    clock = [t_last + INJECT_HOLD_AFTER_S + 1.0]
    service = _service(node, clock, mode)
    held = service.fix()
    kept = "_held_fix" if mode == "land" else "_hover_fix"  # a low landing's hold; a hover's without telemetry
    assert getattr(service, kept) is not None
    clock[0] += 1.0
    node.observed_s["a"] = clock[0]  # a helper's camera saw it (the fix itself is unchanged here)
    service.fix()
    assert (getattr(service, kept) is not None) is stays
    if stays:
        assert (service._held_fix.lat_deg, service._held_fix.lon_deg) == (held.lat_deg, held.lon_deg)
    node.close()


@pytest.mark.parametrize("late_s", [0.2, INJECT_HOLD_AFTER_S + 1.5])
def test_a_late_observation_still_ends_a_hold_when_it_arrives(late_s):
    """An observation arriving ``late_s`` after its exposure ends the hold whatever its age: the fix now rests on
    it. (Judged on the exposure time, a loaded machine's 2-4 s late observations never ended it, the helpers'
    fixes were never injected and SITL flew away on the held position.)"""
    node, t_last = _node()
    clock = [t_last + INJECT_HOLD_AFTER_S + 1.0]
    service = _service(node, clock, "hold")
    service.fix()
    assert service._hover_fix is not None  # nothing measured it yet: held (no telemetry position here)
    clock[0] += 1.0
    node.observed_s["a"] = clock[0] - late_s  # arrives now, exposed late_s ago
    service.fix()
    assert service._hover_fix is None
    clock[0] += INJECT_HOLD_AFTER_S + 0.5  # and nothing since: held again
    service.fix()
    assert service._hover_fix is not None
    node.close()


def test_a_low_landing_holds_at_once_where_it_is():
    """Landing low (the help loop's ``landing_low``), the injected fix is held at once, sightings still coming or
    not: where the fix is then (no jump at touchdown), stated LANDING_HOLD_SIGMA_M accurate (a control value)."""
    node, t_last = _node()
    clock = [t_last]
    help_loop = SimpleNamespace(mode=SimpleNamespace(value="land"), landing_low=False)
    service = _service(node, clock, help_loop)
    node.observed_s["a"] = t_last
    flown = service.fix()
    assert service._held_fix is None and flown.sigma_horizontal_m > LANDING_HOLD_SIGMA_M  # high: flown on
    help_loop.landing_low = True
    clock[0] = t_last + 0.2
    node.observed_s["a"] = t_last + 0.1  # sightings keep coming
    present = node.fix("a", clock[0])
    held = service.fix()
    assert held.sigma_horizontal_m == pytest.approx(LANDING_HOLD_SIGMA_M)
    assert held.sigma_up_m == pytest.approx(present.sigma_up_m)
    assert (held.lat_deg, held.lon_deg) == (present.lat_deg, present.lon_deg)
    clock[0] = t_last + 3.0
    node.observed_s["a"] = t_last + 2.9
    assert service.fix().lat_deg == held.lat_deg  # held to the ground
    node.close()


def test_a_hover_injects_the_autopilots_own_position_with_the_fused_accuracy():
    """Holding unobserved with fresh telemetry: the autopilot's own position (so its EKF keeps its inertial
    velocity and its position controller has nothing to wind up against), stated with the fused covariance."""
    node, t_last = _node()
    clock = [t_last + INJECT_HOLD_AFTER_S + 1.0]
    service = _service(node, clock, "hold")
    _telemetry_at(service, 3.0, -4.0)
    injected = service.fix()
    east, north, _ = FRAME.to_enu(injected.lat_deg, injected.lon_deg, injected.alt_m)
    assert (east, north) == pytest.approx((3.0, -4.0), abs=1e-6)
    fused = node.fix("a", clock[0])
    assert injected.sigma_horizontal_m == pytest.approx(fused.sigma_horizontal_m, rel=1e-6)
    assert injected.alt_m == pytest.approx(fused.alt_m)  # heights stay the fusion's (the autopilot's baro holds it)
    _telemetry_at(service, 3.0, -4.0, age_s=5.0)  # stale telemetry: the last measured fix, held, instead
    held = service.fix()
    assert (held.lat_deg, held.lon_deg) == (service._hover_fix.lat_deg, service._hover_fix.lon_deg)
    node.close()


def test_a_hover_nothing_measures_ends_in_no_injection_until_an_observation():
    """After INJECT_HOLD_MAX_S unobserved the hover injects nothing (ArduPilot: EKF failsafe, a landing); an
    observation arriving brings the fused fix back at once; a landing is never cut off."""
    node, t_last = _node()
    start = t_last + INJECT_HOLD_AFTER_S + 0.5
    clock = [start]
    service = _service(node, clock, "hold")
    _telemetry_at(service, 0.0, 0.0)
    assert service.fix() is not None
    clock[0] = start + INJECT_HOLD_MAX_S - 0.5
    assert service.fix() is not None
    clock[0] = start + INJECT_HOLD_MAX_S + 0.5
    assert service.fix() is None
    node.observed_s["a"] = clock[0] - 3.0  # a (late) sighting arrives
    clock[0] += 0.2
    back = service.fix()
    assert back is not None and back.lat_deg == node.fix("a", clock[0]).lat_deg
    landing = _service(node, [start], "land")  # low: held to the ground, never cut
    for dt in (0.0, INJECT_HOLD_MAX_S + 5.0, 3 * INJECT_HOLD_MAX_S):
        landing.svc.clock = (lambda t: (lambda: t))(start + dt)
        assert landing.fix() is not None
    node.close()


def test_a_high_landing_nothing_measures_is_cut_like_a_hover_and_stays_cut_when_low():
    """Landing still high with nothing measuring it: the autopilot's own position, then after INJECT_HOLD_MAX_S
    nothing, also once it is low (a hold there would be a made-up point far from it: SITL, loaded, a landing held
    from 40 m wound up to 30 deg of roll and 165 m); an observation arriving low holds it where the fix is then."""
    node, t_last = _node()
    start = t_last + INJECT_HOLD_AFTER_S + 0.5
    clock = [start]
    help_loop = SimpleNamespace(mode=SimpleNamespace(value="land"), landing_low=False)
    service = _service(node, clock, help_loop)
    _telemetry_at(service, 2.0, 1.0)
    own = service.fix()
    assert FRAME.to_enu(own.lat_deg, own.lon_deg, own.alt_m)[0] == pytest.approx(2.0, abs=1e-6)
    assert service._held_fix is None
    clock[0] = start + INJECT_HOLD_MAX_S + 0.5
    assert service.fix() is None
    help_loop.landing_low = True
    clock[0] += 2.0
    assert service.fix() is None  # low now, still nothing measures it: stays cut
    node.observed_s["a"] = clock[0] - 1.0
    clock[0] += 0.2
    held = service.fix()
    assert held is not None and held.sigma_horizontal_m == pytest.approx(LANDING_HOLD_SIGMA_M)
    node.close()


@pytest.mark.parametrize("roll_deg, north_mps, lean_s, cut", [
    (25.0, 0.5, WINDUP_FOR_S + 0.5, True),    # leaning hard, standing still by its own account: pinned
    (25.0, 0.5, WINDUP_FOR_S - 1.0, False),   # briefly (braking, a gust)
    (25.0, 6.0, WINDUP_FOR_S + 3.0, False),   # leaning into a fast flight
    (12.0, 0.5, WINDUP_FOR_S + 3.0, False),   # hovering into the wind
])
def test_an_autopilot_leaning_hard_while_standing_still_gets_no_more_injection(roll_deg, north_mps, lean_s, cut):
    """The wind-up guard: WINDUP_TILT_DEG or more for WINDUP_FOR_S while its own estimate moves at most
    WINDUP_SPEED_MPS (SITL flyaways: 6.8-16.1 s in that state; normal flights at most 0.8 s). Once cut, nothing is
    injected in this outage, measured or not, in any mode."""
    node, t_last = _node()
    start = t_last + 0.5
    clock = [start]
    service = _service(node, clock, "hold")
    node.observed_s["a"] = t_last  # observed: the fused fix itself is injected
    _telemetry_at(service, 0.0, 0.0, roll_deg=roll_deg, north_mps=north_mps)
    assert service.fix() is not None
    for dt in np.arange(0.2, lean_s + 1e-9, 0.2):
        clock[0] = start + dt
        _telemetry_at(service, 0.0, 0.0, roll_deg=roll_deg, north_mps=north_mps)
        last = service.fix()
    assert (last is None) is cut
    assert (service.cut_reason is not None) is cut
    assert any("injection stopped" in text for text in service.svc.help.notes) is cut  # on the timeline
    if cut:
        _telemetry_at(service, 0.0, 0.0)  # level again, and a sighting arrives: still nothing
        node.observed_s["a"] = clock[0]
        clock[0] += 0.2
        assert service.fix() is None
    node.close()
